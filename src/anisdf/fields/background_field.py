"""Background of unbounded scenes: a small NeRF outside the bounding sphere, in contracted space.

The SDF covers the sphere of ``radius``; what lies beyond (Mip-NeRF 360 scenes, unmasked photos) is a density +
colour field on a hash grid over the contraction of Mip-NeRF 360 (the authors' release: "a separate background NeRF
(hash grid, contracted space)"). Each ray is sampled uniformly in disparity from where it leaves the sphere to ``far``;
what the background NeRF leaves transparent takes a direction-only environment colour (the sky at infinity).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from anisdf.fields.encodings import sh_encoding
from anisdf.fields.hash_grid import GridSpec, HashGrid
from anisdf.fields.radiance_field import mlp
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


class BackgroundNeRF(nn.Module):
    """Density and colour beyond the sphere of ``radius``, volume-rendered with ``n_samples`` per ray."""

    def __init__(self, radius: float = 1.0, n_samples: int = 32, far: float = 1000.0, n_levels: int = 12,
                 log2_hashmap_size: int = 17, hidden: int = 64, backend: str = "auto") -> None:
        super().__init__()
        self.radius, self.n_samples, self.far = radius, n_samples, far
        spec = GridSpec(n_levels=n_levels, features_per_level=2, log2_hashmap_size=log2_hashmap_size,
                        base_resolution=16, per_level_scale=1.4)
        self.grid = HashGrid(spec, backend=backend)
        self.density = mlp(spec.n_levels * spec.features_per_level, hidden, 1, 16)
        self.color = mlp(15 + 16, hidden, 1, 3)
        self.environment = EnvironmentBackground(hidden)

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
        xc = contract(x / self.radius)  # ball of radius 2
        h = self.density(self.grid((xc.reshape(-1, 3) + 2.0) / 4.0))
        sigma = F.softplus(h[:, 0] - 1.0).view(t.shape)
        # densities live in contracted units: scale the world step by the local contraction (|dx_c/dx| ~ 1/|x|^2)
        n = (x / self.radius).norm(dim=-1).clamp_min(1.0)
        alpha = 1.0 - torch.exp(-sigma * delta / (self.radius * n * n))
        trans = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1.0 - alpha + 1e-7], dim=-1), dim=-1)
        w = alpha * trans[:, :-1]
        sh = sh_encoding(dirs, 4)
        rgb = torch.sigmoid(self.color(torch.cat([h[:, 1:], sh.repeat_interleave(t.shape[1], 0)], dim=-1)))
        opacity = w.sum(-1)
        col = (w[..., None] * rgb.view(*t.shape, 3)).sum(1)
        return {"rgb": col + (1.0 - opacity[:, None]) * self.environment(dirs), "opacity": opacity}
