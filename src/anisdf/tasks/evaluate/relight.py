"""``anisdf eval RUN --relight FOLDER``: the fitted PBR asset relit and scored against renders under other lights.

FOLDER holds one subfolder per light with the views as ``r_i.png`` (RGBA), the light as ``LIGHT_world.exr`` (or
``.hdr`` / ``.npy``) beside them, in the dataset's frame (z up, :mod:`anisdf.materials.environment`), the cameras as
``transforms_test.json`` (else the run's test views) and optionally the true material as ``material.json``: glTF
terms (``base_color``, ``roughness``, ``metallic``) or Mitsuba's ``roughplastic`` (``mitsuba_bsdf`` with
``diffuse_reflectance`` and GGX ``alpha``: roughness ``sqrt(alpha)``, metallic 0). Every view of every light is
rendered (RUN/relight/LIGHT/) and scored on white, whatever ``--max-views`` says.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from anisdf.errors import AnisdfError
from anisdf.run_dir import RunDir

LIGHT_SUFFIXES = (".exr", ".hdr", ".npy")


def lights_in(folder: Path) -> dict[str, Path]:
    """Light name -> its map, for each subfolder of ``folder`` that holds PNG views and has a map beside it."""
    out = {}
    for sub in sorted(p for p in Path(folder).iterdir() if p.is_dir()):
        env = next((folder / f"{sub.name}_world{s}" for s in LIGHT_SUFFIXES if (folder / f"{sub.name}_world{s}")
                    .is_file()), None)
        if env is not None and any(sub.glob("*.png")):
            out[sub.name] = env
    if not out:
        raise AnisdfError(f"--relight {folder}: no LIGHT/ subfolder with views and a LIGHT_world.exr beside it")
    return out


def true_material(folder: Path) -> dict[str, Any] | None:
    """The material ``folder/material.json`` states in glTF terms, None without one."""
    path = Path(folder) / "material.json"
    if not path.is_file():
        return None
    try:
        m = json.loads(path.read_text())
        if "base_color" in m:
            return {"base_color": [float(x) for x in m["base_color"]][:3], "roughness": float(m["roughness"]),
                    "metallic": float(m.get("metallic", 0.0))}
        bsdf = m["mitsuba_bsdf"]
        return {"base_color": [float(x) for x in bsdf["diffuse_reflectance"]["value"]][:3],
                "roughness": math.sqrt(float(bsdf["alpha"])), "metallic": 0.0}
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as e:
        raise AnisdfError(f"{path}: unreadable true material ({type(e).__name__}: {e})") from None


def material_errors(run: Path, truth: dict[str, Any]) -> dict[str, float]:
    """The fitted material against ``truth``: the largest channel error of the surface's mean base colour, the
    mean absolute error per surface point (area-weighted) of base colour and roughness, and the mean's roughness
    error."""
    import torch

    from anisdf.materials.asset import load_fitted

    fitted = load_fitted(run)
    s = fitted.surface
    tri = s.positions[s.faces]
    area = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]).norm(dim=-1)
    w = (area / area.sum()).double()
    with torch.no_grad():
        base, rough, metal = (t.double() for t in fitted.material(tri.mean(1)))
    tb = torch.tensor(truth["base_color"], dtype=torch.float64)
    mean_base = (base * w[:, None]).sum(0)
    mean_rough = float((rough * w).sum())
    return {"base_color": [round(float(x), 4) for x in mean_base],
            "base_color_error": round(float((mean_base - tb).abs().max()), 4),
            "base_color_mae": round(float(((base - tb).abs().mean(1) * w).sum()), 4),
            "roughness": round(mean_rough, 4), "roughness_error": round(abs(mean_rough - truth["roughness"]), 4),
            "roughness_mae": round(float(((rough - truth["roughness"]).abs() * w).sum()), 4),
            "metallic": round(float((metal * w).sum()), 4), "truth": truth}


def _rgba(path: Path, premultiplied: bool) -> np.ndarray:
    """A ground-truth image as float RGBA in [0, 1] with straight colour (:func:`anisdf.data.images.read_rgb`)."""
    from anisdf.data.images import read_rgb

    rgb, a, _ = read_rgb(path, premultiplied=premultiplied)
    a = np.full(rgb.shape[:2], 255, np.uint8) if a is None else a
    return np.concatenate([rgb, a[..., None]], -1).astype(np.float32) / 255.0


def relight_scores(run: Path, folder: Path, progress: bool = True) -> tuple[dict[str, Any], dict[str, Any]]:
    """``{"<light>": {"psnr", "ssim", "views"}, ..., "material": {...}}`` (the last where the truth is known) and
    the protocol entry."""
    from PIL import Image

    from anisdf.data.loader import alpha_convention
    from anisdf.eval.metrics import composite_on_white, psnr, ssim
    from anisdf.tasks.relight import relight

    folder = Path(folder)
    if not folder.is_dir():
        raise AnisdfError(f"--relight {folder}: no such folder")
    rd = RunDir(run)
    cameras = folder / "transforms_test.json"
    scores: dict[str, Any] = {}
    colour: dict[str, str] = {}
    for light, env in lights_in(folder).items():
        views = sorted((folder / light).glob("*.png"))
        convention, evidence = alpha_convention(views, "auto")  # as the training images are read (data.alpha)
        colour[light] = f"{convention} ({evidence})" if evidence else "no alpha"
        size = Image.open(views[0]).size[0]
        out = rd.relight(light)
        info = relight(run, out, env=env, cameras=cameras if cameras.is_file() else None, size=size,
                       progress=progress)
        rows = []
        for name in info["views"]:
            gt_path = folder / light / f"{name}.png"
            if not gt_path.is_file():
                continue
            gt = composite_on_white(_rgba(gt_path, convention == "premultiplied"))
            pred = composite_on_white(np.asarray(Image.open(out / f"{name}.png"), np.float32) / 255.0)
            rows.append((psnr(pred, gt), ssim(pred, gt)))
        if not rows:
            raise AnisdfError(f"--relight {folder / light}: none of its images is named as a rendered view")
        scores[light] = {"psnr": round(float(np.mean([r[0] for r in rows])), 3),
                         "ssim": round(float(np.mean([r[1] for r in rows])), 4), "views": len(rows)}
    truth = true_material(folder)
    if truth is not None:
        scores["material"] = material_errors(run, truth)
    protocol = {"folder": str(folder.resolve()), "background": "white", "renders": str(rd.root / "relight"),
                "ground_truth_colour": colour,
                "cameras": str(cameras) if cameras.is_file() else "the run's test views",
                "renderer": "split-sum reference renderer (anisdf relight), 2 x 2 samples a pixel, Gaussian filter "
                            "0.6 px; no shadows or interreflections"}
    return scores, protocol
