"""instant-ngp / nerfstudio ``transforms.json``.

Intrinsics ``fl_x, fl_y, cx, cy, w, h`` and distortion ``k1, k2, p1, p2`` may be shared (top level) or given
per frame; ``camera_angle_x`` (and ``camera_angle_y``) stand in for missing focal lengths. ``cx, cy`` follow
COLMAP's convention (pixel centres at ``i + 0.5``), which is anisdf's. ``transform_matrix`` is an OpenGL
camera-to-world matrix. nerfstudio's ``applied_transform`` is already baked into the frames and is
ignored, as are instant-ngp's ``aabb_scale``/``scale``/``offset`` (anisdf finds its own region of
interest). anisdf's own ``bounding_sphere`` (``{"center": [x, y, z], "radius": r, "method": m}``, written by
``anisdf process-data``) is the region of interest when present. Frames are sorted by ``file_path``; the test
split holds out every 8th frame. Optional per-frame ``mask_path`` entries (nerfstudio) give object masks.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from anisdf.data.dataparsers._common import (
    GL_TO_CV,
    ParsedScene,
    as_float,
    check_camera,
    check_pose,
    holdout_splits,
    image_size,
    read_json,
    require,
)
from anisdf.data.dataparsers.blender import resolve_image
from anisdf.errors import DataError

SUPPORTED_MODELS = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL")


def parse(root: Path) -> ParsedScene:
    path = root / "transforms.json"
    meta = read_json(path)
    frames = require(meta, "frames", path)
    if not isinstance(frames, list) or not frames:
        raise DataError(path, "'frames' must be a non-empty list")
    for i, frame in enumerate(frames):
        if not isinstance(frame, dict):
            raise DataError(path, f"frame {i} is not an object")
        require(frame, "file_path", path, f"frame {i}")
    order = sorted(range(len(frames)), key=lambda i: str(frames[i]["file_path"]))
    warnings: list[str] = []
    image_paths: list[Path] = []
    poses, intr, dist = [], [], []
    size: tuple[int, int] | None = None
    ignored: set[str] = set()
    for i in order:
        frame = frames[i]
        where = f"frame {i}"

        def get(key: str, frame: dict = frame, where: str = where) -> float | None:
            v = frame.get(key, meta.get(key))
            return None if v is None else as_float(v, path, f"{where}: '{key}'")

        model = str(frame.get("camera_model", meta.get("camera_model", "OPENCV"))).upper()
        if model not in SUPPORTED_MODELS or frame.get("is_fisheye", meta.get("is_fisheye", False)):
            raise DataError(path, f"{where}: camera model {model!r} is not supported (pinhole/OpenCV only)")
        img = resolve_image(root, str(frame["file_path"]))
        w, h = get("w"), get("h")
        if w is None or h is None:
            w_img, h_img = image_size(img)
            w = float(w_img) if w is None else w
            h = float(h_img) if h is None else h
        if size is None:
            size = (int(round(w)), int(round(h)))
        elif (int(round(w)), int(round(h))) != size:
            raise DataError(path, f"{where}: w, h = {w:g}, {h:g} differ from the first frame's {size}")
        fx, fy = get("fl_x"), get("fl_y")
        if fx is None:
            angle = get("camera_angle_x")
            if angle is None:
                raise DataError(path, f"{where}: missing key 'fl_x' (or 'camera_angle_x')")
            if not 0.0 < angle < math.pi:
                raise DataError(path, f"{where}: 'camera_angle_x' = {angle:g} is not an angle in (0, pi)")
            fx = 0.5 * w / math.tan(0.5 * angle)
        if fy is None:
            angle_y = get("camera_angle_y")
            if angle_y is not None and not 0.0 < angle_y < math.pi:
                raise DataError(path, f"{where}: 'camera_angle_y' = {angle_y:g} is not an angle in (0, pi)")
            fy = 0.5 * h / math.tan(0.5 * angle_y) if angle_y is not None else fx
        cx, cy = get("cx"), get("cy")
        intr.append([fx, fy, w / 2.0 if cx is None else cx, h / 2.0 if cy is None else cy])
        dist.append([get(k) or 0.0 for k in ("k1", "k2", "p1", "p2")])
        check_camera(intr[-1], (w, h), path, f"{where} ({img.name})", dist[-1])
        ignored.update(k for k in ("k3", "k4") if get(k))
        c2w = check_pose(require(frame, "transform_matrix", path, where), path, f"{where} ({img.name})")
        poses.append(c2w @ GL_TO_CV)
        image_paths.append(img)
    if ignored:
        warnings.append(f"{path.name}: distortion terms {sorted(ignored)} are not supported and were ignored")
    distortion = np.asarray(dist, dtype=np.float64)
    mask_paths = None
    with_masks = [frames[i].get("mask_path") for i in order]
    if all(m is not None for m in with_masks):
        mask_paths = [resolve_image(root, str(m)) for m in with_masks]
    elif any(m is not None for m in with_masks):
        warnings.append(f"{path.name}: only some frames have 'mask_path'; masks ignored")
    to_world, roi_method = _bounding_sphere(meta, path)
    return ParsedScene(
        format="instant-ngp",
        root=root,
        image_paths=image_paths,
        c2w=np.stack(poses),
        intrinsics=np.asarray(intr, dtype=np.float64),
        size=size,
        splits=holdout_splits(len(image_paths)),
        distortion=distortion if np.any(distortion != 0) else None,
        mask_paths=mask_paths,
        to_world=to_world,
        roi_method=roi_method,
        warnings=warnings,
    )


def _bounding_sphere(meta: dict, path: Path) -> tuple[np.ndarray | None, str]:
    """The similarity mapping the unit sphere onto ``bounding_sphere`` (and its method), or (None, "")."""
    sphere = meta.get("bounding_sphere")
    if sphere is None:
        return None, "bounding-sphere"
    if not isinstance(sphere, dict):
        raise DataError(path, "'bounding_sphere' must be an object with 'center' and 'radius'")
    center = require(sphere, "center", path, "bounding_sphere")
    if not isinstance(center, list) or len(center) != 3:
        raise DataError(path, f"bounding_sphere: 'center' must be a list of 3 numbers, got {center!r}")
    radius = as_float(require(sphere, "radius", path, "bounding_sphere"), path, "bounding_sphere: 'radius'")
    if radius <= 0:
        raise DataError(path, f"bounding_sphere: 'radius' must be positive, got {radius:g}")
    m = np.eye(4)
    m[:3, :3] *= radius
    m[:3, 3] = [as_float(v, path, "bounding_sphere: 'center'") for v in center]
    return m, str(sphere.get("method", "bounding-sphere"))
