#!/usr/bin/env python3
"""`python scripts/simulate.py ...` is `batgraph simulate ...` (see `--help`)."""
from batgraph.cli import run_script

run_script("simulate")
