"""``anisdf inspect DATA``: validate a dataset and print a JSON summary (and the region of interest in one line)."""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path

from anisdf.utils.options import option, positional

NAME = "inspect"


@dataclass(kw_only=True)
class Options:
    data: Path = positional("dataset folder (format detected automatically)")
    overrides: list[str] = positional(
        "data.* config overrides as train takes them, e.g. data.roi_center=0,0,0.1 data.roi_radius=0.8",
        metavar="key=value", nargs="*", default=[])
    picture: Path | None = option(None, "write a PNG of the cameras around the region of interest (red) here",
                                  Path, metavar="PNG")


def run(opts: Options) -> int:
    from anisdf.data.inspect import inspect_dataset, roi_line

    report = inspect_dataset(opts.data, opts.overrides, opts.picture)
    print(json.dumps(report, indent=2))
    print(roi_line(report), file=sys.stderr)
    return 0
