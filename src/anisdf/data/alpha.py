"""How an RGBA image's colour relates to its alpha, and the conversion to the one convention the rest of anisdf uses.

*Straight* colour (Blender's NeRF-synthetic PNGs, the project's own synthetic scenes) is the colour of whatever
covers the pixel; compositing on a background ``bg`` is ``a c + (1 - a) bg``, which is also what volume rendering
produces (Eq. 1 with the background behind the last sample). Path tracers that filter coverage and radiance together
(Mitsuba 3 writing an sRGB PNG, as the bundled ``bunny_plastic`` and ``spot_texture``) store colour *premultiplied in
linear light*: ``rgb = srgb(a * c_linear)``. Read as straight colour, such an image's silhouette pixels are darker
than any colour times coverage can make them, so a model has to darken its rims where it cannot (the rim's colour
does not change with the background it must match), and the test images on white hold dark outlines no render
reproduces. :func:`unpremultiply` turns them into straight colour, ``c = srgb(linear(rgb) / a)``; :func:`detect`
tells the two apart by how the partly covered pixels' colour grows with their coverage.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

import numpy as np

AlphaMode = Literal["straight", "premultiplied"]
ALPHA_MODES = ("auto", "straight", "premultiplied")

_PARTIAL = (8, 247)  # alpha values (of 255) that count as partly covered: away from 8-bit rounding at 0 and 255
_MIN_PIXELS = 100  # fewer partly covered pixels than this: nothing to tell the conventions apart by
_DARK = 1e-3  # linear luminance below which a pixel counts as black


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    """The sRGB transfer function's inverse (IEC 61966-2-1), ``x`` in [0, 1]."""
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    """The sRGB transfer function, ``x`` in [0, 1]."""
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.maximum(x, 0.0) ** (1.0 / 2.4) - 0.055)


def unpremultiply(rgb: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Straight colour of uint8 ``rgb`` [H, W, 3] premultiplied in linear light by uint8 ``alpha`` [H, W]:
    ``srgb(linear(rgb) / a)``, uint8; 0 where ``a`` is 0 (no colour is covered there)."""
    a = alpha.astype(np.float64)[..., None] / 255.0
    lin = srgb_to_linear(rgb.astype(np.float64) / 255.0)
    straight = linear_to_srgb(np.clip(lin / np.maximum(a, 1e-12), 0.0, 1.0))
    return np.where(a > 0, np.round(straight * 255.0), 0).astype(np.uint8)


def detect(samples: Sequence[tuple[np.ndarray, np.ndarray]]) -> tuple[AlphaMode, str]:
    """The convention of uint8 ``(rgb [H, W, 3], alpha [H, W])`` images of one dataset, and the evidence in words.

    Over the partly covered pixels, the slope of log(linear luminance) against log(alpha): premultiplied colour
    grows in proportion to the coverage (slope near 1; 1.02 and 1.06 for the bundled Mitsuba renders), straight colour
    does not change with it (near 0: 0.02 for ``bunny_plastic`` made straight, 0.04 for the synthetic test scene,
    whose rims are shaded darker). Premultiplied above 0.5; straight below, and when too few pixels are partly
    covered to tell."""
    lum, cov = [], []
    for rgb, alpha in samples:
        part = (alpha >= _PARTIAL[0]) & (alpha <= _PARTIAL[1])
        lum.append(srgb_to_linear(rgb[part].astype(np.float64) / 255.0).mean(-1))
        cov.append(alpha[part].astype(np.float64) / 255.0)
    y, x = np.concatenate(lum), np.concatenate(cov)
    lit = y > _DARK  # log of black is no evidence
    if lit.sum() < _MIN_PIXELS:
        return "straight", (f"{int(lit.sum())} partly covered pixels that are not black (fewer than {_MIN_PIXELS}): "
                            "straight colour assumed")
    lx, ly = np.log(x[lit]), np.log(y[lit])
    slope = float(np.cov(lx, ly)[0, 1] / max(float(np.var(lx, ddof=1)), 1e-12))
    mode: AlphaMode = "premultiplied" if slope > 0.5 else "straight"
    return mode, f"colour ~ alpha^{slope:.2f} over {int(lit.sum())} partly covered pixels"
