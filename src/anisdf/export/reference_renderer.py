"""Reference renderer of a baked asset: what the viewer page (export/web/index.html) draws, computed in PyTorch.

Each pixel's ray through its centre is cast against the mesh (candidate pixels from each triangle's projected
bounding box, then an exact ray-triangle test; the nearest hit wins, as a z-buffer), and the hit is shaded as
:mod:`anisdf.export.baked_format` describes: interpolated normal and UV, the view direction reflected about the
normal, 4 texels fetched around the UV, each shaded with its diffuse colour and lobes, blended bilinearly. A
rasteriser samples pixel centres and interpolates perspective-correctly, which is this ray cast; the page's shader
does the same arithmetic in float32. Pixels without a hit show the background.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image
from torch import Tensor

from anisdf.errors import AnisdfError
from anisdf.export import baked_format as fmt

_COMPONENT = {5126: np.float32, 5125: np.uint32, 5123: np.uint16, 5121: np.uint8}
_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}


@dataclass
class BakedAsset:
    """A baked asset in memory: mesh (dataset frame) and texel bytes as the files hold them."""

    positions: Tensor
    """[V, 3] float32."""
    normals: Tensor
    """[V, 3] float32 unit vertex normals."""
    uvs: Tensor
    """[V, 2] float32, (0, 0) at the first pixel of the first image row."""
    faces: Tensor
    """[F, 3] int64."""
    diffuse: Tensor
    """[H, W, 3] uint8."""
    lobe: Tensor
    """[K, H, W, 3] uint8: octahedral axis (R, G) and sharpness (B)."""
    amplitude: Tensor
    """[K, H, W, 3] uint8."""
    sharpness_range: tuple[float, float]
    manifest: dict[str, Any]

    @property
    def k(self) -> int:
        return int(self.lobe.shape[0])

    @classmethod
    def load(cls, folder: str | Path) -> BakedAsset:
        """Read ``folder`` as ``anisdf export`` wrote it (export.json, model.glb, specular_*.png)."""
        folder = Path(folder)
        man_path = folder / fmt.MANIFEST
        if not man_path.is_file():
            raise AnisdfError(f"{folder}: not a baked asset (no {fmt.MANIFEST}; write one with anisdf export)")
        try:
            manifest = json.loads(man_path.read_text())
            k = int(manifest["lobes"])
            srange = tuple(float(v) for v in manifest["sharpness_range"])
        except (json.JSONDecodeError, KeyError, TypeError, ValueError) as e:
            raise AnisdfError(f"{man_path}: unreadable ({e})") from None
        if manifest.get("format") != fmt.FORMAT:
            raise AnisdfError(f"{man_path}: not an {fmt.FORMAT} manifest")
        pos, nrm, uv, faces, png = read_glb(folder / fmt.GLB)
        diffuse = png_rgb(png, folder / fmt.GLB)
        lobes, amps = [], []
        for i in range(k):
            lobes.append(png_rgb((folder / fmt.lobe_png(i)), folder / fmt.lobe_png(i)))
            amps.append(png_rgb((folder / fmt.rgb_png(i)), folder / fmt.rgb_png(i)))
        h, w = lobes[0].shape[:2] if k else (1, 1)
        for path, arr in [(fmt.lobe_png(i), a) for i, a in enumerate(lobes)] + \
                         [(fmt.rgb_png(i), a) for i, a in enumerate(amps)]:
            if arr.shape[:2] != (h, w):
                raise AnisdfError(f"{folder / path}: {arr.shape[1]}x{arr.shape[0]}, {fmt.lobe_png(0)} is {w}x{h}")
        empty = np.zeros((0, h, w, 3), np.uint8)
        return cls(torch.from_numpy(pos), torch.from_numpy(nrm), torch.from_numpy(uv),
                   torch.from_numpy(faces.astype(np.int64)), torch.from_numpy(diffuse),
                   torch.from_numpy(np.stack(lobes) if k else empty), torch.from_numpy(np.stack(amps) if k else empty),
                   (srange[0], srange[1]), manifest)


def png_rgb(src: bytes | Path, name: Path) -> np.ndarray:
    import io

    try:
        img = Image.open(io.BytesIO(src) if isinstance(src, bytes) else src)
        img.load()
    except (OSError, ValueError) as e:
        raise AnisdfError(f"{name}: cannot read the texture ({e})") from None
    if img.mode != "RGB":
        raise AnisdfError(f"{name}: expected an RGB texture, found mode {img.mode}")
    return np.asarray(img, dtype=np.uint8).copy()


def read_glb(path: Path, texture: str = "baseColorTexture"
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, bytes]:
    """Positions, normals, UVs [V, *] float32, triangles [F, 3] and the PNG of the material's ``texture`` (a glTF
    ``pbrMetallicRoughness`` slot) of the glb's first primitive (tightly packed buffer views, as
    :func:`anisdf.export.asset_files.mesh_buffers` writes them)."""
    from pygltflib import GLTF2

    if not path.is_file():
        raise AnisdfError(f"{path}: missing")
    try:
        g = GLTF2.load_binary(str(path))
        blob = g.binary_blob()
        prim = g.meshes[0].primitives[0]

        def accessor(i: int) -> np.ndarray:
            acc = g.accessors[i]
            view = g.bufferViews[acc.bufferView]
            if view.byteStride not in (None, 0):
                raise AnisdfError(f"{path}: interleaved buffer views are not supported")
            width = _WIDTH[acc.type]
            start = (view.byteOffset or 0) + (acc.byteOffset or 0)
            return np.frombuffer(blob, _COMPONENT[acc.componentType], acc.count * width, start).reshape(-1, width)

        pos = accessor(prim.attributes.POSITION).astype(np.float32)
        nrm = accessor(prim.attributes.NORMAL).astype(np.float32)
        uv = accessor(prim.attributes.TEXCOORD_0).astype(np.float32)
        faces = accessor(prim.indices).reshape(-1, 3).astype(np.int64)
        mat = g.materials[prim.material]
        image = g.images[g.textures[getattr(mat.pbrMetallicRoughness, texture).index].source]
        view = g.bufferViews[image.bufferView]
        png = bytes(blob[view.byteOffset or 0:(view.byteOffset or 0) + view.byteLength])
    except (AttributeError, IndexError, KeyError, TypeError, ValueError, OSError) as e:
        raise AnisdfError(f"{path}: not a glb anisdf export wrote ({type(e).__name__}: {e})") from None
    return pos, nrm, uv, faces, png


@dataclass
class PinholeCamera:
    """An OpenCV camera in the asset's (dataset) frame: ``c2w`` [4, 4] (x right, y down, z forward), intrinsics
    in pixels with pixel centres at ``i + 0.5``, optional OpenCV (k1, k2, p1, p2) distortion."""

    c2w: np.ndarray
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    distortion: np.ndarray | None = None

    def to_json(self) -> dict[str, Any]:
        return {"c2w": np.asarray(self.c2w, dtype=float).tolist(), "fx": float(self.fx), "fy": float(self.fy),
                "cx": float(self.cx), "cy": float(self.cy), "width": int(self.width), "height": int(self.height)}


def pixel_rays(cam: PinholeCamera) -> tuple[Tensor, Tensor]:
    """World origin [3] and unit directions [H * W, 3] (row-major) through the pixel centres."""
    from anisdf.data.cameras import undistort

    py, px = torch.meshgrid(torch.arange(cam.height, dtype=torch.float32) + 0.5,
                            torch.arange(cam.width, dtype=torch.float32) + 0.5, indexing="ij")
    x = ((px - cam.cx) / cam.fx).reshape(-1)
    y = ((py - cam.cy) / cam.fy).reshape(-1)
    if cam.distortion is not None:
        x, y = undistort(x, y, torch.as_tensor(cam.distortion, dtype=torch.float32))
    rot = torch.as_tensor(np.asarray(cam.c2w)[:3, :3], dtype=torch.float32)
    d = torch.stack([x, y, torch.ones_like(x)], -1) @ rot.T
    d = d / d.norm(dim=-1, keepdim=True)
    return torch.as_tensor(np.asarray(cam.c2w)[:3, 3], dtype=torch.float32), d


@torch.no_grad()
def cast(asset: BakedAsset, cam: PinholeCamera, chunk: int = 1 << 21) -> tuple[Tensor, Tensor, Tensor]:
    """Nearest hit of each pixel's ray: face [H * W] (-1: none), distance [H * W] and barycentrics [H * W, 3]."""
    from anisdf.data.cameras import distort

    h, w = cam.height, cam.width
    origin, dirs = pixel_rays(cam)
    rot = torch.as_tensor(np.asarray(cam.c2w)[:3, :3], dtype=torch.float32)
    pc = (asset.positions - origin) @ rot  # camera frame
    z = pc[:, 2]
    x, y = pc[:, 0] / z, pc[:, 1] / z
    margin = 0.0
    if cam.distortion is not None:
        x, y = distort(x, y, torch.as_tensor(cam.distortion, dtype=torch.float32))
        margin = 1.0  # the box of the distorted corners may miss a little of the curved edges
    u, v = cam.fx * x + cam.cx, cam.fy * y + cam.cy
    f = asset.faces
    uf, vf = u[f], v[f]
    front = (z[f] > 1e-6).all(dim=1)  # triangles crossing the camera plane are dropped (the page clips them)
    c0 = torch.ceil(uf.min(1).values - 0.5 - margin)
    c1 = torch.floor(uf.max(1).values - 0.5 + margin)
    r0 = torch.ceil(vf.min(1).values - 0.5 - margin)
    r1 = torch.floor(vf.max(1).values - 0.5 + margin)
    c0, r0 = c0.clamp(min=0), r0.clamp(min=0)
    c1, r1 = c1.clamp(max=w - 1), r1.clamp(max=h - 1)
    ok = front & (c1 >= c0) & (r1 >= r0) & torch.isfinite(uf).all(1) & torch.isfinite(vf).all(1)
    fid = ok.nonzero()[:, 0]
    c0, r0 = c0[fid].long(), r0[fid].long()
    nc, nr = (c1[fid].long() - c0 + 1), (r1[fid].long() - r0 + 1)
    counts = nc * nr
    n_pix = h * w
    best_t = torch.full((n_pix,), float("inf"))
    best_face = torch.full((n_pix,), -1, dtype=torch.long)
    best_b = torch.zeros(n_pix, 3)
    tri = asset.positions[f]  # [F, 3, 3] world
    ends = torch.cumsum(counts, 0)
    start = 0
    while start < len(fid):
        base = int(ends[start - 1]) if start else 0
        stop = int(torch.searchsorted(ends, torch.tensor(base + chunk), right=True))
        stop = max(stop, start + 1)
        sl = slice(start, stop)
        cnt = counts[sl]
        owner = torch.repeat_interleave(torch.arange(start, stop), cnt)
        local = torch.arange(int(cnt.sum())) - torch.repeat_interleave(torch.cumsum(cnt, 0) - cnt, cnt)
        col = c0[owner] + local % nc[owner]
        row = r0[owner] + local // nc[owner]
        pix = row * w + col
        face = fid[owner]
        t, b1, b2, hit = _ray_triangle(origin, dirs[pix], tri[face])
        pix, face, t, b1, b2 = pix[hit], face[hit], t[hit], b1[hit], b2[hit]
        if len(pix):
            chunk_t = torch.full((n_pix,), float("inf")).scatter_reduce(0, pix, t, "amin")
            win = (t == chunk_t[pix]).nonzero()[:, 0]
            pick = torch.full((n_pix,), -1, dtype=torch.long).scatter_reduce(0, pix[win], win, "amax")
            sel = pick[pick >= 0]
            p = pix[sel]
            better = t[sel] < best_t[p]
            sel, p = sel[better], p[better]
            best_t[p] = t[sel]
            best_face[p] = face[sel]
            best_b[p] = torch.stack([1.0 - b1[sel] - b2[sel], b1[sel], b2[sel]], -1)
        start = stop
    return best_face, best_t, best_b


