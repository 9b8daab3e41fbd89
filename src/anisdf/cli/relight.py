"""``anisdf relight RUN --env ENV --out DIR``: render the PBR asset of ``anisdf materials`` under another light."""

from __future__ import annotations

from dataclasses import MISSING, dataclass
from pathlib import Path

from anisdf.cli.options import base_options
from anisdf.tasks.relight import RelightOptions
from anisdf.utils.options import option, out_folder, positional

NAME = "relight"


@dataclass(kw_only=True)
class Options(RelightOptions):
    run: Path = positional("run folder")
    out: Path = option(MISSING, "folder of the images", out_folder)
    no_progress: bool = option(False, "no progress bar")


def run(opts: Options) -> int:
    from anisdf.tasks.relight import relight

    info = relight(opts.run, opts.out, base_options(opts, RelightOptions), progress=not opts.no_progress)
    print(f"{len(info['views'])} views in {info['seconds']} s -> {opts.out}")
    return 0
