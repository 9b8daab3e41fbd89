"""``python -m anisdf``: the command line (torchrun launches ``-m anisdf``)."""

import sys

from anisdf.cli import main

sys.exit(main())
