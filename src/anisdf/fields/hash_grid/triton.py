"""Hash-grid encoding for CUDA in Triton: the same function as :func:`hash_encode_reference`, fused.

Why Triton: it ships with every Linux CUDA build of PyTorch, so the fast path needs no CUDA compiler and no
tiny-cuda-nn build on the user's machine; kernels are compiled on first use and cached by Triton. With
``TRITON_INTERPRET=1`` the very same kernels run on CPU tensors, which is how CI (no GPU) checks them against the
reference, values, gradients and the eikonal double backward included.

The three entry points have the signatures of the compiled CPU kernel (``kernels/hashgrid_cpu.cpp``), so the
autograd Functions of :mod:`anisdf.fields.hash_grid.ops` drive either. Math (w_k: trilinear weight of
corner k, t_k: its table row, R: the level's resolution, g: incoming gradient of one level):

* forward: ``out = sum_k w_k t_k``
* backward: ``grad_table[row_k] += w_k g`` (atomic adds), ``grad_x += R sum_k <t_k, g> dw_k/dfrac``
* double backward: with ``v_k = R sum_d ggx_d dw_k/dfrac_d``:
  ``d/dg = sum_k v_k t_k + sum_k w_k ggt_k``, ``d/dt_k += v_k g`` and
  ``d/dx_e = R sum_k <ggt_k, g> dw_k/dfrac_e + R^2 sum_k <t_k, g> sum_{d != e} ggx_d d2w_k/dfrac_d dfrac_e``.

One program encodes ``BLOCK`` points through all levels, so per-point outputs (``grad_x``) need no atomics;
only the scatters into a table gradient do. Float atomics make GPU table gradients order-dependent in the last
bits (as in tiny-cuda-nn); the CPU kernel stays bit-exact.
"""

from __future__ import annotations

import os

import torch
import triton
import triton.language as tl
from torch import Tensor

# Points per program. The interpreter (TRITON_INTERPRET=1, CPU) runs a program's operations one by one in NumPy,
# so there fewer, larger programs are much faster; the arithmetic is the same for any block size.
BLOCK = 1024 if os.environ.get("TRITON_INTERPRET") == "1" else 128
NUM_WARPS = 4


@triton.jit
def _cell(p, res, maxbase):
    """Lower cell corner (uint32) and fraction of coordinate ``p`` (as the reference: clamp(floor(p*R), 0, R-1)).

    NaN maps to the first cell, so a bad point never reads outside the table.
    """
    pos = p * res
    b = tl.floor(pos)
    b = tl.where(b >= 0.0, b, 0.0)
    b = tl.where(b > maxbase, maxbase, b)
    return b.to(tl.int32).to(tl.uint32), pos - b


@triton.jit
def _level_cells(levels_ptr, lvl, px, py, pz):
    """Level ``lvl``'s resolution, dense stride, hashed flag and table offset, and the points' cells in it."""
    r = tl.load(levels_ptr + 3 * lvl)
    hashed = tl.load(levels_ptr + 3 * lvl + 1) != 0
    off = tl.load(levels_ptr + 3 * lvl + 2)
    res = r.to(tl.float32)
    maxbase = tl.maximum(r - 1, 0).to(tl.float32)
    bx, fx = _cell(px, res, maxbase)
    by, fy = _cell(py, res, maxbase)
    bz, fz = _cell(pz, res, maxbase)
    return res, (r + 1).to(tl.uint32), hashed, off, bx, by, bz, fx, fy, fz


