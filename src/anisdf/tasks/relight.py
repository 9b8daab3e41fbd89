"""``anisdf relight``: the PBR asset of ``anisdf materials`` rendered under another light (:mod:`anisdf.materials`).

Cameras: the run's test views, or a ``transforms.json`` (NeRF-synthetic layout: ``camera_angle_x`` or ``fl_x``...,
``frames`` with ``file_path`` and an OpenGL ``transform_matrix``) in the dataset's frame. The light is an
equirectangular map in the dataset's frame, z up (:mod:`anisdf.materials.environment`), turned by ``rotate``
degrees about +z. Writes OUT/<view>.png (RGBA, straight sRGB colour) and OUT/relight.json.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np
from tqdm.auto import tqdm

from anisdf.errors import AnisdfError
from anisdf.run_dir import RunDir
from anisdf.utils.options import float_at_least, int_at_least, option


@dataclasses.dataclass(kw_only=True)
class RelightOptions:
    """``anisdf relight``'s options (:func:`relight`)."""

    env: Path = option(dataclasses.MISSING, "the light: equirectangular .hdr / .exr / .npy in the dataset's frame, "
                                            "z up; `studio`: the bundled studio light (export --pbr's page has it "
                                            "too)", Path, metavar="ENV")
    rotate: float = option(0.0, "turn the light by this many degrees about the up axis (+z)", float)
    cameras: Path | None = option(None, "transforms.json of the cameras (default: the run's test views)", Path)
    size: int = option(0, "image width of --cameras' views in pixels (0: their images' size, else 800)",
                       int_at_least(0))
    supersample: int = option(2, "s x s samples a pixel", int_at_least(1))
    pixel_filter: float = option(0.6, "sigma in pixels of the Gaussian that filters the samples into pixels",
                                 float_at_least(0.0))
    max_views: int = option(0, "render at most this many views (0: all)", int_at_least(0))
    progress: bool = option(True, "show a progress bar", cli=False)


def cameras_from_transforms(path: Path, width: int = 0) -> list[tuple[str, Any]]:
    """(name, camera) of each frame of a NeRF-synthetic ``transforms.json``, in the dataset's frame."""
    from PIL import Image

    from anisdf.export.reference_renderer import PinholeCamera

    path = Path(path)
    try:
        meta = json.loads(path.read_text())
        frames = meta["frames"]
    except (OSError, json.JSONDecodeError, KeyError, TypeError) as e:
        raise AnisdfError(f"{path}: not a transforms.json with frames ({e})") from None
    out = []
    gl_to_cv = np.diag([1.0, -1.0, -1.0, 1.0])
    for frame in frames:
        rel = str(frame["file_path"])
        name = Path(rel).name
        w = h = width
        if not w:
            img = next((p for p in (path.parent / rel, path.parent / f"{rel}.png") if p.is_file()), None)
            w, h = Image.open(img).size if img is not None else (800, 800)
        h = h or w
        fx = frame.get("fl_x", meta.get("fl_x"))
        if fx is None:
            fx = 0.5 * w / math.tan(0.5 * float(meta["camera_angle_x"]))
        fy = frame.get("fl_y", meta.get("fl_y")) or fx
        c2w = np.asarray(frame["transform_matrix"], dtype=np.float64) @ gl_to_cv
        out.append((name, PinholeCamera(c2w, float(fx), float(fy), w / 2.0, h / 2.0, int(w), int(h))))
    return out


def test_cameras(run: Path) -> list[tuple[str, Any]]:
    """(name, camera) of the run's test views at full size, in the dataset's frame."""
    from anisdf.config import config_from_dict
    from anisdf.tasks.loading import dataset_camera, scene_for_run
    from anisdf.training.checkpoint import load_checkpoint

    ck = load_checkpoint(RunDir(run).checkpoint)
    scene = scene_for_run(run, config_from_dict(ck["config"]), ck, downscale=1.0, split="test")
    idx = scene.splits.get("test") or list(range(scene.n_images))
    return [(scene.image_paths[i].stem, dataset_camera(scene, i, ck)) for i in idx]


def relight(run: Path, out: Path, options: RelightOptions | None = None, **changes: Any) -> dict[str, Any]:
    """Render RUN's fitted asset under ``env`` into OUT; returns relight.json's content."""
    import torch

    from anisdf.materials.asset import load_fitted
    from anisdf.materials.environment import read_env, rotate, studio_light
    from anisdf.materials.render import prepare_light, render_view
    from anisdf.utils.atomic import atomic_path, write_text_atomic

    o = dataclasses.replace(options, **changes) if options is not None else RelightOptions(**changes)
    start = time.monotonic()
    fitted = load_fitted(run)
    env = studio_light() if str(o.env) == "studio" and not Path(o.env).exists() else torch.from_numpy(read_env(o.env))
    if o.rotate:
        env = rotate(env, o.rotate)
    light = prepare_light(env)
    cams = cameras_from_transforms(o.cameras, o.size) if o.cameras else test_cameras(run)
    if o.max_views:
        cams = cams[:o.max_views]
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    from PIL import Image

    names = []
    for name, cam in tqdm(cams, desc="relight", disable=not o.progress, unit="view"):
        img = render_view(fitted.surface, fitted.material, light, cam, o.supersample, o.pixel_filter,
                          fitted.visibility, fitted.directions)
        with atomic_path(out / f"{name}.png") as tmp:
            Image.fromarray((img.clip(0, 1) * 255 + 0.5).astype(np.uint8), "RGBA").save(tmp, format="PNG")
        names.append(name)
    info = {"run": str(Path(run).resolve()), "env": str(o.env), "rotate": o.rotate, "views": names,
            "shadows": 0 if fitted.directions is None else len(fitted.directions),
            "supersample": o.supersample, "pixel_filter": o.pixel_filter,
            "seconds": round(time.monotonic() - start, 1)}
    write_text_atomic(out / "relight.json", json.dumps(info, indent=2) + "\n")
    return info
