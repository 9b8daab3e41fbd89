"""Background NeRF of unbounded scenes: contraction, disparity sampling, and that it learns what lies outside."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from anisdf.fields.background_field import BackgroundNeRF, contract, exit_distance


def test_contraction_is_identity_inside_and_bounded_outside() -> None:
    g = torch.Generator().manual_seed(0)
    x = torch.randn(5000, 3, generator=g) * torch.logspace(-2, 4, 5000)[:, None]
    c = contract(x)
    n = x.norm(dim=-1)
    assert torch.equal(c[n <= 1], x[n <= 1])
    assert c.norm(dim=-1).max() < 2.0
    # outside: same direction, radius 2 - 1/|x| (continuous at |x| = 1)
    out = n > 1
    assert torch.allclose(F.normalize(c[out], dim=-1), F.normalize(x[out], dim=-1), atol=1e-5)
    assert torch.allclose(c[out].norm(dim=-1), 2 - 1 / n[out], atol=1e-5)
    # radial order is kept
    r = torch.linspace(0.5, 100, 200)[:, None] * torch.tensor([[0.6, 0.0, 0.8]])
    assert torch.all(contract(r).norm(dim=-1).diff() > 0)


def test_samples_run_from_the_sphere_exit_to_far() -> None:
    bg = BackgroundNeRF(radius=1.0, n_samples=16, far=100.0, n_levels=4, log2_hashmap_size=12, backend="torch")
    o = torch.tensor([[0.0, 0.0, -3.0], [0.2, -0.1, 0.3], [5.0, 5.0, 0.0]])
    d = F.normalize(torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]), dim=-1)
    for gen in (None, torch.Generator().manual_seed(1)):
        e = bg.sample_distances(o, d, gen)
        assert e.shape == (3, 17) and torch.all(e.diff(dim=-1) >= 0)
        assert torch.allclose(e[:, 0], exit_distance(o, d, 1.0).clamp_min(1e-3))
        assert torch.allclose(e[:, -1], torch.full((3,), 100.0))
    assert torch.allclose(exit_distance(o, d, 1.0)[:2], torch.tensor([4.0, -0.2 + (1 - 0.01 - 0.09) ** 0.5]))


@pytest.mark.parametrize("grid", [0, 16])
def test_background_nerf_learns_a_panorama(grid: int) -> None:
    """Rays from inside the sphere see a two-coloured world (warm above the horizon, cool below); the fitted
    background reproduces it far better than its initial guess, with or without its occupancy grid."""
    torch.manual_seed(0)
    bg = BackgroundNeRF(radius=1.0, n_samples=16, n_levels=8, log2_hashmap_size=14, hidden=32, backend="torch",
                        layers=2, grid_resolution=grid)
    opt = torch.optim.Adam(bg.parameters(), lr=1e-2)
    g = torch.Generator().manual_seed(0)

    def batch(n: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        d = F.normalize(torch.randn(n, 3, generator=g), dim=-1)
        o = (torch.rand(n, 3, generator=g) - 0.5) * 0.4
        up = (d[:, 2:3] > 0).float()
        target = up * torch.tensor([0.9, 0.5, 0.2]) + (1 - up) * torch.tensor([0.1, 0.3, 0.8])
        return o, d, target

    o, d, t = batch(2048)
    with torch.no_grad():
        before = F.mse_loss(bg(o, d)["rgb"], t).item()
    for i in range(150):
        if grid and i % 16 == 0:
            bg.update_grid(g, full=i < 64)
        ob, db, tb = batch(512)
        loss = F.mse_loss(bg(ob, db, g)["rgb"], tb)
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        after = F.mse_loss(bg(o, d)["rgb"], t).item()
    assert after < 0.1 * before and after < 0.01, (before, after)


class ShellBackground(BackgroundNeRF):
    """A background whose density is an analytic shell (contracted radius 1.5 to 1.7, the +x half), with a count
    of the points its heads see."""

    seen = 0

    def features(self, xc: torch.Tensor) -> torch.Tensor:
        self.seen += xc.shape[0]
        r = xc.norm(dim=-1)
        inside = (r > 1.5) & (r < 1.7) & (xc[:, 0] > 0)
        h = torch.full((xc.shape[0], 16), -20.0)
        h[:, 0] = torch.where(inside, torch.full_like(r, 6.0), torch.full_like(r, -30.0))
        h[:, 1:] = xc.sum(-1, keepdim=True)
        return h


def test_the_occupancy_grid_skips_empty_space_without_changing_the_picture() -> None:
    gen = torch.Generator().manual_seed(0)
    d = F.normalize(torch.randn(512, 3, generator=gen), dim=-1)
    o = torch.zeros(512, 3)
    plain = ShellBackground(n_samples=128, n_levels=4, log2_hashmap_size=10, backend="torch")
    gridded = ShellBackground(n_samples=128, n_levels=4, log2_hashmap_size=10, backend="torch", grid_resolution=32)
    gridded.load_state_dict(plain.state_dict(), strict=False)
    with torch.no_grad():
        before = gridded(o, d)["rgb"]  # every cell occupied until the first update: the same picture
        ref = plain(o, d)
        assert torch.equal(before, ref["rgb"])
        for _ in range(8):  # one jittered point a cell an update: a few updates find the shell's edge cells
            gridded.update_grid(gen, full=True)
        share = gridded.occupied.float().mean()
        assert 0.01 < share < 0.3, share
        gridded.seen = plain.seen = 0
        out = gridded(o, d)
        plain(o, d)
    assert gridded.seen < 0.3 * plain.seen
    assert ref["opacity"].max() > 0.5 and ref["opacity"].min() < 0.1  # the shell covers some directions only
    err = (out["rgb"] - ref["rgb"]).abs()
    assert float(err.mean()) < 1e-3 and float(err.max()) < 0.03, (float(err.mean()), float(err.max()))