@triton.jit
def _corner(bx, by, bz, fx, fy, fz, stride, hashed, hash_mask, off, K: tl.constexpr):
    """Table row (int64), weight, d weight / d frac (x, y, z) and the mixed second derivatives (xy, xz, yz) of
    corner ``K`` (bits: x, y, z). The weight is linear in each coordinate, so no other second derivative exists."""
    IX: tl.constexpr = K & 1
    IY: tl.constexpr = (K >> 1) & 1
    IZ: tl.constexpr = (K >> 2) & 1
    cx = bx + IX
    cy = by + IY
    cz = bz + IZ
    h = (cx ^ (cy * 2654435761) ^ (cz * 805459861)) & hash_mask
    d = cx + cy * stride + cz * (stride * stride)
    row = off + tl.where(hashed, h, d).to(tl.int64)
    wx = fx if IX else 1.0 - fx
    wy = fy if IY else 1.0 - fy
    wz = fz if IZ else 1.0 - fz
    sx: tl.constexpr = 1.0 if IX else -1.0
    sy: tl.constexpr = 1.0 if IY else -1.0
    sz: tl.constexpr = 1.0 if IZ else -1.0
    return row, wx * wy * wz, sx * wy * wz, sy * wx * wz, sz * wx * wy, (sx * sy) * wz, (sx * sz) * wy, (sy * sz) * wx


@triton.jit
def _points(x_ptr, N, BLOCK_: tl.constexpr):
    n = (tl.program_id(0) * BLOCK_ + tl.arange(0, BLOCK_)).to(tl.int64)
    m = n < N
    px, py, pz = _load3(x_ptr, n, m)
    return n, m, px, py, pz


@triton.jit
def _load3(ptr, n, m):
    return (tl.load(ptr + 3 * n, mask=m, other=0.0), tl.load(ptr + 3 * n + 1, mask=m, other=0.0),
            tl.load(ptr + 3 * n + 2, mask=m, other=0.0))


@triton.jit
def _zeros3(BLOCK_: tl.constexpr):
    return (tl.zeros((BLOCK_,), dtype=tl.float32), tl.zeros((BLOCK_,), dtype=tl.float32),
            tl.zeros((BLOCK_,), dtype=tl.float32))


@triton.jit
def _store3(ptr, n, m, a, b, c):
    tl.store(ptr + 3 * n, a, mask=m)
    tl.store(ptr + 3 * n + 1, b, mask=m)
    tl.store(ptr + 3 * n + 2, c, mask=m)


@triton.jit
def _forward_kernel(x_ptr, table_ptr, levels_ptr, out_ptr, N, L, hash_mask,
                    F: tl.constexpr, BLOCK_: tl.constexpr):
    n, m, px, py, pz = _points(x_ptr, N, BLOCK_)
    fr = tl.arange(0, F)
    m2 = m[:, None]
    for lvl in range(L):
        res, stride, hashed, off, bx, by, bz, fx, fy, fz = _level_cells(levels_ptr, lvl, px, py, pz)
        acc = tl.zeros((BLOCK_, F), dtype=tl.float32)
        for k in tl.static_range(8):
            row, w, _, _, _, _, _, _ = _corner(bx, by, bz, fx, fy, fz, stride, hashed, hash_mask, off, k)
            t = tl.load(table_ptr + row[:, None] * F + fr[None, :], mask=m2, other=0.0)
            acc += w[:, None] * t
        tl.store(out_ptr + n[:, None] * (L * F) + lvl * F + fr[None, :], acc, mask=m2)


@triton.jit
def _backward_kernel(x_ptr, table_ptr, levels_ptr, g_ptr, gt_ptr, gx_ptr, N, L, hash_mask,
                     F: tl.constexpr, NEED_T: tl.constexpr, NEED_X: tl.constexpr, BLOCK_: tl.constexpr):
    n, m, px, py, pz = _points(x_ptr, N, BLOCK_)
    fr = tl.arange(0, F)
    m2 = m[:, None]
    ax, ay, az = _zeros3(BLOCK_)
    for lvl in range(L):
        res, stride, hashed, off, bx, by, bz, fx, fy, fz = _level_cells(levels_ptr, lvl, px, py, pz)
        g = tl.load(g_ptr + n[:, None] * (L * F) + lvl * F + fr[None, :], mask=m2, other=0.0)
        lx, ly, lz = _zeros3(BLOCK_)
        for k in tl.static_range(8):
            row, w, dwx, dwy, dwz, _, _, _ = _corner(bx, by, bz, fx, fy, fz, stride, hashed, hash_mask, off, k)
            rp = row[:, None] * F + fr[None, :]
            if NEED_T:
                tl.atomic_add(gt_ptr + rp, w[:, None] * g, mask=m2)
            if NEED_X:
                s = tl.sum(tl.load(table_ptr + rp, mask=m2, other=0.0) * g, axis=1)
                lx += s * dwx
                ly += s * dwy
                lz += s * dwz
        if NEED_X:
            ax += res * lx
            ay += res * ly
            az += res * lz
    if NEED_X:
        _store3(gx_ptr, n, m, ax, ay, az)


