// CPU multiresolution hash-grid encoding (Mueller et al. 2022) for anisdf.
//
// Computes exactly the function of anisdf/fields/hash_grid/reference.py::hash_encode_reference and its first and
// second derivatives (w_k: trilinear weight of corner k, t_k: its table row, R: the level's resolution):
//   forward          out[n, l*F + f] = sum_k w_k(frac) t_k[f]
//   backward         grad_table[row_k] += w_k g ;  grad_x += R sum_k <t_k, g> dw_k/dfrac
//   double backward  derivatives of (grad_table, grad_x) with respect to (g, table, x), including the
//                    second derivative of the trilinear weights with respect to x (exact, unlike torch-ngp).
//   with Jacobian    out and jac[n, l*F + f, :] = R sum_k t_k[f] dw_k/dfrac in one sweep, and the table gradient
//                    of both in one scatter (the analytic normal's route in training: no double backward).
//
// Memory layout of the work: every pass walks one level at a time over many points, so that level's slice of
// the table (at most 2^log2 rows, 4 MiB for log2 = 19, F = 2) stays in cache (measured 2.5x faster than all
// levels of one point after another), and works in chunks of kChunk points: first the cells of the whole chunk
// are located (a loop the compiler vectorises), and for large slices their table rows prefetched, then the rows
// are read. Prefetching measured 1.1-1.2x faster at log2 = 19 and 1.3-2x at log2 = 22, but 10% slower for
// slices that fit the L2 cache, so it is used only for slices above kPrefetchBytes.
//
// Threads (OpenMP, the same libgomp runtime as torch): passes that only write per-point outputs split the
// points between threads. Passes that scatter into a table gradient give every thread whole levels, so no two
// threads ever write the same table row and no atomics are needed (each thread keeps its own grad_x partial
// sum); this uses at most L threads. Atomic adds over split points (mode 2) are kept for comparison only: they
// measured 7x slower on 2 cores.

#include <torch/extension.h>

#include <ATen/Parallel.h>
#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <memory>
#include <optional>
#include <vector>

