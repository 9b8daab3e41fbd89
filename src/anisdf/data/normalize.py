"""Finding the region of interest (ROI) of a scene and the similarity that maps it to the unit sphere.

Three strategies, in order of preference:

1. a known normalisation (NeuS ``scale_mat``), used as it is;
2. **visual hull** when object masks or alpha exist: a 32^3 grid in a generous box around the cameras'
   look-at point (half-size 1.5 d tan(fov/2), at most 0.75 d, for the median camera distance d; doubled if
   the hull touches its border) is carved with every training mask, then a 64^3 grid over the bounding box
   of the survivors; the ROI is the bounding sphere of the surviving voxels padded by 10%, so the object
   fills about radius 0.9 of the unit sphere. Masks are max-pooled to at most 256 pixels a side, a voxel
   must be seen by 75% of the views to survive, and a hull that would contain the cameras is rejected
   (falling back to strategy 3 with a warning);
3. **camera axes** otherwise: the centre is the point nearest (least squares) to all optical axes, and the
   radius is ``1.2 * d * sin(half fov)`` for the median camera distance ``d``: the sphere that just fills
   the narrower side of a typical view at the look-at distance, plus 20% (instant-ngp's default scale puts
   its unit cube at a similar ~0.4 d). For forward-facing captures (nearly parallel axes) the centre is
   placed ``depth`` in front of the mean camera, with ``depth`` from the LLFF bounds when known.

A user's region of interest (``data.roi_center`` / ``data.roi_radius``, :func:`user_roi`) replaces any of these
(the part of it given); it is checked against the cameras (:func:`check_user_roi`).
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field, replace

import numpy as np
import scipy.ndimage
import torch
import torch.nn.functional as F

from anisdf.data.cameras import Cameras, distort
from anisdf.errors import AnisdfError

HULL_RESOLUTION = 64
HULL_PADDING = 1.1
HULL_MAX_IMAGE_SIZE = 256
"""Masks are max-pooled to at most this many pixels a side before carving."""
CAMERA_ROI_MARGIN = 1.2
"""Camera-axes ROI radius = margin * d * sin(half fov): 1.2 keeps the fox's ears and plaque inside."""
HULL_MIN_VISIBLE = 0.75
"""A voxel must project inside at least this fraction of the views to survive carving."""


ROI_METHODS = {
    "scale_mat": "the dataset's scale_mat (NeuS cameras file)",
    "sparse-points": "the sparse SfM points (process-data's bounding sphere)",
    "bounding-sphere": "the bounding_sphere of transforms.json",
    "visual-hull": "the visual hull of the masks (or alpha)",
    "camera-axes": "the camera rays (the point nearest every optical axis)",
    "forward-facing": "the camera rays of a forward-facing capture (a point in front of the mean camera)",
    "user": "the user's region of interest (data.roi_center, data.roi_radius)",
}
"""How a region of interest was found, as ``anisdf inspect`` says it."""


def describe_roi_method(method: str) -> str:
    """``method`` (a key of :data:`ROI_METHODS`, or ``user-center+<auto>`` / ``user-radius+<auto>``) in words."""
    part, _, auto = method.partition("+")
    if part == "user-center":
        return f"centre given (data.roi_center), radius from {ROI_METHODS.get(auto, auto)}"
    if part == "user-radius":
        return f"radius given (data.roi_radius), centre from {ROI_METHODS.get(auto, auto)}"
    return ROI_METHODS.get(method, method)


def check_roi_values(center: tuple[float, ...] | list[float], radius: float) -> None:
    """AnisdfError unless ``center`` is empty or three finite numbers and ``radius`` is 0 (automatic) or positive."""
    if len(center) not in (0, 3):
        raise AnisdfError(f"data.roi_center needs three numbers x,y,z (the dataset's frame), got {len(center)}: "
                          f"{list(center)}")
    if not all(math.isfinite(float(v)) for v in center):
        raise AnisdfError(f"data.roi_center must be finite, got {list(center)}")
    if not math.isfinite(radius) or radius < 0:
        raise AnisdfError(f"data.roi_radius must be a positive number of dataset units (0: automatic), got {radius:g}")


