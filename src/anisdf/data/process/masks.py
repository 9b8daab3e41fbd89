"""``anisdf process-data --masks``: foreground masks of an object capture, without learned weights.

Per view, GrabCut (OpenCV's graph-cut segmentation with colour mixture models) is seeded by the geometry SfM found:
pixels outside the projection of the object's bounding sphere are background, the convex hull of the projected sparse
points that lie inside the sphere is probable foreground, the rest of the sphere's projection probable background.
A visual-hull pass then makes the views agree: a voxel of the sphere is kept when at least
:data:`HULL_VOTE` of the views that see it call it foreground, the kept voxels are projected back into every view,
and GrabCut runs again with everything outside that silhouette (grown by a margin) fixed as background. The masks
are the largest connected parts of the result, holes filled when they are small.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.ndimage as ndi
from PIL import Image

from anisdf.errors import AnisdfError

HULL_VOTE = 0.8
"""A voxel stays in the consensus hull when this fraction of the views it projects into call it foreground."""
HULL_RESOLUTION = 128
"""Voxels per side of the consensus hull's cube (at most; a quarter of the working image size)."""
WORK_SIZE = 640
"""Images are segmented at most this many pixels a side (masks are scaled back to the image size)."""
GRABCUT_ITERS = 5
HULL_MARGIN = 0.02
"""The consensus silhouette grows by this fraction of the image diagonal before what lies outside is background."""
MIN_PART = 0.05
"""Connected foreground parts under this fraction of the largest one are dropped."""
INSTALL = "pip install 'anisdf[masks]' (or pip install opencv-python-headless)"


def require_cv2():
    """The OpenCV module, or an AnisdfError saying how to install it."""
    try:
        import cv2
    except ImportError:
        raise AnisdfError(f"process-data --masks needs OpenCV's GrabCut: {INSTALL}") from None
    return cv2


@dataclass
class MaskViews:
    """What the mask maker needs of a posed capture (OpenCV axes, one frame for cameras, points and sphere)."""

    images: list[np.ndarray]
    """[H,W,3] uint8 each, all one size."""
    c2w: np.ndarray
    """[N,4,4]"""
    intrinsics: np.ndarray
    """[N,4] fx, fy, cx, cy for the images' size."""
    distortion: np.ndarray | None
    """[N,4] k1, k2, p1, p2 or None."""
    points: np.ndarray
    """[P,3] sparse points."""
    center: np.ndarray
    radius: float


