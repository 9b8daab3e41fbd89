"""``anisdf materials RUN [--minutes M]``: fit a light and a PBR material to a trained run's photos."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from anisdf.cli.options import base_options
from anisdf.tasks.materials import MaterialsOptions
from anisdf.utils.options import option, positional

NAME = "materials"


@dataclass(kw_only=True)
class Options(MaterialsOptions):
    run: Path = positional("run folder")
    no_progress: bool = option(False, "no progress bar")


def run(opts: Options) -> int:
    from anisdf.tasks.materials import materials

    info = materials(opts.run, base_options(opts, MaterialsOptions), progress=not opts.no_progress)
    print(json.dumps({k: info[k] for k in ("step", "seconds", "train_psnr", "material")}, indent=2))
    return 0
