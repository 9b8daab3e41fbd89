// Ray marching through the occupancy grid in one pass per ray (anisdf/model_components/ray_marching.py holds the
// PyTorch reference, which builds every ray's [R, K] steps, their cells and a mask before packing the kept ones).
//
// Sample k of ray i sits at t = near_i + (k + u_i) step, for k < max_samples while t < far_i, and is kept where its
// cell is occupied. The cell is computed as the reference computes it, one axis at a time in cell units:
//   c = floor(a + b t) clamped to [0, res - 1],  a = (o + radius) inv,  b = d inv,  inv = 1 / cell size
// in float32 with the same operations in the same order (built with -ffp-contract=off: no fused multiply-adds),
// so both keep the same samples. Two passes over the rays: count, then write at each ray's offset; the samples
// come out ordered by ray, then by distance, as the reference packs them.

#include <torch/extension.h>

#include <ATen/Parallel.h>

#include <cmath>
#include <cstdint>
#include <vector>

namespace {

struct Ray {
  float a[3], b[3], near, far, u;
};

template <typename Visit>
inline void walk(const Ray& r, float step, int64_t max_samples, const bool* occ, int32_t res, Visit visit) {
  for (int64_t k = 0; k < max_samples; ++k) {
    const float t = r.near + (static_cast<float>(k) + r.u) * step;
    if (!(t < r.far)) break;
    if (occ != nullptr) {
      int32_t idx = 0;
      for (int axis = 0; axis < 3; ++axis) {
        float c = std::floor(r.a[axis] + r.b[axis] * t);
        c = c < 0.0f ? 0.0f : (c > static_cast<float>(res - 1) ? static_cast<float>(res - 1) : c);
        idx = axis == 0 ? static_cast<int32_t>(c) : idx * res + static_cast<int32_t>(c);
      }
      if (!occ[idx]) continue;
    }
    visit(t);
  }
}

}  // namespace

// (ray_idx int64 [S], t float32 [S]) of the kept samples.
std::vector<torch::Tensor> march_rays(torch::Tensor origins, torch::Tensor dirs, torch::Tensor near, torch::Tensor far,
                                      torch::Tensor u, double step, int64_t max_samples,
                                      std::optional<torch::Tensor> occupied, double radius, double inv_cell,
                                      int64_t resolution) {
  auto f32 = [](const torch::Tensor& t, const char* what) {
    TORCH_CHECK(t.device().is_cpu() && t.scalar_type() == torch::kFloat32, what, " must be a float32 CPU tensor");
    return t.contiguous();
  };
  const auto o = f32(origins, "origins"), d = f32(dirs, "dirs"), n = f32(near, "near"), f = f32(far, "far"),
             uu = f32(u, "u");
  const int64_t R = o.size(0);
  TORCH_CHECK(o.dim() == 2 && o.size(1) == 3 && d.sizes() == o.sizes(), "origins and dirs must be [R, 3]");
  TORCH_CHECK(n.numel() == R && f.numel() == R && uu.numel() == R, "near, far and u need one value per ray");
  const bool has_grid = occupied.has_value() && occupied->defined();
  torch::Tensor occ;
  if (has_grid) {
    occ = occupied->contiguous();
    TORCH_CHECK(occ.device().is_cpu() && occ.scalar_type() == torch::kBool &&
                    occ.numel() == resolution * resolution * resolution,
                "occupied must be a bool CPU grid of resolution^3 cells");
  }
  const float rad = static_cast<float>(radius), inv = static_cast<float>(inv_cell), st = static_cast<float>(step);
  const float* op = o.data_ptr<float>();
  const float* dp = d.data_ptr<float>();
  const float* np = n.data_ptr<float>();
  const float* fp = f.data_ptr<float>();
  const float* up = uu.data_ptr<float>();
  const bool* gp = has_grid ? occ.data_ptr<bool>() : nullptr;
  const int32_t res = static_cast<int32_t>(resolution);
  auto ray = [&](int64_t i) {
    Ray r;
    for (int axis = 0; axis < 3; ++axis) {
      r.a[axis] = (op[i * 3 + axis] + rad) * inv;
      r.b[axis] = dp[i * 3 + axis] * inv;
    }
    r.near = np[i];
    r.far = fp[i];
    r.u = up[i];
    return r;
  };
  std::vector<int64_t> offset(static_cast<size_t>(R) + 1, 0);
  at::parallel_for(0, R, 64, [&](int64_t lo, int64_t hi) {
    for (int64_t i = lo; i < hi; ++i) {
      int64_t c = 0;
      walk(ray(i), st, max_samples, gp, res, [&](float) { ++c; });
      offset[i + 1] = c;
    }
  });
  for (int64_t i = 0; i < R; ++i) offset[i + 1] += offset[i];
  auto ray_idx = torch::empty({offset[R]}, o.options().dtype(torch::kLong));
  auto t_out = torch::empty({offset[R]}, o.options());
  int64_t* rp = ray_idx.data_ptr<int64_t>();
  float* tp = t_out.data_ptr<float>();
  at::parallel_for(0, R, 64, [&](int64_t lo, int64_t hi) {
    for (int64_t i = lo; i < hi; ++i) {
      int64_t w = offset[i];
      walk(ray(i), st, max_samples, gp, res, [&](float t) {
        rp[w] = i;
        tp[w] = t;
        ++w;
      });
    }
  });
  return {ray_idx, t_out};
}
