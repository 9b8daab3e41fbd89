"""Everything ``anisdf bench`` measures: ``python benchmarks/bench_all.py [--json] [--quick] [--minutes M]``."""

import sys

from anisdf.cli import main

if __name__ == "__main__":
    sys.exit(main(["bench", *sys.argv[1:]]))
