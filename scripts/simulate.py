#!/usr/bin/env python3
"""`python scripts/simulate.py ...` is `batgraph simulate ...` (see `--help`)."""
from batgraph.cli import run_script

if __name__ == "__main__":  # Dask's local cluster re-imports the main script in its workers
    run_script("simulate")