def _ray_triangle(origin: Tensor, d: Tensor, tri: Tensor, eps: float = 1e-7) -> tuple[Tensor, ...]:
    """Moller-Trumbore: distance, barycentrics of vertices 1 and 2, and whether the ray hits (t > 0)."""
    e1 = tri[:, 1] - tri[:, 0]
    e2 = tri[:, 2] - tri[:, 0]
    p = torch.linalg.cross(d, e2)
    det = (e1 * p).sum(-1)
    inv = 1.0 / torch.where(det.abs() < 1e-20, torch.full_like(det, 1e-20), det)
    s = origin - tri[:, 0]
    b1 = (s * p).sum(-1) * inv
    q = torch.linalg.cross(s, e1)
    b2 = (d * q).sum(-1) * inv
    t = (e2 * q).sum(-1) * inv
    hit = (det.abs() >= 1e-20) & (b1 >= -eps) & (b2 >= -eps) & (b1 + b2 <= 1.0 + eps) & (t > 0)
    return t, b1, b2, hit


def bilinear_taps(uv: Tensor, h: int, w: int) -> list[tuple[Tensor, Tensor, Tensor]]:
    """The 4 texels (row, column) around each UV of an ``h`` x ``w`` texture with their bilinear weights, in the
    shader's order (clamped to the edge)."""
    size = torch.tensor([w, h], dtype=torch.float32)
    p = uv * size - 0.5
    p0 = torch.floor(p)
    frac = p - p0
    i0 = p0.long()
    taps = []
    for j in range(4):
        ox, oy = j & 1, j >> 1
        qx = (i0[:, 0] + ox).clamp(0, w - 1)
        qy = (i0[:, 1] + oy).clamp(0, h - 1)
        wx = frac[:, 0] if ox else 1.0 - frac[:, 0]
        wy = frac[:, 1] if oy else 1.0 - frac[:, 1]
        taps.append((qy, qx, wx * wy))
    return taps


