"""``anisdf train DATA --out RUN``: reconstruct a scene; ``--viewer`` serves it live in the browser, ``--nproc N``
relaunches the command under torchrun."""

from __future__ import annotations

import json
import logging
import os
import shlex
import subprocess
import sys
from collections.abc import Callable
from dataclasses import MISSING, dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from anisdf.cli import extras
from anisdf.cli.options import base_options, field_from
from anisdf.errors import AnisdfError
from anisdf.tasks.train import TrainOptions
from anisdf.utils.options import int_at_least, option, out_folder, port_number, positional
from anisdf.viewer.server import ViewOptions

if TYPE_CHECKING:
    from anisdf.training.trainer import Trainer

log = logging.getLogger("anisdf")

NAME = "train"


@dataclass(kw_only=True)
class Options(TrainOptions):
    data: Path = positional("dataset folder")
    out: Path = option(MISSING, "run folder (checkpoints, logs, renders)", out_folder)
    no_progress: bool = option(False, "no progress bar")
    nproc: int = option(1, "data-parallel ranks on this machine (torchrun --standalone; one per GPU, gloo on CPUs); "
                        "for several machines run torchrun yourself (docs/distributed.md)", int_at_least(1))
    viewer: bool = option(False, "watch it learn in the browser (viser; rendering between steps, not counted as "
                          "training time)")
    port: int | None = option(None, f"viewer port (default {ViewOptions.port}; when taken, the next free one, said at "
                              "start)", port_number)
    host: str = field_from(ViewOptions, "host")
    argv: list[str] = option([], "the command line as given (relaunched under torchrun by --nproc)", cli=False)


def _without_option(argv: list[str], name: str) -> list[str]:
    """``argv`` without ``name VALUE`` / ``name=VALUE``."""
    out, skip = [], False
    for a in argv:
        if skip:
            skip = False
        elif a == name:
            skip = True
        elif not a.startswith(name + "="):
            out.append(a)
    return out


def _torchrun(nproc: int, argv: list[str]) -> int:
    """``anisdf train --nproc N``: the same command under ``torchrun --standalone --nproc-per-node N`` (one node)."""
    if "WORLD_SIZE" in os.environ:
        raise AnisdfError("--nproc: this process is already one rank of a torchrun job; drop --nproc")
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc-per-node={nproc}",
           "-m", "anisdf", *_without_option(argv, "--nproc")]
    log.info("launching %s", shlex.join(cmd))
    return subprocess.call(cmd)


def _live_viewer(opts: Options) -> Callable[[Trainer], Callable[[], None]]:
    """``train``'s setup for ``--viewer``: a live viewer of the model, refreshed between steps."""

    def setup(trainer: Trainer) -> Callable[[], None]:
        from anisdf.viewer import Viewer

        viewer = Viewer(trainer.model, trainer.scene, port=opts.port or ViewOptions.port, host=opts.host, live=True,
                        title=f"anisdf · {opts.out.name} (training)")
        trainer.step_hooks.append(viewer.on_step)
        print(viewer.announce(), flush=True)
        return viewer.close

    return setup


def run(opts: Options) -> int:
    from anisdf.tasks.train import train

    if not opts.viewer and (opts.port is not None or opts.host != ViewOptions.host):
        raise AnisdfError("--port and --host are the viewer's: add --viewer")
    if opts.viewer:
        extras.require("train --viewer", "viewer")
    if opts.nproc > 1:
        return _torchrun(opts.nproc, opts.argv)
    rank = int(os.environ.get("RANK", "0"))
    if rank > 0:  # under torchrun rank 0 speaks for the job
        logging.getLogger("anisdf").setLevel(logging.WARNING)
    summary = train(opts.data, opts.out, base_options(opts, TrainOptions),
                    setup=_live_viewer(opts) if opts.viewer else None, progress=not opts.no_progress)
    if rank == 0:
        print(json.dumps(summary, indent=2))
    return 0
