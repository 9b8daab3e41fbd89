"""``anisdf materials``: the light and a PBR material of a trained run, fitted to its photos (:mod:`anisdf.materials`).

The surface is taken from the run's SDF once (RUN/materials/surface.ply); the fit (RUN/materials/fit.pt) is saved
atomically every ``checkpoint_seconds`` and at the end, and a later call continues it (``restart`` starts anew).
Results: RUN/materials/light.hdr (the fitted light) and RUN/materials/materials.json (settings, steps, the fit's
PSNR on the training pixels, the material's means over the surface).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from pathlib import Path
from typing import Any

import torch
from tqdm.auto import tqdm

from anisdf.errors import AnisdfError
from anisdf.materials.fit import FitSettings
from anisdf.run_dir import RunDir
from anisdf.utils.options import float_at_least, int_at_least, option

log = logging.getLogger("anisdf")


@dataclasses.dataclass(kw_only=True)
class MaterialsOptions:
    """``anisdf materials``'s options (:func:`materials`)."""

    minutes: float = option(10.0, "time budget of the fit in minutes (setup included)",
                            float_at_least(0.0, strict=True))
    steps: int = option(20000, "at most this many steps in all (a resumed fit counts its earlier ones)",
                        int_at_least(1))
    resolution: int = option(256, "marching cubes resolution of the surface", int_at_least(16))
    faces: int = option(200_000, "triangles of the surface", int_at_least(4))
    light_rows: int = option(32, "rows of the fitted light map (columns: twice as many)", int_at_least(8))
    shadows: int = option(0, "shadow the shading with the light's visibility from the surface over this many "
                             "directions (shadow maps, e.g. 64); 0: no shadows", int_at_least(0))
    grid: int = option(48, "cells a side of the material grid", int_at_least(2))
    uniform_prior: float = option(FitSettings.uniform_prior, "pull of roughness and metallic toward their value "
                                  "shared by the whole surface (0: none)", float_at_least(0.0))
    batch: int = option(8192, "pixels a step", int_at_least(16))
    max_views: int = option(0, "use at most this many training views (0: all)", int_at_least(0))
    restart: bool = option(False, "start the fit anew instead of continuing RUN/materials/fit.pt")
    checkpoint_seconds: float = option(60.0, "save the fit this often (seconds)", float_at_least(1.0), cli=False)
    seed: int = option(0, "seed of the pixel batches", cli=False)
    progress: bool = option(True, "show a progress bar", cli=False)


def _training_views(run: Path, cfg, ck: dict[str, Any], max_views: int, model) -> list:
    """(camera in the dataset frame, RGB, coverage or None) of the run's training photos at full size: uint8, or
    float in [0, 255] for the photos of a run that learned a colour transform per image (``appearance.embedding_kind``
    affine or gain), whose exposure and white balance are taken out (the scene's own colour)."""
    from anisdf.models.per_image import undo_colour_transform
    from anisdf.tasks.loading import dataset_camera, scene_for_run

    scene = scene_for_run(run, cfg, ck, downscale=1.0, split="train")
    idx = scene.splits.get("train") or list(range(scene.n_images))
    transforms = None
    if model.colour_transform and model.image_codes is not None:
        # the split's views in order are the trained images in order (load_scene keeps the dataset's order)
        transforms = model.image_codes.codes.detach()[model.image_codes.trained]
        if transforms.shape[0] != len(idx):
            log.warning("materials: %d training photos against %d learned colour transforms; the photos are used "
                        "as they are", len(idx), transforms.shape[0])
            transforms = None
    if max_views:
        idx = idx[:: max(1, math.ceil(len(idx) / max_views))][:max_views]
    cover = scene.alpha if scene.alpha is not None else scene.masks
    views = []
    for i in idx:
        rgb = scene.images[i].numpy()
        if transforms is not None:
            own = undo_colour_transform(model.colour_transform, torch.from_numpy(rgb).float() / 255.0, transforms[i])
            rgb = (own.clamp(0.0, 1.0) * 255.0).numpy()
        views.append((dataset_camera(scene, i, ck), rgb, None if cover is None else cover[i].float().numpy() / 255.0))
    return views


def _load_model(run: Path):
    """The run's model on the CPU with the plain PyTorch hash grid (the same numbers as the compiled kernel; the
    surface is taken once, so the kernel's build or its lock is not worth waiting for)."""
    from anisdf.config import config_from_dict
    from anisdf.tasks.loading import model_from_checkpoint
    from anisdf.training.checkpoint import load_checkpoint

    ck = load_checkpoint(RunDir(run).checkpoint)
    raw = dict(ck["config"])
    raw["geometry"] = {**raw["geometry"], "encoding_backend": "torch"}
    cfg = config_from_dict(raw)
    return cfg, model_from_checkpoint(cfg, ck), ck


def _surface(rd: RunDir, o: MaterialsOptions, cfg, model, ck):
    from anisdf.materials.surface import Surface, surface_of_model

    if rd.materials_surface.is_file() and not o.restart:
        return Surface.load(rd.materials_surface)
    surface = surface_of_model(model, ck["to_world"], o.resolution, o.faces, progress=o.progress)
    surface.save(rd.materials_surface)
    return surface