def shade(asset: BakedAsset, face: Tensor, bary: Tensor, view_dirs: Tensor, specular: bool = True) -> Tensor:
    """Colours [M, 3] of hits (faces [M], barycentrics [M, 3]) seen along unit ``view_dirs`` [M, 3], as the page's
    fragment shader computes them (float32); ``specular=False`` draws the diffuse texture alone."""
    tri = asset.faces[face]
    b = bary[..., None]
    n = (b * asset.normals[tri]).sum(1)
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-20)
    uv = (b * asset.uvs[tri]).sum(1)
    r = view_dirs - 2.0 * (view_dirs * n).sum(-1, keepdim=True) * n
    out = torch.zeros(len(face), 3)
    for qy, qx, wt in bilinear_taps(uv, *asset.diffuse.shape[:2]):
        out = out + wt[:, None] * (asset.diffuse[qy, qx].float() / 255.0)
    if specular and asset.k:
        log_lo = np.float32(np.log(asset.sharpness_range[0]))
        log_span = np.float32(np.log(asset.sharpness_range[1] / asset.sharpness_range[0]))
        for qy, qx, wt in bilinear_taps(uv, *asset.lobe.shape[1:3]):
            texel = torch.zeros(len(face), 3)
            for k in range(asset.k):
                lobe = asset.lobe[k, qy, qx].float() / 255.0
                amp = asset.amplitude[k, qy, qx].float() / 255.0
                mu = torch.from_numpy(fmt.oct_decode(lobe[:, :2].numpy()))
                lam = torch.exp(log_lo + lobe[:, 2] * log_span)
                texel = texel + amp * torch.exp(lam * ((mu * r).sum(-1) - 1.0))[:, None]
            out = out + wt[:, None] * texel
    return out.clamp(0.0, 1.0)


