"""Environment lights as equirectangular HDR maps in the dataset's frame, z up.

Pixel (row i, column j) of an H x W map holds the radiance arriving from direction
``d = (sin t cos p, sin t sin p, cos t)`` with ``t = (i + 0.5) / H pi`` measured from +z and ``p = (j + 0.5) / W 2 pi``
from +x toward +y (the layout of ``bunny_plastic/relight/*_world.exr``). Linear radiance, float32 [H, W, 3].

Files: ``.hdr`` (Radiance RGBE, read and written here), ``.exr`` (through the ``OpenEXR`` package), ``.npy``.
Shading needs the map prefiltered (:class:`Prefiltered`): the irradiance ``E(n) = int L(w) max(n.w, 0) dw / pi``
(an exact sum over the map's texels, at a coarse resolution) and the GGX-filtered radiance of a few roughness levels
(split sum, :mod:`anisdf.materials.brdf`), both differentiable in the map.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from anisdf.errors import AnisdfError
from anisdf.materials.brdf import MIN_ROUGHNESS, hammersley, sample_ggx_half
from anisdf.utils.atomic import atomic_path

ENV_SUFFIXES = (".hdr", ".exr", ".npy")


# ------------------------------------------------------------------------------------------------ geometry
def texel_directions(h: int, w: int, dtype: torch.dtype = torch.float32) -> Tensor:
    """Unit directions [h, w, 3] of the texel centres."""
    t = (torch.arange(h, dtype=torch.float64) + 0.5) / h * math.pi
    p = (torch.arange(w, dtype=torch.float64) + 0.5) / w * 2.0 * math.pi
    t, p = torch.meshgrid(t, p, indexing="ij")
    return torch.stack([torch.sin(t) * torch.cos(p), torch.sin(t) * torch.sin(p), torch.cos(t)], -1).to(dtype)


def solid_angles(h: int, w: int, dtype: torch.dtype = torch.float32) -> Tensor:
    """Solid angle [h, w] of each texel (exact: they sum to 4 pi)."""
    t0 = torch.arange(h, dtype=torch.float64) / h * math.pi
    band = (torch.cos(t0) - torch.cos(t0 + math.pi / h)) * (2.0 * math.pi / w)
    return band[:, None].expand(h, w).to(dtype).contiguous()


def lookup_taps(h: int, w: int, d: Tensor) -> tuple[Tensor, Tensor]:
    """The 4 texels (flat indices [M, 4]) and bilinear weights [M, 4] of an ``h`` x ``w`` map around unit
    directions ``d`` [M, 3] (wrapping around the azimuth, clamped at the poles)."""
    t = torch.acos(d[:, 2].clamp(-1.0, 1.0))
    p = torch.atan2(d[:, 1], d[:, 0]) % (2.0 * math.pi)
    x = p / (2.0 * math.pi) * w - 0.5
    y = t / math.pi * h - 0.5
    x0, y0 = torch.floor(x), torch.floor(y)
    fx, fy = x - x0, y - y0
    c0 = x0.long() % w
    c1 = (c0 + 1) % w
    r0 = y0.long().clamp(0, h - 1)
    r1 = (y0.long() + 1).clamp(0, h - 1)
    idx = torch.stack([r0 * w + c0, r0 * w + c1, r1 * w + c0, r1 * w + c1], -1)
    wts = torch.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], -1)
    return idx, wts


def lookup(env: Tensor, d: Tensor) -> Tensor:
    """Bilinear radiance [..., 3] of ``env`` [H, W, 3] from unit directions ``d`` [..., 3] (wrapping around the
    azimuth, clamped at the poles); differentiable in ``env``."""
    h, w, c = env.shape
    idx, wts = lookup_taps(h, w, d.reshape(-1, 3))
    out = (env.reshape(-1, c)[idx] * wts[..., None].to(env.dtype)).sum(1)
    return out.reshape(*d.shape[:-1], c)


def rotate(env: Tensor, degrees: float) -> Tensor:
    """The light turned by ``degrees`` about +z (counter-clockwise seen from above): what arrived from azimuth ``p``
    arrives from ``p + degrees``. Whole-texel turns are exact column shifts; others resample bilinearly."""
    h, w, _ = env.shape
    shift = degrees / 360.0 * w
    if abs(shift - round(shift)) < 1e-6:
        return torch.roll(env, int(round(shift)) % w, dims=1)
    a = math.radians(degrees)
    d = texel_directions(h, w, env.dtype).to(env.device)
    c, s = math.cos(a), math.sin(a)
    src = torch.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1], d[..., 2]], -1)
    return lookup(env, src)


def downsample(env: Tensor, h: int) -> Tensor:
    """``env`` averaged down to ``h`` rows and ``2 h`` columns (area weights: texels near the poles count less)."""
    H, W, _ = env.shape
    if H == h and W == 2 * h:
        return env
    if H % h or W % (2 * h):
        return F.interpolate(env.permute(2, 0, 1)[None], size=(h, 2 * h), mode="area")[0].permute(1, 2, 0)
    fy, fx = H // h, W // (2 * h)
    wt = solid_angles(H, W, env.dtype).to(env.device)[..., None]
    num = (env * wt).reshape(h, fy, 2 * h, fx, 3).sum((1, 3))
    return num / wt.reshape(h, fy, 2 * h, fx, 1).sum((1, 3))


STUDIO = (  # (azimuth deg, elevation deg, sharpness, linear RGB): a key, a rim and a soft fill from above
    (40.0, 35.0, 60.0, (9.0, 8.4, 7.6)),
    (215.0, 20.0, 90.0, (4.0, 4.6, 5.6)),
    (0.0, 90.0, 4.0, (0.35, 0.35, 0.38)),
)


def studio_light(rows: int = 64, ambient: float = 0.02) -> Tensor:
    """The bundled studio light [rows, 2 rows, 3]: a dark room (``ambient``) with the spherical-Gaussian lamps of
    :data:`STUDIO` (``c exp(s (d.mu - 1))``), made here so that nothing is downloaded or shipped as a file."""
    d = texel_directions(rows, 2 * rows)
    env = torch.full((rows, 2 * rows, 3), ambient)
    for az, el, sharp, rgb in STUDIO:
        a, e = math.radians(az), math.radians(el)
        mu = torch.tensor([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])
        env = env + torch.exp(sharp * ((d @ mu) - 1.0))[..., None] * torch.tensor(rgb)
    return env


# ------------------------------------------------------------------------------------------------ prefiltering
def irradiance_matrix(h_out: int, h_in: int, device: torch.device | str = "cpu") -> Tensor:
    """[h_out * 2 h_out, h_in * 2 h_in]: row k maps a map's texels to ``E(n_k)`` at output texel k's direction."""
    n = texel_directions(h_out, 2 * h_out).reshape(-1, 3)
    d = texel_directions(h_in, 2 * h_in).reshape(-1, 3)
    m = (n @ d.T).clamp_min(0.0) * solid_angles(h_in, 2 * h_in).reshape(1, -1)
    return (m / m.sum(1, keepdim=True)).to(device)  # the quadrature's rows sum to int max(n.w, 0) dw / pi = 1


def ggx_prefilter_matrix(h: int, roughness: float, samples: int, device: torch.device | str = "cpu") -> Tensor:
    """The GGX prefilter of an ``h`` x ``2h`` map as a sparse [h * 2h, h * 2h] matrix: row k holds the
    ``n.l``-weighted mean of ``samples`` importance-sampled bilinear lookups about texel k's direction (Karis's
    split sum with n = v = r)."""
    w = 2 * h
    r = texel_directions(h, w, torch.float64).reshape(-1, 3)
    alpha = torch.tensor(max(roughness, MIN_ROUGHNESS) ** 2, dtype=torch.float64)
    hl = sample_ggx_half(hammersley(samples), alpha)  # [N, 3], local frame
    t, b = tangent_frame(r)
    hw = hl[None, :, 0:1] * t[:, None] + hl[None, :, 1:2] * b[:, None] + hl[None, :, 2:3] * r[:, None]
    light = 2.0 * (r[:, None] * hw).sum(-1, keepdim=True) * hw - r[:, None]
    wt = (light * r[:, None]).sum(-1).clamp_min(0.0)
    wt = wt / wt.sum(1, keepdim=True).clamp_min(1e-12)
    idx, taps = lookup_taps(h, w, light.reshape(-1, 3))
    rows = torch.arange(h * w).repeat_interleave(samples * 4)
    vals = (taps.reshape(h * w, samples, 4) * wt[..., None]).reshape(-1)
    m = torch.sparse_coo_tensor(torch.stack([rows, idx.reshape(-1)]), vals.float(), (h * w, h * w),
                                check_invariants=False)
    return m.coalesce().to(device)


class _SparseLinear(torch.autograd.Function):
    """``m @ x`` for a fixed sparse ``m`` (CSR) with the transpose kept as CSR too: both directions stay fast."""

    @staticmethod
    def forward(ctx, x: Tensor, m: Tensor, mt: Tensor) -> Tensor:  # noqa: D102
        ctx.mt = mt
        return m @ x

    @staticmethod
    def backward(ctx, g: Tensor) -> tuple[Tensor, None, None]:  # noqa: D102
        return ctx.mt @ g, None, None


class SparseOperator:
    """A fixed sparse linear map (from a COO matrix) applied to dense [N, C] arrays, differentiable in them."""

    def __init__(self, m: Tensor) -> None:
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # "sparse CSR support is in beta"
            self.m = m.to_sparse_csr()
            self.mt = m.t().coalesce().to_sparse_csr()

    def __call__(self, x: Tensor) -> Tensor:
        return _SparseLinear.apply(x, self.m, self.mt)


def ggx_prefilter(env: Tensor, roughness: float, samples: int) -> Tensor:
    """``env`` [H, 2H, 3] filtered with the GGX lobe of ``roughness`` (:func:`ggx_prefilter_matrix`)."""
    h = env.shape[0]
    m = SparseOperator(ggx_prefilter_matrix(h, roughness, samples, env.device))
    return m(env.reshape(-1, 3).float()).reshape(env.shape)


def tangent_frame(n: Tensor) -> tuple[Tensor, Tensor]:
    """Two unit tangents orthogonal to unit ``n`` [..., 3] and to each other (Duff et al. 2017)."""
    sign = torch.where(n[..., 2] >= 0, 1.0, -1.0).to(n)
    a = -1.0 / (sign + n[..., 2])
    b = n[..., 0] * n[..., 1] * a
    t = torch.stack([1.0 + sign * n[..., 0] ** 2 * a, sign * b, -sign * n[..., 0]], -1)
    bt = torch.stack([b, sign + n[..., 1] ** 2 * a, -n[..., 1]], -1)
    return t, bt


@dataclass
class Prefiltered:
    """A light ready for split-sum shading: irradiance map and GGX-filtered maps at ``roughness`` levels."""

    irradiance: Tensor
    """[h, 2h, 3]: ``E(n)``."""
    levels: list[Tensor]
    roughness: list[float]

    def specular(self, r: Tensor, roughness: Tensor) -> Tensor:
        """Prefiltered radiance [M, 3] along reflected directions ``r`` [M, 3] at roughness [M] (linear between the
        two levels around it)."""
        rough = roughness.clamp(self.roughness[0], self.roughness[-1])
        vals = torch.stack([lookup(level, r) for level in self.levels], 0)  # [K, M, 3]
        knots = torch.tensor(self.roughness, dtype=r.dtype, device=r.device)
        k = torch.searchsorted(knots, rough.detach().contiguous()).clamp(1, len(knots) - 1)
        lo, hi = knots[k - 1], knots[k]
        f = ((rough - lo) / (hi - lo)).clamp(0.0, 1.0)[:, None]
        idx = torch.arange(len(r), device=r.device)
        return vals[k - 1, idx] * (1.0 - f) + vals[k, idx] * f

    def diffuse(self, n: Tensor) -> Tensor:
        return lookup(self.irradiance, n)


def _level_rows(h: int, roughness: float) -> int:
    """Rows of the map a GGX level is filtered from and kept at: the lobe spans a few texels, no fewer than 8."""
    width = max(roughness * roughness, 1e-3) ** 0.5  # ~ the lobe's angular radius in radians, up to a constant
    return max(8, min(h, 2 ** math.ceil(math.log2(16.0 / width))))


class Prefilter:
    """The linear operators that turn an ``h`` x ``2h`` map into :class:`Prefiltered` (built once, applied at every
    step of a fit; differentiable in the map): roughness levels ``k / (levels - 1)`` (level 0 the map itself;
    rougher levels from coarser copies) and the exact irradiance over a copy of at most 32 rows."""

    def __init__(self, h: int, levels: int = 6, samples: int = 64, irradiance_rows: int = 16,
                 device: torch.device | str = "cpu") -> None:
        self.h = h
        self.roughness = [k / (levels - 1) for k in range(levels)]
        self.rows = [h] + [_level_rows(h, r) for r in self.roughness[1:]]
        self.mats = [None] + [SparseOperator(ggx_prefilter_matrix(rows, r, samples, device))
                              for rows, r in zip(self.rows[1:], self.roughness[1:], strict=True)]
        self.irr_rows = irradiance_rows
        self.irr_src = min(32, h)
        self.irr = irradiance_matrix(irradiance_rows, self.irr_src, device)

    def __call__(self, env: Tensor) -> Prefiltered:
        if env.shape[0] != self.h:
            raise ValueError(f"this prefilter is for {self.h}-row maps, got {env.shape[0]}")
        maps = [env]
        for rows, m in zip(self.rows[1:], self.mats[1:], strict=True):
            src = downsample(env, rows)
            maps.append(m(src.reshape(-1, 3)).reshape(src.shape))
        irr = (self.irr @ downsample(env, self.irr_src).reshape(-1, 3)).reshape(self.irr_rows, 2 * self.irr_rows, 3)
        return Prefiltered(irr, maps, list(self.roughness))


def prefilter(env: Tensor, levels: int = 6, samples: int = 64) -> Prefiltered:
    """:class:`Prefiltered` of ``env`` [H, 2H, 3] (one use of :class:`Prefilter`)."""
    return Prefilter(env.shape[0], levels, samples, device=env.device)(env)


# ------------------------------------------------------------------------------------------------ files
def read_env(path: str | Path) -> np.ndarray:
    """An equirectangular map [H, W, 3] float32 from ``.hdr``, ``.exr`` or ``.npy``."""
    path = Path(path)
    if not path.is_file():
        raise AnisdfError(f"{path}: no such light map")
    suffix = path.suffix.lower()
    try:
        if suffix == ".hdr":
            img = _read_hdr(path.read_bytes())
        elif suffix == ".exr":
            img = _read_exr(path)
        elif suffix == ".npy":
            img = np.load(path)
        else:
            raise AnisdfError(f"{path}: a light map is .hdr, .exr or .npy")
    except (ValueError, OSError, IndexError) as e:
        raise AnisdfError(f"{path}: unreadable light map ({e})") from None
    img = np.asarray(img, dtype=np.float32)
    if img.ndim != 3 or img.shape[2] < 3 or img.shape[1] != 2 * img.shape[0]:
        raise AnisdfError(f"{path}: an equirectangular map is H x 2H with RGB, got {img.shape}")
    return np.ascontiguousarray(img[..., :3])


def write_env(path: str | Path, img: np.ndarray) -> Path:
    """Write ``img`` [H, W, 3] (linear radiance) as ``.hdr``, ``.exr`` or ``.npy``, atomically."""
    path = Path(path)
    img = np.ascontiguousarray(np.asarray(img, dtype=np.float32)[..., :3])
    suffix = path.suffix.lower()
    with atomic_path(path) as tmp:
        if suffix == ".hdr":
            tmp.write_bytes(_hdr_bytes(img))
        elif suffix == ".exr":
            _write_exr(tmp, img)
        elif suffix == ".npy":
            with open(tmp, "wb") as f:
                np.save(f, img)
        else:
            raise AnisdfError(f"{path}: a light map is written as .hdr, .exr or .npy")
    return path


def _openexr():
    try:
        import OpenEXR
    except ImportError:
        raise AnisdfError(".exr light maps need the OpenEXR package: pip install 'anisdf[materials]' "
                          "(or convert the map to .hdr)") from None
    return OpenEXR


def _read_exr(path: Path) -> np.ndarray:
    with _openexr().File(str(path)) as f:
        ch = f.channels()
        if "RGB" in ch:
            return np.asarray(ch["RGB"].pixels, dtype=np.float32)
        if "RGBA" in ch:
            return np.asarray(ch["RGBA"].pixels, dtype=np.float32)[..., :3]
        return np.stack([np.asarray(ch[c].pixels, dtype=np.float32) for c in ("R", "G", "B")], -1)


def _write_exr(path: Path, img: np.ndarray) -> None:
    exr = _openexr()
    header = {"compression": exr.ZIP_COMPRESSION, "type": exr.scanlineimage}
    with exr.File(header, {"RGB": img}) as f:
        f.write(str(path))


def _hdr_bytes(img: np.ndarray) -> bytes:
    """Radiance RGBE, flat (not run-length encoded) scanlines, top row first."""
    h, w, _ = img.shape
    v = np.maximum(img, 0.0)
    m = v.max(-1)
    e = np.ceil(np.log2(np.maximum(m, 1e-38))).astype(np.int32)
    e = np.where(m / np.exp2(e.astype(np.float64)) >= 1.0, e + 1, e)  # mantissas below 1 (256 would overflow a byte)
    scale = np.exp2(8.0 - e.astype(np.float64))[..., None]
    rgbe = np.zeros((h, w, 4), np.uint8)
    ok = m > 1e-32
    rgbe[..., :3] = np.where(ok[..., None], np.clip(np.floor(v * scale), 0, 255), 0).astype(np.uint8)
    rgbe[..., 3] = np.where(ok, np.clip(e + 128, 0, 255), 0).astype(np.uint8)
    head = f"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y {h} +X {w}\n".encode("ascii")
    return head + rgbe.tobytes()


def _read_hdr(data: bytes) -> np.ndarray:
    """Radiance RGBE (flat or new-style run-length encoded scanlines, ``-Y H +X W``)."""
    end = data.find(b"\n\n")
    if not data.startswith(b"#?") or end < 0:
        raise ValueError("not a Radiance file")
    nl = data.index(b"\n", end + 2)
    m = re.fullmatch(rb"-Y (\d+) \+X (\d+)", data[end + 2:nl].strip())
    if not m:
        raise ValueError("only -Y H +X W orientation is read")
    h, w = int(m.group(1)), int(m.group(2))
    buf = np.frombuffer(data, np.uint8, offset=nl + 1)
    out = np.zeros((h, w, 4), np.uint8)
    pos = 0
    for y in range(h):
        if 8 <= w < 32768 and buf[pos] == 2 and buf[pos + 1] == 2 and not buf[pos + 2] & 0x80:
            pos += 4
            for c in range(4):
                x = 0
                while x < w:
                    n = int(buf[pos])
                    pos += 1
                    if n > 128:
                        out[y, x:x + n - 128, c] = buf[pos]
                        pos += 1
                        x += n - 128
                    else:
                        out[y, x:x + n, c] = buf[pos:pos + n]
                        pos += n
                        x += n
        else:
            out[y] = buf[pos:pos + 4 * w].reshape(w, 4)
            pos += 4 * w
    e = out[..., 3].astype(np.int32)
    f = np.where(e > 0, np.ldexp(1.0, e - 136), 0.0)
    return (out[..., :3] * f[..., None]).astype(np.float32)
