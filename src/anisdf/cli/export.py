"""``anisdf export RUN --out DIR``: bake a run into a real-time asset (model.glb, lobe textures, a WebGL page)."""

from __future__ import annotations

import json
from dataclasses import MISSING, dataclass
from pathlib import Path

from anisdf.cli import extras
from anisdf.cli.options import base_options
from anisdf.tasks.export import ExportOptions
from anisdf.utils.options import option, out_folder, positional

NAME = "export"

SUMMARY_KEYS = ("faces", "vertices", "texture", "specular_texture", "lobes", "files", "total_bytes", "seconds")
"""What of export.json is printed."""


@dataclass(kw_only=True)
class Options(ExportOptions):
    run: Path = positional("run folder")
    out: Path = option(MISSING, "folder of the asset", out_folder)
    no_progress: bool = option(False, "no progress bars")


def run(opts: Options) -> int:
    extras.require(NAME, "export")
    from anisdf.tasks.export import export

    manifest = export(opts.run, opts.out, base_options(opts, ExportOptions), progress=not opts.no_progress)
    print(json.dumps({k: manifest[k] for k in SUMMARY_KEYS if k in manifest}, indent=2))
    print(opts.out / ("model.glb" if opts.pbr else "index.html"))
    return 0
