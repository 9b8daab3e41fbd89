"""``anisdf view RUN``: the interactive web viewer of a run, finished or training."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from anisdf.cli import extras
from anisdf.utils.options import positional
from anisdf.viewer.server import ViewOptions

NAME = "view"

@dataclass(kw_only=True)
class Options(ViewOptions):
    run: Path = positional("run folder")


def run(opts: Options) -> int:
    extras.require(NAME, "viewer")
    from anisdf.viewer.run import view

    view(opts.run, opts)
    return 0
