"""Ray marching: the compiled kernel (kernels/march_cpu.cpp) keeps exactly the samples of the PyTorch reference
(model_components/ray_marching.py)."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from anisdf.model_components.occupancy_grid import OccupancyGrid
from anisdf.model_components.ray_marching import march


def _rays(n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    origins = F.normalize(torch.randn(n, 3, generator=g), dim=-1) * 2.5
    target = torch.randn(n, 3, generator=g) * 0.5
    dirs = F.normalize(target - origins, dim=-1)
    origins[: n // 10] = torch.rand(n // 10, 3, generator=g) * 0.4 - 0.2  # some cameras inside the sphere
    return origins, dirs


@pytest.mark.parametrize("with_grid", [True, False])
@pytest.mark.parametrize("train", [True, False])
def test_kernel_keeps_the_reference_samples(kernel, with_grid: bool, train: bool) -> None:
    origins, dirs = _rays(700, 0)
    grid = None
    if with_grid:
        grid = OccupancyGrid(32, 1.0)
        grid.occupied.copy_(torch.rand(32**3, generator=torch.Generator().manual_seed(1)) < 0.3)
    out = []
    for mod in (kernel, None):
        gen = torch.Generator().manual_seed(2) if train else None
        out.append(march(origins, dirs, grid, 1.0, 2.0 / 256, 300, gen, chunk_rays=256, kernel=mod))
    got, want = out
    assert want.n > 1000
    assert torch.equal(got.ray_idx, want.ray_idx) and torch.equal(got.t, want.t) and torch.equal(got.dt, want.dt)


def test_kernel_stops_at_max_samples_and_skips_missed_rays(kernel) -> None:
    origins = torch.tensor([[0.0, 0.0, -3.0], [0.0, 5.0, -3.0]])
    dirs = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])  # the second misses the unit sphere
    s = march(origins, dirs, None, 1.0, 0.01, 50, None, kernel=kernel)
    assert s.n == 50 and (s.ray_idx == 0).all()
    assert torch.allclose(s.t, 2.0 + (torch.arange(50) + 0.5) * 0.01)