def resolve(fine: Tensor, s: int, sigma: float) -> Tensor:
    """Fine samples [H s, W s, C] filtered into pixels [H, W, C] as the page's resolve pass does: the s x s box of
    each pixel (``sigma`` 0), else a Gaussian of ``sigma`` pixels over the fine samples within 3 sigma of the pixel's
    centre in x and in y (a square window), normalised by the weights of the samples inside the image."""
    hs, ws, c = fine.shape
    h, w = hs // s, ws // s
    if sigma <= 0:
        return fine.reshape(h, s, w, s, c).mean(dim=(1, 3))

    def axis_weights(n: int) -> Tensor:
        centre = torch.arange(n, dtype=torch.float64) + 0.5  # output pixel centres, in pixels
        sample = (torch.arange(n * s, dtype=torch.float64) + 0.5) / s
        d = sample[None, :] - centre[:, None]
        wt = torch.exp(-0.5 * (d / sigma) ** 2) * (d.abs() <= 3.0 * sigma + 1e-9)
        return wt.float()

    wy, wx = axis_weights(h), axis_weights(w)  # [h, H s], [w, W s]
    num = torch.einsum("yi,ijc,xj->yxc", wy, fine, wx)
    den = torch.einsum("yi,xj->yx", wy, wx)[..., None]
    return num / den


