"""``anisdf batch JOBS.yaml --out DIR``: train, mesh and evaluate a list of jobs, here or on Ray."""

from __future__ import annotations

import sys
from dataclasses import MISSING, dataclass
from pathlib import Path

from anisdf.cli import extras
from anisdf.cli.options import base_options, field_from
from anisdf.orchestration.batch import BatchOptions
from anisdf.utils.options import option, out_folder, positional

NAME = "batch"


@dataclass(kw_only=True)
class Options(BatchOptions):
    jobs: Path = positional("YAML list of {name, data, preset, overrides: [key=value], minutes} (see "
                            "docs/distributed.md)")
    out: Path = option(MISSING, "folder of the runs and batch.json (a rerun resumes)", out_folder)
    no_progress: bool = option(False, "no progress bars")
    ray: str | None = field_from(BatchOptions, "ray", nargs="?", const="local")


def run(opts: Options) -> int:
    from anisdf.orchestration.batch import run_batch

    if opts.ray is not None:
        extras.require("batch --ray", "cluster")
    result = run_batch(opts.jobs, opts.out, base_options(opts, BatchOptions), progress=not opts.no_progress)
    failed = [r["name"] for r in result["runs"] if r["status"] != "done"]
    print(opts.out / "batch.json")
    if failed:
        print(f"anisdf: error: {len(failed)} of {len(result['runs'])} jobs did not finish: {', '.join(failed)} "
              "(see batch.json; rerun to retry them)", file=sys.stderr)
        return 1
    return 0
