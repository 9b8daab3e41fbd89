"""What ``anisdf process-data`` writes from a reconstruction: the bounding sphere, ``transforms.json``
(nerfstudio / instant-ngp convention), ``sparse_pc.ply`` and the overview picture ``cameras.png``."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image, ImageDraw
from scipy.spatial.transform import Rotation

from anisdf.data.dataparsers._common import GL_TO_CV
from anisdf.data.dataparsers.colmap import ColmapCamera, camera_intrinsics
from anisdf.data.normalize import look_at_point
from anisdf.data.orbit import up_direction

SPHERE_MARGIN = 1.1
MIN_VISIBLE = 0.75
"""A sparse point must lie inside the view frustum of this fraction of the cameras to count for an object (as a
voxel for the visual hull, :data:`anisdf.data.normalize.HULL_MIN_VISIBLE`). On DTU scan 65 the sphere's radius is
1.55 / 1.21 / 1.04 times the dataset's scale_mat sphere for 0.5 / 0.75 / 0.9: the table around the skull is in
fewer views; 0.9 would cut objects that leave the frame in some views."""
MAX_ERROR_PX = 2.0
MIN_TRACK = 3


@dataclass
class Poses:
    """Registered images of a reconstruction as arrays (COLMAP world frame, OpenCV camera axes)."""

    names: list[str]
    image_ids: list[int]
    c2w: np.ndarray
    """[N,4,4]"""
    intrinsics: np.ndarray
    """[4] fx, fy, cx, cy of the shared camera"""
    distortion: np.ndarray
    """[4] k1, k2, p1, p2"""
    width: int
    height: int
    model: str
    points: np.ndarray
    """[P,3] sparse points"""
    colors: np.ndarray
    """[P,3] uint8"""
    errors: np.ndarray
    track_lengths: np.ndarray


def poses_from_reconstruction(rec: Any) -> Poses:
    """Sorted-by-name registered images, their shared camera and the sparse points of a pycolmap Reconstruction."""
    images = sorted((rec.image(i) for i in rec.reg_image_ids()), key=lambda im: im.name)
    cam_ids = {im.camera_id for im in images}
    if len(cam_ids) != 1:
        raise ValueError(f"expected one shared camera, got {len(cam_ids)}")
    cam = rec.camera(cam_ids.pop())
    k, d = camera_intrinsics(ColmapCamera(cam.model.name, cam.width, cam.height, np.asarray(cam.params)))
    c2w = []
    for im in images:
        m = np.eye(4)
        m[:3, :4] = im.cam_from_world().inverse().matrix()
        c2w.append(m)
    pts = list(rec.points3D.values())
    return Poses(
        names=[im.name for im in images],
        image_ids=[int(im.image_id) for im in images],
        c2w=np.stack(c2w),
        intrinsics=np.asarray(k, np.float64),
        distortion=np.asarray(d, np.float64),
        width=int(cam.width),
        height=int(cam.height),
        model=cam.model.name,
        points=np.array([p.xyz for p in pts], np.float64).reshape(-1, 3),
        colors=np.array([p.color for p in pts], np.uint8).reshape(-1, 3),
        errors=np.array([p.error for p in pts], np.float64),
        track_lengths=np.array([p.track.length() for p in pts], np.int64),
    )


@dataclass
class Sphere:
    center: np.ndarray
    radius: float
    n_points: int
    method: str
    warnings: list[str] = field(default_factory=list)


def visible_fraction(points: np.ndarray, c2w: np.ndarray, intrinsics: np.ndarray, width: int, height: int
                     ) -> np.ndarray:
    """[P] fraction of the cameras in whose image (pinhole, in front of the camera) each point projects."""
    count = np.zeros(len(points))
    fx, fy, cx, cy = intrinsics
    for m in c2w:
        p = (points - m[:3, 3]) @ m[:3, :3]
        z = p[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u, v = fx * p[:, 0] / z + cx, fy * p[:, 1] / z + cy
        count += (z > 0) & (u >= 0) & (u < width) & (v >= 0) & (v < height)
    return count / max(len(c2w), 1)


def bounding_sphere(poses: Poses) -> Sphere:
    """Sphere around what the cameras look at, from the sparse points.

    Points with a reprojection error under 2 px seen in 3+ images are kept; for an object capture (optical
    axes that meet) only those inside 75% of the view frustums, anchored at the cameras' look-at point;
    points farther from the anchor than median + 3 MAD (scaled to a standard deviation) are outliers. The
    sphere is centred on the box of the 1st-99th percentiles of the rest and its radius is 1.1 times the 99th
    percentile distance, capped at 0.9 of the nearest camera distance.
    """
    warnings: list[str] = []
    centers, dirs = poses.c2w[:, :3, 3], poses.c2w[:, :3, 2]
    good = np.isfinite(poses.points).all(1) & (poses.errors < MAX_ERROR_PX) & (poses.track_lengths >= MIN_TRACK)
    pts = poses.points[good] if good.sum() >= 20 else poses.points[np.isfinite(poses.points).all(1)]
    anchor, cond = look_at_point(centers, dirs)
    object_centric = cond > 1e-2 and float(np.mean(np.einsum("ij,ij->i", anchor - centers, dirs) > 0)) >= 0.5
    method = "sparse-points"
    if len(pts) < 10:
        dist = float(np.median(np.linalg.norm(centers - anchor, axis=1)))
        half_fov = math.atan(0.5 * min(poses.width / poses.intrinsics[0], poses.height / poses.intrinsics[1]))
        warnings.append(f"only {len(pts)} usable sparse points: sphere taken from the cameras' look-at point")
        return Sphere(anchor, 1.2 * dist * math.sin(half_fov), len(pts), "camera-axes", warnings)
    if object_centric:
        seen = visible_fraction(pts, poses.c2w, poses.intrinsics, poses.width, poses.height) >= MIN_VISIBLE
        if seen.sum() >= 10:
            pts = pts[seen]
    else:
        anchor = np.median(pts, axis=0)
        warnings.append("the cameras' axes do not meet (forward-facing capture): sphere around the median point")
    d = np.linalg.norm(pts - anchor, axis=1)
    med = float(np.median(d))
    mad = float(np.median(np.abs(d - med))) * 1.4826
    pts = pts[d <= med + 3.0 * mad + 1e-12]
    lo, hi = np.percentile(pts, 1, axis=0), np.percentile(pts, 99, axis=0)
    center = 0.5 * (lo + hi)
    radius = SPHERE_MARGIN * float(np.percentile(np.linalg.norm(pts - center, axis=1), 99))
    nearest = float(np.linalg.norm(centers - center, axis=1).min())
    if radius > 0.9 * nearest:
        warnings.append(f"the sparse points reach the cameras: sphere radius capped at 0.9 x the nearest camera "
                        f"distance ({radius:.3g} -> {0.9 * nearest:.3g})")
        radius = 0.9 * nearest
    return Sphere(center, radius, len(pts), method, warnings)


def up_rotation(c2w: np.ndarray) -> np.ndarray:
    """[3,3] rotation taking the cameras' up direction (:func:`~anisdf.data.orbit.up_direction`) to +z."""
    up = up_direction(c2w).numpy()
    rot, _ = Rotation.align_vectors([[0.0, 0.0, 1.0]], [up])
    return rot.as_matrix()


