"""``anisdf inspect DATA``: validate a dataset and print a JSON summary."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from anisdf.utils.options import positional

NAME = "inspect"


@dataclass(kw_only=True)
class Options:
    data: Path = positional("dataset folder (format detected automatically)")


def run(opts: Options) -> int:
    from anisdf.data.inspect import inspect_dataset

    print(json.dumps(inspect_dataset(opts.data), indent=2))
    return 0
