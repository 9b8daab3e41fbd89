"""The files of a baked asset (``anisdf export``) and how their bytes encode the shading model.

A folder holds ``model.glb`` (mesh in the dataset's frame: positions, unit vertex normals, UVs, and the diffuse
texture as its PBR base colour), ``specular_<k>_lobe.png`` and ``specular_<k>_rgb.png`` for each lobe ``k``,
``index.html`` (the viewer, with copies of those files embedded) and ``export.json`` (settings, sizes, timings).
All textures share the glb's UV atlas (UV (0, 0) is the corner of the first pixel of the first image row, as in glTF);
the lobe textures may be smaller than the diffuse texture, and each is looked up at its own size.

Texel bytes (8 bits, value / 255):

* diffuse (glb base colour): RGB colour ``D``;
* ``specular_<k>_lobe.png``: R, G the lobe axis ``mu_k`` in octahedral encoding (:func:`oct_encode`), B its
  sharpness, logarithmic: ``lambda = lo * (hi / lo) ** B`` with ``(lo, hi)`` = export.json's ``sharpness_range``;
* ``specular_<k>_rgb.png``: RGB amplitude ``a_k``.

A pixel's colour (the viewer's shader and :mod:`anisdf.export.reference_renderer` compute the same): with ``n`` the
normalised interpolated vertex normal, ``d`` the unit view direction and ``r = d - 2 (d . n) n``, it is ``D`` blended
bilinearly from the 4 diffuse texels around the pixel's UV, plus ``sum_k a_k exp(lambda_k (mu_k . r - 1))`` evaluated
at each of the 4 lobe texels around it and blended bilinearly (the shading is blended, not the lobe parameters),
clamped to [0, 1]. Texel ``(i, j)`` has its centre at UV ``((i + 0.5) / W, (j + 0.5) / H)``; lookups clamp to the
edge.
"""

from __future__ import annotations

import numpy as np

FORMAT = "anisdf-baked"
VERSION = 1
GLB = "model.glb"
MANIFEST = "export.json"
PAGE = "index.html"
MAX_LOBES = 8
"""Most lobes per texel an asset holds (``anisdf export --lobes``)."""


def lobe_png(k: int) -> str:
    return f"specular_{k}_lobe.png"


def rgb_png(k: int) -> str:
    return f"specular_{k}_rgb.png"


def oct_encode(n: np.ndarray) -> np.ndarray:
    """Unit vectors [..., 3] -> octahedral coordinates in [0, 1]^2 [..., 2]."""
    n = np.asarray(n, dtype=np.float64)
    p = n[..., :2] / np.abs(n).sum(-1, keepdims=True).clip(1e-12)
    folded = (1.0 - np.abs(p[..., ::-1])) * np.where(p >= 0.0, 1.0, -1.0)
    p = np.where(n[..., 2:3] < 0.0, folded, p)
    return p * 0.5 + 0.5


def oct_decode(e: np.ndarray) -> np.ndarray:
    """Octahedral coordinates in [0, 1]^2 [..., 2] -> unit vectors [..., 3] (float32, as the shader computes)."""
    f = np.asarray(e, dtype=np.float32) * np.float32(2.0) - np.float32(1.0)
    z = np.float32(1.0) - np.abs(f[..., 0]) - np.abs(f[..., 1])
    t = np.maximum(-z, np.float32(0.0))
    x = f[..., 0] + np.where(f[..., 0] >= 0.0, -t, t)
    y = f[..., 1] + np.where(f[..., 1] >= 0.0, -t, t)
    v = np.stack([x, y, z], -1)
    return v / np.linalg.norm(v, axis=-1, keepdims=True).clip(np.float32(1e-20))


def oct_bytes(n: np.ndarray) -> np.ndarray:
    """Unit vectors [..., 3] -> the 8-bit octahedral code [..., 2] whose decoded direction is nearest (of the 4 codes
    around the exact one: Cigolle et al. 2014's precise encoding)."""
    n = np.asarray(n, dtype=np.float64)
    e = oct_encode(n) * 255.0
    lo = np.floor(e)
    best = np.zeros(e.shape, np.uint8)
    best_dot = np.full(e.shape[:-1], -np.inf)
    for dx in (0.0, 1.0):
        for dy in (0.0, 1.0):
            code = np.clip(lo + np.array([dx, dy]), 0, 255)
            dot = (oct_decode(code / 255.0).astype(np.float64) * n).sum(-1)
            better = dot > best_dot
            best[better] = code[better].astype(np.uint8)
            best_dot = np.where(better, dot, best_dot)
    return best


def to_byte(x: np.ndarray) -> np.ndarray:
    """Values in [0, 1] -> uint8 (rounded, clipped)."""
    return np.round(np.clip(np.nan_to_num(np.asarray(x, dtype=np.float64)), 0.0, 1.0) * 255.0).astype(np.uint8)


def encode_sharpness(lam: np.ndarray, sharpness_range: tuple[float, float]) -> np.ndarray:
    lo, hi = sharpness_range
    return np.log(np.clip(lam, lo, hi) / lo) / np.log(hi / lo)


def decode_sharpness(b: np.ndarray, sharpness_range: tuple[float, float]) -> np.ndarray:
    """Stored [0, 1] values -> sharpness, in float32 as ``exp(log(lo) + b * log(hi / lo))`` (the shader's form)."""
    lo, hi = sharpness_range
    return np.exp(np.float32(np.log(lo)) + np.asarray(b, dtype=np.float32) * np.float32(np.log(hi / lo)))
