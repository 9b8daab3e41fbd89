// The SDF MLP with its closed-form input gradient, forward and hand-written backward, a tile of rows at a time
// (anisdf/fields/sdf_mlp.py: mlp_with_input_grad_reference is the autograd form; tests/test_sdf_mlp.py compares).
//
// Layers k = 0..K-1, W_k [O_k, I_k]: z_k = a_k W_k^T + b_k, a_{k+1} = softplus_beta(z_k), s_k = sigmoid(beta z_k);
// out0 = a_K . w + b_out; its input gradient g_0 = d out0 / d a_0 from gs_{K-1} = s_{K-1} * w, g_k = gs_k W_k
// (saved as gins[k-1] for k >= 1), gs_{k-1} = g_k * s_{k-1}, g_0 = gs_0 W_0 (the normal of Eq. 5's branches).
//
// Whole-matrix products with an element-wise pass after each move every [N, H] intermediate through memory
// several times (at 25k rows one is 6.4 MB, beyond the L2 cache), and those passes cost a CPU step about as much
// as the products. Here each tile of kTile rows goes through every layer, forward or backward, while it is in
// cache: a tile's products are single-threaded BLAS calls (sgemm_, which torch's x86 builds export from MKL;
// at::mm_out where the symbol is missing or fails a self-check), the tiles split between threads. Weight and bias
// gradients are summed per tile and the tiles added in order, so the result does not depend on the number of
// threads (same seed, same result).

#include <torch/extension.h>

#include <ATen/Parallel.h>

#include <algorithm>
#include <cstdint>
#include <optional>
#include <vector>

#include "fast_math.h"
#include "softplus_rows.h"

extern "C" {
// Weak: where the running torch does not export them, they are null and at::mm_out does the products.
void sgemm_(const char* ta, const char* tb, const int* m, const int* n, const int* k, const float* alpha,
            const float* a, const int* lda, const float* b, const int* ldb, const float* beta, float* c,
            const int* ldc) __attribute__((weak));
// MKL's C function by value (the lower-case names are its Fortran interface, which takes a pointer).
int MKL_Set_Num_Threads_Local(int n) __attribute__((weak));
}

