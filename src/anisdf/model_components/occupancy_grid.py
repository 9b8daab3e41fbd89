"""Occupancy grid for empty-space skipping (pure PyTorch, CPU and CUDA).

A binary grid over ``[-radius, radius]^3``. A cell is occupied when the SDF at a random point in the cell could
reach the surface within the cell or leave non-negligible NeuS density there:
``|sdf(p)| <= cell_diagonal + band / inv_s``, with ``band = ln(4 / renderer.occupancy_threshold)``: beyond it the
logistic density is below that fraction of its peak. Each update re-evaluates a random quarter of all cells plus the
cells that are currently occupied (every cell during warm-up), so an update costs a fraction of a full sweep.

:meth:`OccupancyGrid.refined` splits the occupied cells of a fixed model's grid into finer ones, for rendering
images: the band of samples around the surface shrinks with the cell, so a ray costs fewer SDF queries;
:func:`refine_march_grid` keeps such a finer grid for training rays (``renderer.grid_refine``) within a query budget.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor, nn


def cell_points(idx: Tensor, jitter: Tensor, resolution: int, radius: float) -> Tensor:
    """Points [N, 3] at ``jitter`` [N, 3] (0.5: the centre) within the cells ``idx`` [N] (``(i r + j) r + k``) of a
    ``resolution^3`` grid over ``[-radius, radius]^3``."""
    r = resolution
    ijk = torch.stack([idx // (r * r), (idx // r) % r, idx % r], dim=-1).to(jitter.dtype)
    return (ijk + jitter) * (2.0 * radius / r) - radius


class OccupancyGrid(nn.Module):
    def __init__(self, resolution: int = 128, radius: float = 1.0, band: float = 6.0) -> None:
        super().__init__()
        self.resolution = resolution
        self.radius = radius
        self.band = band
        self.register_buffer("occupied", torch.ones(resolution**3, dtype=torch.bool))
        self.register_buffer("n_updates", torch.zeros((), dtype=torch.long))

    @property
    def cell_size(self) -> float:
        return 2.0 * self.radius / self.resolution

    def cell_index(self, x: Tensor) -> Tensor:
        r = self.resolution
        ijk = ((x + self.radius) / self.cell_size).floor().long().clamp(0, r - 1)
        return (ijk[..., 0] * r + ijk[..., 1]) * r + ijk[..., 2]

    def query(self, x: Tensor) -> Tensor:
        """True where ``x`` [..., 3] falls in an occupied cell (False outside the box)."""
        inside = (x.abs() <= self.radius).all(-1)
        return self.occupied[self.cell_index(x)] & inside

    def query_rays(self, origins: Tensor, dirs: Tensor, t: Tensor) -> Tensor:
        """``query`` of the points ``origins[:, None] + dirs[:, None] * t`` [R, K] of rays that lie in the box.

        The same cells as ``query``, computed one axis at a time in cell units and int32 without building the
        [R, K, 3] points: the dense march's occupancy test was a tenth of a CPU training step. Points outside the
        box are clamped to its border cells, so callers keep only samples inside the bounding sphere (the march does).
        """
        r = self.resolution
        inv = 1.0 / self.cell_size
        a, b = (origins + self.radius) * inv, dirs * inv
        idx = None
        for axis in range(3):
            c = torch.addcmul(a[:, axis, None], b[:, axis, None], t).floor_().clamp_(0, r - 1).to(torch.int32)
            idx = c if idx is None else idx.mul_(r).add_(c)
        return self.occupied[idx]

    @torch.no_grad()
    def update(self, sdf_fn: Callable[[Tensor], Tensor], inv_s: float, generator: torch.Generator,
               full: bool = False, chunk: int = 2**16) -> float:
        """Re-evaluate cells with ``sdf_fn``; returns the occupied fraction."""
        n = self.resolution**3
        dev = self.occupied.device
        if full:
            idx = torch.arange(n, device=dev)
        else:
            rand = torch.randint(0, n, (n // 4,), generator=generator, device=generator.device).to(dev)
            idx = torch.unique(torch.cat([rand, self.occupied.nonzero()[:, 0]]))
        jitter = torch.rand(idx.shape[0], 3, generator=generator, device=generator.device).to(dev)
        thresh = math.sqrt(3.0) * self.cell_size + self.band / max(inv_s, 1e-6)
        new = torch.empty(idx.shape[0], dtype=torch.bool, device=dev)
        for s in range(0, idx.shape[0], chunk):
            p = cell_points(idx[s : s + chunk], jitter[s : s + chunk], self.resolution, self.radius)
            new[s : s + chunk] = sdf_fn(p).abs() <= thresh
        self.occupied[idx] = new
        self.n_updates += 1
        return self.occupied.float().mean().item()

    def upsampled(self, factor: int, occupied: Tensor | None = None) -> Tensor:
        """The occupancy of a grid ``factor`` times finer whose children copy their parent's [(r f)^3] bool (of
        ``occupied``, a mask of this grid's cells, if given)."""
        r, f = self.resolution, int(factor)
        occ = (self.occupied if occupied is None else occupied).view(r, r, r)
        for axis in range(3):
            occ = occ.repeat_interleave(f, dim=axis)
        return occ.reshape(-1)

    @torch.no_grad()
    def refined(self, sdf_fn: Callable[[Tensor], Tensor], inv_s: float, factor: int, lipschitz: float = 1.0,
                chunk: int = 2**16, occupied: Tensor | None = None) -> OccupancyGrid:
        """A grid ``factor`` times finer in which a cell is occupied when its parent is and, seen from outside, the
        SDF at its centre could reach zero within the cell or leave non-negligible density: ``sdf(centre) <=
        lipschitz * cell_diagonal + band / inv_s``. From the centre a 1-Lipschitz SDF needs half a diagonal; the
        default allows for a gradient up to 2 long (the eikonal term holds it near 1), as :meth:`update` does.
        Children inside the object are all kept: NeuS' discrete opacity of a ray going deeper stays high at any
        depth (``alpha ~ 1 - exp(-s |cos| dt)``), so a ray that is not yet opaque at the surface gathers the rest
        there, as in the parent grid. Only the children of occupied cells (of ``occupied``, a mask of this grid's
        cells, if given) are evaluated."""
        r, f = self.resolution, int(factor)
        fine = OccupancyGrid(r * f, self.radius, self.band).to(self.occupied.device)
        fine.n_updates.copy_(self.n_updates)
        parents = (self.occupied if occupied is None else occupied).nonzero()[:, 0]
        dev = parents.device
        pi, pj, pk = parents // (r * r), (parents // r) % r, parents % r
        sub = torch.stack(torch.meshgrid(*[torch.arange(f, device=dev)] * 3, indexing="ij"), -1).reshape(-1, 3)
        thresh = lipschitz * math.sqrt(3.0) * fine.cell_size + self.band / max(inv_s, 1e-6)
        occ = torch.zeros((r * f) ** 3, dtype=torch.bool, device=dev)
        per = max(1, chunk // f**3)
        for s in range(0, parents.shape[0], per):
            ijk = (torch.stack([pi[s : s + per], pj[s : s + per], pk[s : s + per]], -1)[:, None] * f + sub
                   ).reshape(-1, 3)
            centres = (ijk.to(torch.float32) + 0.5) * fine.cell_size - self.radius
            idx = (ijk[:, 0] * (r * f) + ijk[:, 1]) * (r * f) + ijk[:, 2]
            occ[idx] = sdf_fn(centres) <= thresh
        fine.occupied.copy_(occ)
        return fine


@torch.no_grad()
def refine_march_grid(grid: OccupancyGrid, fine: OccupancyGrid, before: Tensor, sdf_fn: Callable[[Tensor], Tensor],
                      inv_s: float, every: int, budget: int) -> None:
    """The grid training rays march (``renderer.grid_refine``), after an update of ``grid`` (``before``: its occupancy
    before): ``grid`` refined (:meth:`OccupancyGrid.refined`) every ``every`` updates; between them the children of
    cells that emptied are dropped and only cells that filled are refined. While refining every occupied cell would
    cost more than ``budget`` queries: before the first refinement the plain copy at the finer resolution (early
    training, a mostly occupied grid); after it a rotating share of the occupied cells is refined at each update
    (:func:`_refine_share`), never the copy: its samples reach the band around the surface that refined rays no
    longer train, and a quiet 10-minute cpu-quick run that crossed the budget saw its eikonal term jump from 0.003 to
    0.48 and its outline erode (benchmarks/RESULTS.md). ``fine.n_updates``: ``grid``'s update count at the last full
    refinement (0: a copy)."""
    f, since = fine.resolution // grid.resolution, int(grid.n_updates - fine.n_updates)
    filled = grid.occupied & ~before
    if int(grid.occupied.sum()) * f**3 > budget:
        if int(fine.n_updates) == 0:
            fine.occupied.copy_(grid.upsampled(f))
        else:
            _refine_share(grid, fine, filled, sdf_fn, inv_s, f, budget // max(every, 1))
    elif 0 < int(fine.n_updates) and since < every:
        _refine_cells(grid, fine, filled, sdf_fn, inv_s, f)
    else:
        fine.occupied.copy_(grid.refined(sdf_fn, inv_s, f).occupied)
        fine.n_updates.copy_(grid.n_updates)


def _refine_share(grid: OccupancyGrid, fine: OccupancyGrid, filled: Tensor, sdf_fn: Callable[[Tensor], Tensor],
                  inv_s: float, f: int, per_update: int) -> None:
    """The cells that filled and one of ``k`` shares of the occupied cells (index modulo ``k``, turning with the
    update count: a resume refines the same) refined afresh (:func:`_refine_cells`), ``k`` such that a share costs
    ``per_update`` queries: a full refinement's cost spread over the updates between two."""
    occ = grid.occupied
    k = -(-int(occ.sum()) * f**3 // max(per_update, 1))
    share = occ & (torch.arange(occ.numel(), device=occ.device) % k == int(grid.n_updates) % k)
    _refine_cells(grid, fine, share | filled, sdf_fn, inv_s, f)


def _refine_cells(grid: OccupancyGrid, fine: OccupancyGrid, redo: Tensor, sdf_fn: Callable[[Tensor], Tensor],
                  inv_s: float, f: int) -> None:
    """The children of the cells ``redo`` refined afresh; the other occupied cells keep theirs, the children of empty
    cells are dropped."""
    fresh = grid.refined(sdf_fn, inv_s, f, occupied=redo).occupied
    fine.occupied.logical_and_(grid.upsampled(f, grid.occupied & ~redo)).logical_or_(fresh)


def march_grid_state(state: dict, prefix: str, grid: OccupancyGrid, march_grid: OccupancyGrid | None) -> None:
    """A state dict's march grid (``renderer.grid_refine``) made to fit a model, in place: loading a run saved
    without one into a model with one, the march grid starts as the loaded ``grid``'s copy at the finer resolution
    (the next grid update refines it); the other way round, the checkpoint's march grid is left out (it is derived
    from the grid)."""
    key = prefix + "march_grid.occupied"
    if march_grid is None:
        state.pop(key, None)
        state.pop(prefix + "march_grid.n_updates", None)
    elif key not in state and prefix + "grid.occupied" in state:
        coarse = OccupancyGrid(grid.resolution, grid.radius, grid.band)
        coarse.occupied.copy_(state[prefix + "grid.occupied"])
        state[key] = coarse.upsampled(march_grid.resolution // grid.resolution)
        state[prefix + "march_grid.n_updates"] = torch.zeros_like(state[prefix + "grid.n_updates"])  # a copy
