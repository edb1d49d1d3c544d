#!/usr/bin/env python3
"""`python scripts/reconstruct.py ...` is `batgraph reconstruct ...` (see `--help`)."""
from batgraph.cli import run_script

run_script("reconstruct")
