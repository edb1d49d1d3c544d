#!/usr/bin/env python3
"""`python scripts/associate.py ...` is `batgraph associate ...` (see `--help`)."""
from batgraph.cli import run_script

if __name__ == "__main__":
    run_script("associate")
