// Branch-free float32 exp, log1p and softplus with its slope for the CPU kernels (softplus_cpu.cpp, asg_cpu.cpp):
// plain arithmetic that GCC vectorises, where std::exp and std::log1p are library calls it does not.
#pragma once

#include <cstdint>
#include <cstring>

namespace anisdf_math {

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

// softplus_beta(v) = max(v, 0) + log1p(exp(-beta |v|)) / beta and its slope sigmoid(beta v), from one exp.
inline void softplus_slope_at(float v, float beta, float inv_beta, float x_max, float& a, float& s) {
  const float e = exp_neg(beta * (v < 0.0f ? -v : v), x_max);
  a = (v > 0.0f ? v : 0.0f) + log1p_unit(e) * inv_beta;
  s = (v >= 0.0f ? 1.0f : e) / (1.0f + e);
}

}  // namespace anisdf_math