namespace {

constexpr uint32_t kPrimeY = 2654435761u;
constexpr uint32_t kPrimeZ = 805459861u;
constexpr int kChunk = 32;
constexpr int64_t kPrefetchBytes = int64_t(1) << 19;

struct Level {
  float res;        // R_l as a float, the scale from [0, 1] to grid units
  float maxbase;    // max(R_l - 1, 0): the lower corner of the last cell
  uint32_t stride;  // R_l + 1, dense row stride
  uint32_t hashed;  // 1: spatial hash, 0: dense index
  int64_t offset;   // first table row of this level
};

// Cells of kChunk points of one level, structure-of-arrays so that locate() vectorises.
struct Chunk {
  alignas(32) float px[3][kChunk];      // the points
  alignas(32) float f[3][kChunk];       // fractional position in the cell
  alignas(32) float w[8][kChunk];       // trilinear weights of the 8 corners
  alignas(32) uint32_t idx[8][kChunk];  // corner rows, relative to the level's offset
  int64_t n[kChunk];                    // point index
};

// Lower cell corner, fraction, corner rows and weights, exactly as corner_indices/trilinear_weights do.
inline void locate(Chunk& c, const Level& lv, uint32_t mask) {
  alignas(32) uint32_t b[3][kChunk];
  const float res = lv.res, maxbase = lv.maxbase;  // locals: c.f could alias lv, which blocks vectorising
  for (int d = 0; d < 3; ++d) {
    for (int i = 0; i < kChunk; ++i) {
      const float pos = c.px[d][i] * res;
      float bf = std::floor(pos);
      bf = bf >= 0.f ? bf : 0.f;  // also maps NaN to the first cell: never read out of bounds
      bf = bf > maxbase ? maxbase : bf;
      b[d][i] = static_cast<uint32_t>(static_cast<int32_t>(bf));
      c.f[d][i] = pos - bf;
    }
  }
  if (lv.hashed) {
    for (int i = 0; i < kChunk; ++i) {
      const uint32_t x0 = b[0][i], x1 = x0 + 1u;
      const uint32_t y0 = b[1][i] * kPrimeY, y1 = y0 + kPrimeY;
      const uint32_t z0 = b[2][i] * kPrimeZ, z1 = z0 + kPrimeZ;
      c.idx[0][i] = (x0 ^ y0 ^ z0) & mask;
      c.idx[1][i] = (x1 ^ y0 ^ z0) & mask;
      c.idx[2][i] = (x0 ^ y1 ^ z0) & mask;
      c.idx[3][i] = (x1 ^ y1 ^ z0) & mask;
      c.idx[4][i] = (x0 ^ y0 ^ z1) & mask;
      c.idx[5][i] = (x1 ^ y0 ^ z1) & mask;
      c.idx[6][i] = (x0 ^ y1 ^ z1) & mask;
      c.idx[7][i] = (x1 ^ y1 ^ z1) & mask;
    }
  } else {
    const uint32_t s = lv.stride, s2 = lv.stride * lv.stride;
    for (int i = 0; i < kChunk; ++i) {
      const uint32_t base = b[0][i] + b[1][i] * s + b[2][i] * s2;
      c.idx[0][i] = base;
      c.idx[1][i] = base + 1u;
      c.idx[2][i] = base + s;
      c.idx[3][i] = base + s + 1u;
      c.idx[4][i] = base + s2;
      c.idx[5][i] = base + s2 + 1u;
      c.idx[6][i] = base + s2 + s;
      c.idx[7][i] = base + s2 + s + 1u;
    }
  }
  for (int i = 0; i < kChunk; ++i) {
    const float fx = c.f[0][i], fy = c.f[1][i], fz = c.f[2][i];
    const float gx = 1.f - fx, gy = 1.f - fy, gz = 1.f - fz;
    c.w[0][i] = gx * gy * gz;
    c.w[1][i] = fx * gy * gz;
    c.w[2][i] = gx * fy * gz;
    c.w[3][i] = fx * fy * gz;
    c.w[4][i] = gx * gy * fz;
    c.w[5][i] = fx * gy * fz;
    c.w[6][i] = gx * fy * fz;
    c.w[7][i] = fx * fy * fz;
  }
}

// d w_k / d frac_d of point i of the chunk (without the factor R).
inline void weight_grads(const Chunk& c, int i, float dw[8][3]) {
  const float wx[2] = {1.f - c.f[0][i], c.f[0][i]};
  const float wy[2] = {1.f - c.f[1][i], c.f[1][i]};
  const float wz[2] = {1.f - c.f[2][i], c.f[2][i]};
  for (int k = 0; k < 8; ++k) {
    const int ix = k & 1, iy = (k >> 1) & 1, iz = (k >> 2) & 1;
    dw[k][0] = (ix ? 1.f : -1.f) * wy[iy] * wz[iz];
    dw[k][1] = (iy ? 1.f : -1.f) * wx[ix] * wz[iz];
    dw[k][2] = (iz ? 1.f : -1.f) * wx[ix] * wy[iy];
  }
}

// Points n0 .. n1-1 of one level in chunks: locate, prefetch(c, i) for every point of the chunk (if the level's
// slice is larger than kPrefetchBytes), then body(c, i). The tail chunk is padded with copies of its last point.
template <int F, class Prefetch, class Body>
inline void sweep(const float* __restrict__ x, const Level& lv, uint32_t mask, int64_t n0, int64_t n1,
                  Prefetch&& prefetch, Body&& body) {
  const int64_t rows = lv.hashed ? int64_t(mask) + 1 : int64_t(lv.stride) * lv.stride * lv.stride;
  const bool use_prefetch = rows * F * static_cast<int64_t>(sizeof(float)) > kPrefetchBytes;
  Chunk c;
  for (int64_t b = n0; b < n1; b += kChunk) {
    const int m = static_cast<int>(std::min<int64_t>(kChunk, n1 - b));
    for (int i = 0; i < kChunk; ++i) {
      const int64_t n = b + (i < m ? i : m - 1);
      c.n[i] = n;
      for (int d = 0; d < 3; ++d) c.px[d][i] = x[3 * n + d];
    }
    locate(c, lv, mask);
    if (use_prefetch)
      for (int i = 0; i < m; ++i) prefetch(c, i);
    for (int i = 0; i < m; ++i) body(c, i);
  }
}

template <int F>
inline void prefetch_rows(const Chunk& c, int i, const float* base, bool for_write) {
  for (int k = 0; k < 8; ++k) {
    const float* p = base + int64_t(c.idx[k][i]) * F;
    if (for_write) __builtin_prefetch(p, 1, 3);
    else __builtin_prefetch(p, 0, 3);
  }
}

std::vector<Level> make_levels(const torch::Tensor& levels) {
  TORCH_CHECK(levels.device().is_cpu() && levels.scalar_type() == torch::kInt64 && levels.dim() == 2 &&
                  levels.size(1) == 3,
              "hashgrid_cpu: levels must be a CPU int64 tensor [L, 3] of (resolution, hashed, offset)");
  auto a = levels.contiguous();
  const int64_t* p = a.data_ptr<int64_t>();
  std::vector<Level> out(a.size(0));
  for (int64_t l = 0; l < a.size(0); ++l) {
    const int64_t r = p[3 * l];
    TORCH_CHECK(r >= 0 && r < (1 << 20), "hashgrid_cpu: resolution ", r, " out of range 0..2^20");
    out[l].res = static_cast<float>(r);
    out[l].maxbase = static_cast<float>(std::max<int64_t>(r - 1, 0));
    out[l].stride = static_cast<uint32_t>(r + 1);
    out[l].hashed = p[3 * l + 1] ? 1u : 0u;
    out[l].offset = p[3 * l + 2];
  }
  return out;
}

void check_inputs(const torch::Tensor& x, const torch::Tensor& table, const std::vector<Level>& lv,
                  int64_t log2_size) {
  TORCH_CHECK(x.device().is_cpu() && table.device().is_cpu(), "hashgrid_cpu: CPU tensors only");
  TORCH_CHECK(x.scalar_type() == torch::kFloat32 && table.scalar_type() == torch::kFloat32,
              "hashgrid_cpu: float32 points and table only");
  TORCH_CHECK(x.dim() == 2 && x.size(1) == 3, "hashgrid_cpu: x must be [N, 3]");
  TORCH_CHECK(table.dim() == 2, "hashgrid_cpu: table must be [T, F]");
  TORCH_CHECK(log2_size >= 1 && log2_size <= 31, "hashgrid_cpu: log2_hashmap_size must be in 1..31");
  const int64_t cap = int64_t(1) << log2_size;
  for (const auto& l : lv) {
    const int64_t s = l.stride;
    const int64_t size = l.hashed ? cap : s * s * s;
    TORCH_CHECK(l.hashed || s * s * s <= cap, "hashgrid_cpu: a dense level does not fit the hash map size");
    TORCH_CHECK(l.offset >= 0 && l.offset + size <= table.size(0), "hashgrid_cpu: table has too few rows for the spec");
  }
}

int num_threads(int64_t work) { return work < 8192 ? 1 : std::max(1, at::get_num_threads()); }

inline void atomic_add(float* p, float v) {
#pragma omp atomic
  *p += v;
}

// Per-point rows [N, L, F] (the layout of the encoding and of its gradient) are staged level-major [L, N, F]
// while a pass runs: writing or reading a strided [N, L*F] array one level at a time touches every cache line
// L times, which measured up to 25% of the forward's time; the blocked transposes below touch each line once.

// dst[l][n] = src[n][l] for levels l0, l0 + lstep, ... and points [n0, n1).
template <int F>
void to_level_major(const float* __restrict__ src, float* __restrict__ dst, int64_t N, int L, int l0, int lstep,
                    int64_t n0, int64_t n1) {
  constexpr int64_t kB = 64;
  for (int64_t b = n0; b < n1; b += kB) {
    const int64_t e = std::min(b + kB, n1);
    for (int l = l0; l < L; l += lstep)
      for (int64_t n = b; n < e; ++n)
        for (int f = 0; f < F; ++f) dst[(l * N + n) * F + f] = src[(n * L + l) * F + f];
  }
}

// dst[n][l] = src[l][n] for all levels and points [n0, n1).
template <int F>
void to_point_major(const float* __restrict__ src, float* __restrict__ dst, int64_t N, int L, int64_t n0,
                    int64_t n1) {
  for (int64_t n = n0; n < n1; ++n)
    for (int l = 0; l < L; ++l)
      for (int f = 0; f < F; ++f) dst[(n * L + l) * F + f] = src[(l * N + n) * F + f];
}

// Runs a pass over every (point, level) pair on the threads, in one of two ways:
//  * by_levels = false: thread t takes the points [n0, n1) and all levels:
//      pre(0, 1, n0, n1); visit(l, n0, n1, gx) for each level; post(n0, n1).
//  * by_levels = true (the passes that scatter into a table gradient): thread t takes the levels t, t + T, ...
//    and all points:
//      pre(t, T, 0, N); visit(l, 0, N, gx_t) for each of its levels; barrier; post(its share of points).
//    gx_t is the thread's own [N, 3] grad_x buffer; they are summed into gx at the end.
// gx may be null (no grad_x output).
template <class Pre, class Visit, class Post>
void run_pass(int64_t N, int L, bool by_levels, float* gx, Pre&& pre, Visit&& visit, Post&& post) {
  const int nt = num_threads(N * L);
  if (!by_levels) {
#pragma omp parallel num_threads(nt)
    {
      const int t = omp_get_thread_num(), T = omp_get_num_threads();
      const int64_t n0 = N * t / T, n1 = N * (t + 1) / T;
      pre(0, 1, n0, n1);
      for (int l = 0; l < L; ++l) visit(l, n0, n1, gx);
      post(n0, n1);
    }
    return;
  }
  const int T = std::min(nt, L);
  std::vector<float> partial;
  if (gx != nullptr && T > 1) partial.assign(static_cast<size_t>(T - 1) * N * 3, 0.f);
#pragma omp parallel num_threads(T)
  {
    const int t = omp_get_thread_num(), TT = omp_get_num_threads();
    float* my_gx = gx == nullptr ? nullptr : (t == 0 ? gx : partial.data() + (t - 1) * N * 3);
    pre(t, TT, int64_t(0), N);
    for (int l = t; l < L; l += TT) visit(l, int64_t(0), N, my_gx);
#pragma omp barrier
    post(N * t / TT, N * (t + 1) / TT);
    if (gx != nullptr && TT > 1) {
#pragma omp for schedule(static)
      for (int64_t i = 0; i < N * 3; ++i) {
        float s = gx[i];
        for (int u = 0; u < TT - 1; ++u) s += partial[u * N * 3 + i];
        gx[i] = s;
      }
    }
  }
}

inline float* alloc_floats(std::unique_ptr<float[]>& hold, int64_t n) {
  hold.reset(new float[static_cast<size_t>(std::max<int64_t>(n, 1))]);
  return hold.get();
}

// --------------------------------------------------------------------------------------------- forward
template <int F>
void forward_impl(const float* __restrict__ x, const float* __restrict__ table, float* __restrict__ out,
                  int64_t N, const std::vector<Level>& lv, uint32_t mask) {
  const int L = static_cast<int>(lv.size());
  std::unique_ptr<float[]> hold;
  float* stage = alloc_floats(hold, N * L * F);  // [L, N, F]
  run_pass(
      N, L, false, nullptr, [](int, int, int64_t, int64_t) {},
      [&](int l, int64_t n0, int64_t n1, float*) {
        const Level& level = lv[l];
        const float* tl = table + level.offset * F;
        float* ol = stage + l * N * F;
        sweep<F>(
            x, level, mask, n0, n1, [&](const Chunk& c, int i) { prefetch_rows<F>(c, i, tl, false); },
            [&](const Chunk& c, int i) {
              float acc[F] = {};
              for (int k = 0; k < 8; ++k) {
                const float* row = tl + int64_t(c.idx[k][i]) * F;
                for (int f = 0; f < F; ++f) acc[f] += c.w[k][i] * row[f];
              }
              float* o = ol + c.n[i] * F;
              for (int f = 0; f < F; ++f) o[f] = acc[f];
            });
      },
      [&](int64_t n0, int64_t n1) { to_point_major<F>(stage, out, N, L, n0, n1); });
}

// -------------------------------------------------------------------------------------------- backward
// One point of one level (gl: the level's incoming gradient [N, F]): scatter w_k g into the table gradient gtl
// (if kTable) and add R sum_k <t_k, g> dw_k/dfrac to gx (if kX).
template <int F, bool kTable, bool kX>
inline void backward_point(const Chunk& c, int i, const Level& level, const float* __restrict__ gl,
                           const float* __restrict__ tl, float* __restrict__ gtl, float* __restrict__ gx,
                           bool atomic) {
  const int64_t n = c.n[i];
  float gv[F];
  for (int f = 0; f < F; ++f) gv[f] = gl[n * F + f];
  if (kTable) {
    for (int k = 0; k < 8; ++k) {
      float* row = gtl + int64_t(c.idx[k][i]) * F;
      const float w = c.w[k][i];
      for (int f = 0; f < F; ++f) {
        if (atomic) atomic_add(row + f, w * gv[f]);
        else row[f] += w * gv[f];
      }
    }
  }
  if (kX) {
    float dw[8][3];
    weight_grads(c, i, dw);
    float acc[3] = {0.f, 0.f, 0.f};
    for (int k = 0; k < 8; ++k) {
      const float* row = tl + int64_t(c.idx[k][i]) * F;
      float s = 0.f;
      for (int f = 0; f < F; ++f) s += row[f] * gv[f];
      for (int d = 0; d < 3; ++d) acc[d] += s * dw[k][d];
    }
    float* gr = gx + 3 * n;
    for (int d = 0; d < 3; ++d) gr[d] += level.res * acc[d];
  }
}

// Passes that scatter into a table gradient and also read table rows: one pass touching two random-access
// arrays, or two passes touching one each (locating the cells twice)? Measured on one core (F = 2, 16 levels):
// one pass is 1.5x faster for log2 <= 15, even at 17, and two passes are 1.15x faster at 19 and 1.7x at 22,
// so two passes once a level's slice outgrows the L2 cache (taken as 1 MiB).
template <int F>
bool two_passes(uint32_t mask) {
  return (static_cast<int64_t>(mask) + 1) * F * static_cast<int64_t>(sizeof(float)) > (int64_t(1) << 20);
}

// mode: 0 or 1 whole levels per thread (no atomics); 2 split points with atomic adds (slower, for comparison).
template <int F, bool kTable, bool kX>
void backward_run(const float* x, const float* g, const float* table, float* gt, float* gx, int64_t N,
                  const std::vector<Level>& lv, uint32_t mask, int mode) {
  const int L = static_cast<int>(lv.size());
  const bool by_levels = kTable && mode != 2;
  const bool atomic = kTable && !by_levels && num_threads(N * L) > 1;
  std::unique_ptr<float[]> hold;
  float* gs = alloc_floats(hold, N * L * F);  // g, level-major
  run_pass(
      N, L, by_levels, gx,
      [&](int l0, int lstep, int64_t n0, int64_t n1) { to_level_major<F>(g, gs, N, L, l0, lstep, n0, n1); },
      [&](int l, int64_t n0, int64_t n1, float* gxp) {
        const Level& level = lv[l];
        const float* tl = table + level.offset * F;
        float* gtl = kTable ? gt + level.offset * F : nullptr;
        const float* gl = gs + l * N * F;
        sweep<F>(
            x, level, mask, n0, n1,
            [&](const Chunk& c, int i) {
              if (kTable) prefetch_rows<F>(c, i, gtl, true);
              if (kX) prefetch_rows<F>(c, i, tl, false);
            },
            [&](const Chunk& c, int i) { backward_point<F, kTable, kX>(c, i, level, gl, tl, gtl, gxp, atomic); });
      },
      [](int64_t, int64_t) {});
}

template <int F>
void backward_impl(const float* x, const float* g, const float* table, float* gt, float* gx, int64_t N,
                   const std::vector<Level>& lv, uint32_t mask, int mode) {
  if (gt && gx && !two_passes<F>(mask)) {
    backward_run<F, true, true>(x, g, table, gt, gx, N, lv, mask, mode);
  } else {
    if (gt) backward_run<F, true, false>(x, g, table, gt, nullptr, N, lv, mask, mode);
    if (gx) backward_run<F, false, true>(x, g, table, nullptr, gx, N, lv, mask, mode);
  }
}

// ------------------------------------------------------------------------------------- double backward
// The backward's outputs: A = grad_table (A[row_k] += w_k g), B = grad_x (B = R sum_k <t_k, g> dw_k/dfrac).
// Incoming: ggt = dLoss/dA [T, F] (optional), ggx = dLoss/dB [N, 3] (optional). With
// v_k = R sum_d ggx_d dw_k/dfrac_d (the change of w_k along ggx):
//   dLoss/dg[f]      = sum_k v_k t_k[f] + sum_k w_k ggt_k[f]
//   dLoss/dt_k      += v_k g                                        (a scatter into the table gradient)
//   dLoss/dx_e       = R sum_k <ggt_k, g> dw_k/dfrac_e + R^2 sum_k <t_k, g> sum_{d != e} ggx_d d2w_k/dfrac_d dfrac_e
// (w_k is linear in each coordinate, so only the mixed second derivatives are non-zero).
struct DoubleArgs {
  const float* x;
  const float* g;
  const float* table;
  const float* ggx;  // may be null
  const float* ggt;  // may be null
  float* out_g;      // may be null
  float* out_t;      // may be null (always null when ggx is)
  float* out_x;      // may be null
};

// One point of one level; gl/ogl: the level's slices [N, F] of g and of dLoss/dg (level-major). The flags say
// which inputs are present and which outputs are wanted (kOutT implies kGGX).
template <int F, bool kGGX, bool kGGT, bool kOutG, bool kOutT, bool kOutX>
inline void double_point(const Chunk& c, int i, const Level& level, const DoubleArgs& a,
                         const float* __restrict__ gl, float* __restrict__ ogl, float* __restrict__ gx) {
  const int64_t n = c.n[i];
  const float R = level.res;
  float gv[F];
  for (int f = 0; f < F; ++f) gv[f] = gl[n * F + f];
  const float fx = c.f[0][i], fy = c.f[1][i], fz = c.f[2][i];
  const float wx[2] = {1.f - fx, fx}, wy[2] = {1.f - fy, fy}, wz[2] = {1.f - fz, fz};
  float gg[3] = {0.f, 0.f, 0.f};
  if (kGGX)
    for (int d = 0; d < 3; ++d) gg[d] = R * a.ggx[3 * n + d];
  float acc_g[F] = {};
  float sxy = 0.f, sxz = 0.f, syz = 0.f;  // mixed second derivatives of the interpolant of <t, g>
  float acc_x[3] = {0.f, 0.f, 0.f};
  for (int k = 0; k < 8; ++k) {
    const int ix = k & 1, iy = (k >> 1) & 1, iz = (k >> 2) & 1;
    const float sx = ix ? 1.f : -1.f, sy = iy ? 1.f : -1.f, sz = iz ? 1.f : -1.f;
    const float dwx = sx * wy[iy] * wz[iz], dwy = sy * wx[ix] * wz[iz], dwz = sz * wx[ix] * wy[iy];
    const int64_t r = (level.offset + int64_t(c.idx[k][i])) * F;
    if (kGGX) {
      const float v = gg[0] * dwx + gg[1] * dwy + gg[2] * dwz;  // R * d w_k along ggx
      if (kOutG || kOutX) {
        const float* row = a.table + r;
        float s = 0.f;
        for (int f = 0; f < F; ++f) {
          acc_g[f] += v * row[f];
          s += row[f] * gv[f];
        }
        if (kOutX) {
          sxy += s * sx * sy * wz[iz];
          sxz += s * sx * sz * wy[iy];
          syz += s * sy * sz * wx[ix];
        }
      }
      if (kOutT) {
        float* trow = a.out_t + r;
        for (int f = 0; f < F; ++f) trow[f] += v * gv[f];
      }
    }
    if (kGGT) {
      const float* row = a.ggt + r;
      float s = 0.f;
      for (int f = 0; f < F; ++f) {
        acc_g[f] += c.w[k][i] * row[f];
        s += row[f] * gv[f];
      }
      if (kOutX) {
        acc_x[0] += s * dwx;
        acc_x[1] += s * dwy;
        acc_x[2] += s * dwz;
      }
    }
  }
  if (kOutG)
    for (int f = 0; f < F; ++f) ogl[n * F + f] = acc_g[f];
  if (kOutX) {
    float* gr = gx + 3 * n;
    // gg already carries one factor R; the second comes from d frac / dx.
    gr[0] += R * (acc_x[0] + gg[1] * sxy + gg[2] * sxz);
    gr[1] += R * (acc_x[1] + gg[0] * sxy + gg[2] * syz);
    gr[2] += R * (acc_x[2] + gg[0] * sxz + gg[1] * syz);
  }
}

template <int F, bool kGGX, bool kGGT, bool kOutG, bool kOutT, bool kOutX>
void double_run(const DoubleArgs& a, int64_t N, const std::vector<Level>& lv, uint32_t mask, float* os) {
  const int L = static_cast<int>(lv.size());
  std::unique_ptr<float[]> hold_g;
  float* gs = alloc_floats(hold_g, N * L * F);  // g, level-major
  run_pass(
      N, L, kOutT, kOutX ? a.out_x : nullptr,
      [&](int l0, int lstep, int64_t n0, int64_t n1) { to_level_major<F>(a.g, gs, N, L, l0, lstep, n0, n1); },
      [&](int l, int64_t n0, int64_t n1, float* gxp) {
        const Level& level = lv[l];
        const int64_t off = level.offset * F;
        const float* gl = gs + l * N * F;
        float* ogl = kOutG ? os + l * N * F : nullptr;
        sweep<F>(
            a.x, level, mask, n0, n1,
            [&](const Chunk& c, int i) {
              if (kGGX && (kOutG || kOutX)) prefetch_rows<F>(c, i, a.table + off, false);
              if (kOutT) prefetch_rows<F>(c, i, a.out_t + off, true);
              if (kGGT) prefetch_rows<F>(c, i, a.ggt + off, false);
            },
            [&](const Chunk& c, int i) { double_point<F, kGGX, kGGT, kOutG, kOutT, kOutX>(c, i, level, a, gl, ogl, gxp); });
      },
      [&](int64_t n0, int64_t n1) {
        if (kOutG && a.out_g) to_point_major<F>(os, a.out_g, N, L, n0, n1);
      });
}

template <int F>
void double_impl(const DoubleArgs& a, int64_t N, const std::vector<Level>& lv, uint32_t mask) {
  const bool gx = a.ggx != nullptr, gt = a.ggt != nullptr, ox = a.out_x != nullptr;
  std::unique_ptr<float[]> hold_o;
  float* os = alloc_floats(hold_o, N * static_cast<int64_t>(lv.size()) * F);  // dLoss/dg, level-major
  // The eikonal loss sends only ggx; ggt appears only when something differentiates the table gradient.
  // As in the backward, the table scatter runs as a pass of its own when the table is large.
  if (a.out_t && gx && !gt && !two_passes<F>(mask)) {
    if (ox) double_run<F, true, false, true, true, true>(a, N, lv, mask, os);
    else double_run<F, true, false, true, true, false>(a, N, lv, mask, os);
    return;
  }
  if (a.out_t) double_run<F, true, false, false, true, false>(a, N, lv, mask, nullptr);
  if (!a.out_g && !a.out_x) return;
  if (gx && !gt) {
    if (ox) double_run<F, true, false, true, false, true>(a, N, lv, mask, os);
    else double_run<F, true, false, true, false, false>(a, N, lv, mask, os);
  } else if (gt && !gx) {
    if (ox) double_run<F, false, true, true, false, true>(a, N, lv, mask, os);
    else double_run<F, false, true, true, false, false>(a, N, lv, mask, os);
  } else if (gx && gt) {
    if (ox) double_run<F, true, true, true, false, true>(a, N, lv, mask, os);
    else double_run<F, true, true, true, false, false>(a, N, lv, mask, os);
  }
}

// --------------------------------------------------------------------- forward with the Jacobian
// The encoding and its Jacobian w.r.t. the point in one sweep: jac[n, l*F + f, d] = R sum_k t_k[f] dw_k/dfrac_d.
// The analytic normal then needs no backward pass of its own (grad_x = jac^T g is a small contraction), and the
// training backward scatters both incoming gradients, of the encoding and of the Jacobian, in one pass
// (jacobian_backward_impl) instead of a backward and a double backward.
template <int F>
void forward_jac_impl(const float* __restrict__ x, const float* __restrict__ table, float* __restrict__ out,
                      float* __restrict__ jac, int64_t N, const std::vector<Level>& lv, uint32_t mask) {
  const int L = static_cast<int>(lv.size());
  std::unique_ptr<float[]> hold, hold_j;
  float* stage = alloc_floats(hold, N * L * F);         // [L, N, F]
  float* stage_j = alloc_floats(hold_j, N * L * F * 3);  // [L, N, F, 3]
  run_pass(
      N, L, false, nullptr, [](int, int, int64_t, int64_t) {},
      [&](int l, int64_t n0, int64_t n1, float*) {
        const Level& level = lv[l];
        const float* tl = table + level.offset * F;
        float* ol = stage + l * N * F;
        float* jl = stage_j + l * N * F * 3;
        sweep<F>(
            x, level, mask, n0, n1, [&](const Chunk& c, int i) { prefetch_rows<F>(c, i, tl, false); },
            [&](const Chunk& c, int i) {
              float dw[8][3];
              weight_grads(c, i, dw);
              float acc[F] = {};
              float aj[F][3] = {};
              for (int k = 0; k < 8; ++k) {
                const float* row = tl + int64_t(c.idx[k][i]) * F;
                for (int f = 0; f < F; ++f) {
                  acc[f] += c.w[k][i] * row[f];
                  for (int d = 0; d < 3; ++d) aj[f][d] += dw[k][d] * row[f];
                }
              }
              float* o = ol + c.n[i] * F;
              float* j = jl + c.n[i] * F * 3;
              for (int f = 0; f < F; ++f) {
                o[f] = acc[f];
                for (int d = 0; d < 3; ++d) j[f * 3 + d] = level.res * aj[f][d];
              }
            });
      },
      [&](int64_t n0, int64_t n1) {
        to_point_major<F>(stage, out, N, L, n0, n1);
        to_point_major<F * 3>(stage_j, jac, N, L, n0, n1);
      });
}

// The table gradient of (out, jac): grad_table[row_k, f] += w_k g[f] + R sum_d dw_k/dfrac_d gj[f, d], whole levels
// per thread as in the backward. g or gj may be null (no gradient reached that output).
template <int F>
void jacobian_backward_impl(const float* x, const float* g, const float* gj, float* gt, int64_t N,
                            const std::vector<Level>& lv, uint32_t mask) {
  const int L = static_cast<int>(lv.size());
  std::unique_ptr<float[]> hold, hold_j;
  float* gs = g ? alloc_floats(hold, N * L * F) : nullptr;          // g, level-major
  float* gjs = gj ? alloc_floats(hold_j, N * L * F * 3) : nullptr;  // gj, level-major
  run_pass(
      N, L, true, nullptr,
      [&](int l0, int lstep, int64_t n0, int64_t n1) {
        if (gs) to_level_major<F>(g, gs, N, L, l0, lstep, n0, n1);
        if (gjs) to_level_major<F * 3>(gj, gjs, N, L, l0, lstep, n0, n1);
      },
      [&](int l, int64_t n0, int64_t n1, float*) {
        const Level& level = lv[l];
        float* gtl = gt + level.offset * F;
        const float* gl = gs ? gs + l * N * F : nullptr;
        const float* jl = gjs ? gjs + l * N * F * 3 : nullptr;
        const float R = level.res;
        sweep<F>(
            x, level, mask, n0, n1, [&](const Chunk& c, int i) { prefetch_rows<F>(c, i, gtl, true); },
            [&](const Chunk& c, int i) {
              const int64_t n = c.n[i];
              float gv[F] = {};
              float jv[F][3] = {};
              if (gl)
                for (int f = 0; f < F; ++f) gv[f] = gl[n * F + f];
              if (jl)
                for (int f = 0; f < F; ++f)
                  for (int d = 0; d < 3; ++d) jv[f][d] = R * jl[(n * F + f) * 3 + d];
              float dw[8][3];
              weight_grads(c, i, dw);
              for (int k = 0; k < 8; ++k) {
                float* row = gtl + int64_t(c.idx[k][i]) * F;
                const float w = c.w[k][i];
                for (int f = 0; f < F; ++f)
                  row[f] += w * gv[f] + (dw[k][0] * jv[f][0] + dw[k][1] * jv[f][1] + dw[k][2] * jv[f][2]);
              }
            });
      },
      [](int64_t, int64_t) {});
}

#define ANISDF_DISPATCH_F(F_VALUE, CALL)                                    \
  switch (F_VALUE) {                                                        \
    case 1: { constexpr int kF = 1; CALL; } break;                          \
    case 2: { constexpr int kF = 2; CALL; } break;                          \
    case 4: { constexpr int kF = 4; CALL; } break;                          \
    case 8: { constexpr int kF = 8; CALL; } break;                          \
    default: TORCH_CHECK(false, "hashgrid_cpu: features_per_level must be 1, 2, 4 or 8"); \
  }

torch::Tensor grad_input(const torch::Tensor& t, int64_t rows, int64_t cols, const char* what) {
  auto out = t.to(torch::kFloat32).contiguous();
  TORCH_CHECK(out.dim() == 2 && out.size(0) == rows && out.size(1) == cols, "hashgrid_cpu: ", what,
              " must be [", rows, ", ", cols, "], got ", out.sizes());
  return out;
}

// Validated, contiguous inputs shared by the three entry points: the one place that checks them.
struct Inputs {
  std::vector<Level> lv;
  torch::Tensor x, table, g;  // g: the incoming gradient [N, L*F] of the backward passes (undefined in forward)
  int64_t N, L, F;
  uint32_t mask;
};

Inputs prepare(const torch::Tensor& x, const torch::Tensor& table, const torch::Tensor& levels,
               int64_t log2_size, const torch::Tensor* g = nullptr) {
  auto lv = make_levels(levels);
  check_inputs(x, table, lv, log2_size);
  const int64_t N = x.size(0), L = static_cast<int64_t>(lv.size()), F = table.size(1);
  torch::Tensor gc;
  if (g != nullptr) gc = grad_input(*g, N, L * F, "incoming gradient g");
  return {std::move(lv), x.contiguous(), table.contiguous(), std::move(gc), N, L, F,
          static_cast<uint32_t>((int64_t(1) << log2_size) - 1)};
}

}  // namespace

