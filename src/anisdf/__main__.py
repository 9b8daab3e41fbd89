"""``python -m anisdf``: the command line (torchrun launches ``-m anisdf``)."""

import logging
import os
import sys

from anisdf.cli import main

code = main()
if int(os.environ.get("WORLD_SIZE", "1")) > 1:
    # A torchrun rank leaves without the interpreter's teardown: gloo's worker threads can still hold work objects
    # whose destruction then aborts the process ("terminate called without an active exception", pytorch#190489),
    # failing a run whose files were all written. Everything is flushed first; files are written atomically before.
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code if isinstance(code, int) else 1)
sys.exit(code)
