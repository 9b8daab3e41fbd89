"""``anisdf process-data INPUT --out SCENE``: camera poses for your own photos or video (pycolmap)."""

from __future__ import annotations

import json
from dataclasses import MISSING, dataclass
from pathlib import Path

from anisdf.cli import extras
from anisdf.cli.options import base_options
from anisdf.data.process import ProcessDataOptions
from anisdf.utils.options import option, positional

NAME = "process-data"


@dataclass(kw_only=True)
class Options(ProcessDataOptions):
    input: Path = positional("folder of images, or a video file (or, with --masks, a scene to add masks to)")
    out: Path = option(MISSING, "scene folder to write (images/, colmap/, transforms.json)")
    no_progress: bool = option(False, "no progress bars")


def run(opts: Options) -> int:
    from anisdf.data.process import process_data, summary_line
    from anisdf.data.process.inputs import is_video

    if opts.masks:
        extras.require(NAME, "masks")
    if not (opts.masks and (opts.input / "transforms.json").is_file()):
        extras.require(NAME, "colmap", None if is_video(opts.input) else ("pycolmap",))
    summary = process_data(opts.input, opts.out, base_options(opts, ProcessDataOptions),
                           progress=not opts.no_progress)
    print(json.dumps(summary, indent=2))
    print(summary_line(summary))
    return 0
