"""The interior prior (anisdf's, not the paper's): the SDF held deep below zero inside the object.

No ray reaches past the surface, and no term of Eq. 18 constrains the SDF there: on a 10-minute cpu-quick bunny it
falls to about -0.035 just behind the surface and stays there, a plateau that the fine hash levels' noise lifts across
zero in places, closed shells deep inside the mesh that no camera sees and that count against Chamfer
(benchmarks/RESULTS.md). Every so often the SDF is swept at the centres of an occupancy grid's cells; the solid
(``sdf <= 0`` inside the bounding sphere, with the enclosed pockets deep enough not to be a concavity the sweep sealed)
gives each cell its depth ``D``, the distance to the nearest cell outside. A true SDF is ``-D`` there, so training
pushes ``sdf(x) <= -(D - cell) / 2`` at random points of the cells at least two cells deep (``loss.interior``;
models/anisdf.py sets how often): no constraint near the surface, none that a real shape breaks.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
from scipy import ndimage
from torch import Tensor, nn

from anisdf.model_components.occupancy_grid import cell_points

DEPTH_SCALE = 0.5
"""The bound's share of the depth: a 1-Lipschitz SDF may be shallower than ``-D`` anywhere, not than ``-D / 2``
beyond a Lipschitz constant of 2 (the occupancy grid's allowance)."""
MIN_DEPTH_CELLS = 2
"""Cells closer to the outside than this many cells get no bound: the surface is the other losses' to place."""
POCKET_WALL_CELLS = 3
"""An enclosed pocket counts as solid only when all of it lies further than this from the open outside: a concavity
whose mouth the sweep's cells happen to seal lies next to the outside."""


def enclosed_pockets(outside: np.ndarray) -> np.ndarray:
    """The voxels of ``outside`` (a bool volume) not connected to the volume's faces through 6-connected
    ``outside`` voxels (so not across an edge): pockets enclosed by the solid."""
    labels, n = ndimage.label(outside)
    if n <= 1:
        return np.zeros_like(outside)
    faces = [labels[0], labels[-1], labels[:, 0], labels[:, -1], labels[:, :, 0], labels[:, :, -1]]
    open_label = np.zeros(n + 1, dtype=bool)
    open_label[np.unique(np.concatenate([f.ravel() for f in faces]))] = True
    open_label[0] = False
    return outside & ~open_label[labels]


def solid_depth(vol: np.ndarray) -> np.ndarray:
    """Depth of each voxel of an SDF volume in voxels: the distance from the solid's voxels to the nearest voxel
    outside (0 outside). Solid: ``vol <= 0`` and the enclosed pockets lying more than :data:`POCKET_WALL_CELLS` from
    the open outside."""
    outside = vol > 0
    pockets = enclosed_pockets(outside)
    if pockets.any():
        open_outside = outside & ~pockets
        to_open = ndimage.distance_transform_edt(~open_outside)
        labels, n = ndimage.label(pockets)
        nearest = ndimage.minimum(to_open, labels, np.arange(1, n + 1))
        deep = np.concatenate([[False], np.asarray(nearest) > POCKET_WALL_CELLS])
        outside = outside & ~deep[labels]
    return ndimage.distance_transform_edt(~outside).astype(np.float32)


class InteriorPrior(nn.Module):
    """The depth of each cell of a ``resolution^3`` grid over ``[-radius, radius]^3`` (a buffer: checkpoints keep it,
    a resume draws the same points) and the bound it sets on the SDF at points drawn in the deep cells."""

    def __init__(self, resolution: int, radius: float) -> None:
        super().__init__()
        self.resolution = resolution
        self.radius = radius
        self.register_buffer("depth", torch.zeros(resolution**3))
        # the deep cells' indices, found once per update or load (a GPU waits for a nonzero, so not at every step)
        self._cells: Tensor | None = None
        self.register_load_state_dict_post_hook(lambda module, _keys: module.forget_cells())

    @property
    def cell_size(self) -> float:
        return 2.0 * self.radius / self.resolution

    @torch.no_grad()
    def update(self, sdf_fn: Callable[[Tensor], Tensor], chunk: int = 2**16) -> float:
        """Sweep ``sdf_fn`` at the cell centres (clipped to the bounding sphere) and recompute the depths; returns
        the share of cells deep enough to be bounded."""
        r, dev = self.resolution, self.depth.device
        idx = torch.arange(r**3, device=dev)
        centres = cell_points(idx, torch.full((r**3, 3), 0.5, device=dev), r, self.radius)
        vol = torch.cat([sdf_fn(centres[s : s + chunk]).float() for s in range(0, centres.shape[0], chunk)])
        vol = torch.maximum(vol, centres.norm(dim=-1) - self.radius)
        self.forget_cells()
        if not bool(torch.isfinite(vol).all()):  # a diverged SDF: no bound rather than one from garbage
            self.depth.zero_()
            return 0.0
        depth = solid_depth(vol.reshape(r, r, r).cpu().numpy())
        self.depth.copy_(torch.from_numpy(depth).reshape(-1).to(dev) * self.cell_size)
        return float((self.depth >= MIN_DEPTH_CELLS * self.cell_size).float().mean())

    def forget_cells(self) -> None:
        """Drop the cached deep cells: ``depth`` changed in place (a data-parallel job's broadcast)."""
        self._cells = None

    def _apply(self, fn: Callable[[Tensor], Tensor], recurse: bool = True) -> InteriorPrior:
        self.forget_cells()  # .to() and the like: the cached indices follow the buffer
        return super()._apply(fn, recurse)

    def sample(self, n: int, generator: torch.Generator | None) -> tuple[Tensor, Tensor] | None:
        """``n`` points drawn uniformly in the cells at least :data:`MIN_DEPTH_CELLS` deep and the bound
        ``-(D - cell) * DEPTH_SCALE`` the SDF should stay below at each; None while no cell is that deep."""
        if self._cells is None:
            self._cells = (self.depth >= MIN_DEPTH_CELLS * self.cell_size).nonzero()[:, 0]
        cells = self._cells
        if cells.numel() == 0:
            return None
        gdev = generator.device if generator is not None else cells.device
        pick = cells[torch.randint(0, cells.numel(), (n,), generator=generator, device=gdev).to(cells.device)]
        jitter = torch.rand(n, 3, generator=generator, device=gdev).to(cells.device)
        x = cell_points(pick, jitter, self.resolution, self.radius)
        return x, -(self.depth[pick] - self.cell_size) * DEPTH_SCALE


def interior_state(state: dict, prefix: str, prior: InteriorPrior | None) -> None:
    """A state dict's interior depths made to fit a model, in place: dropped for a model without the prior, zero (no
    bound until the next sweep) for one with it loading a checkpoint saved without."""
    key = prefix + "interior.depth"
    if prior is None:
        state.pop(key, None)
    elif key not in state:
        state[key] = torch.zeros_like(prior.depth)
