"""Rendering whole views of a trained model into the maps people look at."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from anisdf.data.rays import RayDataset
from anisdf.data.scene import Scene
from anisdf.eval.metrics import psnr_from_mse
from anisdf.models.anisdf import AniSDFModel


@torch.no_grad()
def render_rays_to_maps(model: AniSDFModel, origins: torch.Tensor, dirs: torch.Tensor, bg: torch.Tensor,
                        hw: tuple[int, int], chunk: int, fine_grid: bool = False) -> dict[str, np.ndarray]:
    """Float maps [H, W, C] on the CPU: rgb, normal (unit, world), depth, opacity, c_view, c_ref, weight.
    ``fine_grid``: march the model's refined image grid (a fixed model rendering many views)."""
    h, w = hw
    out = model.render_image(origins, dirs, bg, chunk, fine_grid=fine_grid)
    maps: dict[str, np.ndarray] = {}
    for k, v in out.items():
        if k.startswith("_") or v.shape[0] != h * w:
            continue
        maps[k] = v.float().reshape(h, w, -1).cpu().numpy()
    opacity = maps["opacity"][..., 0]
    n = F.normalize(torch.from_numpy(maps["normal"]), dim=-1).numpy()
    maps["normal"] = n
    if "weight" in maps:  # the blend weight is a per-sample quantity composited by opacity: show it per surface
        maps["weight"] = maps["weight"] / np.maximum(maps["opacity"], 1e-6)
    maps["depth"] = maps["depth"] / np.maximum(maps["opacity"], 1e-6)
    maps["opacity"] = opacity[..., None]
    return maps


MAP_NAMES = ("rgb", "normal", "depth", "c_view", "c_ref", "w", "opacity")
"""The maps people look at, as :func:`map_to_image` names them (``w`` is the blend weight, key ``weight``)."""


def map_to_image(maps: dict[str, np.ndarray], name: str) -> np.ndarray:
    """One of :data:`MAP_NAMES` of :func:`render_rays_to_maps`'s output as a uint8 RGB picture, as ``anisdf render``
    writes it: normals and depth outside the object (opacity <= 0.5) white, scalars in viridis. KeyError when the
    model has no such map (c_view, c_ref and w belong to the blended appearance)."""
    from anisdf.utils.images import depth_to_image, normal_to_image, scalar_to_image, to_uint8

    fg = maps["opacity"][..., 0] > 0.5
    if name in ("rgb", "c_view", "c_ref"):
        return to_uint8(maps[name])
    if name == "normal":
        return normal_to_image(maps["normal"] * fg[..., None])
    if name == "depth":
        return depth_to_image(maps["depth"][..., 0], mask=fg)
    if name in ("w", "opacity"):
        return scalar_to_image(np.clip(maps["weight" if name == "w" else "opacity"][..., 0], 0, 1))
    raise KeyError(f"unknown map {name!r}; one of {', '.join(MAP_NAMES)}")


def render_view(model: AniSDFModel, data: RayDataset, i: int, scene: Scene, chunk: int,
                fine_grid: bool = False) -> dict:
    """Render view ``i`` of a split on a white background; returns maps, the target and its PSNR."""
    batch, hw = data.image(i)
    maps = render_rays_to_maps(model, batch.origins, batch.directions, batch.background, hw, chunk, fine_grid)
    gt = batch.rgb.reshape(*hw, 3).float().cpu().numpy()
    mse = float(np.mean((np.clip(maps["rgb"], 0, 1) - gt) ** 2))
    return {"maps": maps, "gt": gt, "psnr": psnr_from_mse(mse), "hw": hw}


def panel(res: dict) -> np.ndarray:
    """Side-by-side picture: ground truth, render, normals, and the blend maps when present."""
    from anisdf.utils.images import (
        depth_to_image,
        hstack_labeled,
        normal_to_image,
        scalar_to_image,
        to_uint8,
    )

    m = res["maps"]
    fg = m["opacity"][..., 0] > 0.5
    imgs = [to_uint8(res["gt"]), to_uint8(m["rgb"]), normal_to_image(m["normal"] * fg[..., None])]
    labels = ["ground truth", f"render {res['psnr']:.2f} dB", "normal"]
    if "baked" in res:  # eval --baked: the baked asset as the viewer page draws it
        imgs.insert(2, to_uint8(res["baked"]))
        labels.insert(2, f"baked {res['baked_psnr']:.2f} dB")
    imgs.append(depth_to_image(m["depth"][..., 0], mask=fg))
    labels.append("depth")
    if "c_view" in m and "c_ref" in m:
        imgs += [to_uint8(m["c_view"]), to_uint8(m["c_ref"]), scalar_to_image(np.clip(m["weight"][..., 0], 0, 1))]
        labels += ["c_view", "c_ref", "weight w"]
    return hstack_labeled(imgs, labels)


def save_panel(path: Path, res: dict) -> None:
    from anisdf.utils.images import save_image

    save_image(path, panel(res))
