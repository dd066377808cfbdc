// CPU kernels of the NeRF grid field: multi-resolution trilinear grid features (forward and
// the backward to the grid) and occupancy-grid ray marching.
//
// Grid features: every level is a dense grid of R^3 vertices with F features, stored one
// level after another in a table [V, F]; vertex (x, y, z) of a level sits at row
// offset + (z R + y) R + x and at the normalised position -1 + 2 (x, y, z) / (R - 1), as
// torch.nn.functional.grid_sample(align_corners=True, padding_mode="border") reads it.
// The forward runs sample-parallel; the backward runs level-parallel, so no two threads ever
// add into the same row and no atomics are needed.
//
// Marching: each ray's [t_near, t_far] is walked cell by cell through an occupancy grid
// (Amanatides-Woo); the occupied stretches are concatenated, and the ray gets
// n = min(max_samples, ceil(L / min_step)) stratified samples spread evenly over the
// occupied length L. Early in training (everything occupied) a ray costs max_samples; once
// empty space is known its samples crowd into the few occupied cells, never closer than
// min_step. The Python twins in backbones/nerf/reference.py define the same results in torch.

// The few ATen headers these kernels use, not <torch/extension.h>: that one takes 28 s of a
// 35 s build (it parses all of libtorch's C++ API and pybind11); docs/gs_cpu.md, "Build time".
#include <ATen/core/Tensor.h>
#include <ATen/Dispatch.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/zeros.h>
#include <torch/library.h>
#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <type_traits>
#include <vector>