@triton.jit
def _double_kernel(x_ptr, table_ptr, levels_ptr, g_ptr, ggx_ptr, ggt_ptr, og_ptr, ot_ptr, ox_ptr,
                   N, L, hash_mask, F: tl.constexpr, HAS_GGX: tl.constexpr, HAS_GGT: tl.constexpr,
                   OUT_G: tl.constexpr, OUT_T: tl.constexpr, OUT_X: tl.constexpr, BLOCK_: tl.constexpr):
    n, m, px, py, pz = _points(x_ptr, N, BLOCK_)
    fr = tl.arange(0, F)
    m2 = m[:, None]
    ex, ey, ez = _zeros3(BLOCK_)
    qx, qy, qz = _zeros3(BLOCK_)
    if HAS_GGX:
        qx, qy, qz = _load3(ggx_ptr, n, m)
    for lvl in range(L):
        res, stride, hashed, off, bx, by, bz, fx, fy, fz = _level_cells(levels_ptr, lvl, px, py, pz)
        gp = n[:, None] * (L * F) + lvl * F + fr[None, :]
        g = tl.load(g_ptr + gp, mask=m2, other=0.0)
        gx_ = res * qx
        gy_ = res * qy
        gz_ = res * qz
        acc_g = tl.zeros((BLOCK_, F), dtype=tl.float32)
        sxy, sxz, syz = _zeros3(BLOCK_)  # mixed second derivatives of the interpolant of <t, g>
        ax, ay, az = _zeros3(BLOCK_)
        for k in tl.static_range(8):
            row, w, dwx, dwy, dwz, dxy, dxz, dyz = _corner(bx, by, bz, fx, fy, fz, stride, hashed, hash_mask, off, k)
            rp = row[:, None] * F + fr[None, :]
            if HAS_GGX:
                v = gx_ * dwx + gy_ * dwy + gz_ * dwz  # R * (change of w_k along ggx)
                if OUT_G or OUT_X:
                    t = tl.load(table_ptr + rp, mask=m2, other=0.0)
                    acc_g += v[:, None] * t
                    if OUT_X:
                        s = tl.sum(t * g, axis=1)
                        sxy += s * dxy
                        sxz += s * dxz
                        syz += s * dyz
                if OUT_T:
                    tl.atomic_add(ot_ptr + rp, v[:, None] * g, mask=m2)
            if HAS_GGT:
                u = tl.load(ggt_ptr + rp, mask=m2, other=0.0)
                acc_g += w[:, None] * u
                if OUT_X:
                    s2 = tl.sum(u * g, axis=1)
                    ax += s2 * dwx
                    ay += s2 * dwy
                    az += s2 * dwz
        if OUT_G:
            tl.store(og_ptr + gp, acc_g, mask=m2)
        if OUT_X:
            # gx_ .. gz_ carry one factor R; the second comes from d frac / dx.
            ex += res * (ax + gy_ * sxy + gz_ * sxz)
            ey += res * (ay + gx_ * sxy + gz_ * syz)
            ez += res * (az + gx_ * sxz + gy_ * syz)
    if OUT_X:
        _store3(ox_ptr, n, m, ex, ey, ez)


# ------------------------------------------------------------------------------------------ entry points
def _check(x: Tensor, table: Tensor, levels: Tensor, log2_size: int) -> tuple[int, int, int, int]:
    if x.dtype != torch.float32 or table.dtype != torch.float32:
        raise TypeError("hash_grid.triton: float32 points and table only")
    if x.dim() != 2 or x.shape[1] != 3 or table.dim() != 2:
        raise ValueError(f"hash_grid.triton: x must be [N, 3] and table [T, F], got {tuple(x.shape)}, "
                         f"{tuple(table.shape)}")
    if not (x.device == table.device == levels.device):
        raise ValueError("hash_grid.triton: x, table and levels must be on one device")
    f = table.shape[1]
    if f not in (1, 2, 4, 8) or not 1 <= log2_size <= 31:
        raise ValueError("hash_grid.triton: features per level must be 1, 2, 4 or 8 and log2 T in 1..31")
    return x.shape[0], levels.shape[0], f, (1 << log2_size) - 1


