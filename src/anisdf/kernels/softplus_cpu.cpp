// Softplus with its slope in one pass, for the SDF MLPs (anisdf/fields/softplus.py holds the PyTorch reference).
//
//   a = softplus_beta(z) = log(1 + exp(beta z)) / beta      s = sigmoid(beta z) = da/dz
//   backward: dz = da * s + ds * beta * s * (1 - s)
//
// The closed-form SDF normal needs both a and s at every hidden layer (sdf_field.mlp_with_input_grad). PyTorch
// computes them in separate passes, and its softplus was the slowest operator of a CPU training step (several
// times a sigmoid's cost at the pre-activations the SDF MLPs see). Here one branch-free loop computes both from
// e = exp(-beta |z|):
//   a = max(z, 0) + log1p(e) / beta        s = (z >= 0 ? 1 : e) / (1 + e)
// with exp by Cody-Waite range reduction and a degree-7 polynomial (Cephes' expf), and log1p(e), e in [0, 1], as
// 2 atanh(t) = 2 (t + t^3/3 + ... + t^15/15), t = e / (2 + e) <= 1/3 (truncation below 1e-9). Plain arithmetic
// that GCC vectorises; the loops split over threads with at::parallel_for. Agreement with PyTorch's softplus and
// sigmoid: within a few float32 ulps (tests/test_softplus_kernel.py).

#include <torch/extension.h>

#include <ATen/Parallel.h>

#include <algorithm>
#include <cstdint>
#include <vector>

#include "fast_math.h"

namespace {

using anisdf_math::exp_arg_max;
using anisdf_math::softplus_slope_at;

constexpr int64_t kGrain = 16384;

torch::Tensor checked(const torch::Tensor& t, const char* what) {
  TORCH_CHECK(t.device().is_cpu() && t.scalar_type() == torch::kFloat32, what, " must be a float32 CPU tensor");
  return t.contiguous();
}

}  // namespace

// (a, s) or, without want_slope, (a, undefined).
std::vector<torch::Tensor> softplus_slope(torch::Tensor z, double beta, bool want_slope) {
  const auto zc = checked(z, "z");
  auto a = torch::empty_like(zc);
  torch::Tensor s;
  if (want_slope) s = torch::empty_like(zc);
  const float b = static_cast<float>(beta), inv_b = 1.0f / b;
  const float* zp = zc.data_ptr<float>();
  float* ap = a.data_ptr<float>();
  float* sp = want_slope ? s.data_ptr<float>() : nullptr;
  const float x_max = exp_arg_max();
  at::parallel_for(0, zc.numel(), kGrain, [&](int64_t lo, int64_t hi) {
    if (sp != nullptr) {
      for (int64_t i = lo; i < hi; ++i) softplus_slope_at(zp[i], b, inv_b, x_max, ap[i], sp[i]);
    } else {
      for (int64_t i = lo; i < hi; ++i) {
        float unused;  // the slope's division is dead code once inlined
        softplus_slope_at(zp[i], b, inv_b, x_max, ap[i], unused);
      }
    }
  });
  return {a, s};
}

