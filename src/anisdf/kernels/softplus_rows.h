// The element-wise passes around one hidden layer of the SDF MLP, over rows of H values (sdf_mlp_cpu.cpp over a
// tile of rows; softplus_cpu.cpp's no-grad queries use the forward over a whole matrix):
//   forward:  z <- softplus_beta(z + b), s = sigmoid(beta (z + b)), and gs = s * w for the top layer;
//   backward: dz = (da + d_out w^T) * s + (d_gs * G) * beta s (1 - s), G = g or the row w broadcast (top layer),
//             db = the column sums of dz over the rows, dw = the column sums of d_gs * s (top layer).
#pragma once

#include <cstdint>

#include "fast_math.h"

namespace anisdf_rows {

// Rows of z [n / H, H] in place: z <- softplus(z + b), s = its slope (kSlope), gs = s * w (kGs).
template <bool kSlope, bool kGs>
void bias_softplus_rows(float* __restrict__ z, float* __restrict__ s, float* __restrict__ gs,
                        const float* __restrict__ b, const float* __restrict__ w, int64_t n, int64_t H, float beta,
                        float inv_beta, float x_max) {
  for (int64_t o = 0; o < n; o += H) {
    for (int64_t j = 0; j < H; ++j) {
      float a, sl;
      anisdf_math::softplus_slope_at(z[o + j] + b[j], beta, inv_beta, x_max, a, sl);
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

}  // namespace anisdf_rows
