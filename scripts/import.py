#!/usr/bin/env python3
"""`python scripts/import.py ...` is `batgraph import ...` (see `--help`)."""
from batgraph.cli import run_script

run_script("import")
