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
#include "softplus_rows.h"

namespace {

using anisdf_math::exp_arg_max;
using anisdf_math::softplus_slope_at;
using anisdf_rows::bias_softplus_rows;

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
// A hidden layer of the SDF MLP queried without gradient (pruning, occupancy grids, meshes), after z = h W^T (no
// bias: the product writes z once instead of copying the bias in first): z <- softplus_beta(z + b) in place.
// Training's forward and backward with the closed-form gradient run tile by tile in sdf_mlp_cpu.cpp.

torch::Tensor bias_softplus_(torch::Tensor z, torch::Tensor b, double beta) {
  TORCH_CHECK(z.device().is_cpu() && z.scalar_type() == torch::kFloat32 && z.dim() == 2 && z.is_contiguous(),
              "z must be a contiguous float32 CPU matrix (it is overwritten)");
  const int64_t N = z.size(0), H = z.size(1);
  const auto bc = checked(b, "b");
  TORCH_CHECK(bc.dim() == 1 && bc.size(0) == H, "b must have ", H, " elements, got ", bc.sizes());
  const float bt = static_cast<float>(beta), inv_b = 1.0f / bt, x_max = exp_arg_max();
  float* zp = z.data_ptr<float>();
  const float* bp = bc.data_ptr<float>();
  at::parallel_for(0, N, std::max<int64_t>(1, kGrain / std::max<int64_t>(H, 1)), [&](int64_t lo, int64_t hi) {
    bias_softplus_rows<false, false>(zp + lo * H, nullptr, nullptr, bp, nullptr, (hi - lo) * H, H, bt, inv_b, x_max);
  });
  return z;
}
