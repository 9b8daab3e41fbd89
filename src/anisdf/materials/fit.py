"""Fitting the light and the material to the training photos, with the surface fixed.

Every training pixel whose ray hits the surface (and whose photo is fully covered there) gives a sample: point,
normal, view direction, photo colour (:func:`gather_samples`). Each step renders a random batch with the split sum
(:func:`anisdf.materials.shading.shade`) and descends on the squared error of the sRGB-encoded colours, plus small
smoothness terms on the material (total variation of its grid) and on the light (of its log radiance), a pull of
metallic toward 0 (a plastic and a metal can explain the same highlight; the simpler is preferred) and a pull of the
roughness and metallic grids toward the surface's shared value (``uniform_prior``).

The material is a trilinear grid over the surface's bounding box (:class:`MaterialGrid`: base colour, roughness,
metallic through sigmoids), the light an equirectangular map of log radiance (:class:`LightMap`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from anisdf.materials.brdf import MIN_ROUGHNESS
from anisdf.materials.environment import Prefilter
from anisdf.materials.shading import shade
from anisdf.materials.surface import Surface, cast_pixels


def srgb(x: Tensor) -> Tensor:
    """Linear -> sRGB-encoded, clamped to [0, 1] (the photos' encoding)."""
    x = x.clamp(0.0, 1.0)
    return torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.clamp_min(1e-8) ** (1 / 2.4) - 0.055)


def linear(x: Tensor) -> Tensor:
    """sRGB-encoded -> linear."""
    return torch.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


class MaterialGrid(nn.Module):
    """glTF base colour, roughness and metallic on a ``res``^3 trilinear grid over the box ``lo``..``hi``: the
    sigmoids of one value shared by the whole surface plus the grid's trilinear residual. The shared value sees
    every sample of every step, so the object's overall material settles in a few hundred steps; the residual
    (each cell seen only by the samples near it) adds the spatial variation."""

    def __init__(self, lo: Tensor, hi: Tensor, res: int = 64) -> None:
        super().__init__()
        self.register_buffer("lo", lo.float().clone())
        self.register_buffer("hi", hi.float().clone())
        self.mean = nn.Parameter(torch.tensor([0.0, 0.0, 0.0, 0.0, -4.0]))  # base 0.5, roughness ~0.5, metal ~0.02
        self.grid = nn.Parameter(torch.zeros(1, 5, res, res, res))

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Base colour [M, 3], roughness [M], metallic [M] at points ``x`` [M, 3]."""
        u = ((x - self.lo) / (self.hi - self.lo).clamp_min(1e-9)) * 2.0 - 1.0
        g = F.grid_sample(self.grid, u.flip(-1).view(1, -1, 1, 1, 3), mode="bilinear", padding_mode="border",
                          align_corners=True)
        v = g.view(5, -1).T + self.mean
        base = torch.sigmoid(v[:, :3])
        rough = MIN_ROUGHNESS + (1.0 - MIN_ROUGHNESS) * torch.sigmoid(v[:, 3])
        return base, rough, torch.sigmoid(v[:, 4])

    def total_variation(self) -> Tensor:
        g = self.grid
        return sum((g.diff(dim=d) ** 2).mean() for d in (2, 3, 4))


class LightMap(nn.Module):
    """An equirectangular light of ``rows`` x ``2 rows`` texels, stored as log radiance."""

    def __init__(self, rows: int = 64, init: float = 1.0) -> None:
        super().__init__()
        self.log = nn.Parameter(torch.full((rows, 2 * rows, 3), math.log(init)))

    def forward(self) -> Tensor:
        return torch.exp(self.log)

    def total_variation(self) -> Tensor:
        return (self.log.diff(dim=0) ** 2).mean() + (self.log.diff(dim=1) ** 2).mean()


@dataclass
class Samples:
    """Training pixels on the surface: position, normal, view direction and photo colour (sRGB) [N, 3] each."""

    position: Tensor
    normal: Tensor
    view: Tensor
    color: Tensor
    visibility: Tensor | None = None
    """[N, D] uint8 (0..255): the share of each light direction the pixel's point sees (``--shadows``)."""

    def __len__(self) -> int:
        return len(self.position)


