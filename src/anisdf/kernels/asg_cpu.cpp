// The ASG encoding of the reflected direction with its sharpnesses' softplus, forward and backward, for the colour
// heads (anisdf/fields/asg.py::asg_features_reference is the PyTorch reference; paper Eqs. 8-9).
//
// Per row b and lobe l, from the raw parameters p = par[b, l, :] = (r, q, xi_0, xi_1) and the unit direction w:
//   lambda = softplus(r)   mu = softplus(q)   (beta 1)
//   dx, dy, dz = w . x_l, w . y_l, w . z_l      (the lobe's fixed frame)
//   E = exp(-(lambda dx^2 + mu dy^2))   lobe = max(dz, 0) E   out[b, l, c] = xi_c lobe
// Backward, with G = sum_c g_c xi_c the gradient reaching the lobe:
//   d xi_c = g_c lobe    d r = -G lobe dx^2 sigmoid(r)    d q = -G lobe dy^2 sigmoid(q)
//   d w = sum_l (-2 G lobe lambda dx) x_l + (-2 G lobe mu dy) y_l + [dz >= 0] G E z_l
// PyTorch builds this from about twenty [rows, lobes] passes (a strided copy for the softplus, the einsum, the
// exponent, the products and their backward); here each row's lobes are one loop, with the backward recomputing
// the forward's few quantities instead of reading them back. The backward's [dz >= 0] is clamp_min's gradient mask.

#include <torch/extension.h>

#include <ATen/Parallel.h>

#include <cstdint>
#include <vector>

#include "fast_math.h"

