"""COLMAP sparse models: ``sparse/0/{cameras,images}.{bin,txt}`` (or ``sparse/`` directly), ``images/``.

COLMAP stores world-to-camera poses (``qvec`` = w, x, y, z and ``tvec``) in OpenCV axes and intrinsics in
the ``i + 0.5`` pixel-centre convention. Supported camera models: SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL,
RADIAL (radial terms mapped to k1, k2) and OPENCV. Optional ``masks/`` as for LLFF (``a.jpg`` ->
``a.jpg.png`` as COLMAP names them, ``a.png``, or sorted order). Images are sorted by name; the test split
holds out every 8th.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from anisdf.data.dataparsers._common import ParsedScene, check_camera, check_pose, holdout_splits, match_masks
from anisdf.errors import DataError

# model id -> (name, number of parameters), as in COLMAP's src/colmap/sensor/models.h
CAMERA_MODELS = {
    0: ("SIMPLE_PINHOLE", 3),
    1: ("PINHOLE", 4),
    2: ("SIMPLE_RADIAL", 4),
    3: ("RADIAL", 5),
    4: ("OPENCV", 8),
    5: ("OPENCV_FISHEYE", 8),
    6: ("FULL_OPENCV", 12),
    7: ("FOV", 5),
    8: ("SIMPLE_RADIAL_FISHEYE", 4),
    9: ("RADIAL_FISHEYE", 5),
    10: ("THIN_PRISM_FISHEYE", 12),
    11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16),
}
MODEL_PARAMS = {name: n for name, n in CAMERA_MODELS.values()}


@dataclass
class ColmapCamera:
    model: str
    width: int
    height: int
    params: np.ndarray


@dataclass
class ColmapImage:
    qvec: np.ndarray
    tvec: np.ndarray
    camera_id: int
    name: str


def find_model(root: Path) -> Path | None:
    """The folder holding cameras.{bin,txt} and images.{bin,txt}: ``sparse/0`` or ``sparse``."""
    for d in (root / "sparse" / "0", root / "sparse"):
        for ext in (".bin", ".txt"):
            if (d / f"cameras{ext}").is_file() and (d / f"images{ext}").is_file():
                return d
    return None


class _Reader:
    """Little-endian struct reader that turns a short file into a DataError."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.data = path.read_bytes()
        self.pos = 0

    def read(self, fmt: str) -> tuple:
        size = struct.calcsize("<" + fmt)
        if self.pos + size > len(self.data):
            raise DataError(self.path, f"file is truncated (at byte {self.pos} of {len(self.data)})")
        out = struct.unpack_from("<" + fmt, self.data, self.pos)
        self.pos += size
        return out

    def read_cstring(self) -> str:
        end = self.data.find(b"\x00", self.pos)
        if end < 0:
            raise DataError(self.path, "file is truncated (unterminated image name)")
        out = self.data[self.pos:end].decode("utf-8", errors="replace")
        self.pos = end + 1
        return out


def read_cameras_bin(path: Path) -> dict[int, ColmapCamera]:
    r = _Reader(path)
    (n,) = r.read("Q")
    cams = {}
    for _ in range(n):
        cam_id, model_id, width, height = r.read("iiQQ")
        if model_id not in CAMERA_MODELS:
            raise DataError(path, f"camera {cam_id}: unknown camera model id {model_id}")
        name, n_params = CAMERA_MODELS[model_id]
        cams[cam_id] = ColmapCamera(name, width, height, np.array(r.read("d" * n_params)))
    return cams


def read_images_bin(path: Path) -> dict[int, ColmapImage]:
    r = _Reader(path)
    (n,) = r.read("Q")
    images = {}
    for _ in range(n):
        image_id, qw, qx, qy, qz, tx, ty, tz, cam_id = r.read("idddddddi")
        name = r.read_cstring()
        (n_points,) = r.read("Q")
        if r.pos + 24 * n_points > len(r.data):
            raise DataError(path, f"file is truncated (image {name} lists {n_points} points)")
        r.pos += 24 * n_points  # x, y (double) and point3D id (int64) per observation
        images[image_id] = ColmapImage(np.array([qw, qx, qy, qz]), np.array([tx, ty, tz]), cam_id, name)
    return images


def _data_lines(path: Path) -> list[tuple[int, str]]:
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise DataError(path, f"cannot read file ({exc})") from None
    return [(i + 1, line.strip()) for i, line in enumerate(text.splitlines())]


def read_cameras_txt(path: Path) -> dict[int, ColmapCamera]:
    cams = {}
    for lineno, line in _data_lines(path):
        if not line or line.startswith("#"):
            continue
        parts = line.split()
        try:
            cam_id, model, width, height = int(parts[0]), parts[1], int(parts[2]), int(parts[3])
            params = np.array([float(p) for p in parts[4:]])
        except (IndexError, ValueError):
            raise DataError(path, f"line {lineno}: malformed camera line") from None
        if model not in MODEL_PARAMS or len(params) != MODEL_PARAMS[model]:
            raise DataError(path, f"line {lineno}: unknown model {model!r} or wrong number of parameters")
        cams[cam_id] = ColmapCamera(model, width, height, params)
    return cams


