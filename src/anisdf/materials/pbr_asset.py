"""``anisdf export RUN --pbr``: the fitted material as a standard glTF 2.0 PBR asset.

The surface of ``anisdf materials`` is decimated and unwrapped (:mod:`anisdf.export.uv_atlas`), its texels found
(:mod:`anisdf.export.texels`) and the material looked up at each: ``baseColorTexture`` (sRGB-encoded) and
``metallicRoughnessTexture`` (linear: roughness in G, metallic in B, as glTF reads them). The fitted light is written
beside the glb as ``light.hdr`` (equirectangular, the dataset's frame with z up; the glb's coordinates are the
dataset's own, as ``anisdf export`` writes them).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from anisdf.export.asset_files import mesh_buffers, png_bytes
from anisdf.materials.asset import Fitted
from anisdf.materials.fit import srgb

GLB, LIGHT, MANIFEST = "model.glb", "light.hdr", "export.json"


def pbr_glb_bytes(vertices: np.ndarray, normals: np.ndarray, uvs: np.ndarray, faces: np.ndarray, base_png: bytes,
                  mr_png: bytes) -> bytes:
    """A glb of one mesh with a metallic-roughness material: base colour and metallic-roughness textures."""
    import pygltflib as g

    blob, views, accessors = mesh_buffers(vertices, normals, uvs, faces, [base_png, mr_png])
    material = g.Material(name="anisdf-pbr", pbrMetallicRoughness=g.PbrMetallicRoughness(
        baseColorTexture=g.TextureInfo(index=0), metallicRoughnessTexture=g.TextureInfo(index=1),
        metallicFactor=1.0, roughnessFactor=1.0))
    sampler = g.Sampler(magFilter=g.LINEAR, minFilter=g.LINEAR_MIPMAP_LINEAR, wrapS=g.CLAMP_TO_EDGE,
                        wrapT=g.CLAMP_TO_EDGE)
    gltf = g.GLTF2(
        asset=g.Asset(version="2.0", generator="anisdf export --pbr"),
        scene=0, scenes=[g.Scene(nodes=[0])], nodes=[g.Node(mesh=0, name="anisdf")],
        meshes=[g.Mesh(primitives=[g.Primitive(attributes=g.Attributes(POSITION=0, NORMAL=1, TEXCOORD_0=2),
                                               indices=3, material=0)])],
        accessors=accessors, bufferViews=views, buffers=[g.Buffer(byteLength=len(blob))], materials=[material],
        textures=[g.Texture(source=0, sampler=0), g.Texture(source=1, sampler=0)], samplers=[sampler],
        images=[g.Image(bufferView=4, mimeType="image/png"), g.Image(bufferView=5, mimeType="image/png")])
    gltf.set_binary_blob(blob)
    return b"".join(gltf.save_to_bytes())


@torch.no_grad()
def bake_pbr(fitted: Fitted, faces: int, texture: int, padding: int = 2) -> tuple[bytes, dict]:
    """The glb bytes of ``fitted``'s surface decimated to ``faces`` triangles with ``texture``-texel textures, and
    stats."""
    import trimesh
    from scipy.spatial import cKDTree

    from anisdf.export.mesh import decimate
    from anisdf.export.texels import rasterize_uv
    from anisdf.export.uv_atlas import unwrap

    s = fitted.surface
    mesh = decimate(trimesh.Trimesh(s.positions.numpy(), s.faces.numpy(), process=False), faces)
    verts = np.asarray(mesh.vertices, dtype=np.float32)
    _, nearest = cKDTree(s.positions.numpy()).query(verts)
    normals = s.normals.numpy()[nearest]  # the surface's (SDF) normal at the nearest original vertex
    vmap, tris, uvs = unwrap(verts, np.asarray(mesh.faces), normals, texture, padding)
    tex = rasterize_uv(uvs, tris, texture)
    v = torch.as_tensor(verts[vmap])
    points = (tex.bary[:, :, None] * v[torch.as_tensor(tris)[tex.face]]).sum(1)
    base, rough, metal = fitted.material(points)
    base_img = np.full((texture * texture, 3), 255, np.uint8)
    mr_img = np.zeros((texture * texture, 3), np.uint8)
    idx = tex.index.numpy()
    base_img[idx] = (srgb(base) * 255 + 0.5).clamp(0, 255).byte().numpy()
    mr_img[idx, 0] = 255
    mr_img[idx, 1] = (rough * 255 + 0.5).clamp(0, 255).byte().numpy()
    mr_img[idx, 2] = (metal * 255 + 0.5).clamp(0, 255).byte().numpy()
    side = (texture, texture, 3)
    glb = pbr_glb_bytes(verts[vmap], F.normalize(torch.as_tensor(normals[vmap]), dim=-1).numpy(), uvs, tris,
                        png_bytes(base_img.reshape(side)), png_bytes(mr_img.reshape(side)))
    return glb, {"faces": len(tris), "vertices": len(vmap), "texture": texture,
                 "texels": int(tex.inside.sum()), **fitted.summary()}
