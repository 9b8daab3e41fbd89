"""Turn a parser's :class:`ParsedScene` into a normalised :class:`Scene`: decode images, masks and
normal maps (thread pool), check sizes, scale intrinsics, find the region of interest and normalise."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from anisdf.data.alpha import ALPHA_MODES, detect
from anisdf.data.cameras import Cameras
from anisdf.data.dataparsers._common import ParsedScene, image_size
from anisdf.data.images import (
    DECODE_ERRORS,
    capped_downscale,
    parallel_map,
    read_mask,
    read_normal,
    read_rgb,
    target_size,
)
from anisdf.data.normalize import (
    RegionOfInterest,
    camera_roi,
    check_roi_values,
    check_user_roi,
    user_roi,
    visual_hull_roi,
)
from anisdf.data.scene import Scene
from anisdf.errors import AnisdfError, DataError

MIN_ROI_VIEWS = 8
ALPHA_SAMPLE_IMAGES = 8  # images whose partly covered pixels tell straight from premultiplied colour


def _may_have_alpha(path: Path) -> bool:
    """Whether the image's header allows an alpha channel (read without decoding the pixels); True when the header
    cannot be read, so that decoding names the file and the problem."""
    try:
        with Image.open(path) as im:
            return im.mode in ("RGBA", "LA", "PA", "RGBa", "La") or "transparency" in im.info
    except DECODE_ERRORS:
        return True


def alpha_convention(paths: list[Path], requested: str) -> tuple[str, str]:
    """How the RGBA images at ``paths`` hold colour (``data.alpha``: auto | straight | premultiplied) and why: ``auto``
    looks at the first images that have alpha (:func:`anisdf.data.alpha.detect`). ``("straight", "")`` without
    alpha."""
    if requested not in ALPHA_MODES:
        raise AnisdfError(f"data.alpha must be one of {', '.join(ALPHA_MODES)}, got {requested!r}")
    if requested != "auto":
        return requested, f"data.alpha={requested}"
    with_alpha = [p for p in paths[:ALPHA_SAMPLE_IMAGES] if _may_have_alpha(p)]  # photos: no decode here
    samples = [(rgb, a) for rgb, a, _ in (read_rgb(p) for p in with_alpha) if a is not None]
    return detect(samples) if samples else ("straight", "")


def select_images(parsed: ParsedScene, max_images: int) -> list[int]:
    """Indices kept: every image, except that the train split is thinned evenly to ``max_images``."""
    train = parsed.splits["train"]
    if max_images <= 0 or max_images >= len(train):
        return list(range(len(parsed.image_paths)))
    pick = {train[i] for i in np.round(np.linspace(0, len(train) - 1, max_images)).astype(int)}
    dropped = set(train) - pick
    return [i for i in range(len(parsed.image_paths)) if i not in dropped]


def _check_size(paths: list[Path], sizes: list[tuple[int, int]], ref: tuple[int, int], ref_path: Path,
                what: str) -> None:
    for p, s in zip(paths, sizes, strict=True):
        if s != ref:
            raise DataError(p, f"{what} is {s[0]}x{s[1]} but {ref_path.name} is {ref[0]}x{ref[1]} "
                            "(all images of a scene must share one size)")


def build_scene(parsed: ParsedScene, downscale: float = 1.0, max_images: int = 0,
                roi_center: tuple[float, ...] = (), roi_radius: float = 0.0, min_size: int = 0,
                alpha_mode: str = "auto") -> Scene:
    """Decode and normalise a parsed dataset (see :func:`anisdf.data.load_scene`)."""
    if not (math.isfinite(downscale) and downscale > 0):
        raise AnisdfError(f"downscale must be a positive number, got {downscale}")
    check_roi_values(roi_center, roi_radius)
    warnings = list(parsed.warnings)
    keep = select_images(parsed, max_images)
    remap = {old: new for new, old in enumerate(keep)}
    paths = [parsed.image_paths[i] for i in keep]
    if min_size > 0 and downscale > 1.0:
        downscale = capped_downscale(*image_size(paths[0]), downscale, min_size)

    convention, evidence = alpha_convention(paths, alpha_mode)
    decoded = parallel_map(lambda p: read_rgb(p, downscale, convention == "premultiplied"), paths)
    native = decoded[0][2]
    _check_size(paths, [d[2] for d in decoded], native, paths[0], "image")
    images = torch.from_numpy(np.stack([d[0] for d in decoded]))
    alpha = None
    if any(d[1] is not None for d in decoded):
        opaque = np.full(images.shape[1:3], 255, np.uint8)
        alpha_np = np.stack([opaque if d[1] is None else d[1] for d in decoded])
        if (alpha_np < 255).any():
            alpha = torch.from_numpy(alpha_np)
    del decoded

    masks = None
    if parsed.mask_paths is not None:
        mask_paths = [parsed.mask_paths[i] for i in keep]
        dec_masks = parallel_map(lambda p: read_mask(p, downscale), mask_paths)
        _check_size(mask_paths, [m[1] for m in dec_masks], native, paths[0], "mask")
        masks = torch.from_numpy(np.stack([m[0] for m in dec_masks]))

    normals: dict[int, torch.Tensor] = {}
    normal_items = [(remap[i], p) for i, p in sorted(parsed.normal_paths.items()) if i in remap]
    if normal_items:
        dec_normals = parallel_map(lambda p: read_normal(p, downscale), [p for _, p in normal_items])
        _check_size([p for _, p in normal_items], [n[1] for n in dec_normals], native, paths[0], "normal map")
        normals = {i: torch.from_numpy(n[0]) for (i, _), n in zip(normal_items, dec_normals, strict=True)}

    # Intrinsics: from the size the metadata describes to the size on disk, then to the loaded size.
    intr = parsed.intrinsics[keep].copy()
    w0, h0 = native
    if parsed.size is not None and tuple(parsed.size) != native:
        sx0, sy0 = w0 / parsed.size[0], h0 / parsed.size[1]
        described = f"images are {w0}x{h0} but the cameras describe {parsed.size[0]}x{parsed.size[1]}"
        if abs(sx0 - sy0) > 0.01 * max(sx0, sy0):
            warnings.append(f"{described} (different aspect ratio); intrinsics scaled per axis")
        elif parsed.format != "llff":
            warnings.append(f"{described}; intrinsics scaled")
        intr *= np.array([sx0, sy0, sx0, sy0])
    w, h = target_size(w0, h0, downscale)
    intr *= np.array([w / w0, h / h0, w / w0, h / h0])
    distortion = None if parsed.distortion is None else parsed.distortion[keep]

    c2w = parsed.c2w[keep]
    splits = {name: [remap[i] for i in idx if i in remap] for name, idx in parsed.splits.items()}
    coverage = masks if masks is not None else alpha
    if roi_center and roi_radius > 0:
        roi = user_roi(None, roi_center, roi_radius)
    else:
        roi = find_roi(parsed, c2w, intr, distortion, w, h, coverage, splits["train"])
        if roi_center or roi_radius > 0:
            roi = user_roi(roi, roi_center, roi_radius)
    if roi.method.startswith("user"):
        check_user_roi(roi, c2w, intr, w, h, [p.name for p in paths])
    warnings.extend(roi.warnings)
    to_world = roi.to_world()
    c2w_norm = c2w.copy()
    c2w_norm[:, :3, 3] = (c2w[:, :3, 3] - roi.center) / roi.radius

    def f32(a: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))

    cameras = Cameras(
        c2w=f32(c2w_norm[:, :3, :4]),
        fx=f32(intr[:, 0]),
        fy=f32(intr[:, 1]),
        cx=f32(intr[:, 2]),
        cy=f32(intr[:, 3]),
        width=w,
        height=h,
        distortion=None if distortion is None else f32(distortion),
    )
    return Scene(
        format=parsed.format,
        root=parsed.root,
        image_paths=paths,
        images=images,
        alpha=alpha,
        masks=masks,
        normals=normals,
        cameras=cameras,
        splits=splits,
        background="rgba" if alpha is not None else "opaque",
        to_world=to_world,
        scene_radius=float(roi.radius),
        downscale=downscale,
        warnings=warnings,
        roi_method=roi.method,
        alpha_mode=f"{convention} ({evidence})" if alpha is not None else "",
    )


def find_roi(
    parsed: ParsedScene,
    c2w: np.ndarray,
    intr: np.ndarray,
    distortion: np.ndarray | None,
    width: int,
    height: int,
    coverage: torch.Tensor | None,
    train: list[int],
) -> RegionOfInterest:
    """The region of interest in the dataset frame (strategies in :mod:`anisdf.data.normalize`), from the
    training views, or from every loaded view when there are fewer than 8 training views (e.g. with
    ``max_images``), so that thinning the training set hardly moves the normalisation."""
    if parsed.to_world is not None:
        return RegionOfInterest(parsed.to_world[:3, 3].copy(), float(parsed.to_world[0, 0]), parsed.roi_method)
    views = train if len(train) >= MIN_ROI_VIEWS else list(range(len(c2w)))
    if coverage is not None:
        cams = Cameras(
            c2w=torch.from_numpy(c2w[views, :3, :4].astype(np.float32)),
            fx=torch.from_numpy(intr[views, 0].astype(np.float32)),
            fy=torch.from_numpy(intr[views, 1].astype(np.float32)),
            cx=torch.from_numpy(intr[views, 2].astype(np.float32)),
            cy=torch.from_numpy(intr[views, 3].astype(np.float32)),
            width=width,
            height=height,
            distortion=None if distortion is None else torch.from_numpy(distortion[views].astype(np.float32)),
        )
        hull = visual_hull_roi(cams, coverage[views])
        if hull is not None:
            return hull
        roi = camera_roi(c2w[views], intr[views], width, height, parsed.depth_hint)
        roi.warnings.insert(0, "visual hull of the masks is empty or undefined; region of interest taken "
                               "from the cameras")
        return roi
    return camera_roi(c2w[views], intr[views], width, height, parsed.depth_hint)
