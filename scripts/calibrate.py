#!/usr/bin/env python3
"""`python scripts/calibrate.py ...` is `batgraph calibrate ...` (see `--help`)."""
from batgraph.cli import run_script

run_script("calibrate")
