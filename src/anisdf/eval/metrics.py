"""Evaluation metrics: PSNR, SSIM, Chamfer distance between meshes and normal mean angular error.

The protocols (which views, backgrounds, point counts, seeds) are written down in ``docs/evaluation.md``.
Image metrics take HxWxC images in [0, 1] as numpy arrays or torch tensors (uint8 images are scaled
by 1/255); they are computed in float64.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
import trimesh
from scipy.spatial import cKDTree

from anisdf.data.images import composite
from anisdf.errors import AnisdfError, DataError

ArrayLike = np.ndarray | torch.Tensor


def _as_float_tensor(x: ArrayLike) -> torch.Tensor:
    """Convert an image (array or tensor) to a float64 tensor; integer images are scaled to [0, 1]."""
    if isinstance(x, torch.Tensor):
        t = x.detach()
        if not t.is_floating_point():
            t = t.to(torch.float64) / float(torch.iinfo(x.dtype).max)
        return t.to(torch.float64)
    a = np.asarray(x)
    if np.issubdtype(a.dtype, np.integer):
        return torch.from_numpy(a.astype(np.float64) / float(np.iinfo(a.dtype).max))
    return torch.from_numpy(a.astype(np.float64, copy=False))


def _as_mask(mask: ArrayLike, shape: tuple[int, ...], device: torch.device) -> torch.Tensor:
    m = torch.as_tensor(np.asarray(mask) if not isinstance(mask, torch.Tensor) else mask.detach())
    m = m.to(device)
    if m.dim() == 3 and m.shape[-1] == 1:
        m = m[..., 0]
    if tuple(m.shape) != tuple(shape):
        raise ValueError(f"mask shape {tuple(m.shape)} does not match image shape {tuple(shape)}")
    return m > 0.5 if m.is_floating_point() else m.bool()


def _check_pair(pred: torch.Tensor, gt: torch.Tensor) -> None:
    if pred.shape != gt.shape:
        raise ValueError(f"prediction shape {tuple(pred.shape)} differs from reference {tuple(gt.shape)}")
    if pred.dim() not in (2, 3):
        raise ValueError(f"expected an HxW or HxWxC image, got shape {tuple(pred.shape)}")


def composite_on_white(rgba: ArrayLike) -> np.ndarray:
    """Composite an RGBA image (HxWx4, [0, 1] or uint8) on a white background: rgb * a + (1 - a)."""
    t = _as_float_tensor(rgba).cpu().numpy()
    if t.shape[-1] != 4:
        raise ValueError(f"expected an HxWx4 RGBA image, got shape {t.shape}")
    return composite(t[..., :3], t[..., 3:4], 1.0)


def psnr_from_mse(mse: float) -> float:
    """PSNR in dB of images in [0, 1] from their mean squared error (floored at 1e-10, i.e. at most 100 dB)."""
    return -10.0 * math.log10(max(mse, 1e-10))


def psnr(pred: ArrayLike, gt: ArrayLike, mask: ArrayLike | None = None) -> float:
    """Peak signal-to-noise ratio in dB for images in [0, 1]: ``-10 log10(MSE)``.

    ``mask`` (HxW, bool or float > 0.5) selects the pixels that count; the MSE is the mean over the
    selected pixels and all channels. Identical images give ``inf``.
    """
    p, g = _as_float_tensor(pred), _as_float_tensor(gt)
    g = g.to(p.device)
    _check_pair(p, g)
    if mask is not None:
        m = _as_mask(mask, tuple(p.shape[:2]), p.device)
        if not bool(m.any()):
            raise AnisdfError("psnr: the mask selects no pixels")
        p, g = p[m], g[m]
    mse = float(torch.mean((p - g) ** 2))
    if mse == 0.0:
        return math.inf
    return -10.0 * math.log10(mse)


def _gaussian_kernel1d(size: int = 11, sigma: float = 1.5) -> torch.Tensor:
    x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2.0
    k = torch.exp(-(x**2) / (2.0 * sigma**2))
    return k / k.sum()


def ssim(pred: ArrayLike, gt: ArrayLike, win_size: int = 11, sigma: float = 1.5) -> float:
    """Structural similarity (Wang et al. 2004) with the standard settings, mean over channels.

    Gaussian window 11x11 with sigma 1.5, K1 = 0.01, K2 = 0.03, data range 1, population (not sample)
    covariances; the SSIM map is averaged over the pixels whose window lies fully inside the image.
    This equals ``skimage.metrics.structural_similarity(pred, gt, channel_axis=-1, data_range=1,
    gaussian_weights=True, sigma=1.5, use_sample_covariance=False)``.
    """
    p, g = _as_float_tensor(pred), _as_float_tensor(gt)
    g = g.to(p.device)
    _check_pair(p, g)
    if p.dim() == 2:
        p, g = p[..., None], g[..., None]
    h, w, c = p.shape
    if h < win_size or w < win_size:
        raise ValueError(f"ssim needs images of at least {win_size}x{win_size} pixels, got {h}x{w}")
    c1, c2 = 0.01**2, 0.03**2
    k = _gaussian_kernel1d(win_size, sigma).to(p.device)
    kx = k.view(1, 1, 1, win_size).expand(c, 1, 1, win_size)
    ky = k.view(1, 1, win_size, 1).expand(c, 1, win_size, 1)

    def blur(t: torch.Tensor) -> torch.Tensor:  # separable "valid" Gaussian filter, per channel
        return F.conv2d(F.conv2d(t, kx, groups=c), ky, groups=c)

    x = p.permute(2, 0, 1)[None]
    y = g.permute(2, 0, 1)[None]
    mu_x, mu_y = blur(x), blur(y)
    sxx = blur(x * x) - mu_x**2
    syy = blur(y * y) - mu_y**2
    sxy = blur(x * y) - mu_x * mu_y
    num = (2 * mu_x * mu_y + c1) * (2 * sxy + c2)
    den = (mu_x**2 + mu_y**2 + c1) * (sxx + syy + c2)
    return float((num / den).mean())


def sample_surface(mesh: trimesh.Trimesh, n: int, seed: int) -> np.ndarray:
    """``n`` points sampled uniformly (area-weighted) on the surface of ``mesh``; reproducible by ``seed``."""
    if len(mesh.faces) == 0:
        raise AnisdfError("cannot sample points on a mesh without faces")
    if n <= 0:
        raise ValueError(f"n must be positive, got {n}")
    points, _ = trimesh.sample.sample_surface(mesh, int(n), seed=int(seed))
    return np.asarray(points, dtype=np.float64)


def chamfer_distance(
    mesh_a: trimesh.Trimesh, mesh_b: trimesh.Trimesh, n_points: int = 1_000_000, seed: int = 0
) -> dict[str, float]:
    """Symmetric Chamfer distance between two surfaces, in the meshes' units.

    ``n_points`` points are sampled uniformly on each surface (``seed`` for A, ``seed + 1`` for B, so a
    mesh against itself measures the sampling noise, not zero). Returns

    - ``accuracy``: mean distance from A's points to their nearest neighbour among B's points (pred -> gt),
    - ``completeness``: the same from B to A (gt -> pred),
    - ``chamfer``: the mean of the two (the NeRF-synthetic convention),
    - ``n_points``.
    """
    pa = sample_surface(mesh_a, n_points, seed)
    pb = sample_surface(mesh_b, n_points, seed + 1)
    d_ab, _ = cKDTree(pb).query(pa, k=1, workers=-1)
    d_ba, _ = cKDTree(pa).query(pb, k=1, workers=-1)
    acc, comp = float(np.mean(d_ab)), float(np.mean(d_ba))
    return {"chamfer": 0.5 * (acc + comp), "accuracy": acc, "completeness": comp, "n_points": float(n_points)}


def load_mesh(path: str | Path) -> trimesh.Trimesh:
    """Load a triangle mesh (ply, obj, glb, stl, ...); scenes are merged into one mesh.

    Raises :class:`DataError` naming the file if it is missing, unreadable or has no faces.
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(path, "mesh file not found")
    try:
        loaded: Any = trimesh.load(path, force="mesh", process=False)
    except Exception as e:  # trimesh raises many different types for bad files
        raise DataError(path, f"cannot read mesh ({type(e).__name__}: {e})") from e
    if not isinstance(loaded, trimesh.Trimesh):
        raise DataError(path, f"not a triangle mesh (loaded a {type(loaded).__name__})")
    if len(loaded.faces) == 0 or len(loaded.vertices) == 0:
        raise DataError(path, "mesh is empty (no faces)")
    if not np.all(np.isfinite(loaded.vertices)):
        raise DataError(path, "mesh has non-finite vertex coordinates")
    return loaded


