"""Speed and time to quality, as ``anisdf bench`` measures them: ``python benchmarks/speed_and_time_to_psnr.py
[--json] [--quick] [--minutes M] [--data SCENE] [--device D] [--preset P]``.

The hash-grid encoding (reference vs fast kernel), the training step (samples per second with each), peak memory,
and, unless ``--quick``, the seconds a ``--minutes`` training run takes to reach 30 and 34 dB mean test PSNR
(``--data SCENE`` names the scene, e.g. a NeRF-synthetic folder; benchmarks/RESULTS.md used bunny_plastic).
"""

import sys

from anisdf.cli import main

if __name__ == "__main__":
    sys.exit(main(["bench", *sys.argv[1:]]))
