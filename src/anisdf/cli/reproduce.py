"""``anisdf reproduce TABLE --data DIR --out DIR``: train and evaluate a table of the paper, our figures beside
the paper's."""

from __future__ import annotations

import shlex
from dataclasses import MISSING, dataclass
from pathlib import Path

from anisdf.cli import extras
from anisdf.cli.options import base_options, changed_flags, field_from, with_argparse
from anisdf.eval.paper_tables import TABLES
from anisdf.orchestration.reproduce import ReproduceOptions
from anisdf.utils.options import option, out_folder, positional

NAME = "reproduce"


@dataclass(kw_only=True)
class Options(ReproduceOptions):
    table: str = with_argparse(positional("the paper's table"), choices=list(TABLES))
    data: Path = option(MISSING, "dataset root holding the table's scenes, or one scene folder")
    out: Path = option(MISSING, "folder of the runs and the results (a rerun resumes)", out_folder)
    no_progress: bool = option(False, "no progress bars")
    ray: str | None = field_from(ReproduceOptions, "ray", nargs="?", const="local")


def command_line(opts: Options) -> str:
    """The command line as parsed, recorded in reproduce.md."""
    words = ["anisdf", NAME, opts.table, "--data", str(opts.data), "--out", str(opts.out), "--scale", opts.scale]
    words += changed_flags(opts, ReproduceOptions, skip=("scale",))
    return shlex.join(words + list(opts.overrides))


def run(opts: Options) -> int:
    from anisdf.orchestration.reproduce import reproduce

    if opts.ray is not None:
        extras.require("reproduce --ray", "cluster")
    reproduce(opts.table, opts.data, opts.out, base_options(opts, ReproduceOptions), command=command_line(opts),
              progress=not opts.no_progress)
    print(opts.out / "reproduce.md")
    return 0
