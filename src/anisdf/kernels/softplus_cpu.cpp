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

#include <cstdint>
#include <cstring>
#include <vector>

namespace {

constexpr int64_t kGrain = 16384;

// The largest argument of exp_neg: exp(-40) = 4.2e-18. Softplus then differs from log1p(exp(-x)) / beta by less
// than 5e-20 and its slope by less than 5e-18, and no step of it (t^2 in log1p_unit) falls below the smallest
// normal float. Denormal results cost the CPU a microcode assist each, tens of times a normal operation, on any
// thread without flush-to-zero (torch.set_flush_denormal sets only the calling thread's). The bound is read
// through an empty asm statement, once per loop: with a constant bound GCC computes the polynomial on the
// unclamped argument and blends in the constant exp(-40) (legal under -fno-trapping-math), which brings the
// denormals back (20x slower loops for beta |z| > 40, measured).
inline float exp_arg_max() {
  float m = 40.0f;
  asm("" : "+m"(m));
  return m;
}

// exp(-x) for x >= 0, x clamped at x_max (exp_arg_max()).
inline float exp_neg(float x, float x_max) {
  x = x < x_max ? x : x_max;
  const float n = __builtin_floorf(x * 1.44269504088896341f + 0.5f);
  const float r = -(x - n * 0.693359375f + n * 2.12194440e-4f);  // -(x - n ln2), ln2 in two parts
  float p = 1.9875691500e-4f;
  p = p * r + 1.3981999507e-3f;
  p = p * r + 8.3334519073e-3f;
  p = p * r + 4.1665795894e-2f;
  p = p * r + 1.6666665459e-1f;
  p = p * r + 5.0000001201e-1f;
  const float er = p * r * r + r + 1.0f;
  const int32_t bits = (127 - static_cast<int32_t>(n)) << 23;  // 2^-n, n in [0, 126]
  float scale;
  std::memcpy(&scale, &bits, sizeof scale);
  return er * scale;
}

// log(1 + e) for e in [0, 1].
inline float log1p_unit(float e) {
  const float t = e / (2.0f + e);
  const float t2 = t * t;
  float p = 1.0f / 15.0f;
  p = p * t2 + 1.0f / 13.0f;
  p = p * t2 + 1.0f / 11.0f;
  p = p * t2 + 1.0f / 9.0f;
  p = p * t2 + 1.0f / 7.0f;
  p = p * t2 + 1.0f / 5.0f;
  p = p * t2 + 1.0f / 3.0f;
  p = p * t2 + 1.0f;
  return 2.0f * t * p;
}

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
      for (int64_t i = lo; i < hi; ++i) {
        const float v = zp[i];
        const float e = exp_neg(b * (v < 0.0f ? -v : v), x_max);
        ap[i] = (v > 0.0f ? v : 0.0f) + log1p_unit(e) * inv_b;
        sp[i] = (v >= 0.0f ? 1.0f : e) / (1.0f + e);
      }
    } else {
      for (int64_t i = lo; i < hi; ++i) {
        const float v = zp[i];
        const float e = exp_neg(b * (v < 0.0f ? -v : v), x_max);
        ap[i] = (v > 0.0f ? v : 0.0f) + log1p_unit(e) * inv_b;
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
