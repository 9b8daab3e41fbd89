"""The run's surface as a triangle mesh in the dataset's frame, and pixels cast onto it.

The surface is the SDF's zero level set (marching cubes, :func:`anisdf.export.mesh.extract_mesh`), decimated, with
vertex normals from the SDF's gradient. A pixel's ray through its centre hits the nearest triangle
(:func:`anisdf.export.reference_renderer.cast`, the ray cast of the baked asset's reference renderer); the hit's
position and normal are interpolated from the triangle's vertices.

Left out: visibility of the light (no shadows, no occlusion of the environment by the object itself) and light
reflected between parts of the object; both are folded into the fitted material and light where they matter.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from anisdf.export.reference_renderer import PinholeCamera, cast, pixel_rays


@dataclass
class Surface:
    """A triangle mesh in the dataset's frame with unit vertex normals."""

    positions: Tensor
    """[V, 3] float32."""
    normals: Tensor
    """[V, 3] float32."""
    faces: Tensor
    """[F, 3] int64."""

    def save(self, path: Path) -> None:
        """Write the mesh (with its normals) as a PLY file."""
        import trimesh

        from anisdf.utils.atomic import atomic_path

        mesh = trimesh.Trimesh(self.positions.numpy(), self.faces.numpy(), vertex_normals=self.normals.numpy(),
                               process=False)
        with atomic_path(path) as tmp:
            mesh.export(tmp, file_type="ply")

    @classmethod
    def load(cls, path: Path) -> Surface:
        import trimesh

        mesh = trimesh.load(path, process=False, force="mesh")
        normals = np.asarray(mesh.vertex_normals, dtype=np.float32)
        return cls(torch.as_tensor(np.asarray(mesh.vertices), dtype=torch.float32),
                   F.normalize(torch.as_tensor(normals), dim=-1),
                   torch.as_tensor(np.asarray(mesh.faces), dtype=torch.long))

    @property
    def bounds(self) -> tuple[Tensor, Tensor]:
        return self.positions.min(0).values, self.positions.max(0).values


def surface_of_model(model, to_world: np.ndarray, resolution: int, faces: int, progress: bool = False) -> Surface:
    """Marching cubes on ``model``'s SDF at ``resolution``, decimated to ``faces`` triangles, SDF normals, moved to
    the dataset's frame by ``to_world`` (a similarity: uniform scale and translation, normals unchanged)."""
    from anisdf.export.mesh import decimate, extract_mesh, sdf_normals

    dev = next(model.parameters()).device
    mesh = extract_mesh(model.geometry.sdf, radius=model.radius, resolution=resolution, device=dev,
                        progress=progress)
    mesh = decimate(mesh, faces)
    verts = torch.as_tensor(np.asarray(mesh.vertices), dtype=torch.float32)
    normals = sdf_normals(model, verts.to(dev)).cpu()
    bad = ~torch.isfinite(normals).all(-1)
    if bad.any():
        normals[bad] = torch.as_tensor(np.asarray(mesh.vertex_normals)[bad.numpy()], dtype=torch.float32)
    T = torch.as_tensor(np.asarray(to_world), dtype=torch.float32)
    lin = T[:3, :3]
    pos = verts @ lin.T + T[:3, 3]
    normals = F.normalize(normals @ torch.linalg.inv(lin), dim=-1)
    faces_t = torch.as_tensor(np.asarray(mesh.faces), dtype=torch.long)
    if torch.linalg.det(lin) < 0:
        faces_t = faces_t.flip(1)
    return Surface(pos.contiguous(), normals.contiguous(), faces_t)


@dataclass
class Hits:
    """Pixels of one camera whose rays hit the surface: their flat pixel index, position, unit normal and unit
    direction toward the camera."""

    pixel: Tensor
    position: Tensor
    normal: Tensor
    view: Tensor
    face: Tensor
    """[M] the triangle hit."""
    bary: Tensor
    """[M, 3] barycentrics of the hit in it."""


def cast_pixels(surface: Surface, cam: PinholeCamera) -> Hits:
    """The nearest hit of each pixel centre's ray (pixels without one are left out)."""
    face, _, bary = cast(surface, cam)
    _, dirs = pixel_rays(cam)
    hit = (face >= 0).nonzero()[:, 0]
    tri = surface.faces[face[hit]]
    b = bary[hit][..., None]
    pos = (b * surface.positions[tri]).sum(1)
    nrm = F.normalize((b * surface.normals[tri]).sum(1), dim=-1)
    view = -dirs[hit]
    # a shading normal facing away from the viewer (silhouettes of a coarse mesh) is bent to the horizon
    nv = (nrm * view).sum(-1, keepdim=True)
    nrm = torch.where(nv < 1e-3, F.normalize(nrm - (nv - 1e-3) * view, dim=-1), nrm)
    return Hits(hit, pos, nrm, view, face[hit], bary[hit])