def gather_samples(surface: Surface, views: list, progress: Callable[[int], None] | None = None,
                   vertex_vis: Tensor | None = None) -> Samples:
    """Samples of ``views``: (camera, RGB uint8 [H, W, 3], coverage [H, W] in [0, 1] or None) each; pixels not
    fully covered in the photo are left out (their colour mixes the background in). ``vertex_vis`` [V, D]: the
    surface's vertex visibility, interpolated to each sample."""
    from anisdf.materials.visibility import interpolate

    parts: list[list[Tensor]] = [[], [], [], [], []]
    for i, (cam, rgb, cover) in enumerate(views):
        hits = cast_pixels(surface, cam)
        keep = torch.ones(len(hits.pixel), dtype=torch.bool)
        if cover is not None:
            keep = torch.as_tensor(cover).reshape(-1)[hits.pixel] >= 0.999
        color = torch.as_tensor(rgb).reshape(-1, 3)[hits.pixel].float() / 255.0
        for part, t in zip(parts[:4], (hits.position, hits.normal, hits.view, color), strict=True):
            part.append(t[keep])
        if vertex_vis is not None:
            vis = interpolate(vertex_vis, surface.faces, hits.face[keep], hits.bary[keep])
            parts[4].append((vis * 255.0 + 0.5).to(torch.uint8))
        if progress:
            progress(i)
    return Samples(*(torch.cat(p) for p in parts[:4]), torch.cat(parts[4]) if parts[4] else None)


@dataclass(kw_only=True)
class FitSettings:
    batch: int = 8192
    lr: float = 0.02
    light_rows: int = 32
    grid: int = 48
    levels: int = 6
    filter_samples: int = 32
    tv_material: float = 1e-3
    tv_light: float = 1e-4
    metallic_prior: float = 1e-3
    uniform_prior: float = 0.0
    """Weight of the mean squared residual of roughness and metallic (the grid's departure from the shared value):
    where the photos do not constrain them (no highlight seen, a dim part of the light) they stay at the shared
    value instead of drifting."""
    shadows: int = 0
    """Light directions whose visibility from the surface shadows the shading (0: no shadows)."""


class Fit:
    """The state of a fit: material, light, their optimiser and the step reached."""

    def __init__(self, surface: Surface, settings: FitSettings, light_init: float = 1.0) -> None:
        self.settings = settings
        lo, hi = surface.bounds
        pad = 0.02 * (hi - lo).max()
        self.material = MaterialGrid(lo - pad, hi + pad, settings.grid)
        self.light = LightMap(settings.light_rows, light_init)
        self.prefilter = Prefilter(settings.light_rows, settings.levels, settings.filter_samples)
        self.opt = torch.optim.Adam([{"params": self.material.parameters()}, {"params": self.light.parameters()}],
                                    lr=settings.lr)
        self.step = 0
        self.seconds = 0.0
        self.directions: Tensor | None = None  # the light directions of the samples' visibility

    def loss(self, s: Samples, idx: Tensor) -> tuple[Tensor, Tensor]:
        """The objective on samples ``idx`` and its photometric part (the mean squared sRGB error)."""
        cfg = self.settings
        base, rough, metal = self.material(s.position[idx])
        vis = s.visibility[idx].float() / 255.0 if s.visibility is not None and self.directions is not None else None
        rgb = shade(self.prefilter(self.light()), s.normal[idx], s.view[idx], base, rough, metal, vis,
                    self.directions)
        mse = ((srgb(rgb) - s.color[idx]) ** 2).mean()
        reg = (cfg.tv_material * self.material.total_variation() + cfg.tv_light * self.light.total_variation()
               + cfg.metallic_prior * metal.mean())
        if cfg.uniform_prior:
            reg = reg + cfg.uniform_prior * (self.material.grid[:, 3:] ** 2).mean()
        return mse + reg, mse

    def run(self, s: Samples, steps: int, deadline: float, generator: torch.Generator,
            on_step: Callable[[int, float], None] | None = None) -> None:
        """Up to ``steps`` more steps, stopping at ``deadline`` (time.monotonic())."""
        for _ in range(steps):
            if time.monotonic() >= deadline:
                break
            t0 = time.monotonic()
            idx = torch.randint(0, len(s), (min(self.settings.batch, len(s)),), generator=generator)
            loss, mse = self.loss(s, idx)
            self.opt.zero_grad(set_to_none=True)
            loss.backward()
            self.opt.step()
            self.step += 1
            self.seconds += time.monotonic() - t0
            if on_step:
                on_step(self.step, float(mse.detach()))

    def state_dict(self) -> dict:
        return {"material": self.material.state_dict(), "light": self.light.state_dict(),
                "opt": self.opt.state_dict(), "step": self.step, "seconds": self.seconds,
                "settings": vars(self.settings)}

    def load_state_dict(self, state: dict) -> None:
        self.material.load_state_dict(state["material"])
        self.light.load_state_dict(state["light"])
        self.opt.load_state_dict(state["opt"])
        self.step, self.seconds = int(state["step"]), float(state["seconds"])
