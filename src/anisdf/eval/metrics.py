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
from skimage.metrics import structural_similarity

from anisdf.errors import AnisdfError, DataError
from anisdf.utils.images import composite

ArrayLike = np.ndarray | torch.Tensor


CHAMFER_POINTS = 1_000_000
"""Points sampled on each surface for the Chamfer distance unless told otherwise (eval, chamfer, reproduce)."""


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


SSIM_WINDOW = 11
"""Side of skimage's Gaussian SSIM window for sigma 1.5 (truncated at 3.5 sigma): 2 * int(3.5 * 1.5 + 0.5) + 1."""


def ssim(pred: ArrayLike, gt: ArrayLike) -> float:
    """Structural similarity (Wang et al. 2004) with the standard settings, mean over channels.

    ``skimage.metrics.structural_similarity`` with a Gaussian window (sigma 1.5, truncated to 11x11),
    K1 = 0.01, K2 = 0.03, data range 1 and population (not sample) covariances; the SSIM map is averaged
    over the pixels whose window lies fully inside the image. HxW images are single-channel.
    """
    p, g = _as_float_tensor(pred), _as_float_tensor(gt)
    _check_pair(p, g)
    h, w = p.shape[:2]
    if h < SSIM_WINDOW or w < SSIM_WINDOW:
        raise ValueError(f"ssim needs images of at least {SSIM_WINDOW}x{SSIM_WINDOW} pixels, got {h}x{w}")
    return float(structural_similarity(
        p.cpu().numpy(), g.cpu().numpy(), gaussian_weights=True, sigma=1.5,
        use_sample_covariance=False, data_range=1.0, channel_axis=-1 if p.dim() == 3 else None,
    ))


def sample_surface(mesh: trimesh.Trimesh, n: int, seed: int) -> np.ndarray:
    """``n`` points sampled uniformly (area-weighted) on the surface of ``mesh``; reproducible by ``seed``."""
    if len(mesh.faces) == 0:
        raise AnisdfError("cannot sample points on a mesh without faces")
    if n <= 0:
        raise ValueError(f"n must be positive, got {n}")
    points, _ = trimesh.sample.sample_surface(mesh, int(n), seed=int(seed))
    return np.asarray(points, dtype=np.float64)


def chamfer_distance(
    mesh_a: trimesh.Trimesh, mesh_b: trimesh.Trimesh, n_points: int = CHAMFER_POINTS, seed: int = 0
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


NORMAL_LENGTH_TOLERANCE = 0.1
"""Largest median | |n| - 1 | over a reference normal map's covered pixels for it to be read as ``(n + 1) / 2``: the
bundled maps (8-bit, 128 px) give 0.002; the same maps saturated (max(n, 0): negative components clipped, as in
NeRF-synthetic's ``r_i_normal_0001.png``) give 0.27 to 0.46."""


def normal_map_problem(decoded: np.ndarray, coverage: np.ndarray,
                       tolerance: float = NORMAL_LENGTH_TOLERANCE) -> str | None:
    """Why a reference normal map cannot be scored as world normals stored as ``(n + 1) / 2``, None when it can.

    ``decoded``: [H, W, 3+] xyz = 2 RGB - 1, not renormalised (:func:`anisdf.data.images.read_normal_raw`);
    ``coverage``: [H, W] in [0, 1], the pixels > 0.5 are judged (none: nothing to judge, None). Over them the
    vectors must have unit length: median | |n| - 1 | <= ``tolerance``.
    """
    xyz = np.asarray(decoded, dtype=np.float64)[..., :3]
    covered = np.asarray(coverage, dtype=np.float64) > 0.5
    if xyz.shape[:2] != covered.shape:
        raise ValueError(f"coverage shape {covered.shape} does not match the normal map's {xyz.shape[:2]}")
    if not covered.any():
        return None
    length = np.linalg.norm(xyz[covered], axis=-1)
    error = float(np.median(np.abs(length - 1.0)))
    if error <= tolerance:
        return None
    return (f"decoded as (n + 1) / 2 its vectors are not unit length: median | |n| - 1 | = {error:.3f} over "
            f"{int(covered.sum())} covered pixels (tolerance {tolerance}; median length {float(np.median(length)):.3f})"
            "; another encoding (e.g. saturated channels, negative components clipped) that eval cannot read")


def normal_mae_deg(pred_normals: ArrayLike, gt_normals: ArrayLike, mask: ArrayLike | None = None,
                   weights: ArrayLike | None = None) -> float:
    """Mean angular error in degrees between two normal maps, a weighted mean over the foreground.

    ``pred_normals``: [H, W, 3] (or [H, W, 4], extra channel ignored). ``gt_normals``: [H, W, 3] or the
    reference layout [H, W, 4] (xyz + coverage). Each pixel counts with its weight: ``weights`` ([H, W], >= 0)
    when given, as Ref-NeRF's ``compute_weighted_mae`` (its eval.py passes rendered opacity x ground-truth
    alpha); else 1 on ``mask``; else 1 where the reference coverage > 0.5. Both maps are normalised; the angle is
    ``2 atan2(|a - b|, |a + b|)`` (Kahan), accurate near 0 and 180 degrees, and exactly 0 for identical normals
    (Ref-NeRF's ``arccos`` of the dot product clipped to 1 - eps(float32) floors each pixel at 0.028 degrees). A
    zero-length prediction counts as 90 degrees.
    """
    p, g = _as_float_tensor(pred_normals), _as_float_tensor(gt_normals)
    g = g.to(p.device)
    if p.shape[:2] != g.shape[:2] or p.shape[-1] < 3 or g.shape[-1] < 3:
        raise ValueError(
            f"normal maps must be HxWx3/4 of one size, got {tuple(p.shape)} and {tuple(g.shape)}"
        )
    if weights is not None:
        w = _as_float_tensor(weights).to(p.device)
        if w.dim() == 3 and w.shape[-1] == 1:
            w = w[..., 0]
        if tuple(w.shape) != tuple(p.shape[:2]):
            raise ValueError(f"weights shape {tuple(w.shape)} does not match normal maps {tuple(p.shape[:2])}")
        if bool((w < 0).any()) or not bool(torch.isfinite(w).all()):
            raise ValueError("normal_mae_deg: weights must be finite and non-negative")
    elif mask is not None:
        w = _as_mask(mask, tuple(p.shape[:2]), p.device).to(torch.float64)
    elif g.shape[-1] == 4:
        w = (g[..., 3] > 0.5).to(torch.float64)
    else:
        raise ValueError("normal_mae_deg needs weights, a mask or a reference map with a coverage channel")
    m = w > 0
    if not bool(m.any()):
        raise AnisdfError("normal_mae_deg: no foreground pixels (all weights are zero)")
    a = F.normalize(p[..., :3][m], dim=-1, eps=1e-12)
    b = F.normalize(g[..., :3][m], dim=-1, eps=1e-12)
    angle = 2.0 * torch.atan2(torch.linalg.norm(a - b, dim=-1), torch.linalg.norm(a + b, dim=-1))
    wm = w[m]
    return float(torch.rad2deg((angle * wm).sum() / wm.sum()))


def chamfer_main(a: str, b: str, n_points: int = CHAMFER_POINTS, seed: int = 0) -> float:
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
