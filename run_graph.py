#!/usr/bin/env python3
"""Drift-correction runs: ``run_graph.py [options]`` is ``nap3d-graph run [options]``."""

import sys

from nap3d_graph.cli import main

if __name__ == "__main__":
    sys.exit(main(["run", *sys.argv[1:]]))
