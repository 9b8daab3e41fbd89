"""Fused-granularity SDF (paper Sec. 3.2, Eqs. 5-6).

Two parallel hash grids, each with its own MLP, predict ``(SDF, F)``; the outputs are fused (Eq. 6):
``SDF = SDF^c + SDF^f`` and ``F = F^c + F^f`` (``geometry.fusion=mean`` averages them, as the authors'
release does). Following the authors' release, both grids start at the base resolution with the same
per-level scale; the coarse grid holds levels ``1..m`` and starts with ``coarse_start_levels`` active, the fine grid
holds ``1..L`` and starts with its first ``m`` active, all of them trainable from step 0 (Eq. 5 writes the fine set
as ``m..L``; the release, and this code, train its levels ``1..m`` as well). Both switch on one more level every
``level_every`` steps after ``level_start_step`` (release: coarse 4 -> 10, fine 10 -> 16, all active at step
11000). ``geometry.kind=single`` is the ablation: one grid of ``L`` levels switched on coarse-to-fine.
:meth:`SDFField.branch_gradient` gives one branch's normal alone (the curvature term's coarse target).

Analytic normals are computed in closed form through each MLP (:func:`.sdf_mlp.mlp_with_input_grad`) and through
the hash grid by one first-order ``autograd.grad``: training differentiates them once more for the eikonal and curvature
terms, with no second-order autograd through the MLP, so ``train.compile`` can fuse the MLP part as well.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn
from torch.nn.utils.parametrizations import weight_norm

from anisdf.config import GeometryConfig
from anisdf.fields.hash_grid import GridSpec, HashGrid, jacobian_transpose_product
from anisdf.fields.sdf_mlp import BETA, mlp_distance, mlp_with_input_grad
from anisdf.fields.softplus import softplus


class SDFBranch(nn.Module):
    """One hash grid and its MLP (Softplus beta=100, weight norm) with geometric sphere initialisation."""

    def __init__(self, spec: GridSpec, cfg: GeometryConfig, start_levels: int, out_scale: float) -> None:
        super().__init__()
        self.grid = HashGrid(spec, backend=cfg.encoding_backend)
        self.n_levels = spec.n_levels
        self.features = spec.features_per_level
        self.start_levels = min(start_levels, spec.n_levels)
        self.fast = cfg.encoding_backend != "torch"  # the compiled softplus too; "torch" is the pure reference
        self.register_buffer("active_levels", torch.tensor(self.start_levels), persistent=True)
        # the same count as a Python int, changed only by set_step: reading the buffer would wait for the GPU
        self.n_active = self.start_levels
        self.register_load_state_dict_post_hook(lambda module, _keys: module._sync_levels())
        dims = [3 + spec.output_dim] + [cfg.hidden_dim] * cfg.n_hidden + [1 + cfg.feature_dim]
        layers = []
        for i in range(len(dims) - 1):
            lin = nn.Linear(dims[i], dims[i + 1])
            _geometric_init(lin, i, len(dims) - 2, cfg.init_radius, out_scale)
            layers.append(weight_norm(lin))
        self.layers = nn.ModuleList(layers)

    def _sync_levels(self) -> None:
        """After loading a state dict: the Python count follows the loaded buffer."""
        self.n_active = int(self.active_levels)

    def set_step(self, step: int, cfg: GeometryConfig) -> None:
        extra = max(0, (step - cfg.level_start_step) // max(cfg.level_every, 1))
        n = min(self.start_levels + extra, self.n_levels)
        if n != self.n_active:
            self.n_active = n
            self.active_levels.fill_(n)

    def encode(self, x: Tensor) -> Tensor:
        """Hash-grid features of ``x`` in [-1, 1]^3; levels not yet switched on read as zero (and are not looked
        up: early in training a third of the encoding's work)."""
        return self._pad_levels(self.encode_active(x))

    def encode_active(self, x: Tensor) -> Tensor:
        """The switched-on levels' features alone ``[N, n_active * F]``: the input of :meth:`weights_active`."""
        return self.grid((x + 1.0) * 0.5, self.n_active)

    def weights_active(self) -> list[Tensor]:
        """The layers' weights, the first one's columns cut to x and the switched-on levels: the same products as
        the full weights on the zero-padded features, without padding them (nor their gradient)."""
        ws = [lay.weight for lay in self.layers]
        if self.n_active < self.n_levels:
            ws[0] = ws[0][:, : 3 + self.n_active * self.features]
        return ws

    def _pad_levels(self, enc: Tensor) -> Tensor:
        """The active levels' features ``[N, n_active * F]`` with zeros for the levels not yet switched on."""
        if self.n_active == self.n_levels:  # every level on (most of training): no padding, no copy
            return enc
        return F.pad(enc, (0, (self.n_levels - self.n_active) * self.features))

    def forward(self, x: Tensor) -> Tensor:
        """``x`` in [-1, 1]^3 -> [N, 1 + feature_dim] (SDF first)."""
        h = torch.cat([x, self.encode(x)], dim=-1)
        for i, layer in enumerate(self.layers):
            h = layer(h)
            if i < len(self.layers) - 1:
                h = softplus(h, BETA, self.fast)
        return h

    def forward_with_grad(self, x: Tensor, create_graph: bool,
                          mlp: Callable[..., tuple[Tensor, Tensor, Tensor]] = mlp_with_input_grad
                          ) -> tuple[Tensor, Tensor, Tensor]:
        """The SDF output [N], the last hidden activation [N, H] (:meth:`feature` of its rows gives the feature) and
        the SDF output's gradient w.r.t. ``x`` [N, 3]: the MLP's input gradient in closed form (``mlp``, eager or
        compiled), then its grid part carried back through the encoding.

        With ``create_graph`` the outputs are differentiable w.r.t. the parameters (training), else none is.
        Positions are sample points, constants: no gradient flows back to ``x``. Where the compiled CPU kernel
        applies, the encoding comes with its Jacobian ``J`` (:meth:`HashGrid.encode_with_jacobian`) and the grid part
        is ``J^T g``: no backward pass here, and training's backward scatters into the table once, not twice.
        """
        u = (x.detach() + 1.0) * 0.5
        with torch.set_grad_enabled(create_graph):
            with_jac = self.grid.encode_with_jacobian(u, self.n_active)
        if with_jac is not None:
            (enc, jac), weights = with_jac, self.weights_active()
        else:
            with torch.enable_grad():
                xg = x.detach().requires_grad_(True)
                enc = self.encode(xg)
            weights = [lay.weight for lay in self.layers]
        with torch.set_grad_enabled(create_graph):
            out0, hidden, g = mlp(torch.cat([x.detach(), enc], dim=-1), weights, [lay.bias for lay in self.layers],
                                  self.fast)
            if with_jac is not None:
                # J^T g, times d u / d x of the grid's input clamp((x + 1) / 2) as autograd has it
                g_enc = jacobian_transpose_product(jac, g[:, 3:3 + jac.shape[1]]) * (((u >= 0.0) & (u <= 1.0)) * 0.5)
            else:
                (g_enc,) = torch.autograd.grad(enc, xg, g[:, 3:], create_graph=create_graph)
            return out0, hidden, g[:, :3] + g_enc

    def feature(self, hidden: Tensor) -> Tensor:
        """The feature outputs (all but the SDF) of the last layer, from its input ``hidden`` [N, H]."""
        last = self.layers[-1]
        return F.linear(hidden, last.weight[1:], last.bias[1:])


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


@dataclass
class SDFQuery:
    """The SDF [N] and its gradient [N, 3] at N points, with the geometry feature on demand: the renderer needs it
    only where a sample is visible, and the last layer's feature rows are most of that layer's work."""

    sdf: Tensor
    grad: Tensor
    feature_of: Callable[[Tensor | None], Tensor]
    """Rows (indices, or None for all) -> their feature [n, feature_dim], fused over the branches (Eq. 6)."""

    def feature(self, rows: Tensor | None = None) -> Tensor:
        return self.feature_of(rows)

    def select(self, rows: Tensor) -> SDFQuery:
        """The query at the points ``rows`` (indices) only; their features are still computed on demand."""
        return SDFQuery(self.sdf.index_select(0, rows), self.grad.index_select(0, rows),
                        lambda r: self.feature_of(rows if r is None else rows.index_select(0, r)))


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
                SDFBranch(fine, cfg, cfg.coarse_levels, s),
            ])
        else:
            self.branches = nn.ModuleList([SDFBranch(fine, cfg, cfg.coarse_start_levels, 1.0)])
        self.feature_dim = cfg.feature_dim
        # the MLPs with their input gradient; model.compile_heads() swaps in a compiled copy (train.compile)
        self.mlp_fn: Callable[..., tuple[Tensor, Tensor]] = mlp_with_input_grad

    def set_step(self, step: int) -> None:
        for b in self.branches:
            b.set_step(step, self.cfg)

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """SDF [N] and geometry feature F [N, feature_dim] (Eq. 6).

        Always float32, also inside a bf16 autocast region: bf16's 8-bit mantissa is too coarse for a distance
        field whose zero crossing is the surface and whose gradient is the normal.
        """
        with torch.autocast(x.device.type, enabled=False):
            out = self._fuse([b(self._normalised(x)) for b in self.branches])
            return out[:, 0] * self.radius, out[:, 1:]

    def _normalised(self, x: Tensor) -> Tensor:
        return x.to(torch.promote_types(x.dtype, torch.float32)) / self.radius

    def _fuse(self, per_branch: list[Tensor]) -> Tensor:
        """Eq. 6 on any per-branch quantity (outputs, gradients): the sum, or the mean with ``fusion=mean``."""
        out = per_branch[0] if len(per_branch) == 1 else per_branch[0] + per_branch[1]
        return out * 0.5 if self.cfg.kind == "fused" and self.cfg.fusion == "mean" else out

    def cache_weights(self) -> None:
        """Compute every weight-normed weight once; inside ``torch.nn.utils.parametrize.cached()`` later queries
        reuse them (call with grad enabled, else the cached weights carry no gradient)."""
        for b in self.branches:
            for layer in b.layers:
                layer.weight  # noqa: B018  (the access computes and caches the weight)

    def sdf(self, x: Tensor) -> Tensor:
        return self.forward(x)[0]

    def distance(self, x: Tensor) -> Tensor:
        """The SDF alone [N], for queries that need no feature (pruning, grids, meshes): each branch's last layer
        computes only its SDF row. Equal to :meth:`sdf` up to float rounding (another matrix product)."""
        with torch.autocast(x.device.type, enabled=False):
            xn = self._normalised(x)
            parts = []
            for b in self.branches:
                parts.append(mlp_distance(torch.cat([xn, b.encode_active(xn)], dim=-1), b.weights_active(),
                                          [lay.bias for lay in b.layers], b.fast))
            return self._fuse(parts) * self.radius

    def with_gradient(self, x: Tensor, create_graph: bool, fd_eps: float | None = None
                      ) -> tuple[Tensor, Tensor, Tensor]:
        """SDF, feature and the SDF gradient (unnormalised normal) at ``x``: :meth:`query` with every feature row."""
        q = self.query(x, create_graph, fd_eps)
        return q.sdf, q.feature(), q.grad

    def query(self, x: Tensor, create_graph: bool, fd_eps: float | None = None) -> SDFQuery:
        """SDF and its gradient at ``x``, the feature on demand (:class:`SDFQuery`).

        ``geometry.normals=analytic``: the exact gradient through the network (:meth:`SDFBranch.forward_with_grad`;
        ``d sdf / d x = d out_0 / d x_n`` since ``sdf = radius out_0(x / radius)``), differentiable w.r.t. the
        parameters with ``create_graph`` (training); ``x`` is treated as a constant.
        ``finite_difference`` evaluates the field at the 4 vertices ``x + eps v_k`` of a tetrahedron,
        ``v_k in {(1,-1,-1), (-1,-1,1), (-1,1,-1), (1,1,1)}``: ``grad = sum_k v_k f_k / (4 eps)`` and the SDF and
        feature are the vertex means (exact for linear fields, O(eps^2) otherwise). No second-order
        autograd and 4 queries instead of 7 for central differences.
        """
        if self.cfg.normals == "finite_difference":
            sdf, feat, grad = self._finite_difference(self.forward, x, create_graph, fd_eps)
            return SDFQuery(sdf, grad, lambda rows: feat if rows is None else feat.index_select(0, rows))
        with torch.autocast(x.device.type, enabled=False):
            xn = self._normalised(x)
            outs, hidden, grads = zip(*(b.forward_with_grad(xn, create_graph, self.mlp_fn) for b in self.branches),
                                      strict=True)
            sdf, grad = self._fuse(list(outs)), self._fuse(list(grads))

        def feature_of(rows: Tensor | None) -> Tensor:
            with torch.autocast(x.device.type, enabled=False), torch.set_grad_enabled(create_graph):
                return self._fuse([b.feature(h if rows is None else h.index_select(0, rows))
                                   for b, h in zip(self.branches, hidden, strict=True)])

        return SDFQuery(sdf * self.radius, grad, feature_of)

    def branch_gradient(self, x: Tensor, branch: int, create_graph: bool, fd_eps: float | None = None) -> Tensor:
        """The SDF gradient at ``x`` of one branch alone (0: the coarse grid; with ``kind=single`` the one grid),
        before fusion: the same method as :meth:`with_gradient` (closed form, or the tetrahedron with
        ``normals=finite_difference``), differentiable w.r.t. that branch's parameters with ``create_graph``."""
        b = self.branches[branch]
        if self.cfg.normals == "finite_difference":
            def one_branch(p: Tensor) -> tuple[Tensor, Tensor]:
                with torch.autocast(p.device.type, enabled=False):
                    out = b(self._normalised(p))
                return out[:, 0] * self.radius, out[:, 1:]
            return self._finite_difference(one_branch, x, create_graph, fd_eps)[2]
        with torch.autocast(x.device.type, enabled=False):
            return b.forward_with_grad(self._normalised(x), create_graph, self.mlp_fn)[2]

    def _finite_difference(self, fn: Callable[[Tensor], tuple[Tensor, Tensor]], x: Tensor, create_graph: bool,
                           fd_eps: float | None) -> tuple[Tensor, Tensor, Tensor]:
        """``fn`` (an SDF and feature) at the tetrahedron's vertices around ``x``: vertex means and the gradient."""
        eps = fd_eps if fd_eps is not None else self.cfg.fd_eps
        v = torch.tensor(_TETRA, device=x.device, dtype=x.dtype)
        with torch.set_grad_enabled(create_graph and torch.is_grad_enabled()):
            out_sdf, out_feat = fn((x[None] + eps * v[:, None]).reshape(-1, 3))
            f = out_sdf.view(4, -1)
            grad = (v[:, None, :] * f[..., None]).sum(0) / (4.0 * eps)
            feat = out_feat.view(4, x.shape[0], out_feat.shape[-1]).mean(0)
            return f.mean(0), feat, grad


_TETRA = ((1.0, -1.0, -1.0), (-1.0, -1.0, 1.0), (-1.0, 1.0, -1.0), (1.0, 1.0, 1.0))