def scene_transform(poses: Poses, sphere: Sphere) -> np.ndarray:
    """[4,4] rigid map from COLMAP's world to the scene frame: sphere centre at the origin, cameras' up +z."""
    r = up_rotation(poses.c2w)
    m = np.eye(4)
    m[:3, :3] = r
    m[:3, 3] = -r @ sphere.center
    return m


def transforms_dict(poses: Poses, sphere: Sphere, transform: np.ndarray, image_prefix: str, extra: dict[str, Any]
                    ) -> dict[str, Any]:
    """nerfstudio ``transforms.json`` content: OpenGL camera-to-world in the scene frame, shared intrinsics
    (COLMAP's pixel-centre convention), ``applied_transform`` (COLMAP world -> scene frame, 3x4) and anisdf's
    ``bounding_sphere`` (its region of interest)."""
    fx, fy, cx, cy = (float(v) for v in poses.intrinsics)
    k1, k2, p1, p2 = (float(v) for v in poses.distortion)
    frames = []
    for name, image_id, c2w in zip(poses.names, poses.image_ids, poses.c2w, strict=True):
        gl = transform @ c2w @ GL_TO_CV
        frames.append({"file_path": f"{image_prefix}/{name}", "transform_matrix": np.round(gl, 10).tolist(),
                       "colmap_im_id": image_id})
    distorted = any(v != 0.0 for v in (k1, k2, p1, p2))
    return {
        "w": poses.width, "h": poses.height, "fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy,
        "k1": k1, "k2": k2, "p1": p1, "p2": p2,
        "camera_model": "OPENCV" if distorted else "PINHOLE",
        "frames": frames,
        "applied_transform": np.round(transform[:3], 10).tolist(),
        "bounding_sphere": {"center": [0.0, 0.0, 0.0], "radius": float(sphere.radius), "method": sphere.method,
                            "n_points": sphere.n_points},
        **extra,
    }


