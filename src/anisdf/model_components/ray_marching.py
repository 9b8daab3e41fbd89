"""Uniform ray marching inside the bounding sphere, keeping samples in occupied cells (packed layout).

Samples of all rays are stored back to back, ordered by ray then by distance: ``ray_idx`` [S], ``t`` (midpoint)
[S] and ``dt`` [S]. nerfacc offers this on CUDA only; this version runs wherever torch does. On CPU the compiled
kernel (``kernels/march_cpu.cpp``, passed in as ``kernel``) walks each ray once, where the PyTorch reference builds
every ray's steps, their cells and a mask: the same samples (tests/test_march_kernel.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from types import ModuleType

import torch
from torch import Tensor

from anisdf.model_components.occupancy_grid import OccupancyGrid


@dataclass
class Samples:
    ray_idx: Tensor
    t: Tensor
    dt: Tensor
    n_rays: int

    @property
    def n(self) -> int:
        return int(self.t.shape[0])

    def select(self, keep: Tensor) -> Samples:
        """The samples where the mask ``keep`` is true (or at the indices ``keep``), in order."""
        idx = keep.nonzero()[:, 0] if keep.dtype == torch.bool else keep  # one host sync, not one per tensor
        return Samples(self.ray_idx[idx], self.t[idx], self.dt[idx], self.n_rays)

    def positions(self, origins: Tensor, dirs: Tensor) -> Tensor:
        return origins[self.ray_idx] + dirs[self.ray_idx] * self.t[:, None]


def sphere_intersect(origins: Tensor, dirs: Tensor, radius: float) -> tuple[Tensor, Tensor]:
    """Entry and exit distances of rays with the sphere of ``radius`` at the origin (far <= near: miss)."""
    b = (origins * dirs).sum(-1)
    c = (origins * origins).sum(-1) - radius * radius
    disc = b * b - c
    hit = disc > 0
    # the square root only where the ray crosses the sphere: at 0 its derivative is infinite, and rays of refined
    # cameras carry gradients (0 * inf would make them NaN)
    sq = torch.where(hit, torch.where(hit, disc, torch.ones_like(disc)).sqrt(), torch.zeros_like(disc))
    near = (-b - sq).clamp_min(0.0)
    far = torch.where(hit, -b + sq, torch.zeros_like(b))
    return near, far


@torch.no_grad()
def march(origins: Tensor, dirs: Tensor, grid: OccupancyGrid | None, radius: float, step: float,
          max_samples: int, generator: torch.Generator | None = None, chunk_rays: int = 4096,
          kernel: ModuleType | None = None) -> Samples:
    """Stratified samples every ``step`` along each ray within the sphere, kept where the grid is occupied.

    With a ``generator`` the first sample of each ray is jittered inside its step (training); otherwise
    samples sit at the step midpoints (evaluation, deterministic). ``kernel``: the compiled CPU extension
    (:func:`anisdf.fields.hash_grid.cpu_kernel.kernel_for` of float32 CPU rays) to march with, else the reference.
    """
    dev = origins.device
    near, far = sphere_intersect(origins, dirs, radius)
    if kernel is not None:
        if generator is not None:  # the reference's draws, chunk by chunk
            u = torch.cat([torch.rand(min(chunk_rays, origins.shape[0] - s), generator=generator,
                                      device=generator.device) for s in range(0, origins.shape[0], chunk_rays)])
        else:
            u = torch.full((origins.shape[0],), 0.5)
        occ = None if grid is None else grid.occupied
        ray_idx, t = kernel.march_rays(origins, dirs, near, far, u.to(dev), step, max_samples, occ,
                                    0.0 if grid is None else grid.radius, 0.0 if grid is None else 1.0 / grid.cell_size,
                                    0 if grid is None else grid.resolution)
        return Samples(ray_idx, t, torch.full_like(t, step), origins.shape[0])
    out_r, out_t = [], []
    starts = range(0, origins.shape[0], chunk_rays)
    if generator is not None:
        # training: a chunk of random rays almost surely holds a chord close to the diameter, so the bound costs
        # nothing and saves a host read (the GPU's queue draining) every step; samples past the exit are dropped
        chunk_steps = [math.ceil(2.0 * radius / step)] * len(starts)
    else:
        # images: the steps needed by the longest chord of each chunk (none for rows that miss the sphere), read
        # back in one host sync
        span = far - near
        chunk_steps = ([int(v) for v in (torch.stack([span[s : s + chunk_rays].max() for s in starts]).clamp_min(0)
                                         / step).ceil().tolist()] if len(starts) else [])
    for s, n_steps in zip(starts, chunk_steps, strict=True):
        o, d = origins[s : s + chunk_rays], dirs[s : s + chunk_rays]
        n0, f0 = near[s : s + chunk_rays], far[s : s + chunk_rays]
        n_steps = min(n_steps, max_samples)
        if n_steps == 0:
            continue
        if generator is not None:
            u = torch.rand(o.shape[0], 1, generator=generator, device=generator.device).to(dev)
        else:
            u = torch.full((o.shape[0], 1), 0.5, device=dev)
        t = n0[:, None] + (torch.arange(n_steps, device=dev)[None] + u) * step  # [R, K]
        keep = t < f0[:, None]
        if grid is not None:
            keep &= grid.query_rays(o, d, t)
        r_idx, k_idx = keep.nonzero(as_tuple=True)
        out_r.append(r_idx + s)
        out_t.append(t[r_idx, k_idx])
    if not out_r:
        empty = torch.zeros(0, device=dev)
        return Samples(torch.zeros(0, dtype=torch.long, device=dev), empty, empty, origins.shape[0])
    t = torch.cat(out_t)
    return Samples(torch.cat(out_r), t, torch.full_like(t, step), origins.shape[0])