def project(points: np.ndarray, c2w: np.ndarray, intr: np.ndarray, dist: np.ndarray | None
            ) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates [P,2] (corner-origin) and depths [P] of ``points`` in one camera."""
    p = (points - c2w[:3, 3]) @ c2w[:3, :3]
    z = p[:, 2]
    zs = np.where(z > 1e-9, z, 1e-9)
    x, y = p[:, 0] / zs, p[:, 1] / zs
    if dist is not None:
        k1, k2, p1, p2 = dist
        r2 = x * x + y * y
        radial = 1 + k1 * r2 + k2 * r2 * r2
        x, y = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x), y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([intr[0] * x + intr[2], intr[1] * y + intr[3]], -1), z


def sphere_disk(c2w: np.ndarray, intr: np.ndarray, center: np.ndarray, radius: float, w: int, h: int) -> np.ndarray:
    """[H,W] bool: the pixels whose ray passes within ``radius`` of ``center`` (pinhole, the sphere's outline)."""
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    d = np.stack([(u - intr[2]) / intr[0], (v - intr[3]) / intr[1], np.ones_like(u)], -1) @ c2w[:3, :3].T
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    oc = center - c2w[:3, 3]
    along = d @ oc
    return (oc @ oc - along**2 <= radius**2) & (along > 0)


def _splat(uv: np.ndarray, w: int, h: int) -> np.ndarray:
    out = np.zeros((h, w), bool)
    ok = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    out[uv[ok, 1].astype(int), uv[ok, 0].astype(int)] = True
    return out


def _convex_fill(mask: np.ndarray) -> np.ndarray:
    """The convex hull of the true pixels of ``mask``, filled."""
    from skimage.morphology import convex_hull_image

    return convex_hull_image(mask) if mask.sum() >= 3 else mask


def _clean(fg: np.ndarray, hole_fraction: float = 0.002) -> np.ndarray:
    """Largest connected parts (each at least :data:`MIN_PART` of the largest), small holes filled."""
    labels, n = ndi.label(fg)
    if n == 0:
        return fg
    sizes = np.bincount(labels.ravel())[1:]
    keep = np.zeros(n + 1, bool)
    keep[1:] = sizes >= MIN_PART * sizes.max()
    fg = keep[labels]
    holes = ndi.binary_fill_holes(fg) & ~fg
    hl, nh = ndi.label(holes)
    if nh:
        small = np.bincount(hl.ravel())[1:] < hole_fraction * fg.size
        fill = np.zeros(nh + 1, bool)
        fill[1:] = small
        fg = fg | fill[hl]
    return fg


def grabcut(image: np.ndarray, labels: np.ndarray, iters: int = GRABCUT_ITERS) -> np.ndarray:
    """[H,W] bool foreground of GrabCut initialised with ``labels`` (OpenCV's GC_BGD/FGD/PR_BGD/PR_FGD)."""
    cv2 = require_cv2()
    lab = labels.astype(np.uint8).copy()
    if not ((lab == cv2.GC_FGD) | (lab == cv2.GC_PR_FGD)).any() or not ((lab == cv2.GC_BGD) | (lab == cv2.GC_PR_BGD)
                                                                         ).any():
        return (lab == cv2.GC_FGD) | (lab == cv2.GC_PR_FGD)
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    cv2.grabCut(np.ascontiguousarray(image[..., ::-1]), lab, None, bgd, fgd, iters, cv2.GC_INIT_WITH_MASK)
    return (lab == cv2.GC_FGD) | (lab == cv2.GC_PR_FGD)


def seed_labels(views: MaskViews, i: int) -> np.ndarray:
    """GrabCut labels of view ``i`` from the sphere and the sparse points (the module docstring)."""
    cv2 = require_cv2()
    h, w = views.images[i].shape[:2]
    disk = sphere_disk(views.c2w[i], views.intrinsics[i], views.center, views.radius, w, h)
    lab = np.where(disk, cv2.GC_PR_BGD, cv2.GC_BGD).astype(np.uint8)
    dist = None if views.distortion is None else views.distortion[i]
    uv, z = project(views.points, views.c2w[i], views.intrinsics[i], dist)
    dots = _splat(uv[z > 0], w, h) & disk
    if dots.sum() >= 3:
        lab[_convex_fill(dots) & disk] = cv2.GC_PR_FGD
        lab[ndi.binary_dilation(dots, iterations=1)] = cv2.GC_PR_FGD
    return lab


def consensus_hull(views: MaskViews, masks: list[np.ndarray], resolution: int = HULL_RESOLUTION) -> np.ndarray:
    """[R^3] bool voxels of the sphere's bounding cube that :data:`HULL_VOTE` of the views seeing them call
    foreground (and at least two views see)."""
    axis = (np.arange(resolution) + 0.5) / resolution * 2 - 1
    grid = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    inside = np.linalg.norm(grid, axis=1) <= 1.0
    pts = views.center + views.radius * grid[inside]
    votes, seen = np.zeros(len(pts)), np.zeros(len(pts))
    for i, m in enumerate(masks):
        h, w = m.shape
        dist = None if views.distortion is None else views.distortion[i]
        uv, z = project(pts, views.c2w[i], views.intrinsics[i], dist)
        ok = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        seen += ok
        votes[ok] += m[uv[ok, 1].astype(int), uv[ok, 0].astype(int)]
    keep = np.zeros(len(grid), bool)
    keep[np.nonzero(inside)[0]] = (seen >= 2) & (votes >= HULL_VOTE * seen)
    return keep.reshape((resolution,) * 3)


def hull_silhouette(views: MaskViews, hull: np.ndarray, i: int, h: int, w: int) -> np.ndarray:
    """[H,W] bool projection of the hull's voxels into view ``i`` (each splatted at its projected size)."""
    res = hull.shape[0]
    idx = np.argwhere(hull)
    if len(idx) == 0:
        return np.zeros((h, w), bool)
    pts = views.center + views.radius * ((idx + 0.5) / res * 2 - 1)
    dist = None if views.distortion is None else views.distortion[i]
    uv, z = project(pts, views.c2w[i], views.intrinsics[i], dist)
    front = z > 0
    sil = _splat(uv[front], w, h)
    if front.any():
        voxel_px = float(views.intrinsics[i, 0]) * 2 * views.radius / res / float(np.median(z[front]))
        sil = ndi.binary_dilation(sil, iterations=max(1, math.ceil(0.75 * voxel_px)))
    return ndi.binary_closing(sil, iterations=2)


def make_masks(views: MaskViews, progress: bool = False, consistent: bool = True
               ) -> tuple[list[np.ndarray], dict[str, float]]:
    """Foreground masks (bool, one per view, at the images' size) and a few numbers about how they were made;
    ``consistent=False`` stops after the first, per-view pass (the ablation of the visual-hull pass)."""
    cv2 = require_cv2()
    from tqdm.auto import tqdm

    h, w = views.images[0].shape[:2]
    k = max(1.0, max(h, w) / WORK_SIZE)
    sw, sh = round(w / k), round(h / k)
    small = views
    if k > 1:
        small = MaskViews([np.asarray(Image.fromarray(im).resize((sw, sh), Image.BILINEAR)) for im in views.images],
                          views.c2w, views.intrinsics * np.array([sw / w, sh / h, sw / w, sh / h]), views.distortion,
                          views.points, views.center, views.radius)
    first = [_clean(grabcut(small.images[i], seed_labels(small, i)))
             for i in tqdm(range(len(small.images)), desc="masks: first pass", disable=not progress)]
    hull = consensus_hull(small, first, int(np.clip(max(sw, sh) // 4, 32, HULL_RESOLUTION))) if consistent else None
    margin = max(2, round(HULL_MARGIN * math.hypot(sw, sh)))
    out = [] if consistent else first
    for i in tqdm(range(len(small.images) if consistent else 0), desc="masks: consistent pass", disable=not progress):
        sil = hull_silhouette(small, hull, i, sh, sw)
        if sil.sum() < 0.2 * max(first[i].sum(), 1):  # the hull lost this view's object: keep the first pass
            out.append(first[i])
            continue
        lab = np.full((sh, sw), cv2.GC_BGD, np.uint8)
        grown = ndi.binary_dilation(sil, iterations=margin)
        lab[grown] = cv2.GC_PR_BGD
        lab[grown & first[i]] = cv2.GC_PR_FGD
        lab[sil & first[i]] = cv2.GC_PR_FGD
        out.append(_clean(grabcut(small.images[i], lab)))
    if k > 1:
        out = [np.asarray(Image.fromarray(m.astype(np.uint8) * 255).resize((w, h), Image.BILINEAR)) >= 128
               for m in out]
    stats = {"hull_voxels": int(hull.sum()) if hull is not None else 0,
             "mean_coverage": float(np.mean([m.mean() for m in out]))}
    return out, stats


def load_views(scene: Path) -> tuple[MaskViews, list[Path]]:
    """The posed images, sparse points and bounding sphere of a process-data scene folder."""
    import trimesh

    from anisdf.data.dataparsers import instant_ngp
    from anisdf.errors import DataError

    parsed = instant_ngp.parse(scene)
    if parsed.to_world is None:
        raise DataError(scene / "transforms.json", "has no bounding_sphere (write the scene with anisdf process-data)")
    ply = scene / "sparse_pc.ply"
    if not ply.is_file():
        raise DataError(ply, "sparse points are missing (write the scene with anisdf process-data)")
    points = np.asarray(trimesh.load(ply, process=False).vertices, np.float64).reshape(-1, 3)
    center, radius = parsed.to_world[:3, 3], float(parsed.to_world[0, 0])
    points = points[np.linalg.norm(points - center, axis=1) <= radius]
    images = [np.asarray(Image.open(p).convert("RGB")) for p in parsed.image_paths]
    size = images[0].shape[1], images[0].shape[0]
    intr = parsed.intrinsics.copy()
    if parsed.size is not None and tuple(parsed.size) != size:
        intr *= np.array([size[0] / parsed.size[0], size[1] / parsed.size[1]] * 2)
    views = MaskViews(images, parsed.c2w, intr, parsed.distortion, points, center, radius)
    return views, parsed.image_paths