@dataclass
class RegionOfInterest:
    center: np.ndarray
    radius: float
    method: str
    warnings: list[str] = field(default_factory=list)

    def to_world(self) -> np.ndarray:
        """[4,4] similarity mapping the unit sphere onto this region (uniform scale + translation)."""
        m = np.eye(4)
        m[:3, :3] *= self.radius
        m[:3, 3] = self.center
        return m


def look_at_point(centers: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares point nearest to the lines ``centers + t dirs``; returns it and the conditioning
    ``lambda_min / N`` of the normal equations (near 0 for parallel axes)."""
    d = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    proj = np.eye(3)[None] - d[:, :, None] * d[:, None, :]
    a = proj.sum(0)
    b = (proj @ centers[:, :, None]).sum(0)[:, 0]
    conditioning = float(np.linalg.eigvalsh(a)[0]) / len(centers)
    if conditioning < 1e-9:
        return centers.mean(0), conditioning
    return np.linalg.solve(a, b), conditioning


def half_fov(intrinsics: np.ndarray, width: int, height: int) -> float:
    """Median over cameras of the narrower half field of view (radians)."""
    fx, fy = intrinsics[:, 0], intrinsics[:, 1]
    per_cam = np.minimum(np.arctan(0.5 * width / fx), np.arctan(0.5 * height / fy))
    return float(np.median(per_cam))


def camera_roi(
    c2w: np.ndarray, intrinsics: np.ndarray, width: int, height: int, depth_hint: float | None = None
) -> RegionOfInterest:
    """ROI from camera geometry alone (strategy 3 of the module docstring)."""
    centers, dirs = c2w[:, :3, 3], c2w[:, :3, 2]
    fov = half_fov(intrinsics, width, height)
    warnings: list[str] = []
    if len(centers) >= 2:
        point, cond = look_at_point(centers, dirs)
        depth_along = np.einsum("ij,ij->i", point[None] - centers, dirs)
        spread = float(np.linalg.norm(centers - centers.mean(0), axis=1).max())
        if cond > 1e-2 and np.mean(depth_along > 0) >= 0.5:
            dist = float(np.median(np.linalg.norm(centers - point, axis=1)))
            if dist > 0:
                radius = CAMERA_ROI_MARGIN * dist * math.sin(fov)
                return RegionOfInterest(point, radius, "camera-axes", warnings)
    else:
        spread = 0.0
    mean_dir = dirs.mean(0)
    mean_dir /= max(np.linalg.norm(mean_dir), 1e-12)
    depth = depth_hint if depth_hint and depth_hint > 0 else max(4.0 * spread, 1.0)
    warnings.append(
        "cameras look along nearly parallel axes (forward-facing capture): the region of interest is placed "
        f"{depth:.3g} units in front of the mean camera" + ("" if depth_hint else " (a guess)")
    )
    center = centers.mean(0) + depth * mean_dir
    return RegionOfInterest(center, CAMERA_ROI_MARGIN * depth * math.sin(fov), "forward-facing", warnings)


def _carve(
    points: torch.Tensor, vox_radius: float, cams: Cameras, dist_maps: torch.Tensor, min_visible: int,
    chunk: int = 8,
) -> torch.Tensor:
    """Boolean [P] mask of the points that survive carving with every view.

    A point is carved when it projects inside a view (in front of the camera) but farther from that view's
    mask than the voxel's projected radius plus one pixel; survivors must be visible in ``min_visible``
    views. Views are processed ``chunk`` at a time and carved points are dropped as they go.
    """
    alive = torch.arange(points.shape[0])
    n_visible = torch.zeros(points.shape[0], dtype=torch.long)
    n_cams, h, w = dist_maps.shape
    flat_maps = dist_maps.reshape(-1)
    rot, trans = cams.c2w[:, :, :3], cams.c2w[:, :, 3]
    for start in range(0, n_cams, chunk):
        if alive.numel() == 0:
            break
        sl = slice(start, min(start + chunk, n_cams))
        p = points[alive]
        p_cam = torch.einsum("aj,cjk->cak", p, rot[sl]) - (trans[sl, None, :] @ rot[sl])  # (p - t) R
        z = p_cam[..., 2]
        z_safe = z.clamp_min(1e-6)
        x, y = p_cam[..., 0] / z_safe, p_cam[..., 1] / z_safe
        if cams.distortion is not None:
            x, y = distort(x, y, cams.distortion[sl, None, :])
        fx = cams.fx[sl, None]
        u = fx * x + cams.cx[sl, None]
        v = cams.fy[sl, None] * y + cams.cy[sl, None]
        visible = (z > 1e-6) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        cam = torch.arange(sl.start, sl.stop)[:, None]
        flat = (cam * h + v.clamp(0, h - 1).long()) * w + u.clamp(0, w - 1).long()
        outside = visible & (flat_maps[flat] > vox_radius * fx / z_safe + 1.0)
        n_visible[alive] += visible.sum(0)
        alive = alive[~outside.any(0)]
    keep = torch.zeros(points.shape[0], dtype=torch.bool)
    keep[alive] = True
    return keep & (n_visible >= min_visible)


@contextmanager
def _single_thread() -> Iterator[None]:
    """Run torch ops on one thread: the carving ops are small, and intra-op threads on a busy machine cost
    far more than they gain (measured: 0.3 s with one thread vs 4.7 s with two on a loaded 2-core box)."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(n)


def _grid(lo: np.ndarray, hi: np.ndarray, res: int) -> tuple[torch.Tensor, np.ndarray]:
    step = (hi - lo) / res
    axes = [torch.tensor(lo[k] + (np.arange(res) + 0.5) * step[k], dtype=torch.float32) for k in range(3)]
    pts = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).reshape(-1, 3)
    return pts, step