// ------------------------------------------------------------------------------------------ bindings
torch::Tensor encode_forward(torch::Tensor x, torch::Tensor table, torch::Tensor levels, int64_t log2_size) {
  const auto in = prepare(x, table, levels, log2_size);
  auto out = torch::empty({in.N, in.L * in.F}, in.table.options());
  ANISDF_DISPATCH_F(in.F, forward_impl<kF>(in.x.data_ptr<float>(), in.table.data_ptr<float>(),
                                           out.data_ptr<float>(), in.N, in.lv, in.mask));
  return out;
}

std::vector<torch::Tensor> encode_backward(torch::Tensor g, torch::Tensor x, torch::Tensor table,
                                           torch::Tensor levels, int64_t log2_size, bool need_table,
                                           bool need_x, int64_t mode) {
  const auto in = prepare(x, table, levels, log2_size, &g);
  torch::Tensor gt, gx;
  if (need_table) gt = torch::zeros_like(in.table);
  if (need_x) gx = torch::zeros({in.N, 3}, in.x.options());
  ANISDF_DISPATCH_F(in.F, backward_impl<kF>(in.x.data_ptr<float>(), in.g.data_ptr<float>(),
                                            in.table.data_ptr<float>(), need_table ? gt.data_ptr<float>() : nullptr,
                                            need_x ? gx.data_ptr<float>() : nullptr, in.N, in.lv, in.mask,
                                            static_cast<int>(mode)));
  return {gt, gx};
}

