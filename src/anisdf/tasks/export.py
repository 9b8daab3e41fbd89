"""Baking a run into a real-time asset (model.glb, lobe textures, a WebGL page)."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np

from anisdf.errors import AnisdfError
from anisdf.tasks.loading import dataset_camera, scene_for_run

log = logging.getLogger("anisdf")

def _export_camera(run: Path, cfg, ck: dict[str, Any]) -> tuple[dict[str, Any] | None, list[float] | None]:
    """The page's first camera (the first test view, dataset frame) and the scene's up direction (the mean of the
    test cameras' up axes), or (None, None) when the dataset is not at hand."""
    try:
        scene = scene_for_run(run, cfg, ck, downscale=1.0, split="test")
    except AnisdfError as e:
        log.warning("export: %s; the page starts from a default view", e)
        return None, None
    split = scene.splits.get("test") or scene.splits.get("train") or [0]
    T = np.asarray(ck["to_world"], dtype=np.float64)
    up = -scene.cameras.c2w[split, :, 1].double().mean(0).numpy()  # OpenCV y points down
    up = (T[:3, :3] @ up) / np.linalg.norm(T[:3, :3] @ up)
    cam = dataset_camera(scene, split[0], ck).to_json()
    return cam, up.tolist()


def export(run: Path, out: Path, faces: int = 200_000, texture: int = 1024, specular_texture: int = 0,
           lobes: int = 3, directions: int = 64, resolution: int = 512, supersample: int = 2,
           pixel_filter: float = 0.6,
           device: str | None = None, progress: bool = True) -> dict[str, Any]:
    """Bake RUN into a real-time asset in OUT (:mod:`anisdf.export.bake`): model.glb, specular_*.png, index.html and
    export.json (settings, file sizes, timings). Returns export.json's content."""
    import time

    from anisdf import __version__
    from anisdf.export import baked_format as fmt
    from anisdf.export.bake import BakeOptions, bake, write_asset
    from anisdf.export.mesh import extract_mesh as mc
    from anisdf.export.sg_fit import SHARPNESS_RANGE
    from anisdf.tasks.loading import load_run
    from anisdf.utils.atomic import write_text_atomic
    from anisdf.utils.devices import pick_device

    if out.exists() and not out.is_dir():
        raise AnisdfError(f"--out {out} is an existing file, not a folder")
    if out.resolve() == run.resolve():
        raise AnisdfError("--out must not be the run folder itself")
    opts = BakeOptions(faces=faces, texture=texture, specular_texture=specular_texture, lobes=lobes,
                       directions=directions, resolution=resolution)
    opts.validate()
    if not 1 <= supersample <= 4:
        raise AnisdfError(f"--supersample must be between 1 and 4, got {supersample}")
    if not 0.0 <= pixel_filter <= 2.0:
        raise AnisdfError(f"--pixel-filter must be between 0 and 2 pixels, got {pixel_filter}")
    dev = pick_device(device or "auto")
    timings: dict[str, float] = {}
    clock = [time.perf_counter()]

    def tick(name: str) -> None:
        now = time.perf_counter()
        timings[name] = round(now - clock[0], 2)
        clock[0] = now

    cfg, model, ck = load_run(run, dev)
    if cfg.appearance.kind != "blend":
        log.info("export: appearance.kind=%s; the lobes are fitted to its colour all the same", cfg.appearance.kind)
    camera, up = _export_camera(run, cfg, ck)
    tick("load")
    mesh = mc(model.geometry.sdf, radius=model.radius, resolution=resolution, device=dev, progress=progress)
    tick("marching_cubes")
    baked = bake(model, mesh, opts, progress=progress, timer=tick)
    manifest: dict[str, Any] = {
        "format": fmt.FORMAT, "version": fmt.VERSION, "anisdf": __version__, "run": str(run.resolve()),
        "step": int(ck["state"]["step"]), "frame": "dataset",
        "faces": len(baked.faces), "vertices": len(baked.vertices), "marching_cubes_resolution": resolution,
        "faces_requested": faces, "texture": opts.texture, "specular_texture": opts.spec_size,
        "lobes": opts.lobes, "directions": opts.directions, "diffuse_directions": opts.diffuse_directions,
        "fit_iters": opts.fit_iters, "sharpness_range": list(SHARPNESS_RANGE), "supersample": supersample,
        "pixel_filter": pixel_filter,
        "diffuse": "view-independent part of the blended colour w c_view + (1 - w) c_ref: the per-texel fit's "
                   "constant term (hemisphere mean with K = 0)",
        "up": up, "camera": camera, "stats": baked.stats,
    }
    sizes = write_asset(out, baked, np.asarray(ck["to_world"]), manifest)
    tick("write")
    manifest.update(files=sizes, total_bytes=int(sum(sizes.values())), timings=timings,
                    seconds=round(sum(timings.values()), 2))
    write_text_atomic(out / fmt.MANIFEST, json.dumps(manifest, indent=2) + "\n")
    log.info("export: %d faces, %d px diffuse, %d px lobes x %d -> %s (%.1f MB: %s) in %.0f s", len(baked.faces),
             opts.texture, opts.spec_size, opts.lobes, out, manifest["total_bytes"] / 1e6,
             ", ".join(f"{k} {v / 1e6:.2f} MB" for k, v in sizes.items()), manifest["seconds"])
    return manifest
