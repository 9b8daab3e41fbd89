"""The files of a baked asset (:mod:`anisdf.export.baked_format`): PNG and glb bytes, and the folder they are written
to, all files at once."""

from __future__ import annotations

import contextlib
import io
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from anisdf.export import baked_format as fmt
from anisdf.utils.atomic import temp_file


@dataclass
class Baked:
    """A baked mesh and its textures (:func:`anisdf.export.bake.bake`), in the normalised frame."""

    vertices: np.ndarray
    normals: np.ndarray
    uvs: np.ndarray
    faces: np.ndarray
    diffuse: np.ndarray
    """[T, T, 3] uint8."""
    lobe: np.ndarray
    """[K, S, S, 3] uint8."""
    amplitude: np.ndarray
    """[K, S, S, 3] uint8."""
    stats: dict


def png_bytes(img: np.ndarray) -> bytes:
    """An RGB uint8 image as PNG bytes (no gamma or colour profile chunk: the bytes are the values)."""
    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(img), "RGB").save(buf, format="PNG", optimize=False, compress_level=9)
    return buf.getvalue()


def mesh_buffers(vertices: np.ndarray, normals: np.ndarray, uvs: np.ndarray, faces: np.ndarray, images: list[bytes]
                 ) -> tuple[bytes, list, list]:
    """The binary chunk of a one-mesh glb and its buffer views and accessors: POSITION, NORMAL, TEXCOORD_0 and uint32
    indices (views and accessors 0-3), then one view for each image (views 4, 5, ...), 4-byte aligned."""
    import pygltflib as g

    arrays = [np.ascontiguousarray(vertices, np.float32), np.ascontiguousarray(normals, np.float32),
              np.ascontiguousarray(uvs, np.float32), np.ascontiguousarray(faces, np.uint32).reshape(-1)]
    blob = b""
    views = []
    for a in [*arrays, *images]:
        data = a if isinstance(a, bytes) else a.tobytes()
        views.append(g.BufferView(buffer=0, byteOffset=len(blob), byteLength=len(data)))
        blob += data + b"\0" * (-len(data) % 4)
    for i in range(3):
        views[i].target = g.ARRAY_BUFFER
    views[3].target = g.ELEMENT_ARRAY_BUFFER
    pos = arrays[0]
    accessors = [
        g.Accessor(bufferView=0, componentType=g.FLOAT, count=len(pos), type=g.VEC3,
                   min=pos.min(0).tolist(), max=pos.max(0).tolist()),
        g.Accessor(bufferView=1, componentType=g.FLOAT, count=len(pos), type=g.VEC3),
        g.Accessor(bufferView=2, componentType=g.FLOAT, count=len(pos), type=g.VEC2),
        g.Accessor(bufferView=3, componentType=g.UNSIGNED_INT, count=int(arrays[3].size), type=g.SCALAR),
    ]
    return blob, views, accessors


def glb_bytes(vertices: np.ndarray, normals: np.ndarray, uvs: np.ndarray, faces: np.ndarray, diffuse_png: bytes,
              extras: dict | None = None) -> bytes:
    """A glb of one textured triangle mesh: POSITION, NORMAL, TEXCOORD_0, uint32 indices and the diffuse PNG as the
    base colour of a PBR material (metallic 0, roughness 1) that also asks for ``KHR_materials_unlit`` (the colours
    are baked: viewers that know the extension show them as they are)."""
    import pygltflib as g

    blob, views, accessors = mesh_buffers(vertices, normals, uvs, faces, [diffuse_png])
    material = g.Material(
        pbrMetallicRoughness=g.PbrMetallicRoughness(baseColorTexture=g.TextureInfo(index=0), metallicFactor=0.0,
                                                    roughnessFactor=1.0),
        extensions={"KHR_materials_unlit": {}}, name="baked")
    gltf = g.GLTF2(
        asset=g.Asset(version="2.0", generator="anisdf export"),
        scene=0, scenes=[g.Scene(nodes=[0])], nodes=[g.Node(mesh=0, name="anisdf")],
        meshes=[g.Mesh(primitives=[g.Primitive(attributes=g.Attributes(POSITION=0, NORMAL=1, TEXCOORD_0=2),
                                               indices=3, material=0)])],
        accessors=accessors, bufferViews=views, buffers=[g.Buffer(byteLength=len(blob))],
        materials=[material], textures=[g.Texture(source=0, sampler=0)],
        samplers=[g.Sampler(magFilter=g.LINEAR, minFilter=g.LINEAR_MIPMAP_LINEAR, wrapS=g.CLAMP_TO_EDGE,
                            wrapT=g.CLAMP_TO_EDGE)],
        images=[g.Image(bufferView=4, mimeType="image/png")],
        extensionsUsed=["KHR_materials_unlit"], extras=extras or {})
    gltf.set_binary_blob(blob)
    return b"".join(gltf.save_to_bytes())