@torch.no_grad()
def render(asset: BakedAsset, cam: PinholeCamera, background: tuple[float, float, float] = (1.0, 1.0, 1.0),
           specular: bool = True, supersample: int = 1, pixel_filter: float | None = None
           ) -> tuple[np.ndarray, np.ndarray]:
    """The asset seen by ``cam``: float RGB [H, W, 3] in [0, 1] and the fraction of each pixel the mesh covers.

    ``supersample`` s: rays through the centres of an s-times finer pixel grid; ``pixel_filter`` sigma (default: the
    asset's, else 0): each pixel a Gaussian-weighted mean of the fine samples within 3 sigma pixels of its centre
    (:func:`resolve`), or with 0 the mean of its own s x s samples, as the page's resolve pass computes it."""
    s = int(supersample)
    if s < 1:
        raise AnisdfError(f"supersample must be a positive integer, got {supersample}")
    sigma = float(asset.manifest.get("pixel_filter", 0.0) if pixel_filter is None else pixel_filter)
    return render_hits(asset, cam, lambda face, bary, dirs: shade(asset, face, bary, dirs, specular=specular), s,
                       sigma, background)


def render_hits(mesh: Any, cam: PinholeCamera, shade_hits: Any, supersample: int, sigma: float,
                background: tuple[float, float, float]) -> tuple[np.ndarray, np.ndarray]:
    """What a page draws of ``mesh`` (``positions``, ``faces``) from ``cam``: rays through the centres of an
    s-times finer pixel grid, the hits coloured by ``shade_hits(face, barycentrics, directions)``, the others
    ``background``, filtered into pixels by :func:`resolve`. RGB [H, W, 3] and coverage [H, W]."""
    s = int(supersample)
    fine = PinholeCamera(cam.c2w, cam.fx * s, cam.fy * s, cam.cx * s, cam.cy * s, cam.width * s, cam.height * s,
                         cam.distortion)
    face, _, bary = cast(mesh, fine)
    _, dirs = pixel_rays(fine)
    rgb = torch.as_tensor(background, dtype=torch.float32).expand(face.shape[0], 3).clone()
    hit = face >= 0
    if hit.any():
        rgb[hit] = shade_hits(face[hit], bary[hit], dirs[hit])
    samples = torch.cat([rgb, hit.float()[:, None]], -1).reshape(cam.height * s, cam.width * s, 4)
    out = resolve(samples, s, sigma)
    return out[..., :3].numpy(), out[..., 3].numpy()
