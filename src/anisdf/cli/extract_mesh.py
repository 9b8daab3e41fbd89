"""``anisdf extract-mesh RUN``: marching cubes on the SDF -> RUN/mesh.<format> and RUN/mesh.json."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from anisdf.cli.options import base_options
from anisdf.tasks.mesh import MeshOptions
from anisdf.utils.options import positional

NAME = "extract-mesh"


@dataclass(kw_only=True)
class Options(MeshOptions):
    run: Path = positional("run folder")


def run(opts: Options) -> int:
    from anisdf.tasks.mesh import extract_mesh

    print(extract_mesh(opts.run, base_options(opts, MeshOptions)))
    return 0