class AssetFolder:
    """An asset folder written all at once: :meth:`write` puts each file under a temporary name in ``folder``, and
    when the ``with`` block ends without an error the files are moved onto their names and files of an earlier
    export that match ``stale`` and were not written again are removed (lobe textures of an export with more lobes
    would contradict the manifest). On an error the temporary files are removed and the folder keeps what it held.
    """

    def __init__(self, folder: Path, stale: tuple[str, ...] = ("specular_*.png",)) -> None:
        self.folder = Path(folder)
        self.stale = stale
        self._staged: dict[str, Path] = {}

    def __enter__(self) -> AssetFolder:
        self.folder.mkdir(parents=True, exist_ok=True)
        return self

    def write(self, name: str, data: bytes) -> int:
        """Stage ``data`` as file ``name``; returns its size in bytes."""
        path = self.folder / name
        old = self._staged.pop(name, None)
        if old is not None:
            old.unlink(missing_ok=True)
        self._staged[name] = temp_file(path)
        self._staged[name].write_bytes(data)
        return len(data)

    def __exit__(self, exc_type, exc, tb) -> None:
        try:
            if exc_type is None:
                written = set(self._staged)
                while self._staged:  # in the order written: the manifest, written last, lands last
                    name, tmp = next(iter(self._staged.items()))
                    os.replace(tmp, self.folder / name)
                    del self._staged[name]
                for pattern in self.stale:
                    for old in self.folder.glob(pattern):
                        if old.name not in written:
                            old.unlink()
        finally:
            for tmp in self._staged.values():
                with contextlib.suppress(FileNotFoundError):
                    tmp.unlink()
            self._staged.clear()


def asset_bytes(baked: Baked, to_world: np.ndarray, manifest: dict) -> dict[str, bytes]:
    """The bytes of model.glb (mesh moved to the dataset's frame by ``to_world``), specular_*.png and index.html
    (the viewer page, described by ``manifest``: export.json's content without files, sizes and timings)."""
    from anisdf.export.web_page import page_html

    T = np.asarray(to_world, dtype=np.float64)
    lin = T[:3, :3]
    verts = np.asarray(baked.vertices, np.float64) @ lin.T + T[:3, 3]
    normals = np.asarray(baked.normals, np.float64) @ np.linalg.inv(lin)  # normals transform by the inverse transpose
    normals /= np.linalg.norm(normals, axis=1, keepdims=True).clip(1e-12)
    faces = np.asarray(baked.faces)
    if np.linalg.det(lin) < 0:  # a reflection: keep the triangles wound counter-clockwise seen from outside
        faces = faces[:, ::-1]
    glb = glb_bytes(verts, normals, baked.uvs, faces, png_bytes(baked.diffuse),
                    extras={"anisdf": {"format": fmt.FORMAT, "manifest": fmt.MANIFEST}})
    lobe_pngs = [png_bytes(baked.lobe[k]) for k in range(len(baked.lobe))]
    rgb_pngs = [png_bytes(baked.amplitude[k]) for k in range(len(baked.amplitude))]
    files: dict[str, bytes] = {fmt.GLB: glb}
    for k in range(len(lobe_pngs)):
        files[fmt.lobe_png(k)] = lobe_pngs[k]
        files[fmt.rgb_png(k)] = rgb_pngs[k]
    files[fmt.PAGE] = page_html(manifest, glb, lobe_pngs, rgb_pngs).encode("utf-8")
    return files


def write_asset(folder: AssetFolder, baked: Baked, to_world: np.ndarray, manifest: dict) -> dict[str, int]:
    """Stage model.glb, specular_*.png and index.html (:func:`asset_bytes`) in ``folder``; returns their sizes in
    bytes. export.json (``manifest`` with those sizes) is the caller's to write, last."""
    return {name: folder.write(name, data) for name, data in asset_bytes(baked, to_world, manifest).items()}
