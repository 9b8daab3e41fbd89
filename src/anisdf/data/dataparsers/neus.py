"""NeuS / IDR / DTU: ``cameras_sphere.npz`` (``world_mat_i``, ``scale_mat_i``), ``image/``, ``mask/``.

``world_mat_i`` is the 3x4 (or 4x4) projection ``K [R | t]`` into pixel coordinates whose pixel centres lie
at integers (OpenCV / IDR convention: NeuS shoots the ray of pixel ``i`` through coordinate ``i``), so the
principal point is shifted by +0.5 into anisdf's ``i + 0.5`` convention. ``scale_mat_i`` maps the NeuS
unit-sphere frame to the dataset frame (standard NeuS: ``P = world_mat @ scale_mat``); it becomes
``Scene.to_world``. The decomposition is ``load_K_Rt_from_P`` of NeuS, written with ``scipy.linalg.rq``.
"""

from __future__ import annotations

import pickle
import re
import zipfile
from pathlib import Path

import numpy as np
import scipy.linalg

from anisdf.data.dataparsers._common import ParsedScene, check_camera, check_pose, holdout_splits, list_images
from anisdf.errors import DataError

NPZ_NAMES = ("cameras_sphere.npz", "cameras.npz")


def find_npz(root: Path) -> Path | None:
    for name in NPZ_NAMES:
        if (root / name).is_file():
            return root / name
    return None


def decompose_projection(P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split a 3x4 projection ``P = K [R | t]`` into ``K`` (3x3, positive diagonal, ``K[2,2] = 1``) and the
    4x4 camera-to-world matrix ``[R^T | C]`` with ``C = -M^-1 p4`` the camera centre."""
    P = np.asarray(P, dtype=np.float64)[:3, :4]
    if np.linalg.det(P[:, :3]) < 0:  # P and -P are the same projection; pick the one with det(K R) > 0
        P = -P
    M = P[:, :3]
    K, R = scipy.linalg.rq(M)
    T = np.diag(np.sign(np.diag(K)))
    K, R = K @ T, T @ R
    center = -np.linalg.solve(M, P[:, 3])
    c2w = np.eye(4)
    c2w[:3, :3] = R.T
    c2w[:3, 3] = center
    return K / K[2, 2], c2w


def parse(root: Path) -> ParsedScene:
    npz_path = find_npz(root)
    if npz_path is None:
        raise DataError(root / NPZ_NAMES[0], "file is missing")
    image_dir = root / "image"
    images = list_images(image_dir)
    if not images:
        raise DataError(image_dir, "no images found (expected image/*.png)")
    try:
        with np.load(npz_path) as npz:
            cams = {k: np.asarray(npz[k]) for k in npz.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError, pickle.UnpicklingError) as exc:
        raise DataError(npz_path, f"cannot read npz ({exc})") from None
    poses, intr, warnings = [], [], []
    scale_mat: np.ndarray | None = None
    for i, img in enumerate(images):
        for key in (f"world_mat_{i}", f"scale_mat_{i}"):
            if key not in cams:
                raise DataError(npz_path, f"missing key '{key}' (there are {len(images)} images)")
        world = cams[f"world_mat_{i}"].astype(np.float64)
        scale = cams[f"scale_mat_{i}"].astype(np.float64)
        if world.shape not in ((3, 4), (4, 4)) or scale.shape != (4, 4):
            shapes = f"{world.shape}, {scale.shape}"
            raise DataError(npz_path, f"world_mat_{i} / scale_mat_{i} have shapes {shapes}, expected 4x4")
        if not (np.isfinite(world).all() and np.isfinite(scale).all()):
            raise DataError(npz_path, f"world_mat_{i} or scale_mat_{i} ({img.name}) is not finite")
        if abs(np.linalg.det(world[:3, :3])) < 1e-12:
            raise DataError(npz_path, f"world_mat_{i} ({img.name}) is singular")
        K, c2w = decompose_projection(world)
        poses.append(check_pose(c2w, npz_path, f"world_mat_{i} ({img.name})"))
        if abs(K[0, 1]) > 1e-3 * K[0, 0] and not warnings:
            warnings.append(f"{npz_path.name}: camera skew {K[0, 1]:.3g} ignored")
        intr.append([K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5])
        check_camera(intr[-1], None, npz_path, f"world_mat_{i} ({img.name})")
        if scale_mat is None:
            scale_mat = scale
    assert scale_mat is not None
    lin = scale_mat[:3, :3]
    to_world: np.ndarray | None = scale_mat
    if not (np.allclose(lin, lin[0, 0] * np.eye(3), rtol=1e-5, atol=1e-9) and lin[0, 0] > 0):
        warnings.append(f"{npz_path.name}: scale_mat_0 is not a uniform scale + translation; region of "
                        "interest estimated from the images instead")
        to_world = None
    extra = [k for k in cams if (m := re.fullmatch(r"world_mat_(\d+)", k)) and int(m.group(1)) >= len(images)]
    if extra:
        warnings.append(f"{npz_path.name} has {len(extra)} more cameras than image/ has images")
    mask_paths = None
    mask_dir = root / "mask"
    if mask_dir.is_dir():
        masks = list_images(mask_dir)
        if len(masks) != len(images):
            raise DataError(mask_dir, f"{len(masks)} masks for {len(images)} images (counts must match)")
        mask_paths = masks
    return ParsedScene(
        format="neus",
        root=root,
        image_paths=images,
        c2w=np.stack(poses),
        intrinsics=np.asarray(intr),
        size=None,
        splits=holdout_splits(len(images)),
        mask_paths=mask_paths,
        to_world=None if to_world is None else to_world.copy(),
        warnings=warnings,
    )
