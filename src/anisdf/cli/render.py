"""``anisdf render RUN``: every view of a split with its maps, and an orbit video."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

from anisdf.cli import extras
from anisdf.cli.options import base_options
from anisdf.tasks.render import RenderOptions
from anisdf.utils.options import positional

log = logging.getLogger("anisdf")

NAME = "render"


@dataclass(kw_only=True)
class Options(RenderOptions):
    run: Path = positional("run folder")


def run(opts: Options) -> int:
    from anisdf.tasks.render import render

    absent = extras.missing("video") if opts.video else []
    if absent:  # the video is written as a GIF instead: say so now, not after the renders
        log.warning("warning: %s; without it the orbit video is a GIF", extras.install_line("render --video", "video",
                                                                                            absent))
    print(render(opts.run, base_options(opts, RenderOptions)))
    return 0
