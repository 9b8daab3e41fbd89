"""``anisdf process-data``: from a folder of photos or a video to a posed scene that ``anisdf train`` reads.

Writes ``SCENE/images/`` (the photos or the sharpest video frames), ``SCENE/colmap/`` (pycolmap database and
sparse models), ``SCENE/transforms.json`` (nerfstudio convention, with the bounding sphere anisdf uses as its
region of interest), ``SCENE/sparse_pc.ply``, ``SCENE/cameras.png`` and ``SCENE/process_data.json`` (the
summary). A failure leaves everything written so far in place.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from anisdf.data.process.export import (
    bounding_sphere,
    draw_cameras,
    poses_from_reconstruction,
    scene_transform,
    transforms_dict,
    write_json,
    write_points_ply,
)
from anisdf.data.process.inputs import DEFAULT_VIDEO_FRAMES, MIN_IMAGES, import_folder, import_video, is_video
from anisdf.data.process.sfm import (
    ADVICE,
    ANISDF_MODELS,
    MATCHERS,
    check_options,
    require_pycolmap,
    run_sfm,
    undistort,
)
from anisdf.errors import AnisdfError, DataError
from anisdf.utils.options import int_at_least, option

log = logging.getLogger("anisdf")

MIN_REGISTERED_FRACTION = 0.5
"""Fewer registered images than this fraction of the input (or fewer than 3) is an error."""


@dataclass(kw_only=True)
class ProcessDataOptions:
    """How ``anisdf process-data`` / :func:`process_data` poses a capture."""

    matcher: str | None = option(None, "image pairs to match (default: sequential for a video, exhaustive for photos)",
                                 choices=MATCHERS)
    max_frames: int | None = option(
        None, f"keep this many evenly spread images (default: {DEFAULT_VIDEO_FRAMES} for a video, every photo)",
        int_at_least(1))
    downscale: int = option(1, "divide the image size by this integer first", int_at_least(1))
    camera_model: str = option(
        "simple_radial", "COLMAP camera model: simple_radial, radial, opencv, pinhole, ... (others are undistorted)")
    vocab_tree: Path | None = option(None, "COLMAP vocabulary tree file for --matcher vocab", Path)
    force_undistort: bool = option(
        False, "write undistorted pinhole images even when anisdf could model the distortion", flag="--undistort")
    refine_principal_point: bool = option(
        False, "free the principal point in a last bundle adjustment (lenses with an off-centre one)")
    masks: bool = option(
        False, "also make foreground masks of the object (SCENE/masks/; GrabCut seeded by the sparse points and "
        "the object's sphere, made consistent across views): the object presets and the visual-hull sphere then "
        "apply. Given an existing scene as INPUT and as --out, adds the masks to it")
    progress: bool = option(True, "show progress bars", cli=False)


def process_data(input_path: str | Path, out: str | Path, options: ProcessDataOptions | None = None,
                 **changes: Any) -> dict[str, Any]:
    """Pose the photos (folder) or frames (video) at ``input_path`` and write the scene folder ``out``;
    ``changes`` replace fields of ``options``.

    ``matcher`` defaults to sequential for a video and exhaustive for photos; ``max_frames`` (default
    :data:`~anisdf.data.process.inputs.DEFAULT_VIDEO_FRAMES` for a video, all photos) keeps that many evenly spread
    images; ``downscale`` divides the image size before anything else; ``refine_principal_point`` frees the
    principal point in a last bundle adjustment (see :func:`anisdf.data.process.sfm.refine_principal_point`).
    Returns the summary that is also written to ``out/process_data.json``.
    """
    o = dataclasses.replace(options or ProcessDataOptions(), **changes)
    matcher, max_frames, downscale, camera_model = o.matcher, o.max_frames, o.downscale, o.camera_model
    vocab_tree, progress = o.vocab_tree, o.progress
    t_start = time.perf_counter()
    src, scene = Path(input_path), Path(out)
    if o.masks and (src / "transforms.json").is_file():
        if scene.resolve() != src.resolve():
            raise DataError(scene, f"{src} is already a scene: --masks adds masks to it in place; give --out {src}")
        return add_masks(src, progress)
    require_pycolmap()
    if not src.exists():
        raise DataError(src, "input does not exist (expected a folder of images or a video file)")
    if downscale < 1:
        raise AnisdfError(f"--downscale must be an integer >= 1, got {downscale}")
    video = is_video(src)
    if not video and not src.is_dir():
        raise DataError(src, "input is neither a folder of images nor a video file")
    matcher = matcher or ("sequential" if video else "exhaustive")
    check_options(matcher, camera_model, Path(vocab_tree) if vocab_tree else None)
    if (scene / "transforms.json").exists():
        raise DataError(scene / "transforms.json", "already exists; choose another --out or remove the old scene")
    if scene.resolve() == src.resolve():
        raise DataError(scene, "--out must differ from the input folder")
    images_dir = scene / "images"
    if video:
        frames = DEFAULT_VIDEO_FRAMES if max_frames is None else max_frames
        names = import_video(src, images_dir, frames, downscale, progress)
    else:
        names = import_folder(src, images_dir, max_frames or 0, downscale, progress)
    log.info("%d images in %s", len(names), images_dir)

    sfm = run_sfm(images_dir, names, scene / "colmap", matcher, camera_model,
                  Path(vocab_tree) if vocab_tree else None, progress, principal_point=o.refine_principal_point)
    rec = sfm.reconstruction
    registered = {rec.image(i).name for i in rec.reg_image_ids()}
    failed = [n for n in names if n not in registered]
    if len(registered) < max(MIN_IMAGES, MIN_REGISTERED_FRACTION * len(names)):
        listed = ", ".join(failed[:20]) + (" ..." if len(failed) > 20 else "")
        raise AnisdfError(f"{scene}: only {len(registered)} of {len(names)} images registered "
                          f"(not registered: {listed}); {ADVICE}. The images, database and sparse models stay in "
                          f"{scene}")
    warnings: list[str] = []
    if failed:
        warnings.append(f"{len(failed)} of {len(names)} images not registered and left out: "
                        + ", ".join(failed[:20]) + (" ..." if len(failed) > 20 else ""))

    model_dir, image_prefix = sfm.model_dir, "images"
    model_name = rec.camera(next(iter(rec.cameras))).model.name
    t0 = time.perf_counter()
    if o.force_undistort or model_name not in ANISDF_MODELS:
        log.info("undistorting %s images to pinhole", model_name)
        model_dir = undistort(sfm.model_dir, images_dir, scene / "colmap" / "undistorted")
        image_prefix = "colmap/undistorted/images"
        pycolmap = require_pycolmap()
        rec = pycolmap.Reconstruction(model_dir)
    sfm.seconds["undistortion"] = time.perf_counter() - t0

    poses = poses_from_reconstruction(rec)
    sphere = bounding_sphere(poses)
    warnings.extend(sphere.warnings)
    transform = scene_transform(poses, sphere)
    points = poses.points @ transform[:3, :3].T + transform[:3, 3]
    write_points_ply(scene / "sparse_pc.ply", points, poses.colors)
    extra = {"colmap_model": str(model_dir.relative_to(scene)), "ply_file_path": "sparse_pc.ply"}
    write_json(scene / "transforms.json", transforms_dict(poses, sphere, transform, image_prefix, extra))
    c2w_scene = transform[None] @ poses.c2w
    mean_error = float(rec.compute_mean_reprojection_error())
    summary: dict[str, Any] = {
        "input": str(src),
        "scene": str(scene),
        "kind": "video" if video else "images",
        "matcher": matcher,
        "camera_model": poses.model,
        "n_images": len(names),
        "n_registered": len(registered),
        "not_registered": failed,
        "n_models": sfm.n_models,
        "principal_point_refined": sfm.principal_point_refined,
        "mean_reprojection_error_px": round(mean_error, 4),
        "n_points": int(rec.num_points3D()),
        "mean_track_length": round(float(rec.compute_mean_track_length()), 3),
        "image_size": [poses.width, poses.height],
        "intrinsics": [round(float(v), 4) for v in poses.intrinsics],
        "distortion": [round(float(v), 6) for v in poses.distortion],
        "sphere_radius": round(sphere.radius, 6),
        "sphere_points": sphere.n_points,
        "sphere_method": sphere.method,
        "colmap_model": extra["colmap_model"],
        "seconds": {k: round(v, 2) for k, v in sfm.seconds.items()} | {
            "total": round(time.perf_counter() - t_start, 2)},
        "warnings": warnings,
    }
    title = (f"{len(registered)}/{len(names)} registered, {summary['n_points']} points, "
             f"mean reprojection error {mean_error:.3f} px, sphere radius {sphere.radius:.3g} (red)")
    draw_cameras(scene / "cameras.png", c2w_scene, poses.intrinsics, poses.width, poses.height, points,
                 poses.colors, sphere.radius, title)
    write_json(scene / "process_data.json", summary)
    if o.masks:
        summary = add_masks(scene, progress)
    for w in warnings:
        log.warning("warning: %s", w)
    return summary


def add_masks(scene: Path, progress: bool = True) -> dict[str, Any]:
    """Make the foreground masks of the process-data scene ``scene`` (:mod:`anisdf.data.process.masks`), write them
    to ``scene/masks/``, name them in ``transforms.json`` (``mask_path``) in place of the sparse points' sphere, so that
    the region of interest becomes the masks' visual hull, and redraw ``cameras.png`` around it. Returns the updated
    summary (``process_data.json``)."""
    import json

    import numpy as np
    from PIL import Image

    from anisdf.data.dataparsers import load_scene
    from anisdf.data.dataparsers.blender import resolve_image
    from anisdf.data.inspect import draw_scene
    from anisdf.data.process.masks import load_views, make_masks, require_cv2

    require_cv2()
    t0 = time.perf_counter()
    views, paths = load_views(scene)
    masks, stats = make_masks(views, progress)
    mask_dir = scene / "masks"
    mask_dir.mkdir(exist_ok=True)
    by_image = {}
    for path, mask in zip(paths, masks, strict=True):
        Image.fromarray(mask.astype(np.uint8) * 255).save(mask_dir / (path.stem + ".png"))
        by_image[path.resolve()] = f"masks/{path.stem}.png"
    meta = json.loads((scene / "transforms.json").read_text())
    for frame in meta["frames"]:
        frame["mask_path"] = by_image[resolve_image(scene, str(frame["file_path"])).resolve()]
    meta["sparse_points_sphere"] = meta.pop("bounding_sphere", None)
    write_json(scene / "transforms.json", meta)
    loaded = load_scene(scene)
    draw_scene(loaded, scene / "cameras.png")
    summary_path = scene / "process_data.json"
    summary = json.loads(summary_path.read_text()) if summary_path.is_file() else {"scene": str(scene)}
    summary.update({"scene": str(scene), "masks": "masks/", "mask_seconds": round(time.perf_counter() - t0, 2),
                    "mask_mean_coverage": round(stats["mean_coverage"], 4), "sphere_method": loaded.roi_method,
                    "sphere_radius": round(loaded.scene_radius, 6),
                    "sphere_center": [round(float(v), 6) for v in loaded.center]})
    summary["warnings"] = list(summary.get("warnings", [])) + loaded.warnings
    write_json(summary_path, summary)
    log.info("masks: %d views -> %s (mean coverage %.1f%%); region of interest now from %s", len(masks), mask_dir,
             100 * stats["mean_coverage"], loaded.roi_method)
    return summary


def summary_line(summary: dict[str, Any]) -> str:
    """One human line: registered of total, reprojection error, points."""
    if "n_registered" not in summary:
        return f"masks -> {summary['scene']}/masks/ (see cameras.png)"
    return (f"{summary['n_registered']} of {summary['n_images']} images registered, mean reprojection error "
            f"{summary['mean_reprojection_error_px']:.3f} px, {summary['n_points']} points"
            + (", masks" if "masks" in summary else "") + f" -> {summary['scene']}/transforms.json (see cameras.png)")


__all__ = ["ProcessDataOptions", "process_data", "summary_line"]