namespace {

using anisdf_rows::bias_softplus_rows;
using anisdf_rows::layer_backward_block;

constexpr int64_t kTile = 512;  // 128 KB of a 64-wide float matrix: a tile's working set stays in L2

// Row-major C[M, N] (leading dimension ldc) = op(A) op(B), plus C where accumulate; op(X) = X^T where flagged.
void gemm_rows_with(bool blas, bool ta, bool tb, int64_t M, int64_t N, int64_t K, const float* A, int64_t lda,
                    const float* B, int64_t ldb, bool accumulate, float* C, int64_t ldc) {
  if (M == 0 || N == 0) return;
  if (blas) {  // column-major BLAS sees C^T = op(B)^T op(A)^T
    const int m = static_cast<int>(N), n = static_cast<int>(M), k = static_cast<int>(K);
    const int la = static_cast<int>(ldb), lb = static_cast<int>(lda), lc = static_cast<int>(ldc);
    const float one = 1.0f, beta = accumulate ? 1.0f : 0.0f;
    sgemm_(tb ? "T" : "N", ta ? "T" : "N", &m, &n, &k, &one, B, &la, A, &lb, &beta, C, &lc);
    return;
  }
  const auto f = torch::TensorOptions().dtype(torch::kFloat32);
  auto view = [&](const float* p, int64_t rows, int64_t cols, int64_t ld, bool t) {
    auto v = torch::from_blob(const_cast<float*>(p), {t ? cols : rows, t ? rows : cols}, {ld, 1}, f);
    return t ? v.t() : v;
  };
  auto c = torch::from_blob(C, {M, N}, {ldc, 1}, f);
  const auto a = view(A, M, K, lda, ta), b = view(B, K, N, ldb, tb);
  if (accumulate)
    c.addmm_(a, b);
  else
    at::mm_out(c, a, b);
}

// Whether sgemm_ is there and computes a known product right (an interface of another integer width would not).
bool blas_works() {
  if (sgemm_ == nullptr) return false;
  const float a[6] = {1, 2, 3, 4, 5, 6}, b[6] = {1, 0, -1, 2, 1, 0};  // A [2, 3], B [3, 2]
  float c[4] = {9, 9, 9, 9};
  gemm_rows_with(true, false, false, 2, 2, 3, a, 3, b, 2, false, c, 2);
  const float want[4] = {2, 4, 5, 10};
  return std::equal(c, c + 4, want);
}

bool blas_allowed = true;  // sdf_mlp_allow_blas(false): the at::mm_out path, for its test

bool use_blas() {
  static const bool ok = blas_works();
  return ok && blas_allowed;
}

void gemm_rows(bool ta, bool tb, int64_t M, int64_t N, int64_t K, const float* A, int64_t lda, const float* B,
               int64_t ldb, bool accumulate, float* C, int64_t ldc) {
  gemm_rows_with(use_blas(), ta, tb, M, N, K, A, lda, B, ldb, accumulate, C, ldc);
}

// MKL runs a tile's product on the calling thread alone (the tiles are the parallelism), and the same way with one
// thread or many: the products' sums, and so the result, do not depend on the thread count.
struct SingleThreadedBlas {
  int previous = 0;
  SingleThreadedBlas() {
    if (MKL_Set_Num_Threads_Local != nullptr) previous = MKL_Set_Num_Threads_Local(1);
  }
  ~SingleThreadedBlas() {
    if (MKL_Set_Num_Threads_Local != nullptr) MKL_Set_Num_Threads_Local(previous);
  }
};

// out[r] = b + a[r, :] . w for the T rows of a [T, H], with 16 partial sums a row (a loop GCC vectorises).
void row_dots(const float* __restrict__ a, const float* __restrict__ w, int64_t T, int64_t H, float b,
              float* __restrict__ out) {
  for (int64_t r = 0; r < T; ++r) {
    const float* ar = a + r * H;
    float part[16] = {};
    int64_t j = 0;
    for (; j + 16 <= H; j += 16)
      for (int l = 0; l < 16; ++l) part[l] += ar[j + l] * w[j + l];
    float acc = b;
    for (; j < H; ++j) acc += ar[j] * w[j];
    for (int l = 0; l < 16; ++l) acc += part[l];
    out[r] = acc;
  }
}

// dw[j] = sum_r a[r, j] d[r] over the T rows of a [T, H].
void column_dots(const float* __restrict__ a, const float* __restrict__ d, int64_t T, int64_t H,
                 float* __restrict__ dw) {
  for (int64_t j = 0; j < H; ++j) dw[j] = 0.0f;
  for (int64_t r = 0; r < T; ++r)
    for (int64_t j = 0; j < H; ++j) dw[j] += a[r * H + j] * d[r];
}

void multiply(float* __restrict__ out, const float* __restrict__ a, const float* __restrict__ b, int64_t n) {
  for (int64_t i = 0; i < n; ++i) out[i] = a[i] * b[i];
}

torch::Tensor float_matrix(const torch::Tensor& t, int64_t rows, int64_t cols, const char* what) {
  TORCH_CHECK(t.device().is_cpu() && t.scalar_type() == torch::kFloat32, what, " must be a float32 CPU tensor");
  TORCH_CHECK(t.dim() == 2 && (rows < 0 || t.size(0) == rows) && (cols < 0 || t.size(1) == cols), what,
              " must be [", rows, ", ", cols, "] (-1: any), got ", t.sizes());
  return t.contiguous();
}

torch::Tensor float_vector(const torch::Tensor& t, int64_t n, const char* what) {
  TORCH_CHECK(t.device().is_cpu() && t.scalar_type() == torch::kFloat32, what, " must be a float32 CPU tensor");
  TORCH_CHECK(t.numel() == n, what, " must have ", n, " elements, got ", t.sizes());
  return t.contiguous().reshape({n});
}

// The layers' widths: in[k], out[k] of W_k, checked against each other and the input.
struct Widths {
  std::vector<int64_t> in, out;
  int64_t K = 0, widest = 0, sum_weights = 0;
};

Widths layer_widths(const std::vector<torch::Tensor>& ws, int64_t d_in) {
  Widths l;
  l.K = static_cast<int64_t>(ws.size());
  TORCH_CHECK(l.K >= 1, "the SDF MLP needs at least one hidden layer");
  for (int64_t k = 0; k < l.K; ++k) {
    const int64_t i = k == 0 ? d_in : l.out[k - 1];
    TORCH_CHECK(ws[k].dim() == 2 && ws[k].size(1) == i, "weight ", k, " must have ", i, " columns, got ",
                ws[k].sizes());
    l.in.push_back(i);
    l.out.push_back(ws[k].size(0));
    l.widest = std::max({l.widest, i, ws[k].size(0)});
    l.sum_weights += i * ws[k].size(0);
  }
  return l;
}

const float* ptr(const torch::Tensor& t) { return t.data_ptr<float>(); }
float* mut(torch::Tensor& t) { return t.data_ptr<float>(); }

}  // namespace

