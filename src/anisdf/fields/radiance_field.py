"""Blended radiance fields (paper Sec. 3.3, Eqs. 7-12).

``c_view = Psi_v(x, SH(d), n, F)`` (Eq. 10); ``c_ref = Psi_r(ASG(omega_r), omega_r, n.v)`` (Eq. 10) with
``omega_r = d - 2 (d.n) n`` (Eq. 7) and ASG parameters ``lambda, mu, xi = f_par(F, n)`` (Eq. 9);
``w = sigmoid(Psi_w(x, n, F))`` (Eq. 11) and ``C = w c_view + (1 - w) c_ref`` (Eq. 12). ``x`` is the position in
the unit sphere, as the paper's Eqs. 10-11 name it (the release's geometry appends the position to its feature F,
so its heads see it too). ``n.v`` as an extra input of ``Psi_r`` is the release's.
Ablations: ``appearance.kind=pe`` replaces the ASG features by a positional encoding of omega_r;
``appearance.kind=view`` keeps the view branch only.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from anisdf.config import AppearanceConfig
from anisdf.fields.asg import asg_features, asg_frames
from anisdf.fields.encodings import positional_encoding, sh_encoding
from anisdf.fields.mlp import mlp, run_mlp


class RadianceField(nn.Module):
    def __init__(self, cfg: AppearanceConfig, feature_dim: int, code_dim: int = 0, fast: bool = True) -> None:
        """``code_dim`` > 0: the view and reflection heads also take a per-image appearance code of that size
        (NeRF-W's appearance embedding; ``appearance.embedding``). ``fast``: the ASG encoding with its sharpnesses'
        softplus by the compiled kernel where it applies (:func:`anisdf.fields.asg.asg_features`), else PyTorch's."""
        super().__init__()
        self.cfg = cfg
        self.fast = fast
        geo_in = feature_dim + 3
        self.view_mlp = mlp(3 + geo_in + cfg.sh_degree**2 + code_dim, cfg.view_hidden, cfg.view_layers, 3)
        if cfg.kind == "view":
            return
        self.weight_mlp = mlp(3 + geo_in, cfg.weight_hidden, cfg.weight_layers, 1)
        if cfg.kind == "blend":
            self.register_buffer("frames", asg_frames(cfg.asg_theta, cfg.asg_phi), persistent=False)
            self.n_lobes = cfg.asg_theta * cfg.asg_phi
            self.par_mlp = mlp(geo_in, cfg.par_hidden, 2, self.n_lobes * 4)
            ref_in = self.n_lobes * 2 + 3 + 1
        else:
            ref_in = 3 * (1 + 2 * cfg.pe_frequencies) + 1 + geo_in
        self.ref_mlp = mlp(ref_in + code_dim, cfg.ref_hidden, cfg.ref_layers, 3)

    def forward(self, x: Tensor, feat: Tensor, normal: Tensor, dirs: Tensor,
                code: Tensor | None = None) -> dict[str, Tensor]:
        """Colour of points at ``x`` (in the unit sphere) with geometry feature ``feat`` and unit ``normal``, seen
        along unit ``dirs``; ``code``: the points' appearance codes when the field takes them."""
        geo = torch.cat([feat, normal], dim=-1)
        codes = () if code is None else (code.to(feat.dtype),)
        c_view = torch.sigmoid(run_mlp(self.view_mlp, torch.cat([x, geo, sh_encoding(dirs, self.cfg.sh_degree),
                                                                 *codes], dim=-1), self.fast))
        if self.cfg.kind == "view":
            return {"rgb": c_view, "c_view": c_view}
        w = torch.sigmoid(run_mlp(self.weight_mlp, torch.cat([x, geo], dim=-1), self.fast))
        d_dot_n = (dirs * normal).sum(-1, keepdim=True)
        refl = dirs - 2.0 * d_dot_n * normal
        n_dot_v = -d_dot_n
        if self.cfg.kind == "blend":
            f_asg = asg_features(run_mlp(self.par_mlp, geo, self.fast).view(-1, self.n_lobes, 4), refl, self.frames,
                                 self.fast)
            ref_in = torch.cat([f_asg, refl, n_dot_v, *codes], dim=-1)
        else:
            ref_in = torch.cat([positional_encoding(refl, self.cfg.pe_frequencies), n_dot_v, geo, *codes], dim=-1)
        c_ref = torch.sigmoid(run_mlp(self.ref_mlp, ref_in, self.fast))
        rgb = w * c_view + (1.0 - w) * c_ref
        return {"rgb": rgb, "c_view": c_view, "c_ref": c_ref, "weight": w[:, 0]}
