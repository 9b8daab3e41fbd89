"""Normals, analytic vs finite differences: ``python benchmarks/normals_cost_and_accuracy.py [--steps N] [--json]``.

The code lives in :mod:`anisdf.benchmarks.normals`.
"""

import sys

from anisdf.benchmarks.normals import main

if __name__ == "__main__":
    sys.exit(main())
