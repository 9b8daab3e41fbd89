"""The light's visibility from the fixed surface: which directions of the environment each vertex sees.

Shadow maps: for each of ``D`` directions spread evenly over the sphere (a Fibonacci set) the mesh is cast from far
away along that direction (:func:`anisdf.export.reference_renderer.cast`, ``size`` pixels across the object), and a
vertex, nudged along its normal, sees that direction when nothing lies in front of it in that map (within a bias of
two pixels). Points between vertices interpolate their vertices' visibility.

Shading with it (:func:`shadowing`): the diffuse term is scaled by the light-weighted share of the cosine lobe the
point sees, ``sum_d V_d L_d max(n.d, 0) / sum_d L_d max(n.d, 0)`` (``L_d`` the light blurred to the directions'
spacing), and the specular term by the visibility around the reflected direction (a smooth kernel over the
directions). Unoccluded points shade exactly as without it. Left out: light reflected between parts of the object.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from anisdf.data.orbit import look_at
from anisdf.export.reference_renderer import PinholeCamera, cast
from anisdf.materials.environment import Prefiltered, lookup

SPECULAR_SHARPNESS = 6.0
"""``k(r.d) = exp(s (r.d - 1))``: the kernel that reads the visibility around a reflected direction (the
directions of a 64-set lie about 25 degrees apart)."""


def fibonacci_directions(n: int) -> Tensor:
    """``n`` unit directions spread evenly over the sphere [n, 3]."""
    i = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = math.pi * (3.0 - math.sqrt(5.0)) * i
    r = torch.sqrt(1.0 - z * z)
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], -1).float()


def _camera_along(d: np.ndarray, centre: np.ndarray, radius: float, size: int) -> PinholeCamera:
    """A camera far out along ``d`` looking back at ``centre``, the sphere of ``radius`` filling ``size`` pixels."""
    dist = 50.0 * radius
    up = np.array([0.0, 0.0, 1.0]) if abs(d[2]) < 0.9 else np.array([1.0, 0.0, 0.0])  # never along d
    c2w = np.eye(4)
    c2w[:3, :4] = look_at(centre + d * dist, centre, up).numpy()
    f = 0.5 * size * dist / (1.05 * radius)
    return PinholeCamera(c2w, f, f, size / 2.0, size / 2.0, size, size)


@torch.no_grad()
def vertex_visibility(surface, directions: Tensor, size: int = 256) -> Tensor:
    """[V, D] bool: whether vertex ``v`` of ``surface`` (positions, normals, faces) sees direction ``d``."""
    pos, nrm = surface.positions.float(), surface.normals.float()
    lo, hi = pos.min(0).values, pos.max(0).values
    centre = (0.5 * (lo + hi)).double().numpy()
    radius = float(0.5 * (hi - lo).norm())
    pixel = 2.1 * radius / size  # a pixel's footprint on the object
    out = torch.zeros(len(pos), len(directions), dtype=torch.bool)
    probe = pos + nrm * pixel  # off the surface along the normal: no self-shadowing of the vertex's own faces
    for k, d in enumerate(directions.double().numpy()):
        cam = _camera_along(d / np.linalg.norm(d), centre, radius, size)
        _, depth, _ = cast(surface, cam)
        depth = depth.reshape(size, size)
        rot = torch.as_tensor(cam.c2w[:3, :3], dtype=torch.float32)
        eye = torch.as_tensor(cam.c2w[:3, 3], dtype=torch.float32)
        q = probe - eye
        c = q @ rot
        u = (cam.fx * c[:, 0] / c[:, 2] + cam.cx - 0.5).round().long()
        v = (cam.fy * c[:, 1] / c[:, 2] + cam.cy - 0.5).round().long()
        inside = (u >= 0) & (u < size) & (v >= 0) & (v < size)
        front = torch.full((len(pos),), float("inf"))
        front[inside] = depth[v[inside], u[inside]]
        out[:, k] = q.norm(dim=-1) <= front + 2.0 * pixel
    return out


def interpolate(vis: Tensor, faces: Tensor, face: Tensor, bary: Tensor) -> Tensor:
    """Per-point visibility [M, D] in [0, 1] of hits (faces [M], barycentrics [M, 3]) from vertex visibility."""
    tri = faces[face]
    return (bary[..., None] * vis[tri].float()).sum(1)


def shadowing(light: Prefiltered, directions: Tensor, vis: Tensor, n: Tensor, r: Tensor,
              roughness_level: int = 3) -> tuple[Tensor, Tensor]:
    """The factors [M, 3] and [M, 1] by which a point's diffuse and specular terms are scaled, for visibility
    ``vis`` [M, D] over ``directions`` [D, 3], normals ``n`` and reflected directions ``r`` [M, 3]; the light's
    radiance per direction is read from its prefiltered level ``roughness_level`` (blurred to about the directions'
    spacing). Differentiable in the light."""
    radiance = lookup(light.levels[min(roughness_level, len(light.levels) - 1)], directions)  # [D, 3]
    cos = (n @ directions.T).clamp_min(0.0)  # [M, D]
    seen = (vis * cos) @ radiance
    total = (cos @ radiance).clamp_min(1e-8)
    diffuse = (seen / total).clamp(0.0, 1.0)
    # the kernel around r over the directions above the surface only: below it the point sees nothing by
    # definition, which is no shadow (a grazing reflection of an unoccluded point keeps its highlight)
    k = torch.exp(SPECULAR_SHARPNESS * (r @ directions.T - 1.0)) * (cos > 0)
    specular = ((vis * k).sum(-1, keepdim=True) / k.sum(-1, keepdim=True).clamp_min(1e-8))
    specular = torch.where(k.sum(-1, keepdim=True) > 0, specular, torch.ones_like(specular))
    return diffuse, specular
