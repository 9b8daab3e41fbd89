"""NeRF-synthetic / Shiny Blender / Shelly: ``transforms_{train,val,test}.json`` with RGBA images.

Each file holds ``camera_angle_x`` (horizontal field of view, radians) and ``frames`` with ``file_path``
(with or without extension, relative to the dataset folder) and ``transform_matrix`` (camera-to-world in
the OpenGL/Blender camera convention, converted here to OpenCV). Reference normal maps beside test (and val)
images are picked up under the names the public datasets use (:data:`NORMAL_SUFFIXES`): Shiny Blender's
``r_i_normal.png`` and the original NeRF-synthetic test split's ``r_i_normal_0001.png``. Both are meant to hold
Blender world-space normals as ``(n + 1) / 2`` in RGB; the released ``_0001`` maps are saturated instead, so eval
checks every map before scoring it (docs/evaluation.md, "Normals").
"""

from __future__ import annotations

import math
import os
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
from anisdf.errors import DataError

SPLITS = ("train", "val", "test")
NORMAL_SUFFIXES = ("_normal.png", "_normal_0001.png")
"""Reference normal map names, ``<image stem><suffix>``, in order of preference: Shiny Blender (Ref-NeRF) writes
``r_i_normal.png``; NeRF-synthetic's test split has ``r_i_normal_0001.png`` (a Blender File Output node adds the frame
number)."""


def find_normal_map(image: Path) -> Path | None:
    """The reference normal map beside ``image`` (first of :data:`NORMAL_SUFFIXES` that exists), or None."""
    for suffix in NORMAL_SUFFIXES:
        n = image.with_name(image.stem + suffix)
        if n.is_file():
            return n
    return None


def resolve_image(root: Path, file_path: str) -> Path:
    """``file_path`` relative to ``root``; ``.png`` is appended when the name has no usable extension."""
    p = Path(os.path.normpath(root / file_path))
    if p.is_file():
        return p
    for ext in (".png", ".jpg", ".jpeg"):
        q = p.with_name(p.name + ext)
        if q.is_file():
            return q
    return p if p.suffix.lower() in (".png", ".jpg", ".jpeg") else p.with_name(p.name + ".png")


def parse(root: Path) -> ParsedScene:
    files = {s: root / f"transforms_{s}.json" for s in SPLITS if (root / f"transforms_{s}.json").is_file()}
    if "train" not in files:
        raise DataError(root / "transforms_train.json", "file is missing")
    image_paths: list[Path] = []
    poses: list[np.ndarray] = []
    intr: list[list[float]] = []
    splits: dict[str, list[int]] = {}
    size: tuple[int, int] | None = None
    for split, path in files.items():
        meta = read_json(path)
        frames = require(meta, "frames", path)
        if not isinstance(frames, list) or not frames:
            raise DataError(path, "'frames' must be a non-empty list")
        splits[split] = []
        for i, frame in enumerate(frames):
            where = f"frame {i}"
            if not isinstance(frame, dict):
                raise DataError(path, f"{where} is not an object")
            img = resolve_image(root, str(require(frame, "file_path", path, where)))
            if size is None:
                size = image_size(img)
            w, h = size
            c2w = check_pose(require(frame, "transform_matrix", path, where), path, f"{where} ({img.name})")
            fx, fy, cx, cy = _intrinsics(meta, frame, w, h, path, where)
            check_camera((fx, fy, cx, cy), (w, h), path, f"{where} ({img.name})")
            splits[split].append(len(image_paths))
            image_paths.append(img)
            poses.append(c2w @ GL_TO_CV)
            intr.append([fx, fy, cx, cy])
    warnings: list[str] = []
    if "test" not in splits:
        held = holdout_splits(len(splits["train"]))
        train = splits["train"]
        splits["test"] = [train[i] for i in held["test"]]
        splits["train"] = [train[i] for i in held["train"]]
        warnings.append("no transforms_test.json: holding out every 8th training image as the test split")
    normal_paths: dict[int, Path] = {}
    for split in ("val", "test"):
        for idx in splits.get(split, []):
            n = find_normal_map(image_paths[idx])
            if n is not None:
                normal_paths[idx] = n
    return ParsedScene(
        format="nerf-synthetic",
        root=root,
        image_paths=image_paths,
        c2w=np.stack(poses),
        intrinsics=np.asarray(intr, dtype=np.float64),
        size=size,
        splits={k: v for k, v in splits.items() if k in ("train", "test") or v},
        normal_paths=normal_paths,
        warnings=warnings,
    )


def _intrinsics(meta: dict, frame: dict, w: int, h: int, path: Path, where: str) -> tuple[float, ...]:
    """fx, fy, cx, cy from ``fl_x``/``fl_y``/``cx``/``cy`` when given, else from ``camera_angle_x``."""

    def get(key: str) -> float | None:
        v = frame.get(key, meta.get(key))
        return None if v is None else as_float(v, path, f"{where}: '{key}'")

    fx = get("fl_x")
    if fx is None:
        angle = get("camera_angle_x")
        if angle is None:
            raise DataError(path, "missing key 'camera_angle_x'")
        if not 0.0 < angle < math.pi:
            raise DataError(path, f"'camera_angle_x' = {angle} is not an angle in (0, pi)")
        fx = 0.5 * w / math.tan(0.5 * angle)
    fy = get("fl_y")
    if fy is None:
        angle_y = get("camera_angle_y")
        fy = 0.5 * h / math.tan(0.5 * angle_y) if angle_y is not None and 0.0 < angle_y < math.pi else fx
    cx = get("cx")
    cy = get("cy")
    return fx, fy, w / 2.0 if cx is None else cx, h / 2.0 if cy is None else cy