// dz = da * s + ds * beta * s * (1 - s); either gradient may be undefined (zero).
torch::Tensor softplus_slope_backward(torch::Tensor s, std::optional<torch::Tensor> da,
                                      std::optional<torch::Tensor> ds, double beta) {
  const auto sc = checked(s, "s");
  const bool has_a = da.has_value() && da->defined(), has_s = ds.has_value() && ds->defined();
  torch::Tensor dac, dsc;
  if (has_a) dac = checked(*da, "grad of a");
  if (has_s) dsc = checked(*ds, "grad of s");
  auto dz = torch::empty_like(sc);
  const float b = static_cast<float>(beta);
  const float* sp = sc.data_ptr<float>();
  const float* gap = has_a ? dac.data_ptr<float>() : nullptr;
  const float* gsp = has_s ? dsc.data_ptr<float>() : nullptr;
  float* out = dz.data_ptr<float>();
  at::parallel_for(0, sc.numel(), kGrain, [&](int64_t lo, int64_t hi) {
    if (gap != nullptr && gsp != nullptr) {
      for (int64_t i = lo; i < hi; ++i) out[i] = gap[i] * sp[i] + gsp[i] * (b * sp[i] * (1.0f - sp[i]));
    } else if (gap != nullptr) {
      for (int64_t i = lo; i < hi; ++i) out[i] = gap[i] * sp[i];
    } else if (gsp != nullptr) {
      for (int64_t i = lo; i < hi; ++i) out[i] = gsp[i] * (b * sp[i] * (1.0f - sp[i]));
    } else {
      for (int64_t i = lo; i < hi; ++i) out[i] = 0.0f;
    }
  });
  return dz;
}

// ---------------------------------------------------------------------------------------------------------------
// One hidden layer of the SDF MLP with its closed-form input gradient (anisdf/fields/sdf_mlp.py: the hand-written
// backward; sdf_mlp.mlp_with_input_grad_reference is the autograd form). The matrix products stay with PyTorch
// (oneDNN); these two kernels do every element-wise pass around them in one sweep each.
//
// Forward, after z = h W^T (no bias: the product writes z once instead of copying the bias in first):
//   a = softplus_beta(z + b) (written over z), s = sigmoid(beta (z + b)), and with w given gs = s * w (each row
//   times w: the top layer's first factor of the input gradient, g = ((w * s_K) W_K * s_{K-1}) ... W_1);
//   without want_slope a alone (queries of a fixed field: pruning, occupancy grids, meshes).
// Backward of that layer, with G = g (the gradient entering the layer's slope product gs = g * s) or the row w
// broadcast (top layer):
//   dz = (da + d_out w^T) * s + (d_gs * G) * beta s (1 - s),   db = sum_rows dz,   dw = sum_rows d_gs * s (top)
// Column sums are taken over fixed blocks of kBlockRows rows and the blocks added in order: the result does not
// depend on the number of threads (same seed, same result).

namespace {

constexpr int64_t kBlockRows = 256;

torch::Tensor checked_2d(const torch::Tensor& t, int64_t n, int64_t h, const char* what) {
  auto c = checked(t, what);
  TORCH_CHECK(c.dim() == 2 && c.size(0) == n && c.size(1) == h, what, " must be [", n, ", ", h, "], got ",
              c.sizes());
  return c;
}

torch::Tensor checked_1d(const torch::Tensor& t, int64_t n, const char* what) {
  auto c = checked(t, what);
  TORCH_CHECK(c.dim() == 1 && c.size(0) == n, what, " must have ", n, " elements, got ", c.sizes());
  return c;
}

// Rows of z [n / H, H] in place: z <- softplus(z + b), s = its slope (kSlope), gs = s * w (kGs).
template <bool kSlope, bool kGs>
void bias_softplus_rows(float* __restrict__ z, float* __restrict__ s, float* __restrict__ gs,
                        const float* __restrict__ b, const float* __restrict__ w, int64_t n, int64_t H, float beta,
                        float inv_beta, float x_max) {
  for (int64_t o = 0; o < n; o += H) {
    for (int64_t j = 0; j < H; ++j) {
      float a, sl;
      softplus_slope_at(z[o + j] + b[j], beta, inv_beta, x_max, a, sl);
      z[o + j] = a;
      if (kSlope) s[o + j] = sl;
      if (kGs) gs[o + j] = sl * w[j];
    }
  }
}

template <bool kDa, bool kDout, bool kDgs, bool kG>
void layer_backward_block(int64_t lo, int64_t hi, int64_t H, float beta, const float* __restrict__ s,
                          const float* __restrict__ da, const float* __restrict__ d_out,
                          const float* __restrict__ w, const float* __restrict__ d_gs,
                          const float* __restrict__ g, float* __restrict__ dz, float* __restrict__ db,
                          float* __restrict__ dw) {
  for (int64_t j = 0; j < H; ++j) db[j] = 0.0f;
  if (kDgs && !kG)
    for (int64_t j = 0; j < H; ++j) dw[j] = 0.0f;
  for (int64_t i = lo; i < hi; ++i) {
    const int64_t o = i * H;
    const float dn = kDout ? d_out[i] : 0.0f;
    for (int64_t j = 0; j < H; ++j) {
      const float sl = s[o + j];
      float a_grad = kDa ? da[o + j] : 0.0f;
      if (kDout) a_grad += dn * w[j];
      float v = a_grad * sl;
      if (kDgs) {
        const float gin = kG ? g[o + j] : w[j];
        v += (d_gs[o + j] * gin) * (beta * sl * (1.0f - sl));
        if (!kG) dw[j] += d_gs[o + j] * sl;
      }
      dz[o + j] = v;
      db[j] += v;
    }
  }
}

}  // namespace

