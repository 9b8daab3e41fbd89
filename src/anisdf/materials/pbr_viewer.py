"""The PBR asset's page (``anisdf export --pbr`` writes it as index.html) and its Python reference renderer.

The page (export/web/pbr.html) draws model.glb under a light picked on the page: the fitted one, the bundled studio
light (:func:`anisdf.materials.environment.studio_light`) or the user's own ``.hdr``, turned by a slider about +z.
It prefilters the light itself (the JavaScript twin of :func:`anisdf.materials.render.prepare_light`) and shades
each fragment with the split sum (:func:`anisdf.materials.shading.shade`): vertex normal and UV interpolated, base
colour (sRGB texels decoded, then blended) and metallic-roughness (B, G) fetched bilinearly, the shading normal bent
to the horizon where it faces away, the colour clamped and sRGB-encoded per sample, the samples filtered into pixels
as :func:`anisdf.export.reference_renderer.resolve` does. :func:`render_asset` computes the same in PyTorch.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from anisdf.errors import AnisdfError
from anisdf.export.reference_renderer import PinholeCamera, bilinear_taps, png_rgb, read_glb, render_hits
from anisdf.export.web_page import b64, fill_template
from anisdf.materials.brdf import dfg_table
from anisdf.materials.environment import Prefiltered
from anisdf.materials.fit import linear, srgb
from anisdf.materials.pbr_asset import GLB, MANIFEST
from anisdf.materials.shading import shade

PAGE = "index.html"


@dataclass
class PbrAsset:
    """An ``export --pbr`` folder in memory: mesh (dataset frame) and its two textures as the files hold them."""

    positions: Tensor
    normals: Tensor
    uvs: Tensor
    faces: Tensor
    base: Tensor
    """[H, W, 3] uint8, sRGB-encoded base colour."""
    metallic_roughness: Tensor
    """[H, W, 3] uint8: roughness in G, metallic in B."""
    manifest: dict[str, Any]

    @classmethod
    def load(cls, folder: str | Path) -> PbrAsset:
        folder = Path(folder)
        try:
            manifest = json.loads((folder / MANIFEST).read_text())
        except (OSError, json.JSONDecodeError) as e:
            raise AnisdfError(f"{folder}: not a PBR asset ({MANIFEST}: {e})") from None
        if manifest.get("format") != "anisdf-pbr":
            raise AnisdfError(f"{folder / MANIFEST}: not written by anisdf export --pbr")
        pos, nrm, uv, faces, base = read_glb(folder / GLB)
        mr = read_glb(folder / GLB, "metallicRoughnessTexture")[4]
        return cls(torch.from_numpy(pos), torch.from_numpy(nrm), torch.from_numpy(uv),
                   torch.from_numpy(faces.astype(np.int64)), torch.from_numpy(png_rgb(base, folder / GLB)),
                   torch.from_numpy(png_rgb(mr, folder / GLB)), manifest)


def _texture(img: Tensor, uv: Tensor, decode=None) -> Tensor:
    """Bilinear lookups [M, 3] of an 8-bit texture at ``uv``, each texel decoded (``decode``) before blending."""
    out = torch.zeros(len(uv), 3)
    for qy, qx, wt in bilinear_taps(uv, *img.shape[:2]):
        texel = img[qy, qx].float() / 255.0
        out = out + wt[:, None] * (decode(texel) if decode else texel)
    return out


def turn_z(d: Tensor, degrees: float) -> Tensor:
    """Directions ``d`` [..., 3] turned by ``degrees`` about +z."""
    a = math.radians(degrees)
    c, s = math.cos(a), math.sin(a)
    return torch.stack([c * d[..., 0] - s * d[..., 1], s * d[..., 0] + c * d[..., 1], d[..., 2]], -1)


def shade_asset(asset: PbrAsset, light: Prefiltered, face: Tensor, bary: Tensor, dirs: Tensor,
                rotate: float = 0.0) -> Tensor:
    """sRGB-encoded colours [M, 3] of hits (faces, barycentrics) seen along unit ``dirs`` [M, 3] under ``light``
    turned by ``rotate`` degrees about +z, as the page's fragment shader computes them."""
    tri = asset.faces[face]
    b = bary[..., None]
    n = F.normalize((b * asset.normals[tri]).sum(1), dim=-1)
    uv = (b * asset.uvs[tri]).sum(1)
    view = -dirs
    nv = (n * view).sum(-1, keepdim=True)
    n = torch.where(nv < 1e-3, F.normalize(n - (nv - 1e-3) * view, dim=-1), n)
    base = _texture(asset.base, uv, linear)
    mr = _texture(asset.metallic_roughness, uv)
    # the light turned by +rotate is the light as it is, looked up along directions turned by -rotate
    rgb = shade(light, turn_z(n, -rotate), turn_z(view, -rotate), base, mr[:, 1], mr[:, 2])
    return srgb(rgb.clamp(0.0, 1.0))


@torch.no_grad()
def render_asset(asset: PbrAsset, light: Prefiltered, cam: PinholeCamera, rotate: float = 0.0,
                 supersample: int = 2, pixel_filter: float = 0.6,
                 background: tuple[float, float, float] = (1.0, 1.0, 1.0)) -> tuple[np.ndarray, np.ndarray]:
    """What the page draws from ``cam``: sRGB colour [H, W, 3] in [0, 1] over ``background`` (sRGB), and the
    fraction of each pixel the mesh covers."""
    return render_hits(asset, cam, lambda face, bary, dirs: shade_asset(asset, light, face, bary, dirs, rotate),
                       supersample, pixel_filter, background)


def pbr_page_html(manifest: dict[str, Any], glb: bytes, lights: dict[str, np.ndarray]) -> str:
    """index.html of a PBR asset: ``glb`` and the equirectangular ``lights`` ([H, 2H, 3] linear, by name, the
    first shown first) embedded, with the split sum's table (:func:`anisdf.materials.brdf.dfg_table`)."""
    def floats(a: np.ndarray | Tensor) -> str:
        return b64(np.ascontiguousarray(np.asarray(a, dtype="<f4")).tobytes())

    entries = [{"name": name, "rows": int(env.shape[0]), "data": floats(env)} for name, env in lights.items()]
    table = dfg_table()
    return fill_template("pbr.html", {"manifest": manifest, "glb": b64(glb), "lights": entries,
                                      "dfg": {"size": int(table.shape[-1]), "data": floats(table)}})
