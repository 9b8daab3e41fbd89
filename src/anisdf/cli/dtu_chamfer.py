"""``anisdf dtu-chamfer MESH --dtu-root DIR --scan N``: DTU's official accuracy, completeness and Chamfer (mm)."""

from __future__ import annotations

from dataclasses import MISSING, dataclass
from pathlib import Path

from anisdf.eval.dtu import DENSITY_MM, MAX_DIST_MM
from anisdf.utils.options import float_at_least, int_at_least, option, positional

NAME = "dtu-chamfer"


@dataclass(kw_only=True)
class Options:
    mesh: Path = positional("mesh to score (in DTU's world frame, or mapped there by --scale-mat)")
    dtu_root: Path = option(MISSING, "folder with ObsMask/ and Points/stl/ of the DTU benchmark")
    scan: int = option(MISSING, "DTU scan number, e.g. 65", int_at_least(0))
    scale_mat: Path | None = option(None, "cameras_sphere.npz whose scale_mat_0 maps the mesh to mm")
    mask_cull: Path | None = option(None, "NeuS dataset folder (cameras npz, mask/): cull the mesh with the dilated "
                                    "masks first", metavar="DATASET_DIR")
    density: float = option(DENSITY_MM, "sampling and thinning distance in mm", float_at_least(0.0, strict=True))
    max_dist: float = option(MAX_DIST_MM, "distances of this many mm or more are outliers",
                             float_at_least(0.0, strict=True))
    seed: int = option(0, "order of the point thinning", int_at_least(0))
    no_stl_thinning: bool = option(False, "score against every STL point (DTUeval-python) instead of thinning them "
                                   "(MATLAB original)")


def run(opts: Options) -> int:
    from anisdf.eval.dtu import dtu_chamfer, mask_cull_inputs

    mask_cull = mask_cull_inputs(opts.mask_cull) if opts.mask_cull else None
    r = dtu_chamfer(opts.mesh, opts.dtu_root, opts.scan, scale_mat=opts.scale_mat, mask_cull=mask_cull,
                    density=opts.density, max_dist=opts.max_dist, seed=opts.seed, thin_stl=not opts.no_stl_thinning)
    for key, value in r.items():
        if key not in ("accuracy", "completeness", "chamfer"):
            print(f"{key}: {value}")
    print(f"accuracy {r['accuracy']:.3f} completeness {r['completeness']:.3f} chamfer {r['chamfer']:.3f}")
    return 0