def write_json(path: Path, data: dict[str, Any]) -> None:
    path.write_text(json.dumps(data, indent=2) + "\n", encoding="utf-8")


def write_points_ply(path: Path, points: np.ndarray, colors: np.ndarray) -> None:
    """Coloured point cloud (binary PLY) through trimesh."""
    import trimesh

    alpha = np.full((len(colors), 1), 255, np.uint8)
    trimesh.PointCloud(points, colors=np.hstack([colors, alpha])).export(path)


def _frustum(c2w: np.ndarray, intrinsics: np.ndarray, width: int, height: int, size: float) -> np.ndarray:
    """[5,3] apex and image-plane corners (at depth ``size``) of a camera."""
    fx, fy, cx, cy = intrinsics
    corners = [(0, 0), (width, 0), (width, height), (0, height)]
    pts = [np.zeros(3)] + [np.array([(u - cx) / fx, (v - cy) / fy, 1.0]) * size for u, v in corners]
    return np.stack(pts) @ c2w[:3, :3].T + c2w[:3, 3]


def draw_cameras(path: Path, c2w: np.ndarray, intrinsics: np.ndarray, width: int, height: int,
                 points: np.ndarray, colors: np.ndarray, radius: float, title: str = "", panel: int = 600) -> None:
    """Top (looking down -z) and side (looking along +y) orthographic views of the camera frustums (the first
    one green), the sparse points and the bounding sphere (red, centred at the origin), all in the scene frame.
    ``intrinsics``: [4] shared by the cameras, or [N,4]."""
    centers = c2w[:, :3, 3]
    extent = max(float(np.abs(centers).max()), radius) * 1.15
    frustum_size = 0.12 * extent
    img = Image.new("RGB", (2 * panel, panel + 44), "white")
    draw = ImageDraw.Draw(img)
    if len(points) > 60000:
        keep = np.random.default_rng(0).choice(len(points), 60000, replace=False)
        points, colors = points[keep], colors[keep]
    inside = np.abs(points).max(1) < extent
    for k, (ax_u, ax_v, label) in enumerate(((0, 1, "top view (x right, y up)"), (0, 2, "side view (x right, z up)"))):
        x0 = k * panel

        def to_px(p: np.ndarray, x0: int = x0, ax_u: int = ax_u, ax_v: int = ax_v) -> np.ndarray:
            s = 0.5 * panel / extent
            return np.stack([x0 + 0.5 * panel + p[..., ax_u] * s, 24 + 0.5 * panel - p[..., ax_v] * s], -1)

        for (u, v), c in zip(to_px(points[inside]), colors[inside], strict=True):
            draw.rectangle((float(u), float(v), float(u) + 1, float(v) + 1), fill=tuple(int(x) for x in c))
        (cu, cv), r_px = to_px(np.zeros(3)), radius * 0.5 * panel / extent
        draw.ellipse((cu - r_px, cv - r_px, cu + r_px, cv + r_px), outline=(220, 30, 30), width=2)
        for i in range(len(c2w) - 1, -1, -1):  # the first camera (green) last, on top
            f = to_px(_frustum(c2w[i], intrinsics if intrinsics.ndim == 1 else intrinsics[i], width, height,
                               frustum_size))
            colour = (20, 160, 20) if i == 0 else (30, 60, 200)
            for a, b in ((0, 1), (0, 2), (0, 3), (0, 4), (1, 2), (2, 3), (3, 4), (4, 1)):
                draw.line((*f[a], *f[b]), fill=colour, width=1)
        draw.text((x0 + 8, 4), label, fill="black")
        draw.line((x0, 0, x0, panel + 24), fill=(180, 180, 180))
    if title:
        draw.text((8, panel + 28), title, fill="black")
    img.save(path)
