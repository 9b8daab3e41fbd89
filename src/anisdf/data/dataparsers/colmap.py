"""COLMAP sparse models: ``sparse/0/{cameras,images,points3D}.{bin,txt}`` (or ``sparse/`` directly), ``images/``.

Read with pycolmap (the reader ``process-data`` uses too: one reader for one format). COLMAP stores
world-to-camera poses in OpenCV axes and intrinsics in the ``i + 0.5`` pixel-centre convention. Supported camera
models: SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL (radial terms mapped to k1, k2) and OPENCV. Optional
``masks/`` as for LLFF (``a.jpg`` -> ``a.jpg.png`` as COLMAP names them, ``a.png``, or sorted order). Images are
sorted by name; the test split holds out every 8th.
"""

from __future__ import annotations

import shutil
import struct
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from anisdf.data.dataparsers._common import ParsedScene, check_camera, check_pose, holdout_splits, match_masks
from anisdf.errors import DataError

SUPPORTED_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")
MODEL_FILES = ("cameras", "images", "points3D")


@dataclass
class ColmapCamera:
    model: str
    width: int
    height: int
    params: np.ndarray


@dataclass
class ColmapImage:
    rotation: np.ndarray
    """[3, 3] world-to-camera rotation."""
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


def read_model(model_dir: Path) -> tuple[dict[int, ColmapCamera], dict[int, ColmapImage], Path, Path]:
    """Cameras and posed images of the COLMAP model in ``model_dir`` (pycolmap), and the cameras and images files."""
    import pycolmap

    ext = ".bin" if all((model_dir / f"{n}.bin").is_file() for n in ("cameras", "images")) else ".txt"
    cam_file, img_file = model_dir / f"cameras{ext}", model_dir / f"images{ext}"
    files = ", ".join(n + ext for n in MODEL_FILES)
    try:
        if (model_dir / f"points3D{ext}").is_file():
            rec = pycolmap.Reconstruction(str(model_dir))
        else:  # poses written by hand or by other tools often come without 3D points, which pycolmap wants
            with tempfile.TemporaryDirectory() as tmp:
                for f in (cam_file, img_file):
                    shutil.copy(f, tmp)
                points = Path(tmp) / f"points3D{ext}"
                points.write_bytes(struct.pack("<Q", 0)) if ext == ".bin" else points.write_text("")
                rec = pycolmap.Reconstruction(tmp)
    except Exception as exc:  # pycolmap raises ValueError, IndexError, RuntimeError... on a corrupt model
        raise DataError(model_dir, f"COLMAP cannot read {files}: a file is truncated or corrupt "
                        f"(pycolmap: {' '.join(str(exc).split())})") from None
    cams = {i: ColmapCamera(c.model.name, int(c.width), int(c.height), np.asarray(c.params, dtype=np.float64))
            for i, c in rec.cameras.items()}
    images = {}
    for i, im in rec.images.items():
        if not im.has_pose:
            continue
        pose = im.cam_from_world()
        images[i] = ColmapImage(np.asarray(pose.rotation.matrix(), dtype=np.float64),
                                np.asarray(pose.translation, dtype=np.float64), int(im.camera_id), im.name)
    return cams, images, cam_file, img_file


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
    cams, recs, cam_file, img_file = read_model(model_dir)
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
        if cam.model not in SUPPORTED_MODELS:
            raise DataError(cam_file, f"camera {rec.camera_id}: model {cam.model} is not supported")
        if size is None:
            size = (cam.width, cam.height)
        elif (cam.width, cam.height) != size:
            raise DataError(cam_file, f"camera {rec.camera_id}: size {cam.width}x{cam.height} differs from "
                            f"{size[0]}x{size[1]} (all images must share one size)")
        if not (np.isfinite(rec.rotation).all() and np.isfinite(rec.tvec).all()):
            raise DataError(img_file, f"{where}: pose is not finite")
        if not np.isfinite(cam.params).all():
            raise DataError(cam_file, f"camera {rec.camera_id}: parameters are not finite")
        rot = rec.rotation
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
