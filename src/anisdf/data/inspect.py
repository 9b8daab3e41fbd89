"""``anisdf inspect DATA``: validate a whole dataset and summarise it as a JSON-able dict."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from anisdf.data.dataparsers import load_scene


def inspect_dataset(path: str | Path) -> dict[str, Any]:
    """Load every image, mask and normal map of the dataset at ``path`` and check it.

    Loading already raises :class:`~anisdf.errors.DataError` for undecodable images, non-finite or
    non-rotation poses, masks that do not match the images and malformed metadata; this adds checks
    that only warn (empty masks, cameras inside the region of interest, tiny images).
    """
    t0 = time.perf_counter()
    scene = load_scene(path)
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
        "has_masks": scene.masks is not None,
        "has_normals": bool(scene.normals),
        "n_normals": len(scene.normals),
        "has_distortion": cams.distortion is not None,
        "fov_x_deg": round(float(torch.rad2deg(fov_x).median()), 3),
        "roi_method": scene.roi_method,
        "scene_radius": round(float(scene.scene_radius), 6),
        "scene_center": [round(float(v), 6) for v in scene.center],
        "to_world": np.round(scene.to_world, 6).tolist(),
        "camera_distance": [round(float(dist.min()), 4), round(float(dist.max()), 4)],
        "mean_coverage": None if coverage is None else round(float(coverage.float().mean() / 255.0), 4),
        "warnings": warnings,
        "seconds": round(time.perf_counter() - t0, 2),
    }
    return out
