"""Extracting a run's mesh (marching cubes on the SDF) and choosing the mesh that eval scores."""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from anisdf.errors import AnisdfError
from anisdf.run_dir import RunDir
from anisdf.utils.options import comma_list, int_at_least, option

log = logging.getLogger("anisdf")

FLOATER_MIN_FRACTION = 0.01
"""``remove_floaters``: components under this fraction of the largest one's face count are dropped."""
MESH_FORMATS = ("ply", "obj", "glb")


@dataclass(kw_only=True)
class MeshOptions:
    """How ``anisdf extract-mesh`` / :func:`extract_mesh` meshes a run; ``eval`` extracts with the same defaults: the
    mesh as marching cubes found it, not cleaned."""

    resolution: int = option(512, "marching-cubes grid cells per axis", int_at_least(2))
    format: str = option("ply", "file format of RUN/mesh.<format>", choices=MESH_FORMATS)
    remove_floaters: bool = option(
        False, f"drop pieces under {FLOATER_MIN_FRACTION:.0%} of the largest one's faces (default: the mesh is not "
        "cleaned)")
    remove_inner: bool = option(
        False, "drop surfaces around pockets enclosed inside the object (no camera outside sees them)")
    bbox: list[float] | None = option(
        None, "mesh only inside this box of the dataset's frame and units (xmin,ymin,zmin,xmax,ymax,zmax): faces "
        "outside it are cut away", comma_list(float), metavar="XMIN,YMIN,ZMIN,XMAX,YMAX,ZMAX")
    device: str | None = option(None, "auto | cpu | cuda[:N]")
    progress: bool = option(True, "show a progress bar", cli=False)