std::vector<torch::Tensor> encode_double_backward(torch::Tensor g, torch::Tensor x, torch::Tensor table,
                                                  std::optional<torch::Tensor> ggx,
                                                  std::optional<torch::Tensor> ggt, torch::Tensor levels,
                                                  int64_t log2_size, bool need_g, bool need_table,
                                                  bool need_x) {
  const auto in = prepare(x, table, levels, log2_size, &g);
  const int64_t N = in.N, F = in.F;
  torch::Tensor ggx_t, ggt_t;
  if (ggx.has_value() && ggx->defined()) ggx_t = grad_input(*ggx, N, 3, "grad of grad_x");
  if (ggt.has_value() && ggt->defined()) ggt_t = grad_input(*ggt, in.table.size(0), F, "grad of grad_table");
  torch::Tensor og, ot, ox;
  if (need_g) og = torch::empty({N, in.L * F}, in.table.options());
  if (need_table) ot = torch::zeros_like(in.table);
  if (need_x) ox = torch::zeros({N, 3}, in.x.options());
  DoubleArgs a{in.x.data_ptr<float>(),
               in.g.data_ptr<float>(),
               in.table.data_ptr<float>(),
               ggx_t.defined() ? ggx_t.data_ptr<float>() : nullptr,
               ggt_t.defined() ? ggt_t.data_ptr<float>() : nullptr,
               need_g ? og.data_ptr<float>() : nullptr,
               need_table && ggx_t.defined() ? ot.data_ptr<float>() : nullptr,
               need_x ? ox.data_ptr<float>() : nullptr};
  if (a.ggx || a.ggt) ANISDF_DISPATCH_F(F, double_impl<kF>(a, N, in.lv, in.mask));
  return {og, ot, ox};
}