namespace {

void check_cpu(const at::Tensor& t, const char* name) {
  TORCH_CHECK(t.device().is_cpu() && t.is_contiguous(), name, " must be a contiguous CPU tensor");
}

// The 8 corner rows and trilinear weights of one position in one level.
template <typename scalar_t>
inline void corners(const scalar_t* p, int64_t resolution, int64_t offset, int64_t* rows, scalar_t* weights) {
  int64_t base[3];
  scalar_t frac[3];
  const scalar_t top = scalar_t(resolution - 1);
  for (int a = 0; a < 3; ++a) {
    scalar_t u = (p[a] + scalar_t(1)) * scalar_t(0.5) * top;
    u = u > scalar_t(0) ? (u < top ? u : top) : scalar_t(0);  // padding_mode="border"; NaN -> 0
    const int64_t i = std::min(static_cast<int64_t>(u), resolution - 2);  // u >= 0: truncation is floor
    base[a] = i;
    frac[a] = u - scalar_t(i);
  }
  const int64_t row0 = offset + (base[2] * resolution + base[1]) * resolution + base[0];
  const int64_t dy = resolution, dz = resolution * resolution;
  const scalar_t wx[2] = {1 - frac[0], frac[0]}, wy[2] = {1 - frac[1], frac[1]}, wz[2] = {1 - frac[2], frac[2]};
  for (int c = 0; c < 8; ++c) {
    const int x = c & 1, y = (c >> 1) & 1, z = (c >> 2) & 1;
    rows[c] = row0 + x + y * dy + z * dz;
    weights[c] = wx[x] * wy[y] * wz[z];
  }
}

void check_grid_args(const at::Tensor& positions, const at::Tensor& table, const at::Tensor& resolutions,
                     const at::Tensor& offsets) {
  check_cpu(positions, "positions");
  check_cpu(table, "table");
  check_cpu(resolutions, "resolutions");
  check_cpu(offsets, "offsets");
  TORCH_CHECK(positions.dim() == 2 && positions.size(1) == 3, "positions must have shape [M, 3]");
  TORCH_CHECK(table.dim() == 2, "table must have shape [V, F]");
  TORCH_CHECK(positions.scalar_type() == table.scalar_type(), "positions and table must have the same dtype");
  TORCH_CHECK(resolutions.scalar_type() == at::kLong && offsets.scalar_type() == at::kLong,
              "resolutions and offsets must be int64");
  TORCH_CHECK(resolutions.numel() == offsets.numel(), "one offset per level");
  const int64_t* res = resolutions.data_ptr<int64_t>();
  const int64_t* off = offsets.data_ptr<int64_t>();
  for (int64_t l = 0; l < resolutions.numel(); ++l) {
    TORCH_CHECK(res[l] >= 2, "every level needs at least 2 vertices per side");
    TORCH_CHECK(off[l] >= 0 && off[l] + res[l] * res[l] * res[l] <= table.size(0), "level ", l,
                " does not fit in the table");
  }
}

// F (features per level) is a template argument for the common sizes, so the feature loops unroll.
template <typename scalar_t, int F>
void encode_forward_kernel(const scalar_t* pos, const scalar_t* tab, const int64_t* res, const int64_t* off,
                           int64_t M, int64_t L, int64_t features, scalar_t* out) {
  const int64_t width = F > 0 ? F : features;
#pragma omp parallel for schedule(static)
  for (int64_t m = 0; m < M; ++m) {
    int64_t rows[8];
    scalar_t weights[8];
    for (int64_t l = 0; l < L; ++l) {
      corners(pos + 3 * m, res[l], off[l], rows, weights);
      scalar_t* o = out + (m * L + l) * width;
      for (int64_t f = 0; f < width; ++f) o[f] = 0;
      for (int c = 0; c < 8; ++c) {
        const scalar_t* row = tab + rows[c] * width;
        for (int64_t f = 0; f < width; ++f) o[f] += weights[c] * row[f];
      }
    }
  }
}

template <typename scalar_t, int F>
void encode_backward_kernel(const scalar_t* grad, const scalar_t* pos, const int64_t* res, const int64_t* off,
                            int64_t M, int64_t L, int64_t features, scalar_t* out) {
  const int64_t width = F > 0 ? F : features;
#pragma omp parallel for schedule(dynamic, 1)
  for (int64_t l = 0; l < L; ++l) {
    int64_t rows[8];
    scalar_t weights[8];
    for (int64_t m = 0; m < M; ++m) {
      corners(pos + 3 * m, res[l], off[l], rows, weights);
      const scalar_t* g = grad + (m * L + l) * width;
      for (int c = 0; c < 8; ++c) {
        scalar_t* row = out + rows[c] * width;
        for (int64_t f = 0; f < width; ++f) row[f] += weights[c] * g[f];
      }
    }
  }
}

template <typename scalar_t, typename Kernel>
void with_feature_count(int64_t features, Kernel kernel) {
  switch (features) {
    case 1: kernel(std::integral_constant<int, 1>{}); break;
    case 2: kernel(std::integral_constant<int, 2>{}); break;
    case 4: kernel(std::integral_constant<int, 4>{}); break;
    default: kernel(std::integral_constant<int, 0>{});
  }
}

at::Tensor grid_encode_forward(at::Tensor positions, at::Tensor table, at::Tensor resolutions,
                               at::Tensor offsets) {
  check_grid_args(positions, table, resolutions, offsets);
  const int64_t M = positions.size(0), F = table.size(1), L = resolutions.numel();
  auto features = at::empty({M, L * F}, table.options());
  AT_DISPATCH_FLOATING_TYPES(table.scalar_type(), "grid_encode_forward", [&] {
    with_feature_count<scalar_t>(F, [&](auto width) {
      encode_forward_kernel<scalar_t, decltype(width)::value>(
          positions.data_ptr<scalar_t>(), table.data_ptr<scalar_t>(), resolutions.data_ptr<int64_t>(),
          offsets.data_ptr<int64_t>(), M, L, F, features.data_ptr<scalar_t>());
    });
  });
  return features;
}

at::Tensor grid_encode_backward(at::Tensor grad_features, at::Tensor positions, at::Tensor resolutions,
                                at::Tensor offsets, int64_t table_rows) {
  check_cpu(grad_features, "grad_features");
  const int64_t M = positions.size(0), L = resolutions.numel();
  TORCH_CHECK(grad_features.dim() == 2 && grad_features.size(0) == M && grad_features.size(1) % L == 0,
              "grad_features must have shape [M, levels * F]");
  const int64_t F = grad_features.size(1) / L;
  auto grad_table = at::zeros({table_rows, F}, grad_features.options());
  check_grid_args(positions, grad_table, resolutions, offsets);
  AT_DISPATCH_FLOATING_TYPES(grad_features.scalar_type(), "grid_encode_backward", [&] {
    with_feature_count<scalar_t>(F, [&](auto width) {
      encode_backward_kernel<scalar_t, decltype(width)::value>(
          grad_features.data_ptr<scalar_t>(), positions.data_ptr<scalar_t>(), resolutions.data_ptr<int64_t>(),
          offsets.data_ptr<int64_t>(), M, L, F, grad_table.data_ptr<scalar_t>());
    });
  });
  return grad_table;
}

struct Interval {
  float start, end;
};

// The occupied stretches of one ray, in order, touching stretches merged.
void occupied_intervals(const float* p0, const float* dn, float t_near, float t_far, const uint8_t* occupancy,
                        int64_t G, std::vector<Interval>& intervals) {
  intervals.clear();
  const float inf = std::numeric_limits<float>::infinity();
  // Outside the grid's cube [-1, 1]^3 counts as empty: clip the segment to the cube first.
  for (int a = 0; a < 3; ++a) {
    if (dn[a] != 0.0f) {
      const float t0 = (-1.0f - p0[a]) / dn[a], t1 = (1.0f - p0[a]) / dn[a];
      t_near = std::max(t_near, std::min(t0, t1));
      t_far = std::min(t_far, std::max(t0, t1));
    } else if (p0[a] < -1.0f || p0[a] > 1.0f) {
      return;
    }
  }
  if (!(t_far > t_near)) return;
  const float cell = 2.0f / float(G);
  int64_t index[3];
  int step[3];
  float t_next[3], t_delta[3];
  for (int a = 0; a < 3; ++a) {
    const float pos = p0[a] + t_near * dn[a];
    index[a] = std::min<int64_t>(G - 1, std::max<int64_t>(0, static_cast<int64_t>(std::floor((pos + 1.0f) / cell))));
    if (dn[a] > 0.0f) {
      step[a] = 1;
      t_next[a] = (-1.0f + cell * float(index[a] + 1) - p0[a]) / dn[a];
      t_delta[a] = cell / dn[a];
    } else if (dn[a] < 0.0f) {
      step[a] = -1;
      t_next[a] = (-1.0f + cell * float(index[a]) - p0[a]) / dn[a];
      t_delta[a] = -cell / dn[a];
    } else {
      step[a] = 0;
      t_next[a] = inf;
      t_delta[a] = inf;
    }
  }
  float t = t_near;
  while (t < t_far) {
    int axis = 0;
    if (t_next[1] < t_next[axis]) axis = 1;
    if (t_next[2] < t_next[axis]) axis = 2;
    const float t_exit = std::min(std::max(t_next[axis], t), t_far);
    if (occupancy[(index[2] * G + index[1]) * G + index[0]] && t_exit > t) {
      if (!intervals.empty() && intervals.back().end == t) {
        intervals.back().end = t_exit;
      } else {
        intervals.push_back({t, t_exit});
      }
    }
    if (t_exit >= t_far) break;
    index[axis] += step[axis];
    if (index[axis] < 0 || index[axis] >= G) break;
    t = t_exit;
    t_next[axis] += t_delta[axis];
  }
}

std::vector<at::Tensor> march_rays(at::Tensor origins, at::Tensor directions, at::Tensor t_near,
                                   at::Tensor t_far, at::Tensor occupancy, at::Tensor center,
                                   double scale, double min_step, int64_t max_samples, at::Tensor jitter) {
  for (auto* t : {&origins, &directions, &t_near, &t_far, &center}) {
    check_cpu(*t, "marching inputs");
    TORCH_CHECK(t->scalar_type() == at::kFloat, "marching inputs must be float32");
  }
  check_cpu(occupancy, "occupancy");
  TORCH_CHECK(occupancy.scalar_type() == at::kByte && occupancy.dim() == 3 &&
                  occupancy.size(0) == occupancy.size(1) && occupancy.size(1) == occupancy.size(2),
              "occupancy must be a uint8 tensor [G, G, G]");
  const int64_t N = origins.size(0), S = max_samples, G = occupancy.size(0);
  TORCH_CHECK(S >= 1 && min_step > 0 && scale > 0, "max_samples >= 1, min_step > 0 and scale > 0 are required");
  const bool stratified = jitter.numel() > 0;
  if (stratified) {
    check_cpu(jitter, "jitter");
    TORCH_CHECK(jitter.scalar_type() == at::kFloat && jitter.dim() == 2 && jitter.size(0) == N &&
                    jitter.size(1) == S, "jitter must be float32 [N, max_samples]");
  }
  auto t_out = at::zeros({N, S}, origins.options());
  auto delta_out = at::zeros({N, S}, origins.options());
  auto counts = at::zeros({N}, origins.options().dtype(at::kLong));
  const float* o = origins.data_ptr<float>();
  const float* d = directions.data_ptr<float>();
  const float* tn = t_near.data_ptr<float>();
  const float* tf = t_far.data_ptr<float>();
  const float* c = center.data_ptr<float>();
  const uint8_t* occ = occupancy.data_ptr<uint8_t>();
  const float* u = stratified ? jitter.data_ptr<float>() : nullptr;
  float* t_ptr = t_out.data_ptr<float>();
  float* delta_ptr = delta_out.data_ptr<float>();
  int64_t* count_ptr = counts.data_ptr<int64_t>();
  const float inv_scale = float(1.0 / scale);
#pragma omp parallel
  {
    std::vector<Interval> intervals;
#pragma omp for schedule(dynamic, 64)
    for (int64_t r = 0; r < N; ++r) {
      float p0[3], dn[3];
      for (int a = 0; a < 3; ++a) {
        p0[a] = (o[3 * r + a] - c[a]) * inv_scale;
        dn[a] = d[3 * r + a] * inv_scale;
      }
      occupied_intervals(p0, dn, tn[r], tf[r], occ, G, intervals);
      double length = 0.0;
      for (const auto& iv : intervals) length += iv.end - iv.start;
      if (!(length > 0.0)) continue;
      const double step = std::max(min_step, length / double(S));
      const int64_t n = std::max<int64_t>(1, std::min<int64_t>(S, static_cast<int64_t>(std::ceil(length / step - 1e-6))));
      size_t k_interval = 0;
      double before = 0.0;  // occupied length of the intervals before k_interval
      for (int64_t k = 0; k < n; ++k) {
        const double s0 = double(k) * step;
        const double s1 = k == n - 1 ? length : double(k + 1) * step;
        const double s = s0 + (stratified ? double(u[r * S + k]) : 0.5) * (s1 - s0);
        while (k_interval + 1 < intervals.size() &&
               before + (intervals[k_interval].end - intervals[k_interval].start) <= s) {
          before += intervals[k_interval].end - intervals[k_interval].start;
          ++k_interval;
        }
        const Interval& iv = intervals[k_interval];
        t_ptr[r * S + k] = std::min(iv.end, float(iv.start + (s - before)));
        delta_ptr[r * S + k] = float(s1 - s0);
      }
      count_ptr[r] = n;
    }
  }
  return {t_out, delta_out, counts};
}

}  // namespace

TORCH_LIBRARY(TORCH_EXTENSION_NAME, m) {
  m.def("grid_encode_forward", &grid_encode_forward);  // multi-resolution trilinear grid features
  m.def("grid_encode_backward", &grid_encode_backward);  // gradient of grid_encode_forward to the table
  m.def("march_rays", &march_rays);  // stratified samples over the occupied stretches of each ray
}
