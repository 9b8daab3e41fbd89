"""Camera poses with pycolmap (COLMAP's Python bindings, CPU): SIFT features, matching, incremental mapping,
optionally a final bundle adjustment that also refines the principal point, and, for camera models anisdf does
not model, undistortion to pinhole images.

Layout under ``SCENE/colmap/``: ``database.db`` (features and matches), ``sparse/N/`` (every model the mapper
found, COLMAP's numbering) and, when undistorting, ``undistorted/{images,sparse}``.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from PIL import Image
from tqdm import tqdm

from anisdf.errors import AnisdfError

log = logging.getLogger("anisdf")

MATCHERS = ("exhaustive", "sequential", "vocab")
ANISDF_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")
"""Camera models whose distortion anisdf applies itself (k1, k2, p1, p2); others are undistorted."""
EXTRACT_CHUNK = 8
SMALL_IMAGE = 1000
SMALL_IMAGE_PEAK_THRESHOLD = 0.002
"""SIFT peak threshold for images under 1000 pixels a side (COLMAP's default, 0.0067, suits large photos): DTU at
400x300 gives 380 features an image and 47 of 49 registered with the default, 1050 and all 49 with 0.002."""
SMALL_IMAGE_MIN_INLIERS = 15
"""Inliers needed to register an image under 1000 pixels a side (COLMAP: 30): with 0.002 the DTU views 4 and 5
(oblique, 24-38 inlier matches to any other view) still failed at 30; 15 registers all 49 (median rotation
error 0.78 vs 0.77 deg before the principal-point refinement)."""
MAX_PRINCIPAL_SHIFT = 0.1
"""The refined principal point must stay within this fraction of the image size of the image centre."""


def require_pycolmap() -> Any:
    """The pycolmap module, or an AnisdfError saying how to install it."""
    try:
        import pycolmap
    except ImportError:
        raise AnisdfError("process-data needs pycolmap (a CPU wheel, no COLMAP binary): "
                          "pip install pycolmap") from None
    return pycolmap


def camera_models() -> list[str]:
    """Camera model names pycolmap knows (lower case), for the CLI."""
    pycolmap = require_pycolmap()
    return [m.lower() for m in pycolmap.CameraModelId.__members__ if m != "INVALID"]


def check_options(matcher: str, camera_model: str, vocab_tree: Path | None) -> str:
    """Validate the SfM options (before anything is written); returns COLMAP's camera model name."""
    pycolmap = require_pycolmap()
    model = camera_model.upper()
    if model not in pycolmap.CameraModelId.__members__ or model == "INVALID":
        raise AnisdfError(f"--camera-model {camera_model!r} is unknown; choose one of {', '.join(camera_models())}")
    if matcher not in MATCHERS:
        raise AnisdfError(f"--matcher {matcher!r} is unknown; choose one of {', '.join(MATCHERS)}")
    if matcher == "vocab" and (vocab_tree is None or not vocab_tree.is_file()):
        raise AnisdfError("--matcher vocab needs a COLMAP vocabulary tree file (--vocab-tree PATH, e.g. "
                          "vocab_tree_flickr100K_words32K.bin from colmap.github.io); or use exhaustive/sequential")
    return model


@dataclass
class SfmResult:
    reconstruction: Any
    """The pycolmap.Reconstruction with the most registered images."""
    model_dir: Path
    """Where that model was written (``SCENE/colmap/sparse/N``)."""
    n_models: int
    seconds: dict[str, float]
    principal_point_refined: bool = False


def _pbar(desc: str, total: int, progress: bool) -> tqdm:
    return tqdm(total=total, desc=desc, unit="img", disable=not progress, leave=True)


def run_sfm(
    images_dir: Path,
    names: list[str],
    colmap_dir: Path,
    matcher: str = "exhaustive",
    camera_model: str = "simple_radial",
    vocab_tree: Path | None = None,
    progress: bool = True,
    seed: int = 0,
    principal_point: bool = False,
) -> SfmResult:
    """Features, matches and incremental mapping of ``images_dir/names`` with one shared camera; with
    ``principal_point`` a last bundle adjustment also refines the camera's principal point.

    Raises AnisdfError when nothing could be reconstructed (the database and any models stay on disk).
    """
    import time

    pycolmap = require_pycolmap()
    model = check_options(matcher, camera_model, vocab_tree)
    if not args_debug():
        pycolmap.logging.minloglevel = 2  # COLMAP's own INFO/WARNING lines; --debug keeps them
    pycolmap.set_random_seed(seed)
    colmap_dir.mkdir(parents=True, exist_ok=True)
    db = colmap_dir / "database.db"
    if db.exists():  # features of an earlier run would be mixed with these: start the database afresh
        db.unlink()
    seconds: dict[str, float] = {}
    device = pycolmap.Device.cpu

    t0 = time.perf_counter()
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = model
    extraction = pycolmap.FeatureExtractionOptions()
    with Image.open(images_dir / names[0]) as im:
        small = max(im.size) < SMALL_IMAGE
    if small:
        extraction.sift.peak_threshold = SMALL_IMAGE_PEAK_THRESHOLD
    pycolmap.Database.open(db).close()
    pycolmap.import_images(db, images_dir, pycolmap.CameraMode.SINGLE, names, reader)
    with _pbar("features", len(names), progress) as bar:
        for i in range(0, len(names), EXTRACT_CHUNK):
            chunk = names[i:i + EXTRACT_CHUNK]
            pycolmap.extract_features(db, images_dir, image_names=chunk, camera_mode=pycolmap.CameraMode.SINGLE,
                                      reader_options=reader, extraction_options=extraction, device=device)
            bar.update(len(chunk))
    seconds["features"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    with tqdm(total=1, desc=f"matching ({matcher})", unit="stage", disable=not progress, leave=True) as bar:
        if matcher == "exhaustive":
            pycolmap.match_exhaustive(db, device=device)
        elif matcher == "sequential":
            pycolmap.match_sequential(db, device=device)
        else:
            pairing = pycolmap.VocabTreePairingOptions()
            pairing.vocab_tree_path = str(vocab_tree)
            pycolmap.match_vocabtree(db, pairing_options=pairing, device=device)
        bar.update(1)
    seconds["matching"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    sparse = colmap_dir / "sparse"
    sparse.mkdir(parents=True, exist_ok=True)
    options = pycolmap.IncrementalPipelineOptions()
    options.random_seed = seed
    if small:
        options.mapper.abs_pose_min_num_inliers = SMALL_IMAGE_MIN_INLIERS
    with _pbar("mapping (registered)", len(names), progress) as bar:
        callback: Callable[[], None] = lambda: bar.update(1)  # noqa: E731 - one image registered
        models = pycolmap.incremental_mapping(db, images_dir, sparse, options,
                                              initial_image_pair_callback=lambda: bar.update(2),
                                              next_image_callback=callback)
    seconds["mapping"] = time.perf_counter() - t0
    if not models:
        raise AnisdfError(f"{colmap_dir}: no model could be reconstructed from {len(names)} images "
                          "(no image pair had enough matches): " + ADVICE)
    best = max(models, key=lambda k: models[k].num_reg_images())
    t0 = time.perf_counter()
    rec = models[best]
    refined = refine_principal_point(rec) if principal_point else None
    if refined is not None:
        rec = refined
        rec.write(sparse / str(best))
    seconds["principal_point"] = time.perf_counter() - t0
    return SfmResult(rec, sparse / str(best), len(models), seconds, refined is not None)


def refine_principal_point(rec: Any) -> Any | None:
    """A copy of ``rec`` after a global bundle adjustment that also refines the shared camera's principal point,
    or None when the refined point leaves the central 20% of the image or the reprojection error grows.

    The incremental mapper keeps the principal point at the image centre, which tilts every view by the angle of
    the true offset. Measured: on DTU scan 65 (true offset 6, 5 px at 400x300) the median rotation error drops
    from 0.78 to 0.26 deg; on the tests' synthetic ring (true offset 0) it rises from 0.11 to 0.49 deg (the
    point drifts ~1 px: the offset and a common tilt of the cameras are hard to tell apart). Hence opt-in.
    """
    pycolmap = require_pycolmap()
    if rec.num_cameras() != 1 or rec.num_reg_images() < 3:
        return None
    out = pycolmap.Reconstruction(rec)
    options = pycolmap.BundleAdjustmentOptions()
    options.refine_principal_point = True
    options.print_summary = False
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in out.reg_image_ids():
        config.add_image(image_id)
    config.fix_gauge(pycolmap.BundleAdjustmentGauge.THREE_POINTS)
    before = rec.compute_mean_reprojection_error()
    pycolmap.create_default_bundle_adjuster(options, config, out).solve()
    cam = next(iter(out.cameras.values()))
    shift = max(abs(cam.principal_point_x / cam.width - 0.5), abs(cam.principal_point_y / cam.height - 0.5))
    after = out.compute_mean_reprojection_error()
    if not (shift < MAX_PRINCIPAL_SHIFT and after <= before * 1.05):
        log.info("principal point refinement rejected (shift %.3f of the image, error %.3f -> %.3f px)",
                 shift, before, after)
        return None
    return out


ADVICE = ("take photos with more overlap (each part seen in 3+ views, neighbours sharing ~70%), use "
          "--matcher exhaustive (or sequential for a video), keep --camera-model simple_radial unless the lens "
          "needs more, and drop blurry or featureless frames")


def args_debug() -> bool:
    """True when the anisdf logger shows debug messages (``anisdf --debug``)."""
    return log.isEnabledFor(logging.DEBUG)


def undistort(model_dir: Path, images_dir: Path, out_dir: Path) -> Path:
    """Undistort the images of the model in ``model_dir`` to pinhole images in ``out_dir/images`` (COLMAP's
    undistorter); returns the folder of the undistorted model (``out_dir/sparse``)."""
    pycolmap = require_pycolmap()
    pycolmap.undistort_images(out_dir, model_dir, images_dir)
    return out_dir / "sparse"