std::vector<torch::Tensor> softplus_bias_slope(torch::Tensor z, torch::Tensor b, double beta,
                                               std::optional<torch::Tensor> w, bool want_slope) {
  TORCH_CHECK(z.device().is_cpu() && z.scalar_type() == torch::kFloat32 && z.dim() == 2 && z.is_contiguous(),
              "z must be a contiguous float32 CPU matrix (it is overwritten)");
  const int64_t N = z.size(0), H = z.size(1);
  const auto bc = checked_1d(b, H, "b");
  const bool has_w = want_slope && w.has_value() && w->defined();
  torch::Tensor wc, gs, s;
  if (has_w) {
    wc = checked_1d(*w, H, "w");
    gs = torch::empty_like(z);
  }
  if (want_slope) s = torch::empty_like(z);
  const float bt = static_cast<float>(beta), inv_b = 1.0f / bt, x_max = exp_arg_max();
  float* zp = z.data_ptr<float>();
  float* sp = want_slope ? s.data_ptr<float>() : nullptr;
  float* gp = has_w ? gs.data_ptr<float>() : nullptr;
  const float* bp = bc.data_ptr<float>();
  const float* wp = has_w ? wc.data_ptr<float>() : nullptr;
  at::parallel_for(0, N, std::max<int64_t>(1, kGrain / std::max<int64_t>(H, 1)), [&](int64_t lo, int64_t hi) {
    float* zr = zp + lo * H;
    const int64_t n = (hi - lo) * H;
    if (gp != nullptr)
      bias_softplus_rows<true, true>(zr, sp + lo * H, gp + lo * H, bp, wp, n, H, bt, inv_b, x_max);
    else if (sp != nullptr)
      bias_softplus_rows<true, false>(zr, sp + lo * H, nullptr, bp, wp, n, H, bt, inv_b, x_max);
    else
      bias_softplus_rows<false, false>(zr, nullptr, nullptr, bp, wp, n, H, bt, inv_b, x_max);
  });
  return {z, s, gs};
}