namespace {

using anisdf_math::exp_arg_max;
using anisdf_math::exp_neg;
using anisdf_math::softplus_slope_at;

constexpr int64_t kGrainRows = 256;

struct Inputs {
  torch::Tensor par, w;
  std::vector<float> frame;  // [9, L]: x_0 x_1 x_2 y_0 y_1 y_2 z_0 z_1 z_2, each over the lobes
  int64_t B, L;
};

Inputs checked(const torch::Tensor& par, const torch::Tensor& w, const torch::Tensor& frames) {
  for (const auto* t : {&par, &w, &frames})
    TORCH_CHECK(t->device().is_cpu() && t->scalar_type() == torch::kFloat32,
                "asg kernel: inputs must be float32 CPU tensors");
  TORCH_CHECK(frames.dim() == 3 && frames.size(1) == 3 && frames.size(2) == 3, "asg kernel: frames must be [L, 3, 3]");
  const int64_t L = frames.size(0);
  TORCH_CHECK(par.dim() == 3 && par.size(1) == L && par.size(2) == 4, "asg kernel: par must be [B, L, 4]");
  TORCH_CHECK(w.dim() == 2 && w.size(0) == par.size(0) && w.size(1) == 3, "asg kernel: w must be [B, 3]");
  Inputs in{par.contiguous(), w.contiguous(), std::vector<float>(9 * L), par.size(0), L};
  const auto fc = frames.contiguous();
  const float* f = fc.data_ptr<float>();
  for (int64_t l = 0; l < L; ++l)
    for (int64_t k = 0; k < 9; ++k) in.frame[k * L + l] = f[l * 9 + k];
  return in;
}

// One row's lobes in structure-of-arrays form, so that the per-lobe loops vectorise (the interleaved [L, 4]
// parameters and [L, 2] outputs are copied in and out by short loops of their own).
struct RowScratch {
  std::vector<float> r, q, xi0, xi1, dx, dy, dz, lam, mu, s_lam, s_mu, e, g0, g1;
  explicit RowScratch(int64_t L)
      : r(L), q(L), xi0(L), xi1(L), dx(L), dy(L), dz(L), lam(L), mu(L), s_lam(L), s_mu(L), e(L), g0(L), g1(L) {}
};

// The per-lobe quantities of one row: dot products, softplus and slope of r and q, and E. Every array a restrict
// parameter: that is what lets GCC vectorise the loop.
void lobe_terms(const float* __restrict fr, const float* __restrict r, const float* __restrict q, float w0, float w1,
                float w2, int64_t L, float x_max, float* __restrict dx, float* __restrict dy, float* __restrict dz,
                float* __restrict lam, float* __restrict mu, float* __restrict s_lam, float* __restrict s_mu,
                float* __restrict e) {
  for (int64_t l = 0; l < L; ++l) {
    dx[l] = w0 * fr[l] + w1 * fr[L + l] + w2 * fr[2 * L + l];
    dy[l] = w0 * fr[3 * L + l] + w1 * fr[4 * L + l] + w2 * fr[5 * L + l];
    dz[l] = w0 * fr[6 * L + l] + w1 * fr[7 * L + l] + w2 * fr[8 * L + l];
    float la, sl, m, sm;  // locals, not the arrays, as the helper's outputs: else the loop does not vectorise
    softplus_slope_at(r[l], 1.0f, 1.0f, x_max, la, sl);
    softplus_slope_at(q[l], 1.0f, 1.0f, x_max, m, sm);
    lam[l] = la;
    s_lam[l] = sl;
    mu[l] = m;
    s_mu[l] = sm;
    e[l] = exp_neg(la * dx[l] * dx[l] + m * dy[l] * dy[l], x_max);
  }
}

// The backward's per-lobe terms: the parameters' gradients and the coefficients (cx, cy, cz) of the lobe's frame
// axes in d w.
void grad_terms(const float* __restrict dx, const float* __restrict dy, const float* __restrict dz,
                const float* __restrict e, const float* __restrict lam, const float* __restrict mu,
                const float* __restrict s_lam, const float* __restrict s_mu, const float* __restrict xi0,
                const float* __restrict xi1, const float* __restrict g0, const float* __restrict g1, int64_t L,
                float* __restrict d_r, float* __restrict d_q, float* __restrict d_x0, float* __restrict d_x1,
                float* __restrict cx, float* __restrict cy, float* __restrict cz) {
  for (int64_t l = 0; l < L; ++l) {
    const float lobe = (dz[l] > 0.0f ? dz[l] : 0.0f) * e[l];
    const float G = g0[l] * xi0[l] + g1[l] * xi1[l];
    const float gl = G * lobe;
    d_r[l] = -gl * dx[l] * dx[l] * s_lam[l];
    d_q[l] = -gl * dy[l] * dy[l] * s_mu[l];
    d_x0[l] = g0[l] * lobe;
    d_x1[l] = g1[l] * lobe;
    cx[l] = -2.0f * gl * lam[l] * dx[l];
    cy[l] = -2.0f * gl * mu[l] * dy[l];
    cz[l] = dz[l] >= 0.0f ? G * e[l] : 0.0f;
  }
}

// Row b's parameters de-interleaved into t, then its lobe terms.
void row_forward(RowScratch& t, const float* p, float w0, float w1, float w2, const float* fr, int64_t L,
                 float x_max) {
  for (int64_t l = 0; l < L; ++l) {
    t.r[l] = p[4 * l];
    t.q[l] = p[4 * l + 1];
    t.xi0[l] = p[4 * l + 2];
    t.xi1[l] = p[4 * l + 3];
  }
  lobe_terms(fr, t.r.data(), t.q.data(), w0, w1, w2, L, x_max, t.dx.data(), t.dy.data(), t.dz.data(), t.lam.data(),
             t.mu.data(), t.s_lam.data(), t.s_mu.data(), t.e.data());
}

}  // namespace

// out [B, L * 2] (lobe-major, the two amplitude channels last) of par [B, L, 4], w [B, 3], frames [L, 3, 3].
torch::Tensor asg_forward(torch::Tensor par, torch::Tensor w, torch::Tensor frames) {
  const auto in = checked(par, w, frames);
  const int64_t L = in.L;
  auto out = torch::empty({in.B, L * 2}, in.par.options());
  const float* pp = in.par.data_ptr<float>();
  const float* wp = in.w.data_ptr<float>();
  const float* fr = in.frame.data();
  float* op = out.data_ptr<float>();
  const float x_max = exp_arg_max();
  // the lambdas copy their pointers: one read through a captured reference in a loop keeps GCC from vectorising it
  at::parallel_for(0, in.B, kGrainRows, [=](int64_t lo, int64_t hi) {
    RowScratch t(L);
    for (int64_t b = lo; b < hi; ++b) {
      row_forward(t, pp + b * L * 4, wp[b * 3], wp[b * 3 + 1], wp[b * 3 + 2], fr, L, x_max);
      float* o = op + b * L * 2;
      for (int64_t l = 0; l < L; ++l) {
        const float lobe = (t.dz[l] > 0.0f ? t.dz[l] : 0.0f) * t.e[l];
        o[2 * l] = t.xi0[l] * lobe;
        o[2 * l + 1] = t.xi1[l] * lobe;
      }
    }
  });
  return out;
}

