// The element-wise passes of the colour heads' ReLU layers, around PyTorch's matrix products
// (anisdf/fields/mlp.py; the PyTorch reference is the nn.Sequential itself).
//
//   forward, after z = h W^T:  z <- max(z + b, 0) in place (the product writes z once; addmm copies the bias in first)
//   backward:                  d <- d * (a > 0) in place, and db = sum over rows of d
//
// Column sums are taken over fixed blocks of kBlockRows rows and the blocks added in order: the result does not
// depend on the number of threads (same seed, same result).

#include <torch/extension.h>

#include <ATen/Parallel.h>

#include <algorithm>
#include <cstdint>
#include <vector>

namespace {

constexpr int64_t kBlockRows = 256;

void check_rows(const torch::Tensor& t, const char* what) {
  TORCH_CHECK(t.device().is_cpu() && t.scalar_type() == torch::kFloat32 && t.dim() == 2 && t.is_contiguous(), what,
              " must be a contiguous float32 CPU matrix");
}

void check_bias(const torch::Tensor& b, int64_t H) {
  TORCH_CHECK(b.device().is_cpu() && b.scalar_type() == torch::kFloat32 && b.dim() == 1 && b.size(0) == H,
              "b must be a float32 CPU vector of ", H, " elements, got ", b.sizes());
}

}  // namespace

// z <- max(z + b, 0) (relu) or z + b, in place; returns z.
torch::Tensor bias_act_(torch::Tensor z, torch::Tensor b, bool relu) {
  check_rows(z, "z");
  const int64_t N = z.size(0), H = z.size(1);
  check_bias(b, H);
  const auto bc = b.contiguous();
  float* zp = z.data_ptr<float>();
  const float* bp = bc.data_ptr<float>();
  at::parallel_for(0, N, kBlockRows, [&](int64_t lo, int64_t hi) {
    float* __restrict__ zr = zp + lo * H;
    const float* __restrict__ br = bp;
    for (int64_t o = 0; o < (hi - lo) * H; o += H) {
      if (relu) {
        for (int64_t j = 0; j < H; ++j) {
          const float v = zr[o + j] + br[j];
          zr[o + j] = v > 0.0f ? v : 0.0f;
        }
      } else {
        for (int64_t j = 0; j < H; ++j) zr[o + j] += br[j];
      }
    }
  });
  return z;
}

// d <- d * (a > 0) in place; returns the column sums of the result.
torch::Tensor relu_backward_(torch::Tensor d, torch::Tensor a) {
  check_rows(d, "d");
  check_rows(a, "a");
  TORCH_CHECK(a.sizes() == d.sizes(), "a must be shaped like d ", d.sizes(), ", got ", a.sizes());
  const int64_t N = d.size(0), H = d.size(1);
  const int64_t blocks = (N + kBlockRows - 1) / kBlockRows;
  std::vector<float> part(static_cast<size_t>(std::max<int64_t>(blocks, 1) * H), 0.0f);
  float* dp = d.data_ptr<float>();
  const float* ap = a.data_ptr<float>();
  at::parallel_for(0, blocks, 1, [&](int64_t b0, int64_t b1) {
    for (int64_t blk = b0; blk < b1; ++blk) {
      const int64_t lo = blk * kBlockRows, hi = std::min(N, lo + kBlockRows);
      float* __restrict__ dr = dp + lo * H;
      const float* __restrict__ ar = ap + lo * H;
      float* __restrict__ acc = part.data() + blk * H;
      for (int64_t o = 0; o < (hi - lo) * H; o += H) {
        for (int64_t j = 0; j < H; ++j) {
          const float v = ar[o + j] > 0.0f ? dr[o + j] : 0.0f;
          dr[o + j] = v;
          acc[j] += v;
        }
      }
    }
  });
  auto db = torch::zeros({H}, d.options());
  float* dbp = db.data_ptr<float>();
  for (int64_t blk = 0; blk < blocks; ++blk)
    for (int64_t j = 0; j < H; ++j) dbp[j] += part[blk * H + j];
  return db;
}
