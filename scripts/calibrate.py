#!/usr/bin/env python3
"""`python scripts/calibrate.py ...` is `batgraph calibrate ...` (see `--help`)."""
from batgraph.cli import run_script

if __name__ == "__main__":  # Dask's local cluster re-imports the main script in its workers
    run_script("calibrate")
