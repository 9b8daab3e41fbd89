"""AniSDF: wiring of the fused-granularity SDF, the blended radiance field and NeuS rendering, and the loss dict."""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Protocol

import torch
import torch.nn.functional as F
from torch import Tensor, nn
from torch.nn.utils import parametrize

from anisdf.config import Config
from anisdf.fields.background_field import BackgroundNeRF, EnvironmentBackground
from anisdf.fields.hash_grid.cpu_kernel import kernel_for
from anisdf.fields.radiance_field import RadianceField
from anisdf.fields.sdf_field import SDFField, mlp_with_input_grad
from anisdf.model_components import losses as L
from anisdf.model_components.compiled import Compiled
from anisdf.model_components.interior import InteriorPrior, interior_state
from anisdf.model_components.neus_renderer import (
    Variance,
    composite,
    estimated_alpha,
    neus_alpha,
    packed_weights,
    prune_hidden,
    prune_occluded,
)
from anisdf.model_components.occupancy_grid import OccupancyGrid, march_grid_state, refine_march_grid
from anisdf.model_components.ray_marching import march
from anisdf.models.per_image import TRANSFORM_DIMS, CameraRefinement, ImageCodes, colour_transform


@dataclass
class TrainingSamples:
    """Per-sample tensors of a training render: what the geometric losses (Eq. 14-16) read."""

    x: Tensor
    dirs: Tensor
    grad: Tensor
    normal: Tensor
    weights: Tensor
    ray_idx: Tensor


@dataclass
class RenderOutput:
    """What :meth:`AniSDFModel.render_rays` computed: per-ray maps (``rgb``, ``opacity``; when not training also
    ``depth``, ``normal``, ``c_view``, ``c_ref``, ``w``), the NeuS sharpness, the sample counts (plain ints: reading
    them waits for no GPU) and, in training, the per-sample tensors."""

    maps: dict[str, Tensor]
    inv_s: Tensor
    n_samples: int
    """Samples left after the pruning pass (colour and gradients were computed for these)."""
    n_marched: int
    """Samples the march produced (the cheap SDF-only pruning pass looks at these, front to back)."""
    samples: TrainingSamples | None = None

    @property
    def rgb(self) -> Tensor:
        return self.maps["rgb"]

    @property
    def opacity(self) -> Tensor:
        return self.maps["opacity"]


class GridBroadcaster(Protocol):
    """The data-parallel job (training/distributed.py) as the occupancy-grid update sees it."""

    is_main: bool

    def broadcast_module(self, module: nn.Module) -> None: ...

    def broadcast_tensors(self, tensors: list[Tensor]) -> None: ...


REFINE_BUDGET = 4_000_000
"""Most SDF queries :meth:`AniSDFModel.image_grid` spends on refining (a trained cpu-quick bunny: about 2M)."""
GRID_REFINE_BUDGET = 400_000
"""Most SDF queries a full refinement of the training grid spends (``renderer.grid_refine``; a cpu-quick bunny late in
training: 32-52k occupied cells of 64^3, 256-420k children): above it, occupancy_grid.refine_march_grid."""
INTERIOR_EVERY, INTERIOR_POINTS, INTERIOR_STEPS = 16, 1024, 4
"""The interior prior (``loss.interior``) sweeps its depths every 16th grid update (64^3 cells: 0.2 s on 2 CPU cores)
and bounds 1024 points on the schedule steps divisible by 4 (the term alone: 5.9 ms on 2 cores; it is near zero a few
dozen steps after each sweep)."""


