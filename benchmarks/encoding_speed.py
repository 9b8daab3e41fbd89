"""Hash-grid encoding speed, reference vs compiled kernel: ``python benchmarks/encoding_speed.py [--json]``.

The code lives in :mod:`anisdf.benchmarks.encoding` so that ``anisdf bench`` can run it from an installed package.
"""

import sys

from anisdf.benchmarks.encoding import main

if __name__ == "__main__":
    sys.exit(main())
