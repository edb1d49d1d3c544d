#!/usr/bin/env python3
"""`python scripts/detect.py ...` is `batgraph detect ...` (see `--help`)."""
from batgraph.cli import run_script

if __name__ == "__main__":
    run_script("detect")