std::vector<torch::Tensor> softplus_layer_backward(torch::Tensor s, double beta, std::optional<torch::Tensor> da,
                                                   std::optional<torch::Tensor> d_out,
                                                   std::optional<torch::Tensor> w,
                                                   std::optional<torch::Tensor> d_gs,
                                                   std::optional<torch::Tensor> g) {
  const auto sc = checked(s, "s");
  TORCH_CHECK(sc.dim() == 2, "s must be a matrix, got ", sc.sizes());
  const int64_t N = sc.size(0), H = sc.size(1);
  auto given = [](const std::optional<torch::Tensor>& t) { return t.has_value() && t->defined(); };
  const bool has_da = given(da), has_dout = given(d_out), has_w = given(w), has_dgs = given(d_gs),
             has_g = given(g);
  TORCH_CHECK(!has_dout || has_w, "d_out needs w");
  TORCH_CHECK(!has_dgs || has_g || has_w, "d_gs needs g or w");
  torch::Tensor dac, doc, wc, dgc, gc;
  if (has_da) dac = checked_2d(*da, N, H, "da");
  if (has_dout) doc = checked_1d(*d_out, N, "d_out");
  if (has_w) wc = checked_1d(*w, H, "w");
  if (has_dgs) dgc = checked_2d(*d_gs, N, H, "d_gs");
  if (has_g) gc = checked_2d(*g, N, H, "g");
  auto dz = torch::empty_like(sc);
  const bool want_dw = has_dgs && !has_g;
  const int64_t blocks = (N + kBlockRows - 1) / kBlockRows;
  std::vector<float> db_part(static_cast<size_t>(std::max<int64_t>(blocks, 1) * H), 0.0f);
  std::vector<float> dw_part(want_dw ? db_part.size() : 0, 0.0f);
  const float bt = static_cast<float>(beta);
  const float* sp = sc.data_ptr<float>();
  const float* dap = has_da ? dac.data_ptr<float>() : nullptr;
  const float* dop = has_dout ? doc.data_ptr<float>() : nullptr;
  const float* wp = has_w ? wc.data_ptr<float>() : nullptr;
  const float* dgp = has_dgs ? dgc.data_ptr<float>() : nullptr;
  const float* gp = has_g ? gc.data_ptr<float>() : nullptr;
  float* dzp = dz.data_ptr<float>();
  at::parallel_for(0, blocks, 1, [&](int64_t b0, int64_t b1) {
    for (int64_t blk = b0; blk < b1; ++blk) {
      const int64_t lo = blk * kBlockRows, hi = std::min(N, lo + kBlockRows);
      float* dbb = db_part.data() + blk * H;
      float* dwb = want_dw ? dw_part.data() + blk * H : nullptr;
#define ANISDF_LAYER_BWD(A, O, D, G) \
  layer_backward_block<A, O, D, G>(lo, hi, H, bt, sp, dap, dop, wp, dgp, gp, dzp, dbb, dwb)
      if (has_dgs && has_g) {
        if (has_da && has_dout) ANISDF_LAYER_BWD(true, true, true, true);
        else if (has_da) ANISDF_LAYER_BWD(true, false, true, true);
        else if (has_dout) ANISDF_LAYER_BWD(false, true, true, true);
        else ANISDF_LAYER_BWD(false, false, true, true);
      } else if (has_dgs) {
        if (has_da && has_dout) ANISDF_LAYER_BWD(true, true, true, false);
        else if (has_da) ANISDF_LAYER_BWD(true, false, true, false);
        else if (has_dout) ANISDF_LAYER_BWD(false, true, true, false);
        else ANISDF_LAYER_BWD(false, false, true, false);
      } else {
        if (has_da && has_dout) ANISDF_LAYER_BWD(true, true, false, false);
        else if (has_da) ANISDF_LAYER_BWD(true, false, false, false);
        else if (has_dout) ANISDF_LAYER_BWD(false, true, false, false);
        else ANISDF_LAYER_BWD(false, false, false, false);
      }
#undef ANISDF_LAYER_BWD
    }
  });
  auto db = torch::zeros({H}, sc.options());
  torch::Tensor dw;
  if (want_dw) dw = torch::zeros({H}, sc.options());
  float* dbp = db.data_ptr<float>();
  float* dwp = want_dw ? dw.data_ptr<float>() : nullptr;
  for (int64_t blk = 0; blk < blocks; ++blk) {
    for (int64_t j = 0; j < H; ++j) dbp[j] += db_part[blk * H + j];
    if (want_dw)
      for (int64_t j = 0; j < H; ++j) dwp[j] += dw_part[blk * H + j];
  }
  return {dz, db, dw};
}
