"""The "protocol" record of eval.json: how the views were chosen and scored, in words a reader can check."""

from __future__ import annotations

from pathlib import Path
from typing import Any


def view_selection(scene, split: str) -> str:
    """How the dataset's parser chose the views of ``split``."""
    if split == "test" and scene.format == "nerf-synthetic" and (scene.root / "transforms_test.json").is_file():
        return "transforms_test.json"
    if split == "test":
        return "every 8th image in name order from the first (LLFF hold-out; Mip-NeRF 360, Table 5)"
    if split == "train" and scene.format != "nerf-synthetic":
        return "the images not held out (all but every 8th in name order)"
    return f"transforms_{split}.json" if scene.format == "nerf-synthetic" else split


def alpha_source(scene) -> str:
    """Where the ground-truth alpha of the normal MAE comes from (as ``Scene.coverage()`` picks it)."""
    if scene.masks is not None:
        return "masks"
    return "alpha" if scene.alpha is not None else "normal-map coverage"


def views_record(scene, cfg, split: str, n_views: int, held_out: bool, eval_downscale: float,
                 background: str) -> dict[str, Any]:
    """The protocol's views, images and colour metrics; ``normal_mae``, ``mesh``, ``chamfer``, ``inner_shells`` and
    ``baked`` are None until filled in."""
    return {
        "split": split, "views": n_views, "view_selection": view_selection(scene, split), "held_out": held_out,
        "eval_downscale": float(eval_downscale), "train_downscale": float(cfg.data.downscale),
        "images_dir": cfg.data.images_dir or None, "image_size": [scene.width, scene.height],
        "background": ("white: renders on white, ground-truth RGBA (or masked photos) composited on white"
                       if background == "white" else "none: photos as photographed, the model's learned background"),
        "psnr": "mean over views of -10 log10(MSE), float renders in [0, 1] against 8-bit ground truth",
        "ssim": "skimage structural_similarity: gaussian_weights, sigma 1.5, population covariance, data_range 1, "
                "mean over channels; mean over views",
        "normal_mae": None, "mesh": None, "chamfer": None, "inner_shells": None, "baked": None,
    }


def baked_record(folder: Path, manifest: dict[str, Any]) -> dict[str, Any]:
    """How the baked asset in ``folder`` (its manifest) was rendered and scored."""
    return {
        "dir": str(folder), "faces": manifest.get("faces"), "texture": manifest.get("texture"),
        "specular_texture": manifest.get("specular_texture"), "lobes": manifest.get("lobes"),
        "supersample": manifest.get("supersample", 1), "pixel_filter": manifest.get("pixel_filter", 0.0),
        "renderer": "anisdf.export.reference_renderer as the viewer page draws: supersample x supersample rays per "
                    "pixel through the centres of a finer pixel grid, filtered into pixels (a Gaussian of "
                    "pixel_filter pixels; 0: each pixel's own samples averaged); the same ground truth and "
                    "background as the neural render",
    }


def normal_mae_record(n_views: int, reference_names: set[str], normal_mask: str, alpha: str) -> dict[str, Any]:
    """The normal MAE's views, reference maps (``<image>_normal.png`` ...) and pixel weights."""
    return {
        "views": n_views, "reference": sorted(reference_names), "space": "world, (n + 1) / 2 in RGB",
        "mask": normal_mask,
        "weights": "rendered opacity x ground-truth " + alpha if normal_mask == "refnerf" else "ground-truth " + alpha,
    }


def mesh_record(mesh_info: dict[str, Any]) -> dict[str, Any]:
    """The scored mesh's file and extraction settings (from RUN/mesh.json)."""
    return {k: mesh_info.get(k) for k in ("path", "written_by", "step", "resolution", "remove_floaters",
                                          "floater_min_fraction", "remove_inner", "two_pass", "margin", "frame")}


def chamfer_record(points: int, seed: int, gt_mesh: Path) -> dict[str, Any]:
    return {"points": points, "seed_pred": seed, "seed_gt": seed + 1, "gt_mesh": str(gt_mesh), "units": "dataset",
            "distance": "(accuracy + completeness) / 2, nearest neighbours both ways"}
