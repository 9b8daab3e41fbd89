"""``anisdf chamfer A B``: the Chamfer distance between two meshes, printed last."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from anisdf.cli.options import field_from
from anisdf.tasks.evaluate import EvalOptions
from anisdf.utils.options import int_at_least, option, positional

NAME = "chamfer"


@dataclass(kw_only=True)
class Options:
    a: Path = positional("predicted mesh")
    b: Path = positional("reference mesh")
    points: int = field_from(EvalOptions, "chamfer_points")
    seed: int = option(0, "seed of a's points (b's: +1)", int_at_least(0))


def run(opts: Options) -> int:
    from anisdf.eval.metrics import chamfer_main

    print(f"{chamfer_main(str(opts.a), str(opts.b), n_points=opts.points, seed=opts.seed):.6f}")
    return 0
