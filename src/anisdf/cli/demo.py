"""``anisdf demo``: reconstruct the bundled glossy bunny on the CPU, then mesh, evaluate and render it."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from anisdf.cli.options import base_options
from anisdf.tasks.demo import DemoOptions
from anisdf.utils.options import option, out_folder

NAME = "demo"


@dataclass(kw_only=True)
class Options(DemoOptions):
    out: Path = option(Path("runs/demo"), "folder of the demo's run (OUT/run; a rerun resumes it)", out_folder)


def run(opts: Options) -> int:
    from anisdf.tasks.demo import run_demo

    run_demo(opts.out, base_options(opts, DemoOptions))
    return 0