// Whether the tiles' products may use sgemm_ (where it is there and works); whether they did before.
bool sdf_mlp_allow_blas(bool allow) {
  const bool was = blas_allowed;
  blas_allowed = allow;
  return was;
}

// {out0 [N], g0 [N, I_0], a_1..a_K, s_0..s_{K-1}, gs_0..gs_{K-1}, gins_0..gins_{K-2}} of the layers ws, bs.
std::vector<torch::Tensor> sdf_mlp_forward(torch::Tensor h0, std::vector<torch::Tensor> ws,
                                           std::vector<torch::Tensor> bs, torch::Tensor w, torch::Tensor b_out,
                                           double beta) {
  const auto h = float_matrix(h0, -1, -1, "h0");
  const int64_t N = h.size(0);
  const Widths L = layer_widths(ws, h.size(1));
  const int64_t K = L.K;
  TORCH_CHECK(static_cast<int64_t>(bs.size()) == K, "one bias a weight");
  for (int64_t k = 0; k < K; ++k) {
    ws[k] = float_matrix(ws[k], L.out[k], L.in[k], "weight");
    bs[k] = float_vector(bs[k], L.out[k], "bias");
  }
  const auto wv = float_vector(w, L.out[K - 1], "w");
  const float bo = *ptr(float_vector(b_out, 1, "b_out"));  // a CPU read, not an operator (.item())
  const auto opt = h.options();
  auto out0 = torch::empty({N}, opt), g0 = torch::empty({N, L.in[0]}, opt);
  std::vector<torch::Tensor> acts, slopes, gss, gins;
  for (int64_t k = 0; k < K; ++k) {
    acts.push_back(torch::empty({N, L.out[k]}, opt));
    slopes.push_back(torch::empty({N, L.out[k]}, opt));
    gss.push_back(torch::empty({N, L.out[k]}, opt));
    if (k < K - 1) gins.push_back(torch::empty({N, L.out[k]}, opt));
  }
  const float bt = static_cast<float>(beta), inv_b = 1.0f / bt, x_max = anisdf_math::exp_arg_max();
  const int64_t tiles = (N + kTile - 1) / kTile;
  at::parallel_for(0, tiles, 1, [&](int64_t t0, int64_t t1) {
    SingleThreadedBlas one_thread;
    for (int64_t t = t0; t < t1; ++t) {
      const int64_t lo = t * kTile, T = std::min(kTile, N - lo);
      for (int64_t k = 0; k < K; ++k) {  // a_{k+1} = softplus(a_k W_k^T + b_k), its slope; gs at the top
        const int64_t I = L.in[k], O = L.out[k];
        const float* x = k == 0 ? ptr(h) + lo * I : ptr(acts[k - 1]) + lo * I;
        float* z = mut(acts[k]) + lo * O;
        gemm_rows(false, true, T, O, I, x, I, ptr(ws[k]), I, false, z, O);
        if (k == K - 1)
          bias_softplus_rows<true, true>(z, mut(slopes[k]) + lo * O, mut(gss[k]) + lo * O, ptr(bs[k]), ptr(wv),
                                         T * O, O, bt, inv_b, x_max);
        else
          bias_softplus_rows<true, false>(z, mut(slopes[k]) + lo * O, nullptr, ptr(bs[k]), nullptr, T * O, O, bt,
                                          inv_b, x_max);
      }
      row_dots(ptr(acts[K - 1]) + lo * L.out[K - 1], ptr(wv), T, L.out[K - 1], bo, mut(out0) + lo);
      for (int64_t k = K - 1; k >= 1; --k) {  // g_k = gs_k W_k, gs_{k-1} = g_k s_{k-1}
        const int64_t I = L.in[k], O = L.out[k];
        float* g = mut(gins[k - 1]) + lo * I;
        gemm_rows(false, false, T, I, O, ptr(gss[k]) + lo * O, O, ptr(ws[k]), I, false, g, I);
        multiply(mut(gss[k - 1]) + lo * I, g, ptr(slopes[k - 1]) + lo * I, T * I);
      }
      gemm_rows(false, false, T, L.in[0], L.out[0], ptr(gss[0]) + lo * L.out[0], L.out[0], ptr(ws[0]), L.in[0],
                false, mut(g0) + lo * L.in[0], L.in[0]);
    }
  });
  std::vector<torch::Tensor> result{out0, g0};
  for (auto* group : {&acts, &slopes, &gss, &gins}) result.insert(result.end(), group->begin(), group->end());
  return result;
}