def decode_normal_png(array: np.ndarray) -> np.ndarray:
    """Decode a normal map image: RGB = (n + 1) / 2, alpha = coverage.

    Takes an integer (uint8 or uint16) HxWx4 or HxWx3 array; returns float32 [H, W, 4] with xyz in
    [-1, 1] (not renormalised) and coverage in [0, 1] (1 everywhere for a 3-channel image).
    """
    a = np.asarray(array)
    if a.ndim != 3 or a.shape[-1] not in (3, 4):
        raise ValueError(f"expected an HxWx3 or HxWx4 normal map, got shape {a.shape}")
    scale = float(np.iinfo(a.dtype).max) if np.issubdtype(a.dtype, np.integer) else 1.0
    f = a.astype(np.float32) / scale
    out = np.ones((*a.shape[:2], 4), dtype=np.float32)
    out[..., :3] = f[..., :3] * 2.0 - 1.0
    if a.shape[-1] == 4:
        out[..., 3] = f[..., 3]
    return out


def normal_mae_deg(pred_normals: ArrayLike, gt_normals: ArrayLike, mask: ArrayLike | None = None) -> float:
    """Mean angular error in degrees between two normal maps over foreground pixels.

    ``pred_normals``: [H, W, 3] (or [H, W, 4], extra channel ignored). ``gt_normals``: [H, W, 3] or the
    reference layout [H, W, 4] (xyz + coverage). The foreground is ``mask`` when given, otherwise
    ``coverage > 0.5``. Both maps are normalised; the angle is computed as ``2 atan2(|a - b|, |a + b|)``
    (Kahan), accurate near 0 and 180 degrees unlike ``acos`` of the clamped dot product, and exactly 0
    for identical normals. A zero-length prediction counts as 90 degrees.
    """
    p, g = _as_float_tensor(pred_normals), _as_float_tensor(gt_normals)
    g = g.to(p.device)
    if p.shape[:2] != g.shape[:2] or p.shape[-1] < 3 or g.shape[-1] < 3:
        raise ValueError(
            f"normal maps must be HxWx3/4 of one size, got {tuple(p.shape)} and {tuple(g.shape)}"
        )
    if mask is not None:
        m = _as_mask(mask, tuple(p.shape[:2]), p.device)
    elif g.shape[-1] == 4:
        m = g[..., 3] > 0.5
    else:
        raise ValueError("normal_mae_deg needs a mask or a reference map with a coverage channel")
    if not bool(m.any()):
        raise AnisdfError("normal_mae_deg: no foreground pixels")
    a = F.normalize(p[..., :3][m], dim=-1, eps=1e-12)
    b = F.normalize(g[..., :3][m], dim=-1, eps=1e-12)
    angle = 2.0 * torch.atan2(torch.linalg.norm(a - b, dim=-1), torch.linalg.norm(a + b, dim=-1))
    return float(torch.rad2deg(angle).mean())


def chamfer_main(a: str, b: str, n_points: int = 1_000_000, seed: int = 0) -> float:
    """Chamfer distance between the meshes in files ``a`` (prediction) and ``b`` (reference).

    Prints the details (point count, seeds, accuracy, completeness) and returns the Chamfer distance;
    the CLI prints the number itself as its last line.
    """
    mesh_a, mesh_b = load_mesh(a), load_mesh(b)
    r = chamfer_distance(mesh_a, mesh_b, n_points=n_points, seed=seed)
    print(f"A: {a} ({len(mesh_a.vertices)} vertices, {len(mesh_a.faces)} faces)")
    print(f"B: {b} ({len(mesh_b.vertices)} vertices, {len(mesh_b.faces)} faces)")
    print(f"points per surface: {n_points} (seeds {seed} for A, {seed + 1} for B)")
    print(f"accuracy (A->B): {r['accuracy']:.6g}")
    print(f"completeness (B->A): {r['completeness']:.6g}")
    return r["chamfer"]
