"""LLFF: ``poses_bounds.npy`` ``[N,17]`` with ``images/`` (sorted) and optional ``masks/``.

Each row is a 3x5 matrix (row-major) followed by the near/far bounds. Its first three columns are the
camera's axes in the world, in LLFF's order **[down, right, back]**; the fourth is the camera centre and the
fifth is ``[h, w, focal]``. OpenCV's [right, down, forward] is therefore ``[col1, col0, -col2]``.
When the images on disk differ in size from ``h, w`` the focal length is scaled to match (by the loader).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from anisdf.data.dataparsers._common import ParsedScene, check_pose, holdout_splits, list_images, match_masks
from anisdf.errors import DataError


def llff_to_opencv(pose_3x5: np.ndarray) -> np.ndarray:
    """4x4 OpenCV camera-to-world from one LLFF 3x5 pose (hwf column dropped)."""
    down, right, back, center = (pose_3x5[:, j] for j in range(4))
    c2w = np.eye(4)
    c2w[:3, 0] = right
    c2w[:3, 1] = down
    c2w[:3, 2] = -back
    c2w[:3, 3] = center
    return c2w


def parse(root: Path) -> ParsedScene:
    path = root / "poses_bounds.npy"
    try:
        arr = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise DataError(path, f"cannot read npy ({exc})") from None
    if arr.ndim != 2 or arr.shape[1] != 17 or arr.shape[0] == 0:
        raise DataError(path, f"expected an array of shape [N,17], got {list(arr.shape)}")
    arr = arr.astype(np.float64)
    image_dir = root / "images"
    images = list_images(image_dir)
    if not images:
        raise DataError(image_dir, "no images found")
    if len(images) != arr.shape[0]:
        raise DataError(path, f"{arr.shape[0]} poses for {len(images)} images in {image_dir.name}/")
    poses = arr[:, :15].reshape(-1, 3, 5)
    bounds = arr[:, 15:]
    c2w, intr = [], []
    h, w = None, None
    for i, img in enumerate(images):
        where = f"row {i} ({img.name})"
        if not np.isfinite(arr[i]).all():
            raise DataError(path, f"{where}: pose is not finite")
        hi, wi, f = poses[i, :, 4]
        if not (hi > 0 and wi > 0 and f > 0):
            raise DataError(path, f"{where}: invalid h, w, focal = {hi:g}, {wi:g}, {f:g}")
        if h is None:
            h, w = hi, wi
        elif (hi, wi) != (h, w):
            raise DataError(path, f"{where}: h, w = {hi:g}, {wi:g} differ from row 0's {h:g}, {w:g}")
        c2w.append(check_pose(llff_to_opencv(poses[i]), path, where))
        intr.append([f, f, wi / 2.0, hi / 2.0])
        near, far = bounds[i]
        if not near < far:
            raise DataError(path, f"{where}: bounds near, far = {near:g}, {far:g} need near < far")
    assert h is not None and w is not None
    warnings: list[str] = []
    valid = bounds[(bounds > 0).all(axis=1)]
    depth_hint = float(np.median(valid.mean(axis=1))) if len(valid) else None
    mask_paths = match_masks(images, root / "masks") if (root / "masks").is_dir() else None
    return ParsedScene(
        format="llff",
        root=root,
        image_paths=images,
        c2w=np.stack(c2w),
        intrinsics=np.asarray(intr),
        size=(int(round(w)), int(round(h))),
        splits=holdout_splits(len(images)),
        mask_paths=mask_paths,
        depth_hint=depth_hint,
        warnings=warnings,
    )