// {d_h0 (undefined unless need_h0), d_w, d_b_out, d_W_0..d_W_{K-1}, d_b_0..d_b_{K-1}} from the forward's saved
// tensors (acts = a_0..a_K, a_0 the input) and the gradients of its outputs (any may be None).
std::vector<torch::Tensor> sdf_mlp_backward(std::vector<torch::Tensor> ws, torch::Tensor w,
                                            std::vector<torch::Tensor> acts, std::vector<torch::Tensor> slopes,
                                            std::vector<torch::Tensor> gss, std::vector<torch::Tensor> gins,
                                            std::optional<torch::Tensor> d_out0, std::optional<torch::Tensor> d_top,
                                            std::optional<torch::Tensor> d_g0, bool need_h0, double beta) {
  TORCH_CHECK(!acts.empty(), "acts must hold the input and every layer's activation");
  const int64_t N = acts[0].size(0);
  const Widths L = layer_widths(ws, acts[0].size(1));
  const int64_t K = L.K;
  TORCH_CHECK(static_cast<int64_t>(acts.size()) == K + 1 && static_cast<int64_t>(slopes.size()) == K &&
                  static_cast<int64_t>(gss.size()) == K && static_cast<int64_t>(gins.size()) == K - 1,
              "the saved tensors do not match ", K, " layers");
  for (int64_t k = 0; k < K; ++k) {
    ws[k] = float_matrix(ws[k], L.out[k], L.in[k], "weight");
    acts[k] = float_matrix(acts[k], N, L.in[k], "activation");
    slopes[k] = float_matrix(slopes[k], N, L.out[k], "slope");
    gss[k] = float_matrix(gss[k], N, L.out[k], "gs");
    if (k < K - 1) gins[k] = float_matrix(gins[k], N, L.out[k], "g");
  }
  const int64_t top = L.out[K - 1];
  acts[K] = float_matrix(acts[K], N, top, "activation");
  const auto wv = float_vector(w, top, "w");
  auto given = [](const std::optional<torch::Tensor>& t) { return t.has_value() && t->defined(); };
  const bool has_out = given(d_out0), has_top = given(d_top), has_g0 = given(d_g0);
  torch::Tensor dov, dtv, dgv;
  if (has_out) dov = float_vector(*d_out0, N, "d_out0");
  if (has_top) dtv = float_matrix(*d_top, N, top, "d_top");
  if (has_g0) dgv = float_matrix(*d_g0, N, L.in[0], "d_g0");
  const auto opt = acts[0].options();
  torch::Tensor d_h0;
  if (need_h0) d_h0 = torch::empty({N, L.in[0]}, opt);

  // Per tile: every layer's weight gradient, bias gradient, and for the top layer d_w and sum(d_out0).
  const int64_t tiles = (N + kTile - 1) / kTile;
  // Offsets of each layer's weight and bias gradient in a tile's part, and of its d_gs in a tile's scratch.
  int64_t bias_total = 0, dgs_total = 0;
  std::vector<int64_t> w_off(K), b_off(K), dgs_off(K);
  for (int64_t k = 0, wo = 0; k < K; ++k) {
    w_off[k] = wo;
    b_off[k] = bias_total;
    dgs_off[k] = dgs_total;
    wo += L.out[k] * L.in[k];
    bias_total += L.out[k];
    dgs_total += kTile * L.out[k];
  }
  const int64_t slot = L.sum_weights + bias_total + 2 * top + 1;  // W's, b's, d_w (two parts), sum(d_out0)
  std::vector<float> part(static_cast<size_t>(std::max<int64_t>(tiles, 1) * slot), 0.0f);
  const float bt = static_cast<float>(beta);
  at::parallel_for(0, tiles, 1, [&](int64_t t0, int64_t t1) {
    SingleThreadedBlas one_thread;
    std::vector<float> dgs(has_g0 ? dgs_total : 0), dg(kTile * L.widest), dz(kTile * L.widest),
        da_buf(kTile * L.widest);
    for (int64_t t = t0; t < t1; ++t) {
      const int64_t lo = t * kTile, T = std::min(kTile, N - lo);
      float* p = part.data() + t * slot;
      float *p_w = p, *p_b = p + L.sum_weights, *p_dw = p_b + bias_total, *p_dw_chain = p_dw + top,
            *p_dout = p_dw_chain + top;
      if (has_g0) {  // the gradient's chain, bottom up: d_gs_k = d_g W_k^T, d_W_k = gs_k^T d_g, d_g <- d_gs_k s_k
        const float* d_g = ptr(dgv) + lo * L.in[0];
        for (int64_t k = 0; k < K; ++k) {
          const int64_t I = L.in[k], O = L.out[k];
          float* d_gs = dgs.data() + dgs_off[k];
          gemm_rows(false, true, T, O, I, d_g, I, ptr(ws[k]), I, false, d_gs, O);
          gemm_rows(true, false, O, I, T, ptr(gss[k]) + lo * O, O, d_g, I, false, p_w + w_off[k], I);
          if (k < K - 1) {
            multiply(dg.data(), d_gs, ptr(slopes[k]) + lo * O, T * O);
            d_g = dg.data();
          }
        }
      }
      const float* d_a = has_top ? ptr(dtv) + lo * top : nullptr;
      const float* d_o = has_out ? ptr(dov) + lo : nullptr;
      for (int64_t k = K - 1; k >= 0; --k) {  // each layer top down: dz_k, then d_W_k += dz^T a_k, d_a = dz W_k
        const int64_t I = L.in[k], O = L.out[k];
        const bool is_top = k == K - 1;
        const float* s = ptr(slopes[k]) + lo * O;
        const float* d_gs = has_g0 ? dgs.data() + dgs_off[k] : nullptr;
        const float* g = is_top ? nullptr : ptr(gins[k]) + lo * O;
        const float* dn = is_top ? d_o : nullptr;
        float* db = p_b + b_off[k];
#define ANISDF_LAYER(A, O_, D, G) \
  layer_backward_block<A, O_, D, G>(0, T, O, bt, s, d_a, dn, ptr(wv), d_gs, g, dz.data(), db, p_dw_chain)
        const bool a = d_a != nullptr, o = dn != nullptr;
        if (has_g0 && !is_top) {
          if (a && o) ANISDF_LAYER(true, true, true, true);
          else if (a) ANISDF_LAYER(true, false, true, true);
          else if (o) ANISDF_LAYER(false, true, true, true);
          else ANISDF_LAYER(false, false, true, true);
        } else if (has_g0) {
          if (a && o) ANISDF_LAYER(true, true, true, false);
          else if (a) ANISDF_LAYER(true, false, true, false);
          else if (o) ANISDF_LAYER(false, true, true, false);
          else ANISDF_LAYER(false, false, true, false);
        } else {
          if (a && o) ANISDF_LAYER(true, true, false, false);
          else if (a) ANISDF_LAYER(true, false, false, false);
          else if (o) ANISDF_LAYER(false, true, false, false);
          else ANISDF_LAYER(false, false, false, false);
        }
#undef ANISDF_LAYER
        const float* a_k = ptr(acts[k]) + lo * I;
        gemm_rows(true, false, O, I, T, dz.data(), O, a_k, I, has_g0, p_w + w_off[k], I);
        if (k > 0 || need_h0) {
          float* out = k == 0 ? mut(d_h0) + lo * I : da_buf.data();
          gemm_rows(false, false, T, I, O, dz.data(), O, ptr(ws[k]), I, false, out, I);
          d_a = out;
        }
      }
      if (has_out) {
        column_dots(ptr(acts[K]) + lo * top, d_o, T, top, p_dw);
        float sum = 0.0f;
        for (int64_t r = 0; r < T; ++r) sum += d_o[r];
        p_dout[0] = sum;
      }
    }
  });
  // The tiles' parts, added in tile order.
  auto total = torch::zeros({slot}, opt);
  float* tot = mut(total);
  at::parallel_for(0, slot, 1024, [&](int64_t j0, int64_t j1) {
    for (int64_t t = 0; t < tiles; ++t) {
      const float* p = part.data() + t * slot;
      for (int64_t j = j0; j < j1; ++j) tot[j] += p[j];
    }
  });
  std::vector<torch::Tensor> result{d_h0};
  // d_w = the out0 part + the gradient chain's part (zero where d_g0 was None: nothing wrote it)
  const auto d_w = total.narrow(0, L.sum_weights + bias_total, top) +
                   total.narrow(0, L.sum_weights + bias_total + top, top);
  result.push_back(d_w);
  result.push_back(total.narrow(0, slot - 1, 1).reshape({}).clone());
  for (int64_t k = 0; k < K; ++k)  // copies, not views of one buffer: each becomes a parameter's .grad
    result.push_back(total.narrow(0, w_off[k], L.out[k] * L.in[k]).view({L.out[k], L.in[k]}).clone());
  for (int64_t k = 0; k < K; ++k) result.push_back(total.narrow(0, L.sum_weights + b_off[k], L.out[k]).clone());
  return result;
}
