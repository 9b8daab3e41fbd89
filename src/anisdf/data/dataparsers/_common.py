"""What every parser returns, and the small checks they share."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image, UnidentifiedImageError

from anisdf.errors import DataError

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")
ROTATION_TOL = 1e-2

# OpenGL / Blender camera axes (x right, y up, z backward) -> OpenCV (x right, y down, z forward).
GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass
class ParsedScene:
    """Metadata read by a parser, before images are decoded and the scene is normalised."""

    format: str
    root: Path
    image_paths: list[Path]
    c2w: np.ndarray
    """[N,4,4] float64 camera-to-world, OpenCV axes, in the dataset's frame."""
    intrinsics: np.ndarray
    """[N,4] fx, fy, cx, cy in pixels (pixel centres at i + 0.5) for images of size ``size``."""
    size: tuple[int, int] | None
    """(W, H) the intrinsics refer to; None means the size of the images on disk."""
    splits: dict[str, list[int]]
    distortion: np.ndarray | None = None
    mask_paths: list[Path] | None = None
    normal_paths: dict[int, Path] = field(default_factory=dict)
    to_world: np.ndarray | None = None
    """A known normalisation (NeuS scale_mat); None lets the loader find the region of interest."""
    roi_method: str = "scale_mat"
    """How ``to_world`` was found (reported by ``inspect``): scale_mat, or sparse-points (process-data)."""
    depth_hint: float | None = None
    """Typical distance from the cameras to the scene (LLFF bounds), for forward-facing captures."""
    warnings: list[str] = field(default_factory=list)


def read_json(path: Path) -> dict[str, Any]:
    """Parse a JSON file, naming the file (and line, column) on any problem."""
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise DataError(path, "file is missing") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise DataError(path, f"cannot read file ({exc})") from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise DataError(path, f"malformed JSON at line {exc.lineno}, column {exc.colno}: {exc.msg}") from None
    if not isinstance(data, dict):
        raise DataError(path, "expected a JSON object at the top level")
    return data


def require(mapping: dict[str, Any], key: str, path: Path, where: str = "") -> Any:
    """``mapping[key]`` or a DataError naming the file and the missing key."""
    if key not in mapping:
        raise DataError(path, f"missing key '{key}'{' in ' + where if where else ''}")
    return mapping[key]


def as_float(value: Any, path: Path, what: str) -> float:
    try:
        out = float(value)
    except (TypeError, ValueError):
        raise DataError(path, f"{what} is not a number: {value!r}") from None
    if not np.isfinite(out):
        raise DataError(path, f"{what} is not finite: {value!r}")
    return out


def check_camera(intrinsics: Any, size: Any | None, path: Path, where: str, distortion: Any = None) -> None:
    """Raise a DataError naming ``path`` and ``where`` unless the pinhole camera is usable: ``fx, fy`` finite and
    > 0, ``cx, cy`` finite, image size ``(W, H)`` > 0 and distortion ``(k1, k2, p1, p2)`` finite."""
    if size is not None:  # None: the size of the image on disk (checked when it is read)
        w, h = (float(v) for v in size)
        if not (np.isfinite(w) and np.isfinite(h) and w >= 1 and h >= 1):
            raise DataError(path, f"{where}: image size w, h = {w:g}, {h:g} must be positive")
    fx, fy, cx, cy = (float(v) for v in intrinsics)
    for name, value in (("focal length fx", fx), ("focal length fy", fy)):
        if not (np.isfinite(value) and value > 0):
            raise DataError(path, f"{where}: {name} = {value:g} must be positive and finite")
    if not (np.isfinite(cx) and np.isfinite(cy)):
        raise DataError(path, f"{where}: principal point cx, cy = {cx:g}, {cy:g} is not finite")
    if distortion is not None and not np.isfinite(np.asarray(distortion, dtype=np.float64)).all():
        raise DataError(path, f"{where}: distortion {list(distortion)} is not finite")


def check_pose(matrix: Any, path: Path, frame: str) -> np.ndarray:
    """Validate a camera-to-world matrix (3x4 or 4x4, finite, proper rotation) and return it as a 4x4
    float64 matrix with the rotation re-orthonormalised (SVD)."""
    try:
        m = np.asarray(matrix, dtype=np.float64)
    except (TypeError, ValueError):
        raise DataError(path, f"{frame}: pose is not a numeric matrix") from None
    if m.shape not in ((3, 4), (4, 4)):
        raise DataError(path, f"{frame}: pose has shape {m.shape}, expected 3x4 or 4x4")
    if not np.isfinite(m).all():
        raise DataError(path, f"{frame}: pose is not finite")
    rot = m[:3, :3]
    err = np.abs(rot.T @ rot - np.eye(3)).max()
    det = np.linalg.det(rot)
    if err > ROTATION_TOL or abs(det - 1.0) > ROTATION_TOL:
        raise DataError(path, f"{frame}: pose is not a rotation (|R^T R - I| = {err:.3g}, det = {det:.3g})")
    u, _, vt = np.linalg.svd(rot)
    out = np.eye(4)
    out[:3, :3] = u @ vt
    out[:3, 3] = m[:3, 3]
    return out


def list_images(folder: Path) -> list[Path]:
    """Image files directly inside ``folder``, sorted by name."""
    if not folder.is_dir():
        return []
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS)


def image_size(path: Path) -> tuple[int, int]:
    """(W, H) from the image header, without decoding the pixels."""
    if not path.is_file():
        raise DataError(path, "image file is missing")
    try:
        with Image.open(path) as im:
            return im.size
    except (OSError, UnidentifiedImageError, SyntaxError, ValueError) as exc:
        raise DataError(path, f"cannot read image ({exc})") from None


def holdout_splits(n: int, every: int = 8) -> dict[str, list[int]]:
    """LLFF-style deterministic hold-out: images 0, 8, 16, ... are the test split."""
    test = list(range(0, n, every)) if n > 1 else []
    train = [i for i in range(n) if i % every != 0] if n > 1 else list(range(n))
    return {"train": train, "test": test}


def match_masks(image_paths: list[Path], mask_dir: Path) -> list[Path]:
    """Mask files for ``image_paths`` in ``mask_dir``: by name (``a.png``, ``a.jpg.png``, ``a.jpg``), else
    by sorted order when the counts agree; DataError when they do not match."""
    masks = list_images(mask_dir)
    if not masks:
        raise DataError(mask_dir, "mask folder holds no images")
    by_name = {p.name: p for p in masks}
    by_stem: dict[str, Path] = {}
    for p in masks:
        by_stem.setdefault(p.stem, p)
    matched: list[Path] = []
    for img in image_paths:
        hit = by_name.get(img.name + ".png") or by_stem.get(img.stem) or by_name.get(img.name)
        if hit is None:
            break
        matched.append(hit)
    if len(matched) == len(image_paths) and len(set(matched)) == len(matched):
        return matched
    if len(masks) != len(image_paths):
        raise DataError(mask_dir, f"{len(masks)} masks for {len(image_paths)} images (counts must match)")
    return masks