def check_bbox(bbox: list[float] | tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) of ``bbox`` = xmin,ymin,zmin,xmax,ymax,zmax; AnisdfError unless six finite numbers with min < max."""
    if len(bbox) != 6:
        raise AnisdfError(f"--bbox needs six numbers xmin,ymin,zmin,xmax,ymax,zmax, got {len(bbox)}: {list(bbox)}")
    box = np.asarray(bbox, dtype=np.float64)
    if not np.isfinite(box).all():
        raise AnisdfError(f"--bbox must be finite, got {list(bbox)}")
    lo, hi = box[:3], box[3:]
    if not np.all(hi > lo):
        axis = "xyz"[int(np.argmax(hi <= lo))]
        raise AnisdfError(f"--bbox: {axis}max must be greater than {axis}min, got {list(bbox)}")
    return lo, hi


def crop_mesh(mesh: Any, lo: np.ndarray, hi: np.ndarray, tol: float = 0.0) -> Any:
    """``mesh`` without the faces that have a vertex outside the box [lo - tol, hi + tol] (unreferenced vertices
    dropped)."""
    v = np.asarray(mesh.vertices)
    inside = np.all((v >= lo - tol) & (v <= hi + tol), axis=1)
    out = mesh.copy()
    out.update_faces(inside[np.asarray(mesh.faces)].all(axis=1))
    out.remove_unreferenced_vertices()
    return out


def extract_mesh(run: Path, options: MeshOptions | None = None, *, written_by: str = "extract-mesh",
                 **changes: Any) -> Path:
    """Marching cubes on the SDF, vertex colours from the view branch, written in the dataset's frame as
    RUN/mesh.<format>, with its settings in RUN/mesh.json (which ``eval`` reads); ``changes`` replace fields of
    ``options`` (``fmt`` is read as ``format``). Not cleaned unless asked: ``remove_floaters`` drops small
    disconnected pieces, ``remove_inner`` the shells around pockets enclosed inside the object
    (docs/evaluation.md). ``bbox`` (xmin,ymin,zmin,xmax,ymax,zmax in the dataset's frame) meshes only that box, at
    the full ``resolution`` along its longest side within the region of interest."""
    from anisdf.export.mesh import color_vertices, save_mesh, to_world
    from anisdf.export.mesh import extract_mesh as mc
    from anisdf.export.mesh import remove_floaters as drop_floaters
    from anisdf.tasks.loading import load_run
    from anisdf.utils.devices import pick_device

    if "fmt" in changes:
        changes["format"] = changes.pop("fmt")
    o = dataclasses.replace(options or MeshOptions(), **changes)
    box = None if o.bbox is None else check_bbox(o.bbox)
    run = Path(run)
    dev = pick_device(o.device or "auto")
    cfg, model, ck = load_run(run, dev)
    world = np.asarray(ck["to_world"], dtype=np.float64)
    bounds = None
    if box is not None:  # a similarity with a positive uniform scale: the box maps to a box
        scale, shift = float(np.cbrt(np.linalg.det(world[:3, :3]))), world[:3, 3]
        bounds = ((box[0] - shift) / scale, (box[1] - shift) / scale)
        if not np.all((bounds[1] > -model.radius) & (bounds[0] < model.radius)):
            raise AnisdfError(f"--bbox {o.bbox} lies outside the region the run models (centre "
                              f"{np.round(shift, 4).tolist()}, half-size {scale * model.radius:.4g}, dataset frame)")
    mesh = mc(model.geometry.distance, radius=model.radius, resolution=o.resolution, device=dev, progress=o.progress,
              keep_inner=not o.remove_inner, bounds=bounds)
    if box is not None:
        mesh = crop_mesh(mesh, *bounds)
        if len(mesh.faces) == 0:
            raise AnisdfError(f"--bbox {o.bbox}: no surface inside the box")
    if o.remove_floaters:
        mesh = drop_floaters(mesh, min_fraction=FLOATER_MIN_FRACTION)
    mesh = color_vertices(mesh, model.diffuse_color, device=dev)
    mesh = to_world(mesh, world)
    rd = RunDir(run)
    path = rd.mesh(o.format)
    save_mesh(mesh, path, o.format)
    info = {"mesh": path.name, "written_by": written_by, "step": int(ck["state"]["step"]),
            "resolution": int(o.resolution), "remove_floaters": bool(o.remove_floaters),
            "floater_min_fraction": FLOATER_MIN_FRACTION if o.remove_floaters else None,
            "remove_inner": bool(o.remove_inner), "two_pass": True, "margin": 0.1, "frame": "dataset",
            "bbox": None if box is None else [float(v) for v in o.bbox],
            "vertices": len(mesh.vertices), "faces": len(mesh.faces)}
    rd.write_mesh_info(info)
    log.info("mesh: %d vertices, %d faces -> %s (%s)", len(mesh.vertices), len(mesh.faces), path,
             describe_mesh(info))
    return path


def describe_mesh(info: dict[str, Any]) -> str:
    return (f"resolution {info['resolution']}, floaters {'removed' if info['remove_floaters'] else 'kept'}, "
            f"inner shells {'removed' if info['remove_inner'] else 'kept'}, step {info['step']}"
            + (f", cropped to {info['bbox']}" if info.get("bbox") else ""))


def mesh_for_eval(run: Path, step: int, requested: dict[str, Any], re_extract: bool) -> dict[str, Any] | None:
    """The mesh ``eval`` scores: the one ``extract-mesh`` wrote (RUN/mesh.json) when there is one, else None (extract
    one). Raises when that mesh does not fit (another step, other settings asked for, no sidecar) and
    ``re_extract`` is off, rather than scoring or replacing it silently."""
    if re_extract:
        return None
    rd = RunDir(run)
    info = rd.read_mesh_info()
    if info is not None:
        mesh_path = run / str(info["mesh"])
        if not mesh_path.is_file():
            raise AnisdfError(f"{rd.mesh_info} names {info['mesh']}, which is missing; run extract-mesh or pass "
                              "--re-extract")
        if info.get("step") != step:
            raise AnisdfError(f"{mesh_path} was extracted at step {info.get('step')} but the checkpoint is at step "
                              f"{step}; run extract-mesh again or pass --re-extract")
        for key, value in requested.items():
            if value is not None and info.get(key) != value:
                raise AnisdfError(f"{mesh_path} was extracted with {key}={info.get(key)} ({rd.mesh_info.name}), not "
                                  f"{value}; pass --re-extract to replace it, or drop the option to score it")
        return {**info, "path": str(mesh_path)}
    old = rd.existing_mesh()
    if old is not None:
        raise AnisdfError(f"{old} has no {rd.mesh_info.name} (an older anisdf wrote it; its settings are unknown); "
                          "pass --re-extract to replace it")
    return None


