"""Pictures: normal, depth and scalar maps as uint8 images, labelled side-by-side panels, atomic saving.

Inputs may be numpy arrays or torch tensors (any device); outputs are numpy uint8 arrays.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Literal, TypeVar

import numpy as np
import torch
from PIL import Image, ImageDraw, ImageFont

from anisdf.utils.atomic import atomic_path

ArrayLike = np.ndarray | torch.Tensor
A = TypeVar("A", torch.Tensor, np.ndarray)


def composite(rgb: A, alpha: A, background: A | float) -> A:
    """``rgb * alpha + background * (1 - alpha)``: an object's colour over a background (alpha in [0, 1]).

    The one compositing route: training targets (:class:`anisdf.data.rays.RayDataset`, random or white
    backgrounds), RGBA images shown or saved (this module) and RGBA references in metrics.
    Works on tensors and arrays alike; ``alpha`` broadcasts over the colour channels ([..., 1]).
    """
    return rgb * alpha + background * (1.0 - alpha)


# viridis (matplotlib, CC0) sampled at t = 0, 0.1, ..., 1; linear interpolation in between
_VIRIDIS = np.array(
    [
        [0.267004, 0.004874, 0.329415],
        [0.282623, 0.140926, 0.457517],
        [0.253935, 0.265254, 0.529983],
        [0.206756, 0.371758, 0.553117],
        [0.163625, 0.471133, 0.558148],
        [0.127568, 0.566949, 0.550556],
        [0.134692, 0.658636, 0.517649],
        [0.266941, 0.748751, 0.440573],
        [0.477504, 0.821444, 0.318195],
        [0.741388, 0.873449, 0.149561],
        [0.993248, 0.906157, 0.143936],
    ]
)


def _np(x: ArrayLike) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().numpy()
    return np.asarray(x)


def _mask_np(mask: ArrayLike | None, shape: tuple[int, ...]) -> np.ndarray | None:
    if mask is None:
        return None
    m = _np(mask)
    if m.ndim == 3 and m.shape[-1] == 1:
        m = m[..., 0]
    if m.shape != shape:
        raise ValueError(f"mask shape {m.shape} does not match image shape {shape}")
    return m > 0.5 if np.issubdtype(m.dtype, np.floating) else m.astype(bool)


def to_uint8(img: ArrayLike) -> np.ndarray:
    """Float image in [0, 1] -> uint8 (clipped, rounded, NaN -> 0); uint8 input is returned unchanged."""
    a = _np(img)
    if a.dtype == np.uint8:
        return a
    if a.dtype == np.bool_:
        return a.astype(np.uint8) * 255
    a = np.nan_to_num(a.astype(np.float32), nan=0.0)
    return np.round(np.clip(a, 0.0, 1.0) * 255.0).astype(np.uint8)


def colormap(t: ArrayLike, name: Literal["viridis", "gray"] = "viridis") -> np.ndarray:
    """Map values in [0, 1] (clipped) to float RGB [..., 3] with the viridis lookup table or gray."""
    a = np.clip(np.nan_to_num(_np(t).astype(np.float64)), 0.0, 1.0)
    if name == "gray":
        return np.repeat(a[..., None], 3, axis=-1)
    if name != "viridis":
        raise ValueError(f"unknown colormap {name!r}")
    x = a * (len(_VIRIDIS) - 1)
    i0 = np.clip(np.floor(x).astype(np.int64), 0, len(_VIRIDIS) - 2)
    f = (x - i0)[..., None]
    return _VIRIDIS[i0] * (1.0 - f) + _VIRIDIS[i0 + 1] * f


def normal_to_image(n: ArrayLike, mask: ArrayLike | None = None, background: float = 1.0) -> np.ndarray:
    """Normal map [H, W, 3] in [-1, 1] -> uint8 RGB ``(n + 1) / 2``; ``background`` outside ``mask``."""
    a = _np(n).astype(np.float32)[..., :3]
    img = (a + 1.0) * 0.5
    m = _mask_np(mask, a.shape[:2])
    if m is not None:
        img[~m] = background
    return to_uint8(img)


def depth_to_image(
    depth: ArrayLike,
    mask: ArrayLike | None = None,
    near: float | None = None,
    far: float | None = None,
    background: float = 1.0,
) -> np.ndarray:
    """Depth map [H, W] (or [H, W, 1]) -> uint8 RGB with viridis: near is bright (yellow), far is dark.

    The range [near, far] defaults to the 1st and 99th percentiles of the depths inside ``mask``
    (all finite pixels without a mask). Pixels outside the mask or not finite get ``background``.
    """
    d = _np(depth).astype(np.float64)
    if d.ndim == 3 and d.shape[-1] == 1:
        d = d[..., 0]
    valid = np.isfinite(d)
    m = _mask_np(mask, d.shape)
    if m is not None:
        valid &= m
    vals = d[valid]
    if near is None:
        near = float(np.percentile(vals, 1)) if vals.size else 0.0
    if far is None:
        far = float(np.percentile(vals, 99)) if vals.size else 1.0
    t = (d - near) / max(far - near, 1e-12)
    rgb = colormap(1.0 - np.where(valid, t, 0.0))
    rgb[~valid] = background
    return to_uint8(rgb)


def scalar_to_image(
    x: ArrayLike,
    mask: ArrayLike | None = None,
    cmap: Literal["viridis", "gray"] = "viridis",
    background: float = 1.0,
) -> np.ndarray:
    """Scalar field in [0, 1] [H, W] (e.g. the blend weight w or the opacity) -> uint8 RGB."""
    a = _np(x).astype(np.float64)
    if a.ndim == 3 and a.shape[-1] == 1:
        a = a[..., 0]
    rgb = colormap(a, cmap)
    m = _mask_np(mask, a.shape)
    if m is not None:
        rgb[~m] = background
    return to_uint8(rgb)


def to_rgb_uint8(img: ArrayLike) -> np.ndarray:
    """Any image (HxW, HxWx1/3/4, uint8 or float) -> uint8 HxWx3; RGBA is composited on white."""
    a = to_uint8(img)
    if a.ndim == 2:
        a = np.repeat(a[..., None], 3, axis=-1)
    if a.shape[-1] == 1:
        a = np.repeat(a, 3, axis=-1)
    if a.shape[-1] == 4:  # composite on white
        alpha = a[..., 3:4].astype(np.float32) / 255.0
        a = np.round(composite(a[..., :3], alpha, 255.0)).astype(np.uint8)
    return a


def save_image(path: str | Path, array: ArrayLike) -> Path:
    """Save an image (uint8, or float in [0, 1]; HxW, HxWx3 or HxWx4) atomically; format from the suffix."""
    path = Path(path)
    a = to_uint8(array)
    if a.ndim == 3 and a.shape[-1] == 1:
        a = a[..., 0]
    img = Image.fromarray(a)
    fmt = Image.registered_extensions().get(path.suffix.lower())
    if fmt is None:
        raise ValueError(f"{path}: unknown image format {path.suffix!r}")
    with atomic_path(path) as tmp:
        img.save(tmp, format=fmt)
    return path


def hstack_labeled(
    images: Sequence[ArrayLike], labels: Sequence[str] | None = None, gap: int = 4, label_height: int = 16,
    min_width: int = 128,
) -> np.ndarray:
    """Panels side by side (uint8 RGB) with a white strip holding each panel's label above it.

    Images may differ in size (shorter ones are padded with white at the bottom); grayscale images are
    repeated to RGB, RGBA ones composited on white. Panels narrower than ``min_width`` are enlarged by a whole
    factor (nearest pixel), so that small validation renders stay legible and their labels do not overlap.
    """
    if not images:
        raise ValueError("hstack_labeled needs at least one image")
    labels = list(labels) if labels is not None else [""] * len(images)
    if len(labels) != len(images):
        raise ValueError(f"{len(images)} images but {len(labels)} labels")
    panels = [to_rgb_uint8(im) for im in images]
    factor = max(1, -(-min_width // max(p.shape[1] for p in panels)))
    if factor > 1:
        panels = [p.repeat(factor, axis=0).repeat(factor, axis=1) for p in panels]
    top = label_height if any(labels) else 0
    h = max(p.shape[0] for p in panels) + top
    w = sum(p.shape[1] for p in panels) + gap * (len(panels) - 1)
    canvas = np.full((h, w, 3), 255, dtype=np.uint8)
    x = 0
    xs = []
    for p in panels:
        canvas[top : top + p.shape[0], x : x + p.shape[1]] = p
        xs.append(x)
        x += p.shape[1] + gap
    if top:
        pil = Image.fromarray(canvas)
        draw = ImageDraw.Draw(pil)
        font = ImageFont.load_default()
        for x0, label in zip(xs, labels, strict=True):
            draw.text((x0 + 2, 1), label, fill=(0, 0, 0), font=font)
        canvas = np.asarray(pil).copy()
    return canvas
