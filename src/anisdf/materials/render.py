"""Rendering the fitted PBR asset under a light: the Python reference renderer of ``anisdf relight``.

Each pixel is sampled at the centres of an s x s finer grid; each sample's ray hits the surface (or not), hits are
shaded with the split sum (:func:`anisdf.materials.shading.shade`), and the samples are filtered into pixels with a
Gaussian of ``pixel_filter`` pixels (:func:`anisdf.export.reference_renderer.resolve`), colour and coverage alike.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from anisdf.export.reference_renderer import PinholeCamera, resolve
from anisdf.materials.environment import Prefilter, Prefiltered, downsample
from anisdf.materials.fit import MaterialGrid, srgb
from anisdf.materials.shading import shade
from anisdf.materials.surface import Surface, cast_pixels
from anisdf.materials.visibility import interpolate


def prepare_light(env: torch.Tensor, samples: int = 256, rows: int = 64) -> Prefiltered:
    """``env`` [H, 2H, 3] prefiltered for rendering: the rough levels from a ``rows``-row copy, level 0 the map at
    its own resolution."""
    small = downsample(env.float(), min(rows, env.shape[0]))
    with torch.no_grad():
        pre = Prefilter(small.shape[0], samples=samples)(small)
    pre.levels[0] = env.float()
    return pre


@torch.no_grad()
def render_view(surface: Surface, material: MaterialGrid, light: Prefiltered, cam: PinholeCamera,
                supersample: int = 2, pixel_filter: float = 0.6, visibility: Tensor | None = None,
                directions: Tensor | None = None) -> np.ndarray:
    """RGBA float [H, W, 4]: sRGB-encoded straight colour and coverage; with the surface's vertex ``visibility``
    [V, D] of the light's ``directions`` [D, 3], shadowed."""
    s = int(supersample)
    fine = PinholeCamera(cam.c2w, cam.fx * s, cam.fy * s, cam.cx * s, cam.cy * s, cam.width * s, cam.height * s,
                         cam.distortion)
    hits = cast_pixels(surface, fine)
    n_pix = fine.width * fine.height
    samples = torch.zeros(n_pix, 4)
    if len(hits.pixel):
        base, rough, metal = material(hits.position)
        vis = None if visibility is None else interpolate(visibility, surface.faces, hits.face, hits.bary)
        rgb = shade(light, hits.normal, hits.view, base, rough, metal, vis, directions).clamp(0.0, 1.0)
        samples[hits.pixel, :3] = rgb
        samples[hits.pixel, 3] = 1.0
    out = resolve(samples.reshape(fine.height, fine.width, 4), s, pixel_filter)
    alpha = out[..., 3:].clamp(0.0, 1.0)
    color = srgb(out[..., :3] / alpha.clamp_min(1e-6))
    return torch.cat([torch.where(alpha > 0, color, torch.zeros_like(color)), alpha], -1).numpy()
