"""The fitted result of ``anisdf materials`` as files of the run folder, and read back."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from anisdf.errors import AnisdfError
from anisdf.materials.fit import LightMap, MaterialGrid
from anisdf.materials.surface import Surface
from anisdf.run_dir import RunDir


@dataclass
class Fitted:
    """Surface (dataset frame), material on it and fitted light [H, 2H, 3]."""

    surface: Surface
    material: MaterialGrid
    light: Tensor
    visibility: Tensor | None = None
    """[V, D] bool: which of the light's ``directions`` each vertex sees (``anisdf materials --shadows``)."""
    directions: Tensor | None = None

    @torch.no_grad()
    def vertex_material(self) -> tuple[Tensor, Tensor, Tensor]:
        """Base colour, roughness and metallic at the surface's vertices."""
        return self.material(self.surface.positions)

    @torch.no_grad()
    def summary(self) -> dict:
        """Area-weighted means of the material over the surface."""
        s = self.surface
        tri = s.positions[s.faces]
        area = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]).norm(dim=-1) / 2
        base, rough, metal = self.material(tri.mean(1))
        w = (area / area.sum())[:, None]
        return {"base_color": [round(float(x), 4) for x in (base * w).sum(0)],
                "roughness": round(float((rough[:, None] * w).sum()), 4),
                "metallic": round(float((metal[:, None] * w).sum()), 4)}


def load_fitted(run) -> Fitted:
    """The fit ``anisdf materials`` left in ``run``; an error when it has none."""
    rd = RunDir(run)
    if not rd.materials_checkpoint.is_file() or not rd.materials_surface.is_file():
        raise AnisdfError(f"{rd.root}: no material fit; run `anisdf materials {rd.root}` first")
    from anisdf.training.checkpoint import load_checkpoint

    state = load_checkpoint(rd.materials_checkpoint)
    surface = Surface.load(rd.materials_surface)
    grid = state["material"]["grid"]
    material = MaterialGrid(state["material"]["lo"], state["material"]["hi"], grid.shape[-1])
    material.load_state_dict(state["material"])
    light = LightMap(state["light"]["log"].shape[0])
    light.load_state_dict(state["light"])
    with torch.no_grad():
        env = light().detach()
    vis = load_checkpoint(rd.materials_visibility) if rd.materials_visibility.is_file() else None
    if vis is not None and vis["visibility"].shape[0] != len(surface.positions):
        vis = None  # made for another surface
    return Fitted(surface, material.eval(), env, None if vis is None else vis["visibility"],
                  None if vis is None else vis["directions"])


def light_array(fitted: Fitted) -> np.ndarray:
    return fitted.light.numpy().astype(np.float32)
