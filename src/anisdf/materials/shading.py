"""Shading a surface point under an environment light with the glTF metallic-roughness BRDF.

:func:`shade` is the split sum (Karis 2013) the fit and ``anisdf relight`` use: the light's GGX-prefiltered
radiance along the reflected direction times ``f0 A + B``, plus ``c_diff E(n) (1 - f0 - (1 - f0) C)`` (irradiance
``E``, tables :func:`anisdf.materials.brdf.dfg_table`). :func:`shade_reference` is the plain sum of the BRDF over
every texel of the map, what the split sum approximates (equal under a uniform light).
"""

from __future__ import annotations

import torch
from torch import Tensor

from anisdf.materials.brdf import brdf, dfg_lookup, f0_and_diffuse
from anisdf.materials.environment import Prefiltered, solid_angles, texel_directions
from anisdf.materials.visibility import shadowing


def reflect(v: Tensor, n: Tensor) -> Tensor:
    """The view direction ``v`` (toward the viewer) mirrored about ``n``: ``2 (n.v) n - v``."""
    return 2.0 * (n * v).sum(-1, keepdim=True) * n - v


def shade(light: Prefiltered, n: Tensor, v: Tensor, base: Tensor, roughness: Tensor, metallic: Tensor,
          visibility: Tensor | None = None, directions: Tensor | None = None) -> Tensor:
    """Outgoing linear radiance [M, 3] at points with unit normals ``n`` and view directions ``v`` [M, 3], base
    colour [M, 3], roughness and metallic [M] (split sum); with ``visibility`` [M, D] of the light's ``directions``
    [D, 3], shadowed (:func:`anisdf.materials.visibility.shadowing`)."""
    nv = (n * v).sum(-1).clamp(1e-4, 1.0)
    a, b, c = dfg_lookup(nv, roughness)
    f0, c_diff = f0_and_diffuse(base, metallic[:, None])
    spec = light.specular(reflect(v, n), roughness) * (f0 * a[:, None] + b[:, None])
    diff = light.diffuse(n) * c_diff * (1.0 - f0 - (1.0 - f0) * c[:, None])
    if visibility is not None and directions is not None:
        d_fac, s_fac = shadowing(light, directions, visibility, n, reflect(v, n))
        spec, diff = spec * s_fac, diff * d_fac
    return spec + diff


def shade_reference(env: Tensor, n: Tensor, v: Tensor, base: Tensor, roughness: Tensor, metallic: Tensor,
                    chunk: int = 256) -> Tensor:
    """The same radiance as the sum over every texel of ``env`` [H, W, 3] of ``L f n.l`` times its solid angle (no
    visibility): the reference :func:`shade` approximates."""
    h, w, _ = env.shape
    dirs = texel_directions(h, w, env.dtype).reshape(-1, 3)
    radiance = env.reshape(-1, 3) * solid_angles(h, w, env.dtype).reshape(-1, 1)
    out = []
    for s in range(0, len(n), chunk):
        sl = slice(s, s + chunk)
        m = n[sl].shape[0]
        f = brdf(n[sl, None].expand(m, len(dirs), 3), v[sl, None].expand(m, len(dirs), 3), dirs[None].expand(m, -1, 3),
                 base[sl, None].expand(m, len(dirs), 3), roughness[sl, None, None].expand(m, len(dirs), 1),
                 metallic[sl, None, None].expand(m, len(dirs), 1))
        out.append((f * radiance[None]).sum(1))
    return torch.cat(out)
