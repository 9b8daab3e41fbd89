"""Decoding and resizing of images, masks and normal maps (PIL), with a thread pool for whole datasets."""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TypeVar

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image, UnidentifiedImageError

from anisdf.data.alpha import unpremultiply
from anisdf.errors import DataError

T = TypeVar("T")
DECODE_ERRORS = (OSError, UnidentifiedImageError, SyntaxError, ValueError, Image.DecompressionBombError)


def target_size(width: int, height: int, downscale: float) -> tuple[int, int]:
    """(W', H') of an image of size (width, height) divided by ``downscale`` (rounded, at least 1)."""
    return max(1, round(width / downscale)), max(1, round(height / downscale))


def capped_downscale(width: int, height: int, downscale: float, min_size: int) -> float:
    """``downscale`` lowered (not below 1) so that the longer side keeps at least ``min_size`` pixels (0: as is)."""
    if min_size <= 0 or downscale <= 1.0:
        return downscale
    return max(1.0, min(downscale, max(width, height) / min_size))


def _open(path: Path) -> Image.Image:
    if not path.is_file():
        raise DataError(path, "image file is missing")
    try:
        im = Image.open(path)
        im.load()
    except DECODE_ERRORS as exc:
        raise DataError(path, f"cannot decode image ({exc})") from None
    return im


def _to_8bit(im: Image.Image) -> Image.Image:
    """Bring 16-bit / float single-channel images to 8-bit "L"."""
    if im.mode in ("I", "I;16", "I;16B", "I;16L", "F"):
        a = np.asarray(im, dtype=np.float64)
        if im.mode == "F":  # assume 0..1
            scale = 255.0
        else:  # 16-bit data, or small integers stored in a 32-bit image
            scale = 255.0 / 65535.0 if a.max() > 255 else 1.0
        return Image.fromarray(np.clip(a * scale + 0.5, 0, 255).astype(np.uint8), "L")
    return im


def _resize(im: Image.Image, size: tuple[int, int]) -> Image.Image:
    if im.size == size:
        return im
    shrink = size[0] <= im.size[0] and size[1] <= im.size[1]
    # BOX = area average when shrinking (antialiased; Pillow premultiplies RGBA itself).
    return im.resize(size, Image.Resampling.BOX if shrink else Image.Resampling.BICUBIC)


def read_rgb(path: Path, downscale: float = 1.0, premultiplied: bool = False
             ) -> tuple[np.ndarray, np.ndarray | None, tuple[int, int]]:
    """Decode an image: uint8 RGB ``[H',W',3]``, uint8 alpha ``[H',W']`` (None without alpha), and the
    size ``(W, H)`` on disk. ``premultiplied``: an RGBA image's colour is premultiplied in linear light and is
    returned straight (:func:`anisdf.data.alpha.unpremultiply`, before any resize)."""
    with _open(path) as im:
        native = im.size
        im2 = _to_8bit(im)
        if im2.mode == "P":
            im2 = im2.convert("RGBA" if "transparency" in im2.info else "RGB")
        if im2.mode == "LA":
            im2 = im2.convert("RGBA")
        if im2.mode not in ("RGB", "RGBA"):
            im2 = im2.convert("RGB")
        if premultiplied and im2.mode == "RGBA":
            rgba = np.array(im2)
            rgba[..., :3] = unpremultiply(rgba[..., :3], rgba[..., 3])
            im2 = Image.fromarray(rgba, "RGBA")
        im2 = _resize(im2, target_size(*native, downscale))
        arr = np.asarray(im2)
    if arr.shape[-1] == 4:
        return np.ascontiguousarray(arr[..., :3]), np.ascontiguousarray(arr[..., 3]), native
    return arr, None, native


def read_mask(path: Path, downscale: float = 1.0) -> tuple[np.ndarray, tuple[int, int]]:
    """Decode an object mask (any mode; the brightest colour channel counts): uint8 0/255 ``[H',W']``."""
    with _open(path) as im:
        native = im.size
        im2 = _to_8bit(im)
        if im2.mode not in ("L", "1"):
            im2 = Image.fromarray(np.asarray(im2.convert("RGB")).max(axis=-1), "L")
        elif im2.mode == "1":
            im2 = im2.convert("L")
        im2 = _resize(im2, target_size(*native, downscale))
        arr = np.asarray(im2)
    return np.where(arr >= 128, 255, 0).astype(np.uint8), native


def _decode_normal(path: Path, size: tuple[int, int] | None,
                   downscale: float) -> tuple[torch.Tensor, torch.Tensor, tuple[int, int], bool]:
    """xyz = 2 RGB - 1 and alpha of a normal map at ``size`` (else the size on disk / ``downscale``), the size on
    disk, and whether it was resized (then xyz is coverage-weighted: the mean of xyz x alpha)."""
    with _open(path) as im:
        native = im.size
        arr = np.asarray(im.convert("RGBA"), dtype=np.float32) / 255.0
    n = torch.from_numpy(arr[..., :3] * 2.0 - 1.0)
    a = torch.from_numpy(arr[..., 3:4].copy())
    w2, h2 = size or target_size(*native, downscale)
    if (w2, h2) == native:
        return n, a, native, False
    stacked = torch.cat([n * a, a], dim=-1).permute(2, 0, 1)[None]
    mode = "area" if w2 <= native[0] and h2 <= native[1] else "bilinear"
    stacked = F.interpolate(stacked, size=(h2, w2), mode=mode)[0].permute(1, 2, 0)
    return stacked[..., :3], stacked[..., 3:4], native, True


def read_normal(path: Path, downscale: float = 1.0) -> tuple[np.ndarray, tuple[int, int]]:
    """Decode a normal map stored as ``(n + 1) / 2`` in RGB with alpha = coverage: float32 ``[H',W',4]``
    (unit normal xyz, zero where uncovered; coverage in 0..1), resized coverage-weighted."""
    n, a, native, _ = _decode_normal(path, None, downscale)
    norm = n.norm(dim=-1, keepdim=True)
    n = torch.where((a > 0) & (norm > 1e-6), n / norm.clamp_min(1e-6), torch.zeros_like(n))
    return torch.cat([n, a], dim=-1).numpy().astype(np.float32), native


def read_normal_raw(path: Path, size: tuple[int, int] | None = None) -> np.ndarray:
    """A normal map decoded as :func:`read_normal` does but not renormalised: float32 ``[H',W',4]``, xyz = 2 RGB - 1
    as stored (coverage-weighted mean when resized to ``size`` = (W', H'); None: as on disk) and coverage in 0..1.
    Vectors far from unit length mean the file holds another encoding than ``(n + 1) / 2``."""
    n, a, _, resized = _decode_normal(path, size, 1.0)
    if resized:
        n = torch.where(a > 0, n / a.clamp_min(1e-6), torch.zeros_like(n))
    return torch.cat([n, a], dim=-1).numpy().astype(np.float32)


def parallel_map(fn: Callable[[Path], T], paths: Sequence[Path], workers: int | None = None) -> list[T]:
    """``[fn(p) for p in paths]`` on a thread pool (PIL releases the GIL while decoding); the first
    exception, in input order, is raised."""
    if workers is None:
        workers = min(8, max(2, 2 * (os.cpu_count() or 1)))
    if len(paths) <= 1 or workers <= 1:
        return [fn(p) for p in paths]
    with ThreadPoolExecutor(max_workers=workers) as pool:
        return list(pool.map(fn, paths))