std::vector<torch::Tensor> encode_forward_jacobian(torch::Tensor x, torch::Tensor table, torch::Tensor levels,
                                                   int64_t log2_size) {
  const auto in = prepare(x, table, levels, log2_size);
  auto out = torch::empty({in.N, in.L * in.F}, in.table.options());
  auto jac = torch::empty({in.N, in.L * in.F, 3}, in.table.options());
  ANISDF_DISPATCH_F(in.F, forward_jac_impl<kF>(in.x.data_ptr<float>(), in.table.data_ptr<float>(),
                                               out.data_ptr<float>(), jac.data_ptr<float>(), in.N, in.lv, in.mask));
  return {out, jac};
}

torch::Tensor encode_jacobian_backward(std::optional<torch::Tensor> g, std::optional<torch::Tensor> gj,
                                       torch::Tensor x, torch::Tensor table, torch::Tensor levels,
                                       int64_t log2_size) {
  const auto in = prepare(x, table, levels, log2_size);
  torch::Tensor gc, gjc;
  if (g.has_value() && g->defined()) gc = grad_input(*g, in.N, in.L * in.F, "incoming gradient g");
  if (gj.has_value() && gj->defined())
    gjc = grad_input(gj->reshape({in.N, in.L * in.F * 3}), in.N, in.L * in.F * 3, "incoming gradient of the Jacobian");
  auto gt = torch::zeros_like(in.table);
  if (gc.defined() || gjc.defined())
    ANISDF_DISPATCH_F(in.F, jacobian_backward_impl<kF>(in.x.data_ptr<float>(),
                                                       gc.defined() ? gc.data_ptr<float>() : nullptr,
                                                       gjc.defined() ? gjc.data_ptr<float>() : nullptr,
                                                       gt.data_ptr<float>(), in.N, in.lv, in.mask));
  return gt;
}