def read_images_txt(path: Path) -> dict[int, ColmapImage]:
    images = {}
    lines = [(n, s) for n, s in _data_lines(path) if not s.startswith("#")]
    i = 0
    while i < len(lines):
        lineno, line = lines[i]
        if not line:  # blank separators between records (the points line after a record may be blank too)
            i += 1
            continue
        parts = line.split()
        try:
            image_id = int(parts[0])
            vals = [float(p) for p in parts[1:8]]
            cam_id = int(parts[8])
            name = " ".join(parts[9:])
        except (IndexError, ValueError):
            raise DataError(path, f"line {lineno}: malformed image line") from None
        if len(vals) != 7 or not name:
            raise DataError(path, f"line {lineno}: malformed image line")
        images[image_id] = ColmapImage(np.array(vals[:4]), np.array(vals[4:]), cam_id, name)
        i += 2  # the next line lists the 2D points (possibly empty)
    return images


def qvec_to_rotmat(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def camera_intrinsics(cam: ColmapCamera) -> tuple[list[float], list[float]]:
    """(fx, fy, cx, cy) and OpenCV (k1, k2, p1, p2) of a supported COLMAP camera."""
    p = [float(v) for v in cam.params]
    if cam.model == "SIMPLE_PINHOLE":
        return [p[0], p[0], p[1], p[2]], [0.0] * 4
    if cam.model == "PINHOLE":
        return p[:4], [0.0] * 4
    if cam.model == "SIMPLE_RADIAL":
        return [p[0], p[0], p[1], p[2]], [p[3], 0.0, 0.0, 0.0]
    if cam.model == "RADIAL":
        return [p[0], p[0], p[1], p[2]], [p[3], p[4], 0.0, 0.0]
    if cam.model == "OPENCV":
        return p[:4], p[4:8]
    raise ValueError(cam.model)


def parse(root: Path) -> ParsedScene:
    model_dir = find_model(root)
    if model_dir is None:
        raise DataError(root / "sparse" / "0", "no COLMAP model (cameras.bin/.txt and images.bin/.txt)")
    binary = (model_dir / "cameras.bin").is_file() and (model_dir / "images.bin").is_file()
    cam_file = model_dir / ("cameras.bin" if binary else "cameras.txt")
    img_file = model_dir / ("images.bin" if binary else "images.txt")
    cams = read_cameras_bin(cam_file) if binary else read_cameras_txt(cam_file)
    recs = read_images_bin(img_file) if binary else read_images_txt(img_file)
    if not recs:
        raise DataError(img_file, "no registered images")
    image_dir = root / "images"
    records = sorted(recs.values(), key=lambda r: r.name)
    image_paths, poses, intr, dist = [], [], [], []
    size: tuple[int, int] | None = None
    for rec in records:
        where = f"image {rec.name}"
        cam = cams.get(rec.camera_id)
        if cam is None:
            raise DataError(img_file, f"{where}: camera {rec.camera_id} is not in {cam_file.name}")
        if cam.model not in ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV"):
            raise DataError(cam_file, f"camera {rec.camera_id}: model {cam.model} is not supported")
        if size is None:
            size = (cam.width, cam.height)
        elif (cam.width, cam.height) != size:
            raise DataError(cam_file, f"camera {rec.camera_id}: size {cam.width}x{cam.height} differs from "
                            f"{size[0]}x{size[1]} (all images must share one size)")
        finite = np.isfinite(rec.qvec).all() and np.isfinite(rec.tvec).all()
        if not finite or np.linalg.norm(rec.qvec) < 1e-8:
            raise DataError(img_file, f"{where}: pose is not finite")
        if not np.isfinite(cam.params).all():
            raise DataError(cam_file, f"camera {rec.camera_id}: parameters are not finite")
        rot = qvec_to_rotmat(rec.qvec)
        c2w = np.eye(4)
        c2w[:3, :3] = rot.T
        c2w[:3, 3] = -rot.T @ rec.tvec
        poses.append(check_pose(c2w, img_file, where))
        k, d = camera_intrinsics(cam)
        check_camera(k, (cam.width, cam.height), cam_file, f"camera {rec.camera_id} ({rec.name})", d)
        intr.append(k)
        dist.append(d)
        image_paths.append(image_dir / rec.name)
    distortion = np.asarray(dist, dtype=np.float64)
    mask_paths = match_masks(image_paths, root / "masks") if (root / "masks").is_dir() else None
    return ParsedScene(
        format="colmap",
        root=root,
        image_paths=image_paths,
        c2w=np.stack(poses),
        intrinsics=np.asarray(intr, dtype=np.float64),
        size=size,
        splits=holdout_splits(len(image_paths)),
        distortion=distortion if np.any(distortion != 0) else None,
        mask_paths=mask_paths,
    )
