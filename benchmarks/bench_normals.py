"""Normals, analytic vs finite differences: ``python benchmarks/bench_normals.py [--steps N] [--json]``.

The code lives in :mod:`anisdf.benchmarks.normals`.
"""

import sys

from anisdf.benchmarks.normals import main

if __name__ == "__main__":
    sys.exit(main())