// kernels/softplus_cpu.cpp, built into the same extension
std::vector<torch::Tensor> softplus_slope(torch::Tensor z, double beta, bool want_slope);
torch::Tensor softplus_slope_backward(torch::Tensor s, std::optional<torch::Tensor> da,
                                      std::optional<torch::Tensor> ds, double beta);
torch::Tensor bias_softplus_(torch::Tensor z, torch::Tensor b, double beta);
// kernels/sdf_mlp_cpu.cpp
std::vector<torch::Tensor> sdf_mlp_forward(torch::Tensor h0, std::vector<torch::Tensor> ws,
                                           std::vector<torch::Tensor> bs, torch::Tensor w, torch::Tensor b_out,
                                           double beta);
std::vector<torch::Tensor> sdf_mlp_backward(std::vector<torch::Tensor> ws, torch::Tensor w,
                                            std::vector<torch::Tensor> acts, std::vector<torch::Tensor> slopes,
                                            std::vector<torch::Tensor> gss, std::vector<torch::Tensor> gins,
                                            std::optional<torch::Tensor> d_out0, std::optional<torch::Tensor> d_top,
                                            std::optional<torch::Tensor> d_g0, bool need_h0, double beta);
bool sdf_mlp_allow_blas(bool allow);
// kernels/relu_cpu.cpp
torch::Tensor bias_act_(torch::Tensor z, torch::Tensor b, bool relu);
torch::Tensor relu_backward_(torch::Tensor d, torch::Tensor a);
// kernels/march_cpu.cpp
std::vector<torch::Tensor> march_rays(torch::Tensor origins, torch::Tensor dirs, torch::Tensor near, torch::Tensor far,
                                      torch::Tensor u, double step, int64_t max_samples,
                                      std::optional<torch::Tensor> occupied, double radius, double inv_cell,
                                      int64_t resolution);
