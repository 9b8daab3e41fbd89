"""Direction encodings: real spherical harmonics (view branch) and NeRF positional encoding (ablation)."""

from __future__ import annotations

import torch
from torch import Tensor


def sh_encoding(d: Tensor, degree: int = 4) -> Tensor:
    """Real spherical harmonics of unit directions ``d`` [N, 3] up to ``degree`` (1..5 bands -> degree**2 dims)."""
    if not 1 <= degree <= 5:
        raise ValueError("sh degree must be in 1..5")
    x, y, z = d.unbind(-1)
    out = [torch.full_like(x, 0.28209479177387814)]
    if degree > 1:
        out += [-0.48860251190291987 * y, 0.48860251190291987 * z, -0.48860251190291987 * x]
    if degree > 2:
        xy, xz, yz, x2, y2, z2 = x * y, x * z, y * z, x * x, y * y, z * z
        out += [
            1.0925484305920792 * xy,
            -1.0925484305920792 * yz,
            0.94617469575755997 * z2 - 0.31539156525251999,
            -1.0925484305920792 * xz,
            0.54627421529603959 * (x2 - y2),
        ]
    if degree > 3:
        out += [
            0.59004358992664352 * y * (-3.0 * x2 + y2),
            2.8906114426405538 * xy * z,
            0.45704579946446572 * y * (1.0 - 5.0 * z2),
            0.3731763325901154 * z * (5.0 * z2 - 3.0),
            0.45704579946446572 * x * (1.0 - 5.0 * z2),
            1.4453057213202769 * z * (x2 - y2),
            0.59004358992664352 * x * (-x2 + 3.0 * y2),
        ]
    if degree > 4:
        x4, y4, z4 = x2 * x2, y2 * y2, z2 * z2
        out += [
            2.5033429417967046 * xy * (x2 - y2),
            1.7701307697799304 * yz * (-3.0 * x2 + y2),
            0.94617469575756008 * xy * (7.0 * z2 - 1.0),
            0.66904654355728921 * yz * (3.0 - 7.0 * z2),
            -3.1735664074561294 * z2 + 3.7024941420321507 * z4 + 0.31735664074561293,
            0.66904654355728921 * xz * (3.0 - 7.0 * z2),
            0.47308734787878004 * (x2 - y2) * (7.0 * z2 - 1.0),
            1.7701307697799304 * xz * (-x2 + 3.0 * y2),
            -3.7550144126950569 * x2 * y2 + 0.62583573544917614 * x4 + 0.62583573544917614 * y4,
        ]
    return torch.stack(out, dim=-1)


def positional_encoding(v: Tensor, n_frequencies: int) -> Tensor:
    """``[v, sin(2^k pi v), cos(2^k pi v)]`` for k < n_frequencies: [N, 3 * (1 + 2 n)]."""
    freqs = 2.0 ** torch.arange(n_frequencies, device=v.device, dtype=v.dtype) * torch.pi
    ang = v[..., None, :] * freqs[:, None]  # [N, K, 3]
    return torch.cat([v, ang.sin().flatten(-2), ang.cos().flatten(-2)], dim=-1)
