"""``anisdf inspect DATA``: validate a whole dataset and summarise it as a JSON-able dict; ``--picture`` draws the
cameras around the region of interest."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from anisdf.data.dataparsers import load_scene
from anisdf.data.normalize import describe_roi_method
from anisdf.data.scene import Scene
from anisdf.errors import AnisdfError


def data_options(overrides: list[str] | None) -> dict[str, Any]:
    """``load_scene`` keywords from ``data.*`` config overrides (``data.roi_radius=0.5``); other keys are an error."""
    from anisdf.config import load_config

    items = list(overrides or [])
    other = [o for o in items if not o.strip().startswith("data.")]
    if other:
        raise AnisdfError(f"inspect reads data.* settings only (the ones that change how the dataset loads), not "
                          f"{other[0]!r}")
    d = load_config(None, items).data
    return {"downscale": d.downscale, "max_images": d.max_images, "images_dir": d.images_dir,
            "roi_center": d.roi_center, "roi_radius": d.roi_radius, "min_size": d.min_size, "alpha": d.alpha}


def inspect_dataset(path: str | Path, overrides: list[str] | None = None, picture: str | Path | None = None
                    ) -> dict[str, Any]:
    """Load every image, mask and normal map of the dataset at ``path`` and check it.

    Loading already raises :class:`~anisdf.errors.DataError` for undecodable images, non-finite or
    non-rotation poses, masks that do not match the images and malformed metadata; this adds checks
    that only warn (empty masks, cameras inside the region of interest, tiny images). ``overrides`` are ``data.*``
    config overrides (a region of interest of one's own: ``data.roi_center=x,y,z``, ``data.roi_radius=r``);
    ``picture`` writes a PNG of the cameras around the region of interest (:func:`draw_scene`).
    """
    t0 = time.perf_counter()
    scene = load_scene(path, **data_options(overrides))
    warnings = list(scene.warnings)
    cams = scene.cameras
    dist = cams.centers.norm(dim=-1)
    n_inside = int((dist < 1.0).sum())
    if n_inside:
        warnings.append(f"{n_inside} cameras lie inside the normalised unit sphere (region of interest)")
    if scene.masks is not None:
        peak = scene.masks.reshape(scene.n_images, -1).amax(dim=1)
        empty = [scene.image_paths[i].name for i in torch.nonzero(peak == 0)[:, 0].tolist()]
        if empty:
            warnings.append(f"{len(empty)} masks are empty (e.g. for {empty[0]})")
    if min(scene.width, scene.height) < 32:
        warnings.append(f"images are only {scene.width}x{scene.height} pixels")
    peak = scene.images.reshape(scene.n_images, -1).amax(dim=1)
    dead = [scene.image_paths[i].name for i in torch.nonzero(peak == 0)[:, 0].tolist()]
    if dead:
        warnings.append(f"{len(dead)} images are entirely black (e.g. {dead[0]})")
    coverage = scene.coverage()
    fov_x = 2.0 * torch.atan(0.5 * scene.width / cams.fx)
    center = [round(float(v), 6) for v in scene.center]
    out: dict[str, Any] = {
        "path": str(Path(path)),
        "format": scene.format,
        "n_images": scene.n_images,
        "n_train": len(scene.splits.get("train", [])),
        "n_test": len(scene.splits.get("test", [])),
        "n_val": len(scene.splits.get("val", [])),
        "width": scene.width,
        "height": scene.height,
        "background": scene.background,
        "has_alpha": scene.alpha is not None,
        "alpha_mode": scene.alpha_mode,
        "has_masks": scene.masks is not None,
        "has_normals": bool(scene.normals),
        "n_normals": len(scene.normals),
        "has_distortion": cams.distortion is not None,
        "fov_x_deg": round(float(torch.rad2deg(fov_x).median()), 3),
        "roi": {"center": center, "radius": round(float(scene.scene_radius), 6), "method": scene.roi_method,
                "found_from": describe_roi_method(scene.roi_method)},
        "roi_method": scene.roi_method,
        "scene_radius": round(float(scene.scene_radius), 6),
        "scene_center": center,
        "to_world": np.round(scene.to_world, 6).tolist(),
        "camera_distance": [round(float(dist.min()), 4), round(float(dist.max()), 4)],
        "mean_coverage": None if coverage is None else round(float(coverage.float().mean() / 255.0), 4),
        "warnings": warnings,
    }
    if picture is not None:
        draw_scene(scene, Path(picture))
        out["picture"] = str(picture)
    out["seconds"] = round(time.perf_counter() - t0, 2)
    return out


def roi_line(report: dict[str, Any]) -> str:
    """One human line: the sphere used, in the dataset's frame, and how it was found."""
    roi = report["roi"]
    c = ", ".join(f"{v:.4g}" for v in roi["center"])
    return f"region of interest: centre ({c}), radius {roi['radius']:.4g} (dataset frame), from {roi['found_from']}"


def draw_scene(scene: Scene, path: Path) -> None:
    """Top and side views of the cameras around the region of interest (red circle), in the normalised frame turned
    so that the cameras' up is +z; the sparse points of ``sparse_pc.ply`` (process-data) when the dataset has it."""
    from anisdf.data.process.export import draw_cameras, up_rotation

    c2w = np.tile(np.eye(4), (scene.n_images, 1, 1))
    c2w[:, :3, :4] = scene.cameras.c2w.double().numpy()
    rot = np.eye(4)
    rot[:3, :3] = up_rotation(c2w)
    c2w = rot[None] @ c2w
    points, colors = np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
    ply = scene.root / "sparse_pc.ply"
    if scene.format == "instant-ngp" and ply.is_file():
        import trimesh

        cloud = trimesh.load(ply, process=False)
        points = scene.to_normalised_frame(np.asarray(cloud.vertices, np.float64)) @ rot[:3, :3].T
        colors = np.asarray(cloud.colors, np.uint8)[:, :3] if len(getattr(cloud, "colors", [])) else np.full(
            (len(points), 3), 90, np.uint8)
    intr = torch.stack([scene.cameras.fx, scene.cameras.fy, scene.cameras.cx, scene.cameras.cy], -1).double().numpy()
    c = ", ".join(f"{v:.4g}" for v in scene.center)
    title = (f"{scene.n_images} cameras; region of interest (red): centre ({c}), radius {scene.scene_radius:.4g} "
             f"(dataset frame), from {describe_roi_method(scene.roi_method)}")
    path.parent.mkdir(parents=True, exist_ok=True)
    draw_cameras(path, c2w, intr, scene.width, scene.height, points, colors, 1.0, title)