// kernels/asg_cpu.cpp
torch::Tensor asg_forward(torch::Tensor par, torch::Tensor w, torch::Tensor frames);
std::vector<torch::Tensor> asg_backward(torch::Tensor grad_out, torch::Tensor par, torch::Tensor w,
                                        torch::Tensor frames, bool need_w);
// kernels/jacobian_product_cpu.cpp
torch::Tensor jacobian_product_forward(torch::Tensor jac, torch::Tensor g);
std::vector<torch::Tensor> jacobian_product_backward(torch::Tensor d, torch::Tensor jac, torch::Tensor g,
                                                     bool need_jac, bool need_g);

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  namespace py = pybind11;
  // The kernels run without the GIL, so other Python threads (data loading, logging) keep going.
  const auto nogil = py::call_guard<py::gil_scoped_release>();
  m.doc() =
      "anisdf CPU kernels: hash-grid encoding (forward, backward, double backward, forward with the Jacobian), "
      "softplus with its slope, the SDF MLP with its input gradient (forward and backward), the colour heads' ReLU "
      "layers, ray marching, the ASG encoding, the Jacobian's product J^T g";
  m.def("encode_forward", &encode_forward, "out[N, L*F] = hash_encode(x, table)", py::arg("x"), py::arg("table"),
        py::arg("levels"), py::arg("log2_size"), nogil);
  m.def("encode_backward", &encode_backward, "(grad_table, grad_x) of hash_encode; None where not needed",
        py::arg("g"), py::arg("x"), py::arg("table"), py::arg("levels"), py::arg("log2_size"),
        py::arg("need_table"), py::arg("need_x"), py::arg("mode") = 0, nogil);
  m.def("encode_double_backward", &encode_double_backward,
        "(grad_g, grad_table, grad_x) of the backward's outputs; None where not needed", py::arg("g"),
        py::arg("x"), py::arg("table"), py::arg("ggx"), py::arg("ggt"), py::arg("levels"),
        py::arg("log2_size"), py::arg("need_g"), py::arg("need_table"), py::arg("need_x"), nogil);
  m.def("encode_forward_jacobian", &encode_forward_jacobian,
        "(out [N, L*F], jac [N, L*F, 3]): the encoding and its Jacobian w.r.t. x", py::arg("x"), py::arg("table"),
        py::arg("levels"), py::arg("log2_size"), nogil);
  m.def("encode_jacobian_backward", &encode_jacobian_backward,
        "grad_table of (out, jac) from their incoming gradients (either may be None)", py::arg("g"), py::arg("gj"),
        py::arg("x"), py::arg("table"), py::arg("levels"), py::arg("log2_size"), nogil);
  m.def("softplus_slope", &softplus_slope, "(softplus_beta(z), sigmoid(beta z)); the second undefined without want_slope",
        py::arg("z"), py::arg("beta"), py::arg("want_slope"), nogil);
  m.def("softplus_slope_backward", &softplus_slope_backward, "dz = da * s + ds * beta * s * (1 - s)", py::arg("s"),
        py::arg("da"), py::arg("ds"), py::arg("beta"), nogil);
  m.def("bias_softplus_", &bias_softplus_, "z <- softplus_beta(z + b) in place; returns z", py::arg("z"),
        py::arg("b"), py::arg("beta"), nogil);
  m.def("sdf_mlp_forward", &sdf_mlp_forward,
        "[out0, g0, a_1..a_K, s_0..s_K-1, gs_0..gs_K-1, g_1..g_K-1]: the SDF MLP and its input gradient, by tiles",
        py::arg("h0"), py::arg("ws"), py::arg("bs"), py::arg("w"), py::arg("b_out"), py::arg("beta"), nogil);
  m.def("sdf_mlp_backward", &sdf_mlp_backward,
        "[d_h0 or None, d_w, d_b_out, d_W_0..d_W_K-1, d_b_0..d_b_K-1] of sdf_mlp_forward, by tiles", py::arg("ws"),
        py::arg("w"), py::arg("acts"), py::arg("slopes"), py::arg("gss"), py::arg("gins"), py::arg("d_out0"),
        py::arg("d_top"), py::arg("d_g0"), py::arg("need_h0"), py::arg("beta"), nogil);
  m.def("sdf_mlp_allow_blas", &sdf_mlp_allow_blas,
        "whether the SDF MLP kernel's tile products may use BLAS's sgemm_ (else at::mm_out); returns the last setting",
        py::arg("allow"));
  m.def("bias_act_", &bias_act_, "z <- max(z + b, 0) (relu) or z + b, in place; returns z", py::arg("z"),
        py::arg("b"), py::arg("relu"), nogil);
  m.def("relu_backward_", &relu_backward_, "d <- d * (a > 0) in place; returns the column sums", py::arg("d"),
        py::arg("a"), nogil);
  m.def("march_rays", &march_rays, "(ray_idx, t) of the samples near + (k + u) step < far in occupied cells",
        py::arg("origins"), py::arg("dirs"), py::arg("near"), py::arg("far"), py::arg("u"), py::arg("step"),
        py::arg("max_samples"), py::arg("occupied"), py::arg("radius"), py::arg("inv_cell"), py::arg("resolution"),
        nogil);
  m.def("asg_forward", &asg_forward, "ASG features [B, L*2] of raw lobe parameters par [B, L, 4] and directions w",
        py::arg("par"), py::arg("w"), py::arg("frames"), nogil);
  m.def("asg_backward", &asg_backward, "(grad_par, grad_w or None) of asg_forward", py::arg("grad_out"),
        py::arg("par"), py::arg("w"), py::arg("frames"), py::arg("need_w"), nogil);
  m.def("jacobian_product_forward", &jacobian_product_forward, "out[n] = sum_k g[n, k] jac[n, k, :]", py::arg("jac"),
        py::arg("g"), nogil);
  m.def("jacobian_product_backward", &jacobian_product_backward, "(d_jac or None, d_g or None) of the product",
        py::arg("d"), py::arg("jac"), py::arg("g"), py::arg("need_jac"), py::arg("need_g"), nogil);
}