class AniSDFModel(nn.Module):
    one_pass_pruning: tuple[str, ...] = ("cuda",)
    """Device types whose training steps prune in one pass over all marched samples: each round of the progressive
    pass (front to back, 57% fewer SDF queries late in a cpu-quick bunny) reads the selection back from the GPU."""

    def __init__(self, cfg: Config, learn_background: bool = False, trained: Tensor | None = None,
                 camera_poses: Tensor | None = None, image_codes: bool = False) -> None:
        """``trained``: [N] bool, which of the scene's N images train; with it, ``camera_poses`` ([N,3,4]) are refined
        (``cameras.refine``) and ``image_codes`` gives every image an appearance code (``appearance.embedding``)."""
        super().__init__()
        self.cfg = cfg
        r = cfg.renderer
        self.radius = r.radius
        self.geometry = SDFField(cfg.geometry, radius=r.radius)
        per_image = image_codes and trained is not None
        # appearance.embedding_kind: a code the heads read, or a colour transform of each image's rendering
        kind = cfg.appearance.embedding_kind
        self.colour_transform = kind if per_image and kind in TRANSFORM_DIMS else None
        code_dim = cfg.appearance.embedding_dim if per_image and not self.colour_transform else 0
        self.appearance = RadianceField(cfg.appearance, cfg.geometry.feature_dim, code_dim,
                                        fast=cfg.geometry.encoding_backend != "torch")
        self.variance = Variance(r.variance_init, r.variance_scale, r.inv_s_max)
        self.grid = OccupancyGrid(r.grid_resolution, r.radius, band=math.log(4.0 / r.occupancy_threshold))
        # renderer.grid_refine: the grid training rays march, refined at each update (a buffer: exact resume); never
        # finer than two march steps a cell, or the thinner shell could fall between a ray's samples
        fine_res = r.grid_resolution * r.grid_refine
        self.march_grid = (OccupancyGrid(fine_res, r.radius, self.grid.band)
                           if r.grid_refine > 1 and 2.0 * r.radius / fine_res >= 2.0 * self.step_size else None)
        self.register_load_state_dict_pre_hook(
            lambda _m, state, prefix, *_: march_grid_state(state, prefix, self.grid, self.march_grid))
        # loss.interior: the depth of the training grid's cells inside the object, renewed every INTERIOR_EVERY updates
        self.interior = InteriorPrior(r.grid_resolution, r.radius) if cfg.loss.interior > 0 else None
        self.register_load_state_dict_pre_hook(lambda _m, st, prefix, *_: interior_state(st, prefix, self.interior))
        # opaque photos without masks: what lies beyond the sphere is learned too
        self.background: nn.Module | None = None
        if learn_background:
            self.background = (BackgroundNeRF(r.radius, r.background_samples, n_levels=r.background_levels,
                                              log2_hashmap_size=r.background_log2_hashmap_size,
                                              hidden=r.background_hidden, layers=r.background_layers,
                                              grid_resolution=r.background_grid_resolution,
                                              backend=cfg.geometry.encoding_backend)
                               if r.background_model == "nerf" else EnvironmentBackground())
        self.cameras = (CameraRefinement(camera_poses, trained, cfg.cameras.anchor)
                        if camera_poses is not None and trained is not None else None)
        n_codes = TRANSFORM_DIMS[self.colour_transform] if self.colour_transform else code_dim
        self.image_codes = ImageCodes(trained.shape[0], n_codes, trained) if n_codes else None
        self.register_buffer("step", torch.zeros((), dtype=torch.long))
        # the step as a Python int, which schedules read without waiting for the GPU (the buffer is for checkpoints)
        self.step_int = 0
        # after loading, the mirror follows the loaded buffer (each SDF branch keeps its own level mirror the same way)
        self.register_load_state_dict_post_hook(lambda module, _keys: setattr(module, "step_int", int(module.step)))
        # the radiance heads and the opacity, eager until compile_heads() (plain attributes, not submodules)
        self.color_fn: Callable[..., dict[str, Tensor]] = self.appearance.__call__
        self.alpha_fn: Callable[..., Tensor] = neus_alpha

    def compile_heads(self) -> None:
        """``train.compile``: ``torch.compile`` the SDF MLPs with their closed-form input gradient, the radiance
        field and the NeuS opacity (model_components/compiled); the hash grids keep their own kernels."""
        self.geometry.mlp_fn = Compiled(mlp_with_input_grad, "the SDF MLPs")
        self.color_fn = Compiled(self.appearance.forward, "the radiance field")
        self.alpha_fn = Compiled(neus_alpha, "the NeuS opacity")

    # ----------------------------------------------------------------------------------------- schedule
    def set_step(self, step: int) -> None:
        self.step_int = step
        self.step.fill_(step)
        self.geometry.set_step(step)

    @property
    def cos_anneal(self) -> float:
        n = self.cfg.renderer.cos_anneal_steps
        return 1.0 if n <= 0 else min(1.0, self.step_int / n)

    @property
    def step_size(self) -> float:
        return math.sqrt(3.0) * 2.0 * self.radius / self.cfg.renderer.march_steps

    def finest_cell(self, branch: int = -1) -> float:
        """Cell size of the finest active level of a branch (default: the fine grid, or the single one)."""
        b = self.geometry.branches[branch]
        res = b.grid.spec.resolutions[b.n_active - 1]
        return 2.0 * self.radius / res

    def curvature_eps(self) -> float:
        """The curvature term's tangent step (``loss.curvature_eps``): the fine grid's finest active cell, or the mean
        of the coarse and fine grids' finest active cells (one grid: its cell)."""
        if self.cfg.loss.curvature_eps == "mean_cells":
            n = len(self.geometry.branches)
            return sum(self.finest_cell(i) for i in range(n)) / n
        return self.finest_cell()

    def fd_eps(self) -> float:
        e = self.cfg.geometry.fd_eps
        return e if e > 0 else 0.5 * self.finest_cell()

    @torch.no_grad()
    def update_grid(self, generator: torch.Generator, full: bool = False, job: GridBroadcaster | None = None) -> None:
        """Re-evaluate the occupancy grid; in a data-parallel ``job`` rank 0 does it (drawing from the shared
        generator) and sends the grid to every rank, so float noise between devices cannot make the grids differ."""
        bg = self.background if isinstance(self.background, BackgroundNeRF) and self.background.grid_resolution \
            else None
        def interior_due() -> bool:  # this update's count, rank 0's after the broadcast: every rank reads the same
            return (self.interior is not None and self.step_int >= self.cfg.loss.interior_start
                    and int(self.grid.n_updates) % INTERIOR_EVERY == 0)
        if job is None or job.is_main:
            before = self.grid.occupied.clone()
            self.grid.update(self.geometry.distance, float(self.variance()), generator, full=full)
            if self.march_grid is not None:
                refine_march_grid(self.grid, self.march_grid, before, self.geometry.distance, float(self.variance()),
                                  self.cfg.renderer.grid_refine_every, GRID_REFINE_BUDGET)
            if interior_due():
                self.interior.update(self.geometry.distance)
            if bg is not None:
                bg.update_grid(generator, full=full)
        if job is not None:
            job.broadcast_module(self.grid)
            if interior_due():  # the depths change at these updates only (and the cached cells are dropped)
                job.broadcast_module(self.interior)
                self.interior.forget_cells()
            if self.march_grid is not None:
                job.broadcast_module(self.march_grid)
            if bg is not None:
                job.broadcast_tensors([bg.density_ema, bg.occupied])

    @contextlib.contextmanager
    def cached_weights(self) -> Iterator[None]:
        """A training step's scope: each weight-normed SDF layer's weight is computed once (with grad) and reused
        by every SDF query inside (the render's passes and the curvature loss's)."""
        with parametrize.cached():
            self.geometry.cache_weights()
            yield

    # ----------------------------------------------------------------------------------------- render
    def render_rays(self, origins: Tensor, dirs: Tensor, background: Tensor, train: bool = False,
                    generator: torch.Generator | None = None, codes: Tensor | None = None,
                    grid: OccupancyGrid | None = None, prune_after_query: bool = False) -> RenderOutput:
        """Render rays (NeuS, Eq. 1): per-ray maps, and in training the per-sample tensors the losses read.
        ``codes``: [B, dim] per-ray appearance codes (:meth:`codes_for`) when the model has them (default: the mean
        code). ``grid``: the occupancy grid to march (default: the training grid, refined in training with
        ``renderer.grid_refine``). ``prune_after_query`` (training): every marched sample is queried with its
        gradient and the query's SDF values prune (the mask of the SDF-only pass, which is then skipped): cheaper
        while little is hidden (``renderer.prune_after_query_below``)."""
        n_rays = origins.shape[0]
        rc = self.cfg.renderer
        if grid is None:
            grid = self.march_grid if train and self.march_grid is not None else self.grid
        s = march(origins, dirs, grid, self.radius, self.step_size, rc.max_samples_per_ray,
                  generator if train else None, kernel=kernel_for(origins) if self.appearance.fast else None)
        inv_s = self.variance()
        n_marched, sdf_kept = s.n, None
        prune = rc.early_stop_eps > 0 and s.n > 0  # drop samples hidden behind the surface
        late = prune and train and prune_after_query
        if prune and not late:  # by the SDF-only pass (no grad)
            keep, sdf_kept = prune_hidden(self.geometry.distance, origins, dirs, s, self.step_size, inv_s.detach(),
                                          rc.early_stop_eps, train and origins.device.type in self.one_pass_pruning,
                                          need_sdf=not train)
            s = s.select(keep)
        # index_select: with refined cameras the rays carry gradients, and its backward (index_add) sums the
        # samples of a ray in a fixed order where indexing's (a parallel scatter on CPU) does not: exact resume
        d = dirs.index_select(0, s.ray_idx)
        x = origins.index_select(0, s.ray_idx) + d * s.t[:, None]
        sub = None
        if sdf_kept is not None and not train and rc.eval_normal_band > 0 and self.cos_anneal >= 1.0:  # an image of
            # a trained model: normals only near the surface; elsewhere the opacity from SDF values alone
            alpha0 = estimated_alpha(sdf_kept, s.t, s.ray_idx, self.step_size, inv_s)
            sub = (sdf_kept.abs() * inv_s < rc.eval_normal_band).nonzero()[:, 0]
        xq = x if sub is None else x[sub]
        q = self.geometry.query(xq, create_graph=train, fd_eps=self.fd_eps())
        if late:  # the same estimate from the query's SDF values; the hidden samples' rows leave the query
            rows = prune_occluded(q.sdf.detach(), s.t, s.ray_idx, n_rays, self.step_size, inv_s.detach(),
                                  rc.early_stop_eps).nonzero()[:, 0]
            if rows.numel() < s.n:
                q, s, x, d = q.select(rows), s.select(rows), x.index_select(0, rows), d.index_select(0, rows)
                xq = x
        sdf, grad = q.sdf, q.grad
        if xq.requires_grad:  # rays of refined cameras, or a camera eval fits: the field treats x as a constant, so
            # the SDF's first-order change with the point, sdf(x + dx) = sdf + grad . dx, carries the gradient to them
            sdf = sdf + (grad.detach() * (xq - xq.detach())).sum(-1)
        normal = F.normalize(grad, dim=-1)
        if sub is None:
            alpha = self.alpha_fn(sdf, grad, d, s.dt, inv_s, self.cos_anneal)
            weights, _ = packed_weights(alpha, s.ray_idx, n_rays)
            w_all, s_all = weights, s  # opacity and depth sum every sample's weight
        else:
            alpha = alpha0.index_put((sub,), self.alpha_fn(sdf, grad, d[sub], s.dt[sub], inv_s, self.cos_anneal))
            w_all, s_all = packed_weights(alpha, s.ray_idx, n_rays)[0], s
            weights, s, x, d = w_all[sub], s.select(sub), xq, d[sub]
        # colour only where it can be seen: samples of negligible weight add nothing to any pixel
        vis = (weights.detach() > self.cfg.renderer.color_weight_eps).nonzero()[:, 0]  # indices: one host sync
        if self.image_codes is not None and codes is None:
            codes = self.image_codes(None, n_rays)
        extra = () if codes is None or self.colour_transform else (codes.index_select(0, s.ray_idx[vis]),)
        col_vis = self.color_fn(x[vis] / self.radius, q.feature(vis), normal[vis], d[vis], *extra)
        w_vis, r_vis = weights[vis], s.ray_idx[vis]
        out: dict[str, Tensor] = {}
        opacity = composite(torch.ones_like(w_all), w_all, s_all.ray_idx, n_rays)
        if isinstance(self.background, BackgroundNeRF):
            background = self.background(origins, dirs, generator if train else None)["rgb"]
        elif self.background is not None:
            background = self.background(dirs)
        # training needs the colour and opacity only; the other maps (branch colours, blend weight, depth, normal)
        # are for viewing and evaluation
        for key, val in col_vis.items():
            if key == "rgb" or not train:
                out[key] = composite(val, w_vis, r_vis, n_rays)
        if self.colour_transform:  # the image's exposure and white balance, on what the camera saw of the scene
            out["rgb"] = colour_transform(self.colour_transform, out["rgb"], codes, opacity)
            if self.background is not None:  # a learned background is part of the photo; a given colour is not
                background = colour_transform(self.colour_transform, background, codes, torch.ones_like(opacity))
        out["rgb"] = out["rgb"] + (1.0 - opacity[:, None]) * background
        out["opacity"] = opacity
        if not train:
            out["depth"] = composite(s_all.t, w_all, s_all.ray_idx, n_rays)
            out["normal"] = composite(normal, weights, s.ray_idx, n_rays)
        # the geometric losses do not move the cameras (no-op detaches without camera refinement)
        samples = TrainingSamples(x.detach(), d.detach(), grad, normal, weights, s.ray_idx) if train else None
        return RenderOutput(out, inv_s.detach(), s.n, n_marched, samples)

    @torch.no_grad()
    def image_grid(self) -> OccupancyGrid:
        """The occupancy grid refined for images (``renderer.image_grid_resolution``), built once per model state
        (step and grid update) and kept until either changes; the training grid when refinement is off or would
        take more than ``REFINE_BUDGET`` SDF queries."""
        target = self.cfg.renderer.image_grid_resolution
        factor = -(-target // self.grid.resolution) if target > 0 else 1
        # a grid that is still mostly occupied (early training) gains little and would cost millions of queries
        if factor <= 1 or int(self.grid.occupied.sum()) * factor**3 > REFINE_BUDGET:
            return self.grid
        key = (self.step_int, int(self.grid.n_updates), factor, float(self.variance()))
        if getattr(self, "_image_grid", (None, None))[0] != key:
            fine = self.grid.refined(self.geometry.distance, key[3], factor)
            self._image_grid = (key, fine)
        return self._image_grid[1]

    @torch.no_grad()
    def render_image(self, origins: Tensor, dirs: Tensor, background: Tensor, chunk: int,
                     fine_grid: bool = False) -> dict[str, Tensor]:
        """Chunked rendering of many rays (an image) within a memory budget; outputs on the rays' device.
        ``fine_grid``: march :meth:`image_grid` (a fixed model rendering many images: eval, render, export)."""
        parts: dict[str, list[Tensor]] = {}
        grid = self.image_grid() if fine_grid else None
        with parametrize.cached():  # the weight-normed weights once per image, not once per query
            for i in range(0, origins.shape[0], chunk):
                out = self.render_rays(origins[i : i + chunk], dirs[i : i + chunk], background[i : i + chunk],
                                       grid=grid)
                for k, v in out.maps.items():
                    parts.setdefault(k, []).append(v.detach())
        return {k: torch.cat(v) for k, v in parts.items()}

    # ----------------------------------------------------------------------------------------- losses
    def losses(self, out: RenderOutput, target: Tensor, mask: Tensor | None,
               generator: torch.Generator | None, sample_share: float = 1.0) -> dict[str, Tensor]:
        """Loss dict (Eq. 18): weighted terms and their sum under ``total``. ``sample_share`` scales the weights of
        the means over samples (eikonal, curvature) in ``total``: a rank's share of all ranks' samples times their
        number, so that averaging the ranks' gradients gives the gradient over all samples (training/distributed)."""
        lc = self.cfg.loss
        step = self.step_int
        terms: dict[str, Tensor] = {"rgb": L.rgb_loss(out.rgb, target, lc.rgb)}
        if out.samples is None:
            raise ValueError("losses() needs a training render (render_rays(..., train=True))")
        smp = out.samples
        grad = smp.grad
        if grad.shape[0] == 0:
            terms["total"] = terms["rgb"]
            return terms
        weights: dict[str, float] = {"rgb": 1.0}
        if lc.eikonal > 0:
            terms["eikonal"] = L.eikonal_loss(grad)
            weights["eikonal"] = lc.eikonal if sample_share == 1.0 else lc.eikonal * sample_share
        curv_w = self.curvature_weight()
        if curv_w > 0:
            terms["curvature"] = self.curvature_term(smp.x, smp.normal, generator)
            weights["curvature"] = curv_w if sample_share == 1.0 else curv_w * sample_share
        orient_w = _ramp(lc.orientation_start, lc.orientation, step, lc.orientation_ramp_steps)
        if orient_w > 0:
            terms["orientation"] = L.orientation_loss(smp.weights, smp.normal, smp.dirs, smp.ray_idx,
                                                      target.shape[0])
            weights["orientation"] = orient_w
        if lc.entropy > 0:
            terms["entropy"] = L.alpha_entropy_loss(out.opacity)
            weights["entropy"] = lc.entropy
        if lc.mask > 0 and mask is not None:
            terms["mask"] = L.mask_loss(out.opacity, mask)
            weights["mask"] = lc.mask
        drawn = (self.interior.sample(INTERIOR_POINTS, generator)
                 if self.interior is not None and step % INTERIOR_STEPS == 0 else None)
        if drawn is not None:
            terms["interior"] = L.interior_loss(self.geometry.distance(drawn[0]), drawn[1])
            weights["interior"] = lc.interior
        terms["total"] = sum(weights[k] * terms[k] for k in weights)
        return terms

    def curvature_term(self, x: Tensor, normal: Tensor, generator: torch.Generator | None) -> Tensor:
        """Eq. 15 on a random ``curvature_fraction`` of the samples (at least 1024): the unit normal ``n`` at ``x``
        against the normal at ``x + eps t`` (``t`` a random tangent, ``eps`` from :meth:`curvature_eps`) of the fused
        field or of the coarse branch (``loss.curvature_target``), in ``loss.curvature_form``."""
        lc = self.cfg.loss
        k = min(x.shape[0], max(1024, int(x.shape[0] * lc.curvature_fraction)))
        dev = generator.device if generator is not None else x.device
        sel = torch.randperm(x.shape[0], generator=generator, device=dev)[:k].to(x.device)
        x_eps = L.tangent_perturbation(x[sel], normal[sel], self.curvature_eps(), generator)
        if lc.curvature_target == "coarse":
            g_eps = self.geometry.branch_gradient(x_eps, 0, create_graph=True, fd_eps=self.fd_eps())
        else:
            g_eps = self.geometry.query(x_eps, create_graph=True, fd_eps=self.fd_eps()).grad
        return L.curvature_loss(normal[sel], F.normalize(g_eps, dim=-1), lc.curvature_form)

    def curvature_weight(self) -> float:
        """Eq. 15's weight: a linear ramp from 0 over ``curvature_ramp_steps``, then ``curvature_decay``: levels
        divides it by the per-level scale for each level the fine (or single) grid has switched on since the start
        (Neuralangelo); exponential multiplies it by ``exp(-(t - ramp) ln(per_level_scale) / level_every)`` for the
        rest of the run (the release's DTU schedule)."""
        lc = self.cfg.loss
        w = _ramp(0.0, lc.curvature, self.step_int, lc.curvature_ramp_steps)
        if lc.curvature_decay == "levels":
            b = self.geometry.branches[-1]
            w /= self.cfg.geometry.per_level_scale() ** (b.n_active - b.start_levels)
        elif lc.curvature_decay == "exponential":
            g = self.cfg.geometry
            t = max(self.step_int - lc.curvature_ramp_steps, 0)
            w *= math.exp(-t * math.log(g.per_level_scale()) / max(g.level_every, 1))
        return w

    # ----------------------------------------------------------------------------------------- queries
    @torch.no_grad()
    def diffuse_color(self, x: Tensor) -> Tensor:
        """View-branch colour at ``x`` seen head-on (along -n): vertex colours for exported meshes."""
        _, feat, grad = self.geometry.with_gradient(x, create_graph=False, fd_eps=self.fd_eps())
        n = F.normalize(grad, dim=-1)
        return self.appearance(x / self.radius, feat, n, -n, *self.codes_for(None, x.shape[0]))["c_view"]

    def codes_for(self, cam_idx: Tensor | None, n: int) -> tuple[Tensor, ...]:
        """The appearance codes the radiance field takes for ``n`` rays or points of the images ``cam_idx`` (None:
        the mean code) as a tuple of extra arguments: empty when the model has none."""
        return () if self.image_codes is None or self.colour_transform else (self.image_codes(cam_idx, n),)

    def param_groups(self) -> list[dict]:
        """The optimiser's groups: model, variance, the per-image codes (``appearance.embedding_lr``) when learned, and
        the camera corrections (own learning rate, no weight decay: ``cameras.reg`` holds them) when refined."""
        var = [self.variance.variance]
        other = [p for n, p in self.named_parameters() if not n.startswith(("variance.", "cameras.", "image_codes."))]
        groups = [{"params": other, "name": "model"}, {"params": var, "name": "variance"}]
        if self.image_codes is not None:
            groups.append({"params": [self.image_codes.codes], "name": "image codes",
                           "lr": self.cfg.appearance.embedding_lr})
        if self.cameras is not None:
            groups.append({"params": [self.cameras.delta], "name": "cameras", "lr": self.cfg.cameras.lr,
                           "weight_decay": 0.0})
        return groups


def _ramp(start: float, end: float, step: int, steps: int) -> float:
    """Linear from ``start`` at step 0 to ``end`` at ``steps`` and after; a negative ``start`` or no ``steps``
    means ``end`` throughout."""
    if start < 0 or steps <= 0:
        return end
    return start + (end - start) * min(1.0, step / steps)
