"""Fused-granularity SDF (paper Sec. 3.2, Eqs. 4-5).

Two parallel hash grids, each with its own MLP, predict ``(SDF, F)``; the outputs are fused:
``SDF = SDF^c + SDF^f`` and ``F = F^c + F^f`` (``geometry.fusion=mean`` averages them, as the authors'
release does). Following the release (NOTES.md), both grids start at the base resolution with the same
per-level scale; the coarse grid has ``m`` levels and starts with ``coarse_start_levels`` active, the fine grid
has ``L`` levels and starts with ``fine_start_levels`` active, and both switch on one more level every
``level_every`` steps after ``level_start_step``. ``geometry.kind=single`` is the ablation: one grid of ``L``
levels switched on coarse-to-fine.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn
from torch.nn.utils.parametrizations import weight_norm

from anisdf.config import GeometryConfig
from anisdf.fields.hash_encoding import GridSpec, HashGrid


class SDFBranch(nn.Module):
    """One hash grid and its MLP (Softplus beta=100, weight norm) with geometric sphere initialisation."""

    def __init__(self, spec: GridSpec, cfg: GeometryConfig, start_levels: int, out_scale: float) -> None:
        super().__init__()
        self.grid = HashGrid(spec, backend=cfg.encoding_backend)
        self.n_levels = spec.n_levels
        self.features = spec.features_per_level
        self.start_levels = min(start_levels, spec.n_levels)
        self.register_buffer("active_levels", torch.tensor(self.start_levels), persistent=True)
        # the same count as a Python int and as a 0/1 weight per encoding feature, changed only by set_step: reading
        # the buffer would wait for the GPU, and rebuilding the weights costs a few kernels per SDF query
        self.n_active = self.start_levels
        self.register_buffer("level_weights", self._weights(self.n_active), persistent=False)
        self.register_load_state_dict_post_hook(lambda module, _keys: module._sync_levels())
        dims = [3 + spec.output_dim] + [cfg.hidden_dim] * cfg.n_hidden + [1 + cfg.feature_dim]
        layers = []
        for i in range(len(dims) - 1):
            lin = nn.Linear(dims[i], dims[i + 1])
            _geometric_init(lin, i, len(dims) - 2, cfg.init_radius, out_scale)
            layers.append(weight_norm(lin))
        self.layers = nn.ModuleList(layers)

    def _weights(self, n_active: int) -> Tensor:
        return (torch.arange(self.n_levels) < n_active).float().repeat_interleave(self.features)

    def _sync_levels(self) -> None:
        """After loading a state dict: the Python count and the weights follow the loaded buffer."""
        self.n_active = int(self.active_levels)
        self.level_weights.copy_(self._weights(self.n_active))

    def set_step(self, step: int, cfg: GeometryConfig) -> None:
        extra = 0 if step < cfg.level_start_step else 1 + (step - cfg.level_start_step) // max(cfg.level_every, 1)
        n = min(self.start_levels + extra, self.n_levels)
        if n != self.n_active:
            self.n_active = n
            self.active_levels.fill_(n)
            self.level_weights.copy_(self._weights(n))

    def forward(self, x: Tensor) -> Tensor:
        """``x`` in [-1, 1]^3 -> [N, 1 + feature_dim] (SDF first); levels not yet switched on read as zero."""
        enc = self.grid((x + 1.0) * 0.5) * self.level_weights
        h = torch.cat([x, enc], dim=-1)
        for i, layer in enumerate(self.layers):
            h = layer(h)
            if i < len(self.layers) - 1:
                h = F.softplus(h, beta=100.0)
        return h


def _geometric_init(lin: nn.Linear, i: int, last: int, radius: float, out_scale: float) -> None:
    """SAL-style initialisation (Atzmon & Lipman 2020) so that the SDF starts as a sphere of ``radius``.

    Only the xyz inputs are used at the start (encoding weights of the first layer are zero).
    """
    out_dim, in_dim = lin.weight.shape
    with torch.no_grad():
        if i == last:
            lin.weight.normal_(math.sqrt(math.pi) / math.sqrt(in_dim), 1e-4)
            lin.bias.fill_(-radius)
            lin.weight.mul_(out_scale)
            lin.bias.mul_(out_scale)
        else:
            lin.weight.normal_(0.0, math.sqrt(2.0) / math.sqrt(out_dim))
            lin.bias.zero_()
            if i == 0:
                lin.weight[:, 3:].zero_()


class SDFField(nn.Module):
    """Fused-granularity (or single-grid) SDF in normalised coordinates ``x`` in [-radius, radius]^3."""

    def __init__(self, cfg: GeometryConfig, radius: float = 1.0) -> None:
        super().__init__()
        self.cfg = cfg
        self.radius = radius
        scale = cfg.per_level_scale()
        fine = GridSpec(cfg.n_levels, cfg.features_per_level, cfg.log2_hashmap_size, cfg.base_resolution, scale)
        if cfg.kind == "fused":
            coarse = GridSpec(min(cfg.coarse_levels, cfg.n_levels), cfg.features_per_level,
                              cfg.log2_hashmap_size, cfg.base_resolution, scale)
            s = 0.5 if cfg.fusion == "sum" else 1.0
            self.branches = nn.ModuleList([
                SDFBranch(coarse, cfg, cfg.coarse_start_levels, s),
                SDFBranch(fine, cfg, cfg.fine_start_levels, s),
            ])
        else:
            self.branches = nn.ModuleList([SDFBranch(fine, cfg, cfg.coarse_start_levels, 1.0)])
        self.feature_dim = cfg.feature_dim

    def set_step(self, step: int) -> None:
        for b in self.branches:
            b.set_step(step, self.cfg)

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """SDF [N] and geometry feature F [N, feature_dim] (Eq. 5).

        Always float32, also inside a bf16 autocast region: bf16's 8-bit mantissa is too coarse for a distance
        field whose zero crossing is the surface and whose gradient is the normal.
        """
        with torch.autocast(x.device.type, enabled=False):
            xn = x.to(torch.promote_types(x.dtype, torch.float32)) / self.radius
            outs = [b(xn) for b in self.branches]
            out = outs[0] if len(outs) == 1 else outs[0] + outs[1]
            if self.cfg.kind == "fused" and self.cfg.fusion == "mean":
                out = out * 0.5
            return out[:, 0] * self.radius, out[:, 1:]

    def cache_weights(self) -> None:
        """Compute every weight-normed weight once; inside ``torch.nn.utils.parametrize.cached()`` later queries
        reuse them (call with grad enabled, else the cached weights carry no gradient)."""
        for b in self.branches:
            for layer in b.layers:
                layer.weight  # noqa: B018  (the access computes and caches the weight)

    def sdf(self, x: Tensor) -> Tensor:
        return self.forward(x)[0]

    def with_gradient(self, x: Tensor, create_graph: bool, fd_eps: float | None = None
                      ) -> tuple[Tensor, Tensor, Tensor]:
        """SDF, feature and the SDF gradient (unnormalised normal) at ``x``.

        ``geometry.normals=analytic`` differentiates through the network (double backward in training).
        ``finite_difference`` evaluates the field at the 4 vertices ``x + eps v_k`` of a tetrahedron,
        ``v_k in {(1,-1,-1), (-1,-1,1), (-1,1,-1), (1,1,1)}``: ``grad = sum_k v_k f_k / (4 eps)`` and the SDF and
        feature are the vertex means (exact for linear fields, O(eps^2) otherwise). No second-order
        autograd and 4 queries instead of 7 for central differences.
        """
        if self.cfg.normals == "finite_difference":
            eps = fd_eps if fd_eps is not None else self.cfg.fd_eps
            v = torch.tensor(_TETRA, device=x.device, dtype=x.dtype)
            with torch.set_grad_enabled(create_graph and torch.is_grad_enabled()):
                out_sdf, out_feat = self.forward((x[None] + eps * v[:, None]).reshape(-1, 3))
                f = out_sdf.view(4, -1)
                grad = (v[:, None, :] * f[..., None]).sum(0) / (4.0 * eps)
                feat = out_feat.view(4, x.shape[0], out_feat.shape[-1]).mean(0)
                return f.mean(0), feat, grad
        with torch.enable_grad():
            xg = x if x.requires_grad else x.detach().requires_grad_(True)
            sdf, feat = self.forward(xg)
            (grad,) = torch.autograd.grad(sdf, xg, torch.ones_like(sdf), create_graph=create_graph)
        if not create_graph:
            sdf, feat, grad = sdf.detach(), feat.detach(), grad.detach()
        return sdf, feat, grad


_TETRA = ((1.0, -1.0, -1.0), (-1.0, -1.0, 1.0), (-1.0, 1.0, -1.0), (1.0, 1.0, 1.0))