// (grad_par [B, L, 4], grad_w [B, 3] or undefined without need_w) from grad_out [B, L * 2].
std::vector<torch::Tensor> asg_backward(torch::Tensor grad_out, torch::Tensor par, torch::Tensor w,
                                        torch::Tensor frames, bool need_w) {
  const auto in = checked(par, w, frames);
  const int64_t L = in.L;
  TORCH_CHECK(grad_out.device().is_cpu() && grad_out.scalar_type() == torch::kFloat32 &&
                  grad_out.numel() == in.B * L * 2,
              "asg kernel: grad_out must be a float32 CPU tensor of [B, L * 2]");
  const auto gc = grad_out.contiguous();
  auto gpar = torch::empty_like(in.par);
  torch::Tensor gw;
  if (need_w) gw = torch::empty_like(in.w);
  const float* pp = in.par.data_ptr<float>();
  const float* wp = in.w.data_ptr<float>();
  const float* gp = gc.data_ptr<float>();
  const float* fr = in.frame.data();
  float* dpp = gpar.data_ptr<float>();
  float* dwp = need_w ? gw.data_ptr<float>() : nullptr;
  const float x_max = exp_arg_max();
  at::parallel_for(0, in.B, kGrainRows, [=](int64_t lo, int64_t hi) {
    RowScratch t(L);
    std::vector<float> d_r(L), d_q(L), d_x0(L), d_x1(L), cx(L), cy(L), cz(L);
    for (int64_t b = lo; b < hi; ++b) {
      row_forward(t, pp + b * L * 4, wp[b * 3], wp[b * 3 + 1], wp[b * 3 + 2], fr, L, x_max);
      const float* g = gp + b * L * 2;
      for (int64_t l = 0; l < L; ++l) {
        t.g0[l] = g[2 * l];
        t.g1[l] = g[2 * l + 1];
      }
      grad_terms(t.dx.data(), t.dy.data(), t.dz.data(), t.e.data(), t.lam.data(), t.mu.data(), t.s_lam.data(),
                 t.s_mu.data(), t.xi0.data(), t.xi1.data(), t.g0.data(), t.g1.data(), L, d_r.data(), d_q.data(),
                 d_x0.data(), d_x1.data(), cx.data(), cy.data(), cz.data());
      float a0 = 0.0f, a1 = 0.0f, a2 = 0.0f;  // d w, summed over the lobes in order (deterministic)
      for (int64_t l = 0; l < L; ++l) {
        a0 += cx[l] * fr[l] + cy[l] * fr[3 * L + l] + cz[l] * fr[6 * L + l];
        a1 += cx[l] * fr[L + l] + cy[l] * fr[4 * L + l] + cz[l] * fr[7 * L + l];
        a2 += cx[l] * fr[2 * L + l] + cy[l] * fr[5 * L + l] + cz[l] * fr[8 * L + l];
      }
      float* dp = dpp + b * L * 4;
      for (int64_t l = 0; l < L; ++l) {
        dp[4 * l] = d_r[l];
        dp[4 * l + 1] = d_q[l];
        dp[4 * l + 2] = d_x0[l];
        dp[4 * l + 3] = d_x1[l];
      }
      if (dwp != nullptr) {
        dwp[b * 3] = a0;
        dwp[b * 3 + 1] = a1;
        dwp[b * 3 + 2] = a2;
      }
    }
  });
  return {gpar, gw};
}
