// The analytic normal's grid part, J^T g, and its backward, for the SDF branches (anisdf/fields/hash_grid/ops.py,
// whose _JacobianTransposeProduct is the PyTorch reference):
//   out[n, :] = sum_k g[n, k] jac[n, k, :]        d jac[n, k, :] = g[n, k] d[n, :]        d g[n, k] = jac[n, k, :] . d[n, :]
// with jac [N, K, 3] from encode_forward_jacobian (K = active levels x features, at most a few dozen) and g a
// column slice of the MLP's input gradient (rows of any stride). PyTorch's batched products of N tiny matrices
// cost several times their memory traffic; here each row is one short loop.

#include <torch/extension.h>

#include <ATen/Parallel.h>

#include <cstdint>
#include <vector>

namespace {

constexpr int64_t kGrainRows = 1024;

void check_inputs(const torch::Tensor& jac, const torch::Tensor& g) {
  TORCH_CHECK(jac.device().is_cpu() && jac.scalar_type() == torch::kFloat32 && g.device().is_cpu() &&
                  g.scalar_type() == torch::kFloat32,
              "jacobian product: float32 CPU tensors expected");
  TORCH_CHECK(jac.dim() == 3 && jac.size(2) == 3 && g.dim() == 2 && g.size(0) == jac.size(0) &&
                  g.size(1) == jac.size(1),
              "jacobian product: jac must be [N, K, 3] and g [N, K]");
}

// g with unit column stride (a column slice of a contiguous matrix keeps its row stride).
torch::Tensor unit_columns(const torch::Tensor& g) { return g.stride(1) == 1 ? g : g.contiguous(); }

}  // namespace

torch::Tensor jacobian_product_forward(torch::Tensor jac, torch::Tensor g) {
  check_inputs(jac, g);
  const auto jc = jac.contiguous();
  const auto gc = unit_columns(g);
  const int64_t N = jc.size(0), K = jc.size(1), gs = gc.stride(0);
  auto out = torch::empty({N, 3}, jc.options());
  const float* jp = jc.data_ptr<float>();
  const float* gp = gc.data_ptr<float>();
  float* op = out.data_ptr<float>();
  at::parallel_for(0, N, kGrainRows, [=](int64_t lo, int64_t hi) {
    for (int64_t n = lo; n < hi; ++n) {
      const float* j = jp + n * K * 3;
      const float* gr = gp + n * gs;
      float a0 = 0.0f, a1 = 0.0f, a2 = 0.0f;
      for (int64_t k = 0; k < K; ++k) {
        a0 += gr[k] * j[3 * k];
        a1 += gr[k] * j[3 * k + 1];
        a2 += gr[k] * j[3 * k + 2];
      }
      op[n * 3] = a0;
      op[n * 3 + 1] = a1;
      op[n * 3 + 2] = a2;
    }
  });
  return out;
}

// (d_jac or undefined, d_g or undefined) from the gradient d [N, 3] of the forward's output.
std::vector<torch::Tensor> jacobian_product_backward(torch::Tensor d, torch::Tensor jac, torch::Tensor g,
                                                     bool need_jac, bool need_g) {
  check_inputs(jac, g);
  TORCH_CHECK(d.device().is_cpu() && d.scalar_type() == torch::kFloat32 && d.dim() == 2 && d.size(0) == jac.size(0) &&
                  d.size(1) == 3,
              "jacobian product: d must be a float32 CPU tensor of [N, 3]");
  const auto jc = jac.contiguous();
  const auto gc = unit_columns(g);
  const auto dc = d.contiguous();
  const int64_t N = jc.size(0), K = jc.size(1), gs = gc.stride(0);
  torch::Tensor djac, dg;
  if (need_jac) djac = torch::empty_like(jc);
  if (need_g) dg = torch::empty({N, K}, jc.options());
  const float* jp = jc.data_ptr<float>();
  const float* gp = gc.data_ptr<float>();
  const float* dp = dc.data_ptr<float>();
  float* djp = need_jac ? djac.data_ptr<float>() : nullptr;
  float* dgp = need_g ? dg.data_ptr<float>() : nullptr;
  at::parallel_for(0, N, kGrainRows, [=](int64_t lo, int64_t hi) {
    for (int64_t n = lo; n < hi; ++n) {
      const float d0 = dp[n * 3], d1 = dp[n * 3 + 1], d2 = dp[n * 3 + 2];
      if (djp != nullptr) {
        const float* gr = gp + n * gs;
        float* o = djp + n * K * 3;
        for (int64_t k = 0; k < K; ++k) {
          o[3 * k] = gr[k] * d0;
          o[3 * k + 1] = gr[k] * d1;
          o[3 * k + 2] = gr[k] * d2;
        }
      }
      if (dgp != nullptr) {
        const float* j = jp + n * K * 3;
        float* o = dgp + n * K;
        for (int64_t k = 0; k < K; ++k) o[k] = j[3 * k] * d0 + j[3 * k + 1] * d1 + j[3 * k + 2] * d2;
      }
    }
  });
  return {djac, dg};
}