def _grid(n: int) -> tuple[int]:
    return (max(triton.cdiv(n, BLOCK), 1),)


def _grad_input(t: Tensor, shape: tuple[int, int]) -> Tensor:
    t = t.to(torch.float32).contiguous()
    if tuple(t.shape) != shape:
        raise ValueError(f"hash_grid.triton: gradient of shape {tuple(t.shape)}, expected {shape}")
    return t


def encode_forward(x: Tensor, table: Tensor, levels: Tensor, log2_size: int) -> Tensor:
    """``out[N, L*F] = hash_encode(x, table)``."""
    n, nl, f, mask = _check(x, table, levels, log2_size)
    x, table = x.contiguous(), table.contiguous()
    out = torch.empty(n, nl * f, device=x.device, dtype=torch.float32)
    if n:
        _forward_kernel[_grid(n)](x, table, levels, out, n, nl, mask, F=f, BLOCK_=BLOCK, num_warps=NUM_WARPS)
    return out


def encode_backward(g: Tensor, x: Tensor, table: Tensor, levels: Tensor, log2_size: int, need_table: bool,
                    need_x: bool, mode: int = 0) -> list[Tensor | None]:
    """``(grad_table, grad_x)`` of the encoding for the incoming gradient ``g`` [N, L*F]; None where not needed.

    ``mode`` exists for signature parity with the CPU kernel and is ignored.
    """
    n, nl, f, mask = _check(x, table, levels, log2_size)
    x, table = x.contiguous(), table.contiguous()
    g = _grad_input(g, (n, nl * f))
    gt = torch.zeros_like(table) if need_table else None
    gx = torch.zeros(n, 3, device=x.device, dtype=torch.float32) if need_x else None
    if n and (need_table or need_x):
        _backward_kernel[_grid(n)](x, table, levels, g, table if gt is None else gt, x if gx is None else gx,
                                   n, nl, mask, F=f, NEED_T=need_table, NEED_X=need_x, BLOCK_=BLOCK,
                                   num_warps=NUM_WARPS)
    return [gt, gx]


def encode_double_backward(g: Tensor, x: Tensor, table: Tensor, ggx: Tensor | None, ggt: Tensor | None,
                           levels: Tensor, log2_size: int, need_g: bool, need_table: bool,
                           need_x: bool) -> list[Tensor | None]:
    """``(d/dg, d/dtable, d/dx)`` of ``<ggt, grad_table> + <ggx, grad_x>``; None where not needed."""
    n, nl, f, mask = _check(x, table, levels, log2_size)
    x, table = x.contiguous(), table.contiguous()
    g = _grad_input(g, (n, nl * f))
    has_gx, has_gt = ggx is not None, ggt is not None
    ggx = _grad_input(ggx, (n, 3)) if has_gx else x
    ggt = _grad_input(ggt, tuple(table.shape)) if has_gt else table
    og = torch.zeros(n, nl * f, device=x.device, dtype=torch.float32) if need_g else None
    ot = torch.zeros_like(table) if need_table else None
    ox = torch.zeros(n, 3, device=x.device, dtype=torch.float32) if need_x else None
    out_t = need_table and has_gx  # the table enters the backward's outputs only through grad_x
    if n and (has_gx or has_gt) and (need_g or out_t or need_x):
        _double_kernel[_grid(n)](x, table, levels, g, ggx, ggt, g if og is None else og,
                                 table if ot is None else ot, x if ox is None else ox, n, nl, mask, F=f,
                                 HAS_GGX=has_gx, HAS_GGT=has_gt, OUT_G=need_g, OUT_T=out_t, OUT_X=need_x,
                                 BLOCK_=BLOCK, num_warps=NUM_WARPS)
    return [og, ot, ox]
