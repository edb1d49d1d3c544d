#!/usr/bin/env python3
"""`python scripts/validate.py ...` is `batgraph validate ...` (see `--help`)."""
from batgraph.cli import run_script

if __name__ == "__main__":  # the validation folds' worker processes ("spawn") re-import the main script
    run_script("validate")