def _visibility(rd: RunDir, o: MaterialsOptions, surface) -> dict[str, Any] | None:
    """The surface's vertex visibility for ``--shadows`` directions, computed once and kept beside the surface
    (None without shadows; a file made for another surface or direction count is made anew)."""
    from anisdf.materials.visibility import fibonacci_directions, vertex_visibility
    from anisdf.training.checkpoint import atomic_save, load_checkpoint

    path = rd.materials_visibility
    if not o.shadows:
        path.unlink(missing_ok=True)  # a fit without shadows is rendered without them
        return None
    if path.is_file() and not o.restart:
        vis = load_checkpoint(path)
        if vis["visibility"].shape == (len(surface.positions), o.shadows):
            return vis
    start = time.monotonic()
    directions = fibonacci_directions(o.shadows)
    vis = {"directions": directions, "visibility": vertex_visibility(surface, directions)}
    atomic_save(vis, path)
    log.info("materials: the light's visibility over %d directions in %.0f s", o.shadows, time.monotonic() - start)
    return vis


def materials(run: Path, options: MaterialsOptions | None = None, **changes: Any) -> dict[str, Any]:
    """Fit RUN's light and material for ``minutes`` (continuing RUN/materials/fit.pt unless ``restart``); returns
    materials.json's content."""
    from anisdf.materials.asset import load_fitted
    from anisdf.materials.environment import write_env
    from anisdf.materials.fit import Fit, gather_samples, linear
    from anisdf.training.checkpoint import atomic_save, load_checkpoint

    o = dataclasses.replace(options or MaterialsOptions(), **changes)
    start = time.monotonic()
    deadline = start + o.minutes * 60.0
    rd = RunDir(run)
    if not rd.has_checkpoint():
        raise AnisdfError(f"{rd.root}: no trained run here (checkpoints/last.pt is missing)")
    torch.set_num_threads(max(1, torch.get_num_threads()))
    cfg, model, ck = _load_model(rd.root)
    surface = _surface(rd, o, cfg, model, ck)
    views = _training_views(rd.root, cfg, ck, o.max_views, model)
    del model
    bar = tqdm(total=len(views), desc="materials: pixels", disable=not o.progress, leave=False, unit="view")
    vis = _visibility(rd, o, surface)
    samples = gather_samples(surface, views, progress=lambda _i: bar.update(1),
                             vertex_vis=None if vis is None else vis["visibility"])
    bar.close()
    if len(samples) < 16:
        raise AnisdfError(f"{rd.root}: the training photos show too little of the surface to fit a material")
    settings = FitSettings(batch=o.batch, light_rows=o.light_rows, grid=o.grid, shadows=o.shadows,
                           uniform_prior=o.uniform_prior)
    fit = Fit(surface, settings, light_init=float(2.0 * linear(samples.color).mean()))
    fit.directions = None if vis is None else vis["directions"]
    if rd.materials_checkpoint.is_file() and not o.restart:
        state = load_checkpoint(rd.materials_checkpoint)
        if {**vars(FitSettings()), **state.get("settings", {})} != vars(settings):  # older fits lack newer keys
            raise AnisdfError(f"{rd.materials_checkpoint}: fitted with other settings ({state.get('settings')}); "
                              "pass --restart to start anew")
        fit.load_state_dict(state)
        log.info("materials: continuing the fit at step %d", fit.step)
    gen = torch.Generator().manual_seed(o.seed + fit.step)
    mses: list[float] = []
    total = o.steps
    bar = tqdm(total=total, initial=min(fit.step, total), desc="materials", disable=not o.progress, unit="step")

    def on_step(step: int, mse: float) -> None:
        mses.append(mse)
        bar.update(1)
        if step % 20 == 0:
            bar.set_postfix(psnr=f"{-10 * math.log10(max(sum(mses[-20:]) / len(mses[-20:]), 1e-12)):.2f}")

    while fit.step < total and time.monotonic() < deadline:
        chunk_end = min(deadline, time.monotonic() + o.checkpoint_seconds)
        fit.run(samples, total - fit.step, chunk_end, gen, on_step)
        atomic_save(fit.state_dict(), rd.materials_checkpoint)
    bar.close()
    atomic_save(fit.state_dict(), rd.materials_checkpoint)
    fitted = load_fitted(rd.root)
    write_env(rd.materials_light, fitted.light.numpy())
    with torch.no_grad():
        idx = torch.randperm(len(samples), generator=torch.Generator().manual_seed(1))[:65536]
        _, mse = fit.loss(samples, idx)
    info = {"run": str(rd.root.resolve()), "step": fit.step, "fit_seconds": round(fit.seconds, 1),
            "seconds": round(time.monotonic() - start, 1), "pixels": len(samples), "views": len(views),
            "train_psnr": round(-10 * math.log10(max(float(mse), 1e-12)), 3),
            "surface": {"faces": len(surface.faces), "vertices": len(surface.positions)},
            "material": fitted.summary(), "settings": vars(settings),
            "light": rd.materials_light.name, "light_rows": o.light_rows}
    rd.write_json(rd.materials_info, info)
    log.info("materials: %d steps, %.2f dB on the training pixels, base colour %s, roughness %.3f, metallic %.3f",
             fit.step, info["train_psnr"], info["material"]["base_color"], info["material"]["roughness"],
             info["material"]["metallic"])
    return info
