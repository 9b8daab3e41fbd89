"""``anisdf view RUN``: the interactive web viewer of a run, finished or training."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from anisdf.cli import extras
from anisdf.utils.options import int_at_least, option, port_number, positional

NAME = "view"
HELP = "interactive web viewer of a run (finished or training): maps, cameras, mesh"

PORT = 7007
"""The viewer's port unless ``--port`` is given (``view`` and ``train --viewer``)."""
HOST = "127.0.0.1"
"""The address the viewer listens on unless ``--host`` is given: this machine only."""


@dataclass(kw_only=True)
class Options:
    run: Path = positional("run folder")
    port: int = option(PORT, f"viewer port (default {PORT}; when taken, the next free one, said at start)",
                       port_number)
    host: str = option(HOST, "viewer address to listen on (0.0.0.0: every interface)")
    max_resolution: int = option(512, "long side in pixels of a resting view (a slider in the page changes it)",
                                 int_at_least(64))
    device: str | None = option(None, "auto | cpu | cuda[:N]")


def run(opts: Options) -> int:
    extras.require(NAME, "viewer")
    from anisdf.viewer.run import view

    view(opts.run, port=opts.port, host=opts.host, device=opts.device, max_resolution=opts.max_resolution)
    return 0
