"""Background of unbounded scenes: a small NeRF outside the bounding sphere, in contracted space.

The SDF covers the sphere of ``radius``; what lies beyond (Mip-NeRF 360 scenes, unmasked photos) is a density +
colour field on a hash grid over the contraction of Mip-NeRF 360 (the authors' release: "a separate background NeRF
(hash grid, contracted space)"). Each ray is sampled uniformly in disparity from where it leaves the sphere to ``far``;
what the background NeRF leaves transparent takes a direction-only environment colour (the sky at infinity).

At the release's size (the mipnerf360 preset: 16 levels, a 2^22 table, two hidden layers of 64, 256 samples a ray) an
occupancy grid over the contracted ball (``grid_resolution`` cells a side of the cube [-2, 2]^3) keeps the hash grid
and the heads to the samples in cells where density was seen, as the release's nerfacc grid does: each cell keeps
the running maximum (decay 0.95) of the density at a jittered point, and a cell is occupied while crossing it would
stop more than ``GRID_ALPHA`` of the light (or its density is above the grid's mean, early on).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from anisdf.fields.encodings import sh_encoding
from anisdf.fields.hash_grid import GridSpec, HashGrid
from anisdf.fields.mlp import mlp
from anisdf.model_components.ray_marching import sphere_intersect


def contract(x: Tensor) -> Tensor:
    """Mip-NeRF 360 contraction (its Eq. 10): identity inside the unit ball, ``(2 - 1/|x|) x/|x|`` outside,
    so all of space maps into the ball of radius 2."""
    n = x.norm(dim=-1, keepdim=True).clamp_min(1e-9)
    return torch.where(n <= 1.0, x, (2.0 - 1.0 / n) * (x / n))


class EnvironmentBackground(nn.Module):
    """Colour seen along rays that leave the scene, as a function of direction only."""

    def __init__(self, hidden: int = 64) -> None:
        super().__init__()
        self.net = mlp(16, hidden, 1, 3)

    def forward(self, dirs: Tensor) -> Tensor:
        return torch.sigmoid(self.net(sh_encoding(dirs, 4)))


def exit_distance(origins: Tensor, dirs: Tensor, radius: float) -> Tensor:
    """Where each ray leaves the sphere of ``radius``; for rays that miss it, the point closest to the centre."""
    _, far = sphere_intersect(origins, dirs, radius)
    return torch.where(far > 0, far, -(origins * dirs).sum(-1).clamp_max(0.0))


GRID_ALPHA = 0.01
"""A background cell is occupied while crossing it would stop more than this fraction of the light."""
GRID_DECAY = 0.95


class BackgroundNeRF(nn.Module):
    """Density and colour beyond the sphere of ``radius``, volume-rendered with ``n_samples`` per ray; heads of
    ``layers`` hidden layers of ``hidden``; an occupancy grid of ``grid_resolution`` cells a side (0: none)."""

    def __init__(self, radius: float = 1.0, n_samples: int = 32, far: float = 1000.0, n_levels: int = 12,
                 log2_hashmap_size: int = 17, hidden: int = 64, backend: str = "auto", layers: int = 1,
                 grid_resolution: int = 0) -> None:
        super().__init__()
        self.radius, self.n_samples, self.far = radius, n_samples, far
        # more than 12 levels: the finest at 4096 cells across the contracted cube (16 levels: a scale of 1.447, as
        # instant-nsr-pl's background NeRF); up to 12, the scale of 1.4 the earlier presets were measured with
        scale = (4096 / 16) ** (1.0 / (n_levels - 1)) if n_levels > 12 else 1.4
        spec = GridSpec(n_levels=n_levels, features_per_level=2, log2_hashmap_size=log2_hashmap_size,
                        base_resolution=16, per_level_scale=scale)
        self.grid = HashGrid(spec, backend=backend)
        self.density = mlp(spec.n_levels * spec.features_per_level, hidden, layers, 16)
        self.color = mlp(15 + 16, hidden, layers, 3)
        self.environment = EnvironmentBackground(hidden)
        self.grid_resolution = int(grid_resolution)
        if self.grid_resolution:
            g = self.grid_resolution
            self.register_buffer("density_ema", torch.zeros(g**3))
            self.register_buffer("occupied", torch.ones(g**3, dtype=torch.bool))

    def features(self, xc: Tensor) -> Tensor:
        """The density head's output [M, 16] at contracted points ``xc`` [M, 3] (channel 0: raw density)."""
        return self.density(self.grid((xc + 2.0) / 4.0))

    def cell_index(self, xc: Tensor) -> Tensor:
        g = self.grid_resolution
        ijk = ((xc + 2.0) / 4.0 * g).floor().long().clamp(0, g - 1)
        return (ijk[..., 0] * g + ijk[..., 1]) * g + ijk[..., 2]

    @torch.no_grad()
    def update_grid(self, generator: torch.Generator, full: bool = False, chunk: int = 1 << 18) -> None:
        """Refresh the occupancy grid: every cell (``full``), else a random quarter of the cells and a quarter of
        the occupied ones; each at a jittered point."""
        if not self.grid_resolution:
            return
        g, dev = self.grid_resolution, self.density_ema.device
        n = g**3
        if full:
            cells = torch.arange(n, device=dev)
        else:
            some = torch.randint(0, n, (n // 4,), generator=generator).to(dev)
            occ = self.occupied.nonzero()[:, 0]
            pick = torch.randint(0, max(len(occ), 1), (min(len(occ), n // 4),), generator=generator).to(dev)
            cells = torch.cat([some, occ[pick]]).unique()
        jitter = torch.rand(len(cells), 3, generator=generator).to(dev)
        ijk = torch.stack([cells // (g * g), (cells // g) % g, cells % g], -1).float()
        xc = (ijk + jitter) / g * 4.0 - 2.0
        sigma = torch.cat([F.softplus(self.features(xc[i:i + chunk])[:, 0] - 1.0) for i in range(0, len(xc), chunk)])
        self.density_ema[cells] = torch.maximum(self.density_ema[cells] * GRID_DECAY, sigma)
        step = 4.0 / g  # a cell's width in contracted units, where the densities live
        alpha = 1.0 - torch.exp(-self.density_ema * step)
        self.occupied.copy_(alpha > min(GRID_ALPHA, float(alpha.mean())))

    def sample_distances(self, origins: Tensor, dirs: Tensor, generator: torch.Generator | None) -> Tensor:
        """[R, K+1] bin edges, uniform in disparity between the sphere exit and ``far * radius``."""
        t0 = exit_distance(origins, dirs, self.radius).clamp_min(1e-3)
        t1 = torch.full_like(t0, self.far * self.radius)
        k = self.n_samples
        u = torch.arange(k + 1, device=origins.device, dtype=origins.dtype) / k
        if generator is not None:  # jitter the interior edges within their bins
            jit = torch.rand(origins.shape[0], k + 1, generator=generator, device=generator.device).to(origins.device)
            u = (u + (jit - 0.5) / k).clamp(0.0, 1.0)
            u = torch.cat([torch.zeros_like(u[:, :1]), u[:, 1:-1], torch.ones_like(u[:, :1])], dim=-1)
        else:
            u = u.expand(origins.shape[0], -1)
        return 1.0 / torch.lerp(1.0 / t0[:, None], 1.0 / t1[:, None], u)

    def forward(self, origins: Tensor, dirs: Tensor, generator: torch.Generator | None = None
                ) -> dict[str, Tensor]:
        """Per-ray background colour ``[R, 3]`` (NeRF composite, then the environment behind it) and the
        NeRF's own opacity ``[R]``."""
        edges = self.sample_distances(origins, dirs, generator)
        t = 0.5 * (edges[:, 1:] + edges[:, :-1])
        delta = edges[:, 1:] - edges[:, :-1]
        x = origins[:, None] + dirs[:, None] * t[..., None]  # [R, K, 3]
        xc = contract(x / self.radius).reshape(-1, 3)  # ball of radius 2
        if self.grid_resolution:  # the heads run on samples in occupied cells; the others are empty space
            occ = self.occupied[self.cell_index(xc)]
            keep = occ.nonzero()[:, 0]
            h = torch.zeros(xc.shape[0], 16, dtype=xc.dtype, device=xc.device)
            h = h.index_put((keep,), self.features(xc[keep]))
            sigma = torch.where(occ, F.softplus(h[:, 0] - 1.0), torch.zeros_like(h[:, 0])).view(t.shape)
        else:
            keep = None
            h = self.features(xc)
            sigma = F.softplus(h[:, 0] - 1.0).view(t.shape)
        # densities live in contracted units: scale the world step by the local contraction (|dx_c/dx| ~ 1/|x|^2)
        n = (x / self.radius).norm(dim=-1).clamp_min(1.0)
        alpha = 1.0 - torch.exp(-sigma * delta / (self.radius * n * n))
        trans = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1.0 - alpha + 1e-7], dim=-1), dim=-1)
        w = alpha * trans[:, :-1]
        sh = sh_encoding(dirs, 4).repeat_interleave(t.shape[1], 0)
        if keep is None:
            rgb = torch.sigmoid(self.color(torch.cat([h[:, 1:], sh], dim=-1)))
        else:
            rgb = torch.zeros(xc.shape[0], 3, dtype=xc.dtype, device=xc.device)
            rgb = rgb.index_put((keep,), torch.sigmoid(self.color(torch.cat([h[keep, 1:], sh[keep]], dim=-1))))
        opacity = w.sum(-1)
        col = (w[..., None] * rgb.view(*t.shape, 3)).sum(1)
        return {"rgb": col + (1.0 - opacity[:, None]) * self.environment(dirs), "opacity": opacity}
