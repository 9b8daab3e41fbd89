"""Tiny datasets with known cameras, written in every supported format (for tests and smoke runs).

:func:`write_test_scene` renders a sphere (coloured by its normal) from cameras on a ring around it and
writes images, masks, normal maps and camera files exactly as each format's own tools would. The returned
:class:`SceneTruth` keeps the ground-truth cameras (OpenCV axes, dataset frame, pixel centres at i + 0.5)
and projects points with a plain numpy implementation that shares no code with :mod:`anisdf.data`.
"""

from __future__ import annotations

import json
import math
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

TEST_FORMATS = ("nerf-synthetic", "neus", "instant-ngp", "llff", "colmap")


@dataclass
class SceneTruth:
    root: Path
    format: str
    c2w: np.ndarray
    """[N,4,4] OpenCV camera-to-world in the dataset frame."""
    intrinsics: np.ndarray
    """[N,4] fx, fy, cx, cy (pixel centres at i + 0.5)."""
    distortion: np.ndarray | None
    """[N,4] k1, k2, p1, p2 or None."""
    width: int
    height: int
    image_paths: list[Path]
    sphere_center: np.ndarray
    sphere_radius: float

    def project(self, points: np.ndarray, i: int) -> np.ndarray:
        """Reference projection of dataset-frame points ``[M,3]`` into camera ``i``: ``[M,2]`` pixels."""
        rot, center = self.c2w[i, :3, :3], self.c2w[i, :3, 3]
        pc = (points - center) @ rot
        x, y = pc[:, 0] / pc[:, 2], pc[:, 1] / pc[:, 2]
        if self.distortion is not None:
            k1, k2, p1, p2 = self.distortion[i]
            r2 = x * x + y * y
            radial = 1 + k1 * r2 + k2 * r2 * r2
            x, y = (x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
                    y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)
        fx, fy, cx, cy = self.intrinsics[i]
        return np.stack([fx * x + cx, fy * y + cy], axis=-1)

    def pixel_rays(self, i: int, px: np.ndarray, py: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Reference world rays (origin [3], unit directions [M,3]) through pixels, undistorting by a
        fixed-point iteration."""
        fx, fy, cx, cy = self.intrinsics[i]
        xd, yd = (px - cx) / fx, (py - cy) / fy
        x, y = xd.copy(), yd.copy()
        if self.distortion is not None:
            k1, k2, p1, p2 = self.distortion[i]
            for _ in range(100):
                r2 = x * x + y * y
                radial = 1 + k1 * r2 + k2 * r2 * r2
                x = (xd - 2 * p1 * x * y - p2 * (r2 + 2 * x * x)) / radial
                y = (yd - p1 * (r2 + 2 * y * y) - 2 * p2 * x * y) / radial
        d = np.stack([x, y, np.ones_like(x)], axis=-1) @ self.c2w[i, :3, :3].T
        return self.c2w[i, :3, 3], d / np.linalg.norm(d, axis=-1, keepdims=True)


def look_at(eye: np.ndarray, target: np.ndarray | None = None, up: np.ndarray | None = None) -> np.ndarray:
    """OpenCV camera-to-world (x right, y down, z forward) at ``eye`` looking at ``target`` (the origin), ``up``
    (+z) pointing up the image."""
    eye = np.asarray(eye, dtype=np.float64)
    target = np.zeros(3) if target is None else np.asarray(target, dtype=np.float64)
    up = np.array([0.0, 0.0, 1.0]) if up is None else np.asarray(up, dtype=np.float64)
    z = target - eye
    z = z / np.linalg.norm(z)
    x = np.cross(z, up)  # right = forward x up
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, y, z, eye
    return m


def rotmat_to_qvec(r: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a rotation matrix (Shepperd's method)."""
    tr = np.trace(r)
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = [0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = 2.0 * math.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2])
        q = [(r[2, 1] - r[1, 2]) / s, 0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s]
    elif r[1, 1] > r[2, 2]:
        s = 2.0 * math.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2])
        q = [(r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1])
        q = [(r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s]
    q = np.asarray(q)
    return q if q[0] >= 0 else -q


def _render(truth: SceneTruth, i: int, supersample: int = 4) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """RGB (sphere coloured (n+1)/2 over a gradient backdrop), coverage 0..1 and the normal map of view i."""
    w, h, s = truth.width, truth.height, supersample
    sub = (np.arange(s) + 0.5) / s
    px = (np.arange(w)[:, None] + sub[None]).reshape(-1)
    py = (np.arange(h)[:, None] + sub[None]).reshape(-1)
    gx, gy = np.meshgrid(px, py)
    origin, d = truth.pixel_rays(i, gx.reshape(-1), gy.reshape(-1))
    oc = origin - truth.sphere_center
    b = d @ oc
    disc = b * b - (oc @ oc - truth.sphere_radius**2)
    hit = disc > 0
    t = -b - np.sqrt(np.maximum(disc, 0.0))
    n = (origin + t[:, None] * d - truth.sphere_center) / truth.sphere_radius
    n[~hit] = 0.0
    colour = np.where(hit[:, None], 0.5 * (n + 1.0), 0.0)

    def pool(a: np.ndarray) -> np.ndarray:
        return a.reshape(h, s, w, s, -1).mean(axis=(1, 3))

    cov = pool(hit[:, None].astype(np.float64))[..., 0]
    rgb = pool(colour) / np.maximum(cov[..., None], 1e-9)  # straight colour of the covered part
    nmap = pool(n)
    nmap /= np.maximum(np.linalg.norm(nmap, axis=-1, keepdims=True), 1e-9)
    return rgb, cov, nmap


def _u8(a: np.ndarray) -> np.ndarray:
    return np.clip(np.round(a * 255.0), 0, 255).astype(np.uint8)


def _backdrop(h: int, w: int, i: int) -> np.ndarray:
    yy, xx = np.mgrid[0:h, 0:w]
    return np.stack([xx / max(w - 1, 1), yy / max(h - 1, 1), np.full((h, w), (i % 5) / 5.0)], axis=-1) * 0.6


def _write_view_images(truth: SceneTruth, rgba: bool, masks_dir: Path | None, normals: set[int],
                       normal_suffix: str = "_normal.png") -> None:
    for i, path in enumerate(truth.image_paths):
        rgb, cov, nmap = _render(truth, i)
        path.parent.mkdir(parents=True, exist_ok=True)
        if rgba:
            Image.fromarray(np.dstack([_u8(rgb), _u8(cov)]), "RGBA").save(path)
        else:
            photo = rgb * cov[..., None] + _backdrop(truth.height, truth.width, i) * (1 - cov[..., None])
            Image.fromarray(_u8(photo), "RGB").save(path)
        if masks_dir is not None:
            masks_dir.mkdir(parents=True, exist_ok=True)
            Image.fromarray(np.where(cov >= 0.5, 255, 0).astype(np.uint8), "L").save(
                masks_dir / (path.stem + ".png"))
        if i in normals:
            enc = np.dstack([_u8(0.5 * (nmap + 1.0) * (cov[..., None] > 0)), _u8(cov)])
            Image.fromarray(enc, "RGBA").save(path.with_name(path.stem + normal_suffix))


def write_test_scene(
    root: str | Path,
    fmt: str,
    n_images: int = 6,
    width: int = 16,
    height: int = 12,
    distortion: tuple[float, float, float, float] | None = None,
    binary: bool = True,
    masks: bool = False,
    radius: float = 2.5,
    center: tuple[float, float, float] = (0.3, -0.2, 0.1),
    sphere_radius: float = 0.5,
    normal_suffix: str = "_normal.png",
    aim: tuple[float, float, float] | None = None,
) -> SceneTruth:
    """Write a tiny dataset of format ``fmt`` into ``root`` (created) and return its ground truth.

    Cameras sit on a ring (alternating elevations) of ``radius`` around ``center`` and look at it; a sphere
    of ``sphere_radius`` sits at ``center``. ``distortion`` (k1, k2, p1, p2) applies to instant-ngp and
    COLMAP (OPENCV model; PINHOLE without it); ``binary`` picks COLMAP's .bin or .txt; ``masks`` writes
    object masks (always for NeuS; nerf-synthetic uses alpha). nerf-synthetic holds out views 1 and N-2 as
    its test split, with world-space normal maps ``(n + 1) / 2`` named ``<image stem><normal_suffix>``
    (``_normal.png`` as Shiny Blender, ``_normal_0001.png`` as NeRF-synthetic's test split). ``aim``: the point the
    cameras look at (default ``center``; elsewhere, the automatic region of interest of a capture without masks
    misses the sphere).
    """
    if fmt not in TEST_FORMATS:
        raise ValueError(f"unknown format {fmt!r}")
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    c = np.asarray(center, dtype=np.float64)
    up = np.array([0.0, 0.0, 1.0])
    c2w, intr = [], []
    base_f = 0.9 * width
    for i in range(n_images):
        phi = 2 * math.pi * i / n_images + 0.3
        elev = math.radians(25.0 if i % 2 == 0 else -10.0)
        ring = np.array([math.cos(elev) * math.cos(phi), math.cos(elev) * math.sin(phi), math.sin(elev)])
        eye = c + radius * ring
        c2w.append(look_at(eye, c if aim is None else np.asarray(aim, dtype=np.float64), up))
        if fmt in ("nerf-synthetic", "llff"):  # a single focal length, centred principal point
            intr.append([base_f, base_f, width / 2, height / 2])
        else:
            f = base_f * (1 + 0.02 * i)
            intr.append([f, 1.03 * f, width / 2 + 0.7, height / 2 - 0.4])
    c2w_a, intr_a = np.stack(c2w), np.asarray(intr)
    if fmt in ("instant-ngp", "colmap") and distortion is not None:
        dist = np.tile(np.asarray(distortion, dtype=np.float64), (n_images, 1))
    else:
        dist = None
    if fmt in ("colmap", "llff"):  # one shared camera
        intr_a[:] = intr_a[0]
    folder = {"nerf-synthetic": "train", "neus": "image", "instant-ngp": "images", "llff": "images",
              "colmap": "images"}[fmt]
    test_views = {1, n_images - 2} if fmt == "nerf-synthetic" and n_images >= 4 else set()
    paths = []
    for i in range(n_images):
        if i in test_views:
            paths.append(root / "test" / f"r_{i}.png")
        else:
            paths.append(root / folder / (f"{i:06d}.png" if fmt == "neus" else f"r_{i}.png"))
    truth = SceneTruth(root, fmt, c2w_a, intr_a, dist, width, height, paths, c, sphere_radius)
    mask_dir = {"neus": root / "mask"}.get(fmt, root / "masks" if masks and fmt != "nerf-synthetic" else None)
    _write_view_images(truth, fmt == "nerf-synthetic", mask_dir, test_views, normal_suffix)
    {"nerf-synthetic": _write_blender, "neus": _write_neus, "instant-ngp": _write_ngp, "llff": _write_llff,
     "colmap": _write_colmap}[fmt](truth, binary)
    return truth


GL_FROM_CV = np.diag([1.0, -1.0, -1.0, 1.0])


def _write_blender(t: SceneTruth, binary: bool) -> None:
    fx = t.intrinsics[0, 0]
    angle_x = 2 * math.atan(0.5 * t.width / fx)
    for split in ("train", "test"):
        frames = [
            {"file_path": f"./{split}/{p.stem}", "transform_matrix": (t.c2w[i] @ GL_FROM_CV).tolist()}
            for i, p in enumerate(t.image_paths)
            if p.parent.name == split
        ]
        meta = {"camera_angle_x": angle_x, "frames": frames}
        (t.root / f"transforms_{split}.json").write_text(json.dumps(meta, indent=1))


def _write_neus(t: SceneTruth, binary: bool) -> None:
    scale = 1.2 * t.sphere_radius
    scale_mat = np.eye(4)
    scale_mat[:3, :3] *= scale
    scale_mat[:3, 3] = t.sphere_center
    out = {}
    for i in range(len(t.image_paths)):
        fx, fy, cx, cy = t.intrinsics[i]
        # IDR/OpenCV intrinsics put pixel centres at integers: shift the principal point by -0.5.
        k = np.array([[fx, 0, cx - 0.5, 0], [0, fy, cy - 0.5, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
        w2c = np.linalg.inv(t.c2w[i])
        out[f"world_mat_{i}"] = k @ w2c
        out[f"scale_mat_{i}"] = scale_mat
        out[f"world_mat_inv_{i}"] = np.linalg.inv(k @ w2c)
    np.savez(t.root / "cameras_sphere.npz", **out)


def _write_ngp(t: SceneTruth, binary: bool) -> None:
    frames = []
    for i, p in enumerate(t.image_paths):
        fx, fy, cx, cy = t.intrinsics[i]
        frame = {"file_path": f"images/{p.name}", "transform_matrix": (t.c2w[i] @ GL_FROM_CV).tolist(),
                 "fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy}
        frames.append(frame)
    meta: dict = {"w": t.width, "h": t.height, "aabb_scale": 4, "frames": frames,
                  "applied_transform": np.eye(4)[:3].tolist()}
    if t.distortion is not None:
        meta.update(dict(zip(("k1", "k2", "p1", "p2"), t.distortion[0].tolist(), strict=True)))
    if (t.root / "masks").is_dir():
        for f, p in zip(frames, t.image_paths, strict=True):
            f["mask_path"] = f"masks/{p.stem}.png"
    (t.root / "transforms.json").write_text(json.dumps(meta, indent=1))


def _write_llff(t: SceneTruth, binary: bool) -> None:
    rows = []
    for i in range(len(t.image_paths)):
        right, down, fwd, cen = (t.c2w[i, :3, j] for j in range(4))
        hwf = np.array([t.height, t.width, t.intrinsics[i, 0]])
        pose = np.stack([down, right, -fwd, cen, hwf], axis=1)  # LLFF columns: [down, right, back, t, hwf]
        depth = np.linalg.norm(cen - t.sphere_center)
        rows.append(np.concatenate([pose.reshape(-1), [depth - 1.0, depth + 1.0]]))
    np.save(t.root / "poses_bounds.npy", np.asarray(rows))


def _write_colmap(t: SceneTruth, binary: bool) -> None:
    d = t.root / "sparse" / "0"
    d.mkdir(parents=True, exist_ok=True)
    fx, fy, cx, cy = t.intrinsics[0]
    if t.distortion is not None:
        model, model_id, params = "OPENCV", 4, [fx, fy, cx, cy, *t.distortion[0]]
    else:
        model, model_id, params = "PINHOLE", 1, [fx, fy, cx, cy]
    poses = []
    for i, p in enumerate(t.image_paths):
        w2c = np.linalg.inv(t.c2w[i])
        poses.append((i + 1, rotmat_to_qvec(w2c[:3, :3]), w2c[:3, 3], p.name))
    if binary:
        cam = struct.pack("<QiiQQ", 1, 1, model_id, t.width, t.height)
        (d / "cameras.bin").write_bytes(cam + struct.pack(f"<{len(params)}d", *params))
        blob = struct.pack("<Q", len(poses))
        for image_id, q, tv, name in poses:
            blob += struct.pack("<idddddddi", image_id, *q, *tv, 1) + name.encode() + b"\x00"
            blob += struct.pack("<Q", 2) + struct.pack("<ddqddq", 1.5, 2.5, -1, 3.5, 4.5, 7)
        (d / "images.bin").write_bytes(blob)
    else:
        (d / "cameras.txt").write_text(
            "# Camera list with one line of data per camera:\n"
            f"1 {model} {t.width} {t.height} {' '.join(repr(float(v)) for v in params)}\n")
        lines = ["# Image list with two lines of data per image:"]
        for k, (image_id, q, tv, name) in enumerate(poses):
            vals = " ".join(repr(float(v)) for v in (*q, *tv))
            lines.append(f"{image_id} {vals} 1 {name}")
            lines.append("" if k % 2 else "1.5 2.5 -1 3.5 4.5 7")
        (d / "images.txt").write_text("\n".join(lines) + "\n")
    if binary:  # a model has its three files in one format; no 3D points here
        (d / "points3D.bin").write_bytes(struct.pack("<Q", 0))
    else:
        (d / "points3D.txt").write_text("# empty\n")


@dataclass
class ObjectCapture:
    root: Path
    truth_masks: list[np.ndarray]
    """[H,W] bool per view, the object's true silhouettes (in image order)."""


def _object_hit(origin: np.ndarray, d: np.ndarray, spheres: list[tuple[np.ndarray, float]]
                ) -> tuple[np.ndarray, np.ndarray]:
    """Nearest hit distance (inf for a miss) and unit normal of rays against a union of spheres."""
    t_best = np.full(len(d), np.inf)
    n_best = np.zeros_like(d)
    for c, r in spheres:
        oc = origin - c
        b = d @ oc
        disc = b * b - (oc @ oc - r * r)
        t = np.where(disc > 0, -b - np.sqrt(np.maximum(disc, 0.0)), np.inf)
        t = np.where(t > 0, t, np.inf)
        closer = t < t_best
        t_best = np.where(closer, t, t_best)
        n_best[closer] = (origin + t[closer, None] * d[closer] - c) / r
    return t_best, n_best


def write_object_capture(root: str | Path, n_images: int = 16, width: int = 64, height: int = 48,
                         supersample: int = 2) -> ObjectCapture:
    """A process-data style object capture without its masks: a striped orange object (two spheres) in a room
    papered with a blue-grey checker, seen from a ring of cameras; ``transforms.json`` (instant-ngp, with anisdf's
    ``bounding_sphere``) and ``sparse_pc.ply`` (points on the object and a few on the walls), as
    ``anisdf process-data`` writes them. The true silhouettes are returned, not written."""
    import trimesh

    root = Path(root)
    (root / "images").mkdir(parents=True, exist_ok=True)
    spheres = [(np.array([0.0, 0.0, 0.0]), 0.5), (np.array([0.25, 0.1, 0.45]), 0.28)]
    rng = np.random.default_rng(3)
    f = 0.9 * width
    frames, truths = [], []
    s = supersample
    sub = (np.arange(s) + 0.5) / s
    for i in range(n_images):
        phi = 2 * math.pi * i / n_images
        elev = math.radians(30.0 if i % 2 == 0 else 5.0)
        eye = 2.6 * np.array([math.cos(elev) * math.cos(phi), math.cos(elev) * math.sin(phi), math.sin(elev)])
        c2w = look_at(eye, np.array([0.0, 0.0, 0.1]), np.array([0.0, 0.0, 1.0]))
        px = (np.arange(width)[:, None] + sub[None]).reshape(-1)
        py = (np.arange(height)[:, None] + sub[None]).reshape(-1)
        gx, gy = np.meshgrid(px, py)
        d = np.stack([(gx - width / 2) / f, (gy - height / 2) / f, np.ones_like(gx)], -1).reshape(-1, 3) @ c2w[:3, :3].T
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        t, n = _object_hit(eye, d, spheres)
        hit = np.isfinite(t)
        p = eye + np.where(hit, t, 0.0)[:, None] * d
        stripes = 0.5 + 0.5 * np.sin(14.0 * p[:, 2] + 6.0 * p[:, 0])
        shade = 0.45 + 0.55 * np.clip(n @ np.array([0.4, -0.3, 0.87]), 0.0, 1.0)
        obj = np.stack([0.9 * np.ones_like(stripes), 0.35 + 0.25 * stripes, 0.1 + 0.05 * stripes], -1) * shade[:, None]
        az, el = np.arctan2(d[:, 1], d[:, 0]), np.arcsin(np.clip(d[:, 2], -1, 1))
        check = (np.floor(az * 6 / math.pi) + np.floor(el * 6 / math.pi)) % 2
        light = 0.85 + 0.15 * np.cos(3 * az)
        wall = np.where(check[:, None] > 0, [0.55, 0.6, 0.68], [0.25, 0.3, 0.42]) * light[:, None]
        rgb = np.where(hit[:, None], obj, wall).reshape(height, s, width, s, 3).mean(axis=(1, 3))
        cov = hit.astype(np.float64).reshape(height, s, width, s).mean(axis=(1, 3))
        Image.fromarray(_u8(rgb), "RGB").save(root / "images" / f"view_{i:02d}.png")
        truths.append(cov >= 0.5)
        frames.append({"file_path": f"images/view_{i:02d}.png", "transform_matrix": (c2w @ GL_FROM_CV).tolist()})
    surface = []
    for c, r in spheres:
        v = rng.standard_normal((150, 3))
        surface.append(c + r * v / np.linalg.norm(v, axis=1, keepdims=True))
    pts = np.concatenate(surface)
    pts = pts[np.min([np.linalg.norm(pts - c, axis=1) - r for c, r in spheres], axis=0) > -1e-9]
    walls = rng.standard_normal((20, 3))
    pts = np.concatenate([pts, 6.0 * walls / np.linalg.norm(walls, axis=1, keepdims=True)])
    trimesh.PointCloud(pts, colors=np.full((len(pts), 4), 200, np.uint8)).export(root / "sparse_pc.ply")
    meta = {"w": width, "h": height, "fl_x": f, "fl_y": f, "cx": width / 2, "cy": height / 2,
            "camera_model": "PINHOLE", "frames": frames, "ply_file_path": "sparse_pc.ply",
            "bounding_sphere": {"center": [0.05, 0.02, 0.12], "radius": 0.95, "method": "sparse-points"}}
    (root / "transforms.json").write_text(json.dumps(meta, indent=1))
    return ObjectCapture(root, truths)
