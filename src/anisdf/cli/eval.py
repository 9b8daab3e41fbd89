"""``anisdf eval RUN``: PSNR, SSIM, normal MAE and Chamfer -> RUN/eval.json and the report."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from anisdf.cli.options import base_options
from anisdf.tasks.evaluate import EvalOptions
from anisdf.utils.options import positional

NAME = "eval"


@dataclass(kw_only=True)
class Options(EvalOptions):
    run: Path = positional("run folder")


def run(opts: Options) -> int:
    from anisdf.tasks.evaluate import evaluate

    print(json.dumps(evaluate(opts.run, base_options(opts, EvalOptions)), indent=2))
    return 0