def visual_hull_roi(
    cams: Cameras, coverage: torch.Tensor, resolution: int = HULL_RESOLUTION
) -> RegionOfInterest | None:
    """Bounding sphere (padded 10%) of the visual hull of ``coverage`` ([M,H,W] uint8, 128+ = object)
    seen by ``cams`` (CPU, dataset frame, same image size); None when carving leaves nothing."""
    with _single_thread():
        return _visual_hull_roi(cams, coverage, resolution)


def _visual_hull_roi(cams: Cameras, coverage: torch.Tensor, resolution: int) -> RegionOfInterest | None:
    warnings: list[str] = []
    inside_t = coverage.cpu() >= 128
    k = math.ceil(max(cams.width, cams.height) / HULL_MAX_IMAGE_SIZE)
    if k > 1:  # carve on max-pooled (conservative) masks, intrinsics scaled to the pooled pixel grid
        inside_t = F.max_pool2d(inside_t[:, None].float(), k, stride=k, ceil_mode=True)[:, 0] > 0
        cams = replace(cams, fx=cams.fx / k, fy=cams.fy / k, cx=cams.cx / k, cy=cams.cy / k,
                       width=inside_t.shape[2], height=inside_t.shape[1])
    inside = inside_t.numpy()
    frac = inside.reshape(len(inside), -1).mean(axis=1)
    use = np.nonzero(frac > 1e-4)[0]
    if len(use) < len(inside):
        warnings.append(f"{len(inside) - len(use)} empty masks ignored for the visual hull")
    if len(use) < 2:
        return None
    cams = cams.subset(use.tolist())
    dist_maps = torch.from_numpy(
        np.stack([scipy.ndimage.distance_transform_edt(~inside[i]) for i in use]).astype(np.float32)
    )
    c2w = cams.c2w.double().numpy()
    point, cond = look_at_point(c2w[:, :3, 3], c2w[:, :3, 2])
    cam_dist = np.linalg.norm(c2w[:, :3, 3] - point, axis=1)
    # Everything seen by all views lies roughly within d * tan(fov / 2) of the look-at point.
    fov = float(torch.maximum(torch.atan(0.5 * cams.width / cams.fx), torch.atan(0.5 * cams.height / cams.fy))
                .median())
    half = float(np.median(cam_dist)) * min(0.75, 1.5 * math.tan(fov))
    if cond < 1e-2 or not half > 0:
        return None
    min_visible = max(1, math.ceil(HULL_MIN_VISIBLE * len(cams)))
    coarse = max(8, resolution // 2)
    lo, hi = point - half, point + half
    for attempt in range(2):
        pts, step = _grid(lo, hi, coarse)
        keep = _carve(pts, 0.5 * float(np.linalg.norm(step)), cams, dist_maps, min_visible)
        if not keep.any():
            return None
        idx = keep.reshape(coarse, coarse, coarse).nonzero()
        if not bool((idx == 0).any() or (idx == coarse - 1).any()):
            break
        if attempt == 0:
            lo, hi = point - 2 * half, point + 2 * half
        else:
            warnings.append("the visual hull reaches the border of the search box; the region of interest "
                            "may be too small")
    survivors = pts[keep].double().numpy()
    # Fine pass: the bounding box of the coarse survivors, one coarse voxel larger on each side.
    lo2, hi2 = survivors.min(0) - step, survivors.max(0) + step
    pts2, step2 = _grid(lo2, hi2, resolution)
    keep2 = _carve(pts2, 0.5 * float(np.linalg.norm(step2)), cams, dist_maps, min_visible)
    if keep2.any():
        survivors, step = pts2[keep2].double().numpy(), step2
    center = 0.5 * (survivors.min(0) + survivors.max(0))
    extent = float(np.linalg.norm(survivors - center, axis=1).max() + 0.5 * np.linalg.norm(step))
    radius = HULL_PADDING * extent
    if radius > 0.9 * float(np.median(np.linalg.norm(c2w[:, :3, 3] - center, axis=1))):
        return None  # the sphere would swallow the cameras: too few or inconsistent views to trust
    return RegionOfInterest(center, radius, "visual-hull", warnings)


def user_roi(auto: RegionOfInterest | None, center: tuple[float, ...] | list[float], radius: float
             ) -> RegionOfInterest:
    """The region of interest with the user's ``center`` (3 numbers, or empty) and ``radius`` (0: not given) put in
    place of the automatic sphere ``auto``'s (None: both are given)."""
    check_roi_values(center, radius)
    if auto is None:
        return RegionOfInterest(np.asarray(center, dtype=np.float64), float(radius), "user")
    if center and radius > 0:
        return RegionOfInterest(np.asarray(center, dtype=np.float64), float(radius), "user", auto.warnings)
    if center:
        return RegionOfInterest(np.asarray(center, dtype=np.float64), auto.radius, f"user-center+{auto.method}",
                                auto.warnings)
    return RegionOfInterest(auto.center, float(radius), f"user-radius+{auto.method}", auto.warnings)


def check_user_roi(roi: RegionOfInterest, c2w: np.ndarray, intrinsics: np.ndarray, width: int, height: int,
                   names: list[str]) -> None:
    """AnisdfError when the sphere holds a camera (the unit sphere must leave the cameras outside) or lies in no
    camera's view: its centre must be in front of a camera, within the camera's diagonal half field of view plus
    the angle the sphere spans from there."""
    centers, dirs = c2w[:, :3, 3], c2w[:, :3, 2]
    where = (f"the region of interest (centre {', '.join(f'{v:.4g}' for v in roi.center)}, radius {roi.radius:.4g}, "
             "dataset frame)")
    dist = np.linalg.norm(centers - roi.center, axis=1)
    inside = np.nonzero(dist <= roi.radius)[0]
    if len(inside):
        i = int(inside[np.argmin(dist[inside])])
        raise AnisdfError(f"{where} holds {len(inside)} of {len(c2w)} cameras (e.g. {names[i]}, at distance "
                          f"{dist[i]:.4g} from its centre); the cameras must stay outside: make data.roi_radius "
                          f"smaller than {dist.min():.4g} or move data.roi_center")
    fx, fy = intrinsics[:, 0], intrinsics[:, 1]
    half_diag = np.arctan(np.hypot(0.5 * width / fx, 0.5 * height / fy))
    cos_off = np.einsum("ij,ij->i", roi.center - centers, dirs) / np.maximum(dist, 1e-12)
    off_axis = np.arccos(np.clip(cos_off, -1.0, 1.0))
    if not np.any(off_axis <= half_diag + np.arcsin(np.clip(roi.radius / dist, 0.0, 1.0))):
        raise AnisdfError(f"{where} is in the view of none of the {len(c2w)} cameras; give it in the dataset's own "
                          "frame and units (anisdf inspect prints the automatic one)")
