// CPU kernels of the 3D Gaussian Splatting rasteriser: spherical harmonics, projection, tile
// binning, front-to-back compositing of any number of channels, and their analytic backward passes.
//
// Projection culls and compacts: everything after it (SH colours, binning, compositing) works
// on the V visible Gaussians only, and the backward passes scatter into the N rows again.
//
// Compositing runs Gaussian-outer, pixel-inner inside each 16 x 16 tile, 8 pixels at a time:
// each row of a Gaussian's box is covered by the one or two aligned 8-pixel chunks it touches,
// a fixed-width loop the compiler turns into vector instructions (a box is typically 3-12
// pixels wide, too short for a variable-length loop to vectorise). Per pixel, Gaussians are
// still visited in depth order, so every pixel follows the exact 3DGS rules (alpha clamp 0.99,
// skip alpha < 1/255, stop before T < 1e-4). The plain-torch twins in backbones/gs/reference.py
// and backbones/gs/sh.py define the same results.

// The few ATen headers these kernels use, not <torch/extension.h>: that one takes 28 s of a
// 35 s build (it parses all of libtorch's C++ API and pybind11); docs/gs_cpu.md, "Build time".
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/zeros.h>
#include <ATen/ops/zeros_like.h>
#include <torch/library.h>
#include <omp.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <vector>

namespace {

constexpr int kTile = 16;
constexpr int kTilePixels = kTile * kTile;
constexpr int kChunk = 8;
constexpr float kAlphaMax = 0.99f;
constexpr float kAlphaMin = 1.0f / 255.0f;
constexpr float kTransmittanceMin = 1e-4f;
constexpr float kDilation = 0.3f;
constexpr float kQuatNormMin2 = 1e-20f;
constexpr float kDirectionNormMin = 1e-12f;

// exp(x) for the x <= 0 this rasteriser needs, in a form the compiler vectorises on any x86-64
// (Cephes range reduction and polynomial, within 2 ulp of expf). For t <= 0, truncating t - 0.5
// rounds to nearest, which needs no floor instruction.
inline float exp_nonpositive(float x) {
  x = x < -87.0f ? -87.0f : x;
  const float n = static_cast<float>(static_cast<int32_t>(x * 1.44269504088896341f - 0.5f));
  const float r = x - n * 0.693359375f + n * 2.12194440e-4f;
  float p = 1.9875691500e-4f;
  p = p * r + 1.3981999507e-3f;
  p = p * r + 8.3334519073e-3f;
  p = p * r + 4.1665795894e-2f;
  p = p * r + 1.6666665459e-1f;
  p = p * r + 5.0000001201e-1f;
  p = p * r * r + r + 1.0f;
  const int32_t bits = (static_cast<int32_t>(n) + 127) << 23;
  float scale;
  std::memcpy(&scale, &bits, sizeof(float));
  return p * scale;
}

void check_cpu_float(const at::Tensor& t, const char* name) {
  TORCH_CHECK(t.device().is_cpu() && t.scalar_type() == at::kFloat && t.is_contiguous(), name,
              " must be a contiguous float32 CPU tensor");
}

void check_rows(const at::Tensor& t, const char* name, int64_t rows, int64_t width) {
  check_cpu_float(t, name);
  TORCH_CHECK(t.dim() == 2 && t.size(0) == rows && t.size(1) == width, name, " must have shape [", rows, ", ",
              width, "]");
}

// ------------------------------------------------------------------------ spherical harmonics
constexpr float kC0 = 0.28209479177387814f;
constexpr float kC1 = 0.4886025119029199f;
constexpr float kC2[5] = {1.0925484305920792f, -1.0925484305920792f, 0.31539156525252005f, -1.0925484305920792f,
                          0.5462742152960396f};
constexpr float kC3[7] = {-0.5900435899266435f, 2.890611442640554f, -0.4570457994644658f, 0.3731763325901154f,
                          -0.4570457994644658f, 1.445305721320277f, -0.5900435899266435f};

// SH basis values b[16] at unit direction (x, y, z), and with `grad` their partial derivatives
// db/dx, db/dy, db/dz, in the 3DGS order.
inline void sh_basis(int degree, float x, float y, float z, float* b, float (*grad)[3]) {
  b[0] = kC0;
  if (grad) grad[0][0] = grad[0][1] = grad[0][2] = 0.f;
  if (degree < 1) return;
  b[1] = -kC1 * y; b[2] = kC1 * z; b[3] = -kC1 * x;
  if (grad) {
    const float g[3][3] = {{0.f, -kC1, 0.f}, {0.f, 0.f, kC1}, {-kC1, 0.f, 0.f}};
    for (int j = 0; j < 3; ++j)
      for (int a = 0; a < 3; ++a) grad[1 + j][a] = g[j][a];
  }
  if (degree < 2) return;
  const float xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
  b[4] = kC2[0] * xy; b[5] = kC2[1] * yz; b[6] = kC2[2] * (2.f * zz - xx - yy);
  b[7] = kC2[3] * xz; b[8] = kC2[4] * (xx - yy);
  if (grad) {
    const float g[5][3] = {{kC2[0] * y, kC2[0] * x, 0.f},
                           {0.f, kC2[1] * z, kC2[1] * y},
                           {-2.f * kC2[2] * x, -2.f * kC2[2] * y, 4.f * kC2[2] * z},
                           {kC2[3] * z, 0.f, kC2[3] * x},
                           {2.f * kC2[4] * x, -2.f * kC2[4] * y, 0.f}};
    for (int j = 0; j < 5; ++j)
      for (int a = 0; a < 3; ++a) grad[4 + j][a] = g[j][a];
  }
  if (degree < 3) return;
  b[9] = kC3[0] * y * (3.f * xx - yy);
  b[10] = kC3[1] * xy * z;
  b[11] = kC3[2] * y * (4.f * zz - xx - yy);
  b[12] = kC3[3] * z * (2.f * zz - 3.f * xx - 3.f * yy);
  b[13] = kC3[4] * x * (4.f * zz - xx - yy);
  b[14] = kC3[5] * z * (xx - yy);
  b[15] = kC3[6] * x * (xx - 3.f * yy);
  if (grad) {
    const float g[7][3] = {{kC3[0] * 6.f * xy, kC3[0] * (3.f * xx - 3.f * yy), 0.f},
                           {kC3[1] * yz, kC3[1] * xz, kC3[1] * xy},
                           {kC3[2] * -2.f * xy, kC3[2] * (4.f * zz - xx - 3.f * yy), kC3[2] * 8.f * yz},
                           {kC3[3] * -6.f * xz, kC3[3] * -6.f * yz, kC3[3] * (6.f * zz - 3.f * xx - 3.f * yy)},
                           {kC3[4] * (4.f * zz - 3.f * xx - yy), kC3[4] * -2.f * xy, kC3[4] * 8.f * xz},
                           {kC3[5] * 2.f * xz, kC3[5] * -2.f * yz, kC3[5] * (xx - yy)},
                           {kC3[6] * (3.f * xx - 3.f * yy), kC3[6] * -6.f * xy, 0.f}};
    for (int j = 0; j < 7; ++j)
      for (int a = 0; a < 3; ++a) grad[9 + j][a] = g[j][a];
  }
}

// Unit direction from the camera centre to a mean, with the norm clamped as view_directions does.
inline float view_direction(const float* mean, const float* center, float* dir) {
  float offset[3], norm2 = 0.f;
  for (int a = 0; a < 3; ++a) {
    offset[a] = mean[a] - center[a];
    norm2 += offset[a] * offset[a];
  }
  const float norm = std::max(std::sqrt(norm2), kDirectionNormMin);
  for (int a = 0; a < 3; ++a) dir[a] = offset[a] / norm;
  return std::sqrt(norm2);
}

}  // namespace

// Colours [V, 3] (without 3DGS's +0.5) of the Gaussians `index` [V] seen from `center` [3].
// sh_dc [N, 1, 3] and sh_rest [N, K - 1, 3] are the coefficients; `degree` the active degree.
at::Tensor sh_forward(at::Tensor sh_dc, at::Tensor sh_rest, at::Tensor means, at::Tensor index,
                      at::Tensor center, int64_t degree) {
  check_cpu_float(sh_dc, "sh_dc");
  check_cpu_float(sh_rest, "sh_rest");
  check_cpu_float(means, "means");
  check_cpu_float(center, "center");
  TORCH_CHECK(index.scalar_type() == at::kLong && index.is_contiguous(), "index must be contiguous int64");
  const int64_t rest = sh_rest.size(1), v_count = index.size(0);
  TORCH_CHECK((degree + 1) * (degree + 1) <= rest + 1, "SH degree ", degree, " needs ", (degree + 1) * (degree + 1),
              " coefficients per channel, got ", rest + 1);
  const int bases = (int)((degree + 1) * (degree + 1));
  auto colors = at::empty({v_count, 3}, sh_dc.options());
  const float *dc = sh_dc.data_ptr<float>(), *rs = sh_rest.data_ptr<float>(), *m = means.data_ptr<float>();
  const float* c = center.data_ptr<float>();
  const int64_t* idx = index.data_ptr<int64_t>();
  float* out = colors.data_ptr<float>();
#pragma omp parallel for schedule(static)
  for (int64_t v = 0; v < v_count; ++v) {
    const int64_t g = idx[v];
    float dir[3], b[16];
    view_direction(m + 3 * g, c, dir);
    sh_basis((int)degree, dir[0], dir[1], dir[2], b, nullptr);
    for (int ch = 0; ch < 3; ++ch) {
      float sum = b[0] * dc[3 * g + ch];
      for (int j = 1; j < bases; ++j) sum += b[j] * rs[(g * rest + j - 1) * 3 + ch];
      out[3 * v + ch] = sum;
    }
  }
  return colors;
}

// Gradients of sh_forward with respect to sh_dc, sh_rest and means (through the view direction).
std::vector<at::Tensor> sh_backward(at::Tensor sh_dc, at::Tensor sh_rest, at::Tensor means,
                                    at::Tensor index, at::Tensor center, int64_t degree,
                                    at::Tensor v_colors) {
  check_cpu_float(v_colors, "v_colors");
  const int64_t rest = sh_rest.size(1), v_count = index.size(0);
  const int bases = (int)((degree + 1) * (degree + 1));
  auto v_dc = at::zeros_like(sh_dc);
  auto v_rest = at::zeros_like(sh_rest);
  auto v_means = at::zeros_like(means);
  const float *dc = sh_dc.data_ptr<float>(), *rs = sh_rest.data_ptr<float>(), *m = means.data_ptr<float>();
  const float *c = center.data_ptr<float>(), *vc = v_colors.data_ptr<float>();
  const int64_t* idx = index.data_ptr<int64_t>();
  float *gdc = v_dc.data_ptr<float>(), *grs = v_rest.data_ptr<float>(), *gm = v_means.data_ptr<float>();
#pragma omp parallel for schedule(static)
  for (int64_t v = 0; v < v_count; ++v) {
    const int64_t g = idx[v];
    float dir[3], b[16], db[16][3];
    const float norm = view_direction(m + 3 * g, c, dir);
    sh_basis((int)degree, dir[0], dir[1], dir[2], b, db);
    float v_dir[3] = {0.f, 0.f, 0.f};
    for (int ch = 0; ch < 3; ++ch) {
      const float gc = vc[3 * v + ch];
      gdc[3 * g + ch] = b[0] * gc;
      for (int j = 1; j < bases; ++j) {
        const float coeff = rs[(g * rest + j - 1) * 3 + ch];
        grs[(g * rest + j - 1) * 3 + ch] = b[j] * gc;
        for (int a = 0; a < 3; ++a) v_dir[a] += db[j][a] * coeff * gc;
      }
    }
    // dir = offset / max(|offset|, eps): project out the radial part when the norm is not clamped
    if (norm > kDirectionNormMin) {
      const float radial = v_dir[0] * dir[0] + v_dir[1] * dir[1] + v_dir[2] * dir[2];
      for (int a = 0; a < 3; ++a) gm[3 * g + a] = (v_dir[a] - radial * dir[a]) / norm;
    } else {
      for (int a = 0; a < 3; ++a) gm[3 * g + a] = v_dir[a] / kDirectionNormMin;
    }
  }
  return {v_dc, v_rest, v_means};
}

// ----------------------------------------------------------------------------- projection
namespace {

struct Intrinsics {
  float fx, fy, cx, cy;
  int width, height;
  float near_plane;
};

// Everything the projection computes for one Gaussian; the backward pass recomputes it.
struct Projected {
  float t[3];        // camera-space mean
  float qn[4];       // unit quaternion (w, x, y, z)
  float rot[9];      // rotation from qn, row-major
  float sigma3[9];   // 3D covariance
  float jw[6];       // J W, 2 x 3
  float txc, tyc;    // camera x, y clamped to the widened frustum (for J)
  bool clamped_x, clamped_y;
  float lim_x, lim_y;  // the clamped value of x / z and y / z
  float cov[3];      // dilated 2D covariance (a, b, c)
  float conic[3];
  float mean2d[2];
  bool visible;
};

inline void project_one(const float* m, const float* q, const float* s, const float* view, const Intrinsics& k,
                        Projected& p) {
  p.visible = false;
  for (int i = 0; i < 3; ++i)
    p.t[i] = view[4 * i] * m[0] + view[4 * i + 1] * m[1] + view[4 * i + 2] * m[2] + view[4 * i + 3];
  if (!std::isfinite(p.t[0]) || !std::isfinite(p.t[1]) || !std::isfinite(p.t[2])) return;
  if (!(p.t[2] >= k.near_plane)) return;

  const float norm2 = q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3];
  if (norm2 > kQuatNormMin2 && std::isfinite(norm2)) {
    const float inv = 1.0f / std::sqrt(norm2);
    for (int i = 0; i < 4; ++i) p.qn[i] = q[i] * inv;
  } else {  // a zero quaternion means "no rotation"; its gradient is zero
    p.qn[0] = 1.0f; p.qn[1] = p.qn[2] = p.qn[3] = 0.0f;
  }
  const float w = p.qn[0], x = p.qn[1], y = p.qn[2], z = p.qn[3];
  float* R = p.rot;
  R[0] = 1.f - 2.f * (y * y + z * z); R[1] = 2.f * (x * y - w * z);       R[2] = 2.f * (x * z + w * y);
  R[3] = 2.f * (x * y + w * z);       R[4] = 1.f - 2.f * (x * x + z * z); R[5] = 2.f * (y * z - w * x);
  R[6] = 2.f * (x * z - w * y);       R[7] = 2.f * (y * z + w * x);       R[8] = 1.f - 2.f * (x * x + y * y);
  float M[9];
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) M[3 * i + j] = R[3 * i + j] * s[j];
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j)
      p.sigma3[3 * i + j] = M[3 * i] * M[3 * j] + M[3 * i + 1] * M[3 * j + 1] + M[3 * i + 2] * M[3 * j + 2];

  // As in 3DGS, J is evaluated at a mean clamped to 1.3 x the field of view, so Gaussians far
  // outside the image do not get huge, ill-conditioned footprints.
  const float tz = p.t[2];
  const float tan_x = 0.5f * k.width / k.fx, tan_y = 0.5f * k.height / k.fy;
  const float lim_x_pos = (k.width - k.cx) / k.fx + 0.3f * tan_x, lim_x_neg = k.cx / k.fx + 0.3f * tan_x;
  const float lim_y_pos = (k.height - k.cy) / k.fy + 0.3f * tan_y, lim_y_neg = k.cy / k.fy + 0.3f * tan_y;
  const float ux = p.t[0] / tz, uy = p.t[1] / tz;
  p.lim_x = std::min(lim_x_pos, std::max(-lim_x_neg, ux));
  p.lim_y = std::min(lim_y_pos, std::max(-lim_y_neg, uy));
  p.clamped_x = ux < -lim_x_neg || ux > lim_x_pos;
  p.clamped_y = uy < -lim_y_neg || uy > lim_y_pos;
  p.txc = tz * p.lim_x;
  p.tyc = tz * p.lim_y;
  const float J[6] = {k.fx / tz, 0.f, -k.fx * p.txc / (tz * tz), 0.f, k.fy / tz, -k.fy * p.tyc / (tz * tz)};
  for (int i = 0; i < 2; ++i)
    for (int j = 0; j < 3; ++j)
      p.jw[3 * i + j] = J[3 * i] * view[j] + J[3 * i + 1] * view[4 + j] + J[3 * i + 2] * view[8 + j];
  float TS[6];  // (J W) Sigma
  for (int i = 0; i < 2; ++i)
    for (int j = 0; j < 3; ++j)
      TS[3 * i + j] = p.jw[3 * i] * p.sigma3[j] + p.jw[3 * i + 1] * p.sigma3[3 + j] + p.jw[3 * i + 2] * p.sigma3[6 + j];
  p.cov[0] = TS[0] * p.jw[0] + TS[1] * p.jw[1] + TS[2] * p.jw[2] + kDilation;
  p.cov[1] = TS[0] * p.jw[3] + TS[1] * p.jw[4] + TS[2] * p.jw[5];
  p.cov[2] = TS[3] * p.jw[3] + TS[4] * p.jw[4] + TS[5] * p.jw[5] + kDilation;
  const float det = p.cov[0] * p.cov[2] - p.cov[1] * p.cov[1];
  if (!(det > 0.f) || !std::isfinite(det)) return;
  p.conic[0] = p.cov[2] / det;
  p.conic[1] = -p.cov[1] / det;
  p.conic[2] = p.cov[0] / det;
  if (!std::isfinite(p.conic[0]) || !std::isfinite(p.conic[1]) || !std::isfinite(p.conic[2])) return;
  p.mean2d[0] = k.fx * p.t[0] / tz + k.cx;
  p.mean2d[1] = k.fy * p.t[1] / tz + k.cy;
  p.visible = std::isfinite(p.mean2d[0]) && std::isfinite(p.mean2d[1]);
}

Intrinsics make_intrinsics(double fx, double fy, double cx, double cy, int64_t width, int64_t height,
                           double near_plane) {
  return Intrinsics{(float)fx, (float)fy, (float)cx, (float)cy, (int)width, (int)height, (float)near_plane};
}

}  // namespace

// Projects all N Gaussians and keeps the V visible ones. Returns index [V] (int64, ascending),
// radii [N] (int32, ceil of 3 sigma, 0 when culled), and for the visible ones means2d [V,2],
// conics [V,3], depths [V] and boxes [V,4] (int32 x0, y0, x1, y1, end-exclusive: the pixels
// where alpha can reach 1/255).
std::vector<at::Tensor> project_forward(at::Tensor means, at::Tensor quats, at::Tensor scales,
                                        at::Tensor opacities, at::Tensor viewmat, double fx, double fy,
                                        double cx, double cy, int64_t width, int64_t height, double near_plane) {
  const int64_t n = means.size(0);
  check_rows(means, "means", n, 3);
  check_rows(quats, "quats", n, 4);
  check_rows(scales, "scales", n, 3);
  check_cpu_float(opacities, "opacities");
  check_cpu_float(viewmat, "viewmat");
  const Intrinsics k = make_intrinsics(fx, fy, cx, cy, width, height, near_plane);
  auto opts = means.options();
  auto radii = at::zeros({n}, opts.dtype(at::kInt));
  std::vector<float> all(8 * (size_t)n);  // mean x, y, conic a, b, c, depth, box packed below
  std::vector<int32_t> all_boxes(4 * (size_t)n);
  const float *m = means.data_ptr<float>(), *q = quats.data_ptr<float>(), *s = scales.data_ptr<float>();
  const float *o = opacities.data_ptr<float>(), *view = viewmat.data_ptr<float>();
  int32_t* out_r = radii.data_ptr<int32_t>();

#pragma omp parallel for schedule(static)
  for (int64_t g = 0; g < n; ++g) {
    Projected p;
    project_one(m + 3 * g, q + 4 * g, s + 3 * g, view, k, p);
    // alpha = opacity * exp(-d^2 / 2) reaches 1/255 only for d^2 <= 2 ln(255 opacity): the
    // box of that Mahalanobis radius holds every pixel the Gaussian can touch.
    const float reach2 = 2.0f * std::log(255.0f * o[g]);
    if (!p.visible || !(reach2 > 0.f)) continue;
    const float mid = 0.5f * (p.cov[0] + p.cov[2]);
    const float det = p.cov[0] * p.cov[2] - p.cov[1] * p.cov[1];
    const float sigma = std::sqrt(mid + std::sqrt(std::max(0.1f, mid * mid - det)));
    const float extent = std::sqrt(reach2) * sigma;
    const float bx0 = std::floor(p.mean2d[0] - extent), bx1 = std::ceil(p.mean2d[0] + extent);
    const float by0 = std::floor(p.mean2d[1] - extent), by1 = std::ceil(p.mean2d[1] + extent);
    const int x0 = (int)std::min<float>(width, std::max(0.f, bx0)), x1 = (int)std::min<float>(width, std::max(0.f, bx1));
    const int y0 = (int)std::min<float>(height, std::max(0.f, by0)), y1 = (int)std::min<float>(height, std::max(0.f, by1));
    if (x0 >= x1 || y0 >= y1 || !std::isfinite(sigma)) continue;
    float* row = all.data() + 8 * g;
    row[0] = p.mean2d[0]; row[1] = p.mean2d[1];
    row[2] = p.conic[0]; row[3] = p.conic[1]; row[4] = p.conic[2];
    row[5] = p.t[2];
    out_r[g] = (int32_t)std::min(1e9f, std::ceil(3.0f * sigma));
    int32_t* b = all_boxes.data() + 4 * g;
    b[0] = x0; b[1] = y0; b[2] = x1; b[3] = y1;
  }
  int64_t v_count = 0;
  for (int64_t g = 0; g < n; ++g) v_count += out_r[g] > 0;
  auto index = at::empty({v_count}, opts.dtype(at::kLong));
  auto means2d = at::empty({v_count, 2}, opts);
  auto conics = at::empty({v_count, 3}, opts);
  auto depths = at::empty({v_count}, opts);
  auto boxes = at::empty({v_count, 4}, opts.dtype(at::kInt));
  int64_t* idx = index.data_ptr<int64_t>();
  float *out_m = means2d.data_ptr<float>(), *out_c = conics.data_ptr<float>(), *out_d = depths.data_ptr<float>();
  int32_t* out_b = boxes.data_ptr<int32_t>();
  for (int64_t g = 0, v = 0; g < n; ++g) {
    if (out_r[g] <= 0) continue;
    const float* row = all.data() + 8 * g;
    idx[v] = g;
    out_m[2 * v] = row[0]; out_m[2 * v + 1] = row[1];
    out_c[3 * v] = row[2]; out_c[3 * v + 1] = row[3]; out_c[3 * v + 2] = row[4];
    out_d[v] = row[5];
    std::memcpy(out_b + 4 * v, all_boxes.data() + 4 * g, 4 * sizeof(int32_t));
    ++v;
  }
  return {index, radii, means2d, conics, depths, boxes};
}

// Gradients of project_forward's means2d, conics and depths [V, ...] with respect to means,
// quats and scales [N, ...] (zero for culled Gaussians).
std::vector<at::Tensor> project_backward(at::Tensor means, at::Tensor quats, at::Tensor scales,
                                         at::Tensor viewmat, at::Tensor index, double fx, double fy,
                                         double cx, double cy, int64_t width, int64_t height,
                                         double near_plane, at::Tensor v_means2d, at::Tensor v_conics,
                                         at::Tensor v_depths) {
  const int64_t v_count = index.size(0);
  const Intrinsics k = make_intrinsics(fx, fy, cx, cy, width, height, near_plane);
  auto v_means = at::zeros_like(means);
  auto v_quats = at::zeros_like(quats);
  auto v_scales = at::zeros_like(scales);
  const float *m = means.data_ptr<float>(), *q = quats.data_ptr<float>(), *s = scales.data_ptr<float>();
  const float* view = viewmat.data_ptr<float>();
  const int64_t* idx = index.data_ptr<int64_t>();
  const float *vm2 = v_means2d.data_ptr<float>(), *vc = v_conics.data_ptr<float>(), *vd = v_depths.data_ptr<float>();
  float *gm = v_means.data_ptr<float>(), *gq = v_quats.data_ptr<float>(), *gs = v_scales.data_ptr<float>();

#pragma omp parallel for schedule(static)
  for (int64_t v = 0; v < v_count; ++v) {
    const int64_t g = idx[v];
    Projected p;
    project_one(m + 3 * g, q + 4 * g, s + 3 * g, view, k, p);
    const float tz = p.t[2];
    float vt[3];
    vt[0] = k.fx / tz * vm2[2 * v];
    vt[1] = k.fy / tz * vm2[2 * v + 1];
    vt[2] = -(k.fx * p.t[0] * vm2[2 * v] + k.fy * p.t[1] * vm2[2 * v + 1]) / (tz * tz) + vd[v];

    // conic = cov^-1: dL/dcov = -A G A, with G the symmetric gradient of the conic matrix
    const float A[4] = {p.conic[0], p.conic[1], p.conic[1], p.conic[2]};
    const float G[4] = {vc[3 * v], 0.5f * vc[3 * v + 1], 0.5f * vc[3 * v + 1], vc[3 * v + 2]};
    float AG[4], V2[4];
    for (int i = 0; i < 2; ++i)
      for (int j = 0; j < 2; ++j) AG[2 * i + j] = A[2 * i] * G[j] + A[2 * i + 1] * G[2 + j];
    for (int i = 0; i < 2; ++i)
      for (int j = 0; j < 2; ++j) V2[2 * i + j] = -(AG[2 * i] * A[j] + AG[2 * i + 1] * A[2 + j]);

    // cov = T Sigma T^T with T = J W: dL/dT = 2 V2 T Sigma, dL/dSigma = T^T V2 T
    float TS[6], vT[6], V2T[6], vSigma[9];
    for (int i = 0; i < 2; ++i)
      for (int j = 0; j < 3; ++j)
        TS[3 * i + j] = p.jw[3 * i] * p.sigma3[j] + p.jw[3 * i + 1] * p.sigma3[3 + j] + p.jw[3 * i + 2] * p.sigma3[6 + j];
    for (int i = 0; i < 2; ++i)
      for (int j = 0; j < 3; ++j) {
        vT[3 * i + j] = 2.f * (V2[2 * i] * TS[j] + V2[2 * i + 1] * TS[3 + j]);
        V2T[3 * i + j] = V2[2 * i] * p.jw[j] + V2[2 * i + 1] * p.jw[3 + j];
      }
    for (int i = 0; i < 3; ++i)
      for (int j = 0; j < 3; ++j) vSigma[3 * i + j] = p.jw[i] * V2T[j] + p.jw[3 + i] * V2T[3 + j];

    // Sigma = M M^T with M = R diag(s)
    float M[9], vM[9], vR[9];
    for (int i = 0; i < 3; ++i)
      for (int j = 0; j < 3; ++j) M[3 * i + j] = p.rot[3 * i + j] * s[3 * g + j];
    for (int i = 0; i < 3; ++i)
      for (int j = 0; j < 3; ++j)
        vM[3 * i + j] = (vSigma[3 * i] + vSigma[i]) * M[j] + (vSigma[3 * i + 1] + vSigma[3 + i]) * M[3 + j] +
                        (vSigma[3 * i + 2] + vSigma[6 + i]) * M[6 + j];
    for (int j = 0; j < 3; ++j) {
      float acc = 0.f;
      for (int i = 0; i < 3; ++i) {
        vR[3 * i + j] = vM[3 * i + j] * s[3 * g + j];
        acc += vM[3 * i + j] * p.rot[3 * i + j];
      }
      gs[3 * g + j] = acc;
    }
    const float w = p.qn[0], x = p.qn[1], y = p.qn[2], z = p.qn[3];
    float vqn[4];
    vqn[0] = 2.f * (-z * vR[1] + y * vR[2] + z * vR[3] - x * vR[5] - y * vR[6] + x * vR[7]);
    vqn[1] = 2.f * (y * vR[1] + z * vR[2] + y * vR[3] - 2.f * x * vR[4] - w * vR[5] + z * vR[6] + w * vR[7] - 2.f * x * vR[8]);
    vqn[2] = 2.f * (-2.f * y * vR[0] + x * vR[1] + w * vR[2] + x * vR[3] + z * vR[5] - w * vR[6] + z * vR[7] - 2.f * y * vR[8]);
    vqn[3] = 2.f * (-2.f * z * vR[0] - w * vR[1] + x * vR[2] + w * vR[3] - 2.f * z * vR[4] + y * vR[5] + x * vR[6] + y * vR[7]);
    const float* qg = q + 4 * g;
    const float norm2 = qg[0] * qg[0] + qg[1] * qg[1] + qg[2] * qg[2] + qg[3] * qg[3];
    if (norm2 > kQuatNormMin2 && std::isfinite(norm2)) {
      const float inv = 1.0f / std::sqrt(norm2);
      const float dot = vqn[0] * p.qn[0] + vqn[1] * p.qn[1] + vqn[2] * p.qn[2] + vqn[3] * p.qn[3];
      for (int i = 0; i < 4; ++i) gq[4 * g + i] = (vqn[i] - dot * p.qn[i]) * inv;
    }

    // T = J W; J depends on the (clamped) camera-space mean
    float vJ[6];
    for (int i = 0; i < 2; ++i)
      for (int j = 0; j < 3; ++j)
        vJ[3 * i + j] = vT[3 * i] * view[4 * j] + vT[3 * i + 1] * view[4 * j + 1] + vT[3 * i + 2] * view[4 * j + 2];
    const float tz2 = tz * tz, tz3 = tz2 * tz;
    const float v_txc = -k.fx / tz2 * vJ[2], v_tyc = -k.fy / tz2 * vJ[5];
    vt[2] += -k.fx / tz2 * vJ[0] - k.fy / tz2 * vJ[4] + 2.f * k.fx * p.txc / tz3 * vJ[2] + 2.f * k.fy * p.tyc / tz3 * vJ[5];
    if (p.clamped_x) vt[2] += v_txc * p.lim_x; else vt[0] += v_txc;
    if (p.clamped_y) vt[2] += v_tyc * p.lim_y; else vt[1] += v_tyc;
    for (int j = 0; j < 3; ++j) gm[3 * g + j] = view[j] * vt[0] + view[4 + j] * vt[1] + view[8 + j] * vt[2];
  }
  return {v_means, v_quats, v_scales};
}

// ------------------------------------------------------------------------------- binning
// Tile lists: tile_offsets [T+1] and ids [M] (rows of boxes), each tile's ids front to back,
// ties by id. One stable sort of all depths, then every tile's list is filled in that order.
// Tiles are row-major, ceil(width/16) per row.
std::vector<at::Tensor> bin_tiles(at::Tensor boxes, at::Tensor depths, int64_t width, int64_t height) {
  const int64_t n = boxes.size(0);
  const int tiles_x = (int)((width + kTile - 1) / kTile), tiles_y = (int)((height + kTile - 1) / kTile);
  const int n_tiles = tiles_x * tiles_y;
  const int32_t* b = boxes.data_ptr<int32_t>();
  const float* d = depths.data_ptr<float>();

  // Stable LSD radix sort on the float bits, mapped so that unsigned order is float order.
  std::vector<uint32_t> keys(n), keys_tmp(n);
  std::vector<int32_t> order(n), order_tmp(n);
  for (int64_t g = 0; g < n; ++g) {
    uint32_t bits;
    std::memcpy(&bits, d + g, sizeof(float));
    keys[g] = (bits & 0x80000000u) ? ~bits : bits | 0x80000000u;
    order[g] = (int32_t)g;
  }
  for (int shift = 0; shift < 32; shift += 11) {
    std::array<int64_t, 2049> count{};
    for (int64_t i = 0; i < n; ++i) ++count[((keys[i] >> shift) & 2047u) + 1];
    for (int i = 0; i < 2048; ++i) count[i + 1] += count[i];
    for (int64_t i = 0; i < n; ++i) {
      const int64_t to = count[(keys[i] >> shift) & 2047u]++;
      keys_tmp[to] = keys[i];
      order_tmp[to] = order[i];
    }
    keys.swap(keys_tmp);
    order.swap(order_tmp);
  }

  auto offsets = at::zeros({n_tiles + 1}, boxes.options());
  int32_t* off = offsets.data_ptr<int32_t>();
  for (int64_t g = 0; g < n; ++g) {
    const int32_t* bg = b + 4 * g;
    if (bg[0] >= bg[2] || bg[1] >= bg[3]) continue;
    for (int ty = bg[1] / kTile; ty < (bg[3] + kTile - 1) / kTile; ++ty)
      for (int tx = bg[0] / kTile; tx < (bg[2] + kTile - 1) / kTile; ++tx) ++off[ty * tiles_x + tx + 1];
  }
  for (int t = 0; t < n_tiles; ++t) off[t + 1] += off[t];
  auto ids = at::empty({(int64_t)off[n_tiles]}, boxes.options());
  int32_t* id = ids.data_ptr<int32_t>();
  std::vector<int32_t> cursor(off, off + n_tiles);
  for (int64_t i = 0; i < n; ++i) {
    const int32_t g = order[i];
    const int32_t* bg = b + 4 * g;
    if (bg[0] >= bg[2] || bg[1] >= bg[3]) continue;
    for (int ty = bg[1] / kTile; ty < (bg[3] + kTile - 1) / kTile; ++ty)
      for (int tx = bg[0] / kTile; tx < (bg[2] + kTile - 1) / kTile; ++tx) id[cursor[ty * tiles_x + tx]++] = g;
  }
  return {offsets, ids};
}

// ---------------------------------------------------------------------------- compositing
namespace {

struct TileGeometry {
  int x0, y0, width, height;  // pixel origin and size (edge tiles are smaller)
};

inline TileGeometry tile_geometry(int tile, int tiles_x, int64_t width, int64_t height) {
  TileGeometry t;
  t.x0 = (tile % tiles_x) * kTile;
  t.y0 = (tile / tiles_x) * kTile;
  t.width = (int)std::min<int64_t>(kTile, width - t.x0);
  t.height = (int)std::min<int64_t>(kTile, height - t.y0);
  return t;
}

// The pixel rows/columns of a tile a Gaussian's box covers, in tile-local coordinates.
inline bool box_in_tile(const int32_t* box, const TileGeometry& t, int& lx0, int& lx1, int& ly0, int& ly1) {
  lx0 = std::max(box[0], t.x0) - t.x0;
  lx1 = std::min(box[2], t.x0 + t.width) - t.x0;
  ly0 = std::max(box[1], t.y0) - t.y0;
  ly1 = std::min(box[3], t.y0 + t.height) - t.y0;
  return lx0 < lx1 && ly0 < ly1;
}

// Eight pixels at a time as GCC vector types: AVX2 registers where the build enables them, pairs
// of SSE registers otherwise. Masks are int lanes of -1 (true) or 0.
typedef float f8 __attribute__((vector_size(32)));
typedef int32_t i8 __attribute__((vector_size(32)));

inline f8 splat(float x) { return f8{} + x; }
inline i8 splat_int(int32_t x) { return i8{} + x; }
inline f8 vmin(f8 a, f8 b) { return a < b ? a : b; }
inline f8 select(i8 mask, f8 yes, f8 no) { return mask ? yes : no; }
inline f8 load8(const float* p) { f8 v; std::memcpy(&v, p, sizeof(v)); return v; }
inline void store8(float* p, f8 v) { std::memcpy(p, &v, sizeof(v)); }
inline i8 load8(const int32_t* p) { i8 v; std::memcpy(&v, p, sizeof(v)); return v; }
inline void store8(int32_t* p, i8 v) { std::memcpy(p, &v, sizeof(v)); }
inline float sum8(f8 v) { return ((v[0] + v[1]) + (v[2] + v[3])) + ((v[4] + v[5]) + (v[6] + v[7])); }
inline int32_t count8(i8 mask) { i8 ones = mask & 1; return ones[0] + ones[1] + ones[2] + ones[3] + ones[4] + ones[5] + ones[6] + ones[7]; }
inline bool any8(i8 mask) { i8 a = mask | __builtin_shufflevector(mask, mask, 4, 5, 6, 7, 0, 1, 2, 3); return (a[0] | a[1] | a[2] | a[3]) != 0; }

// exp_nonpositive, eight lanes at once.
inline f8 exp8_nonpositive(f8 x) {
  x = select(x < -87.0f, splat(-87.0f), x);
  const f8 n = __builtin_convertvector(__builtin_convertvector(x * 1.44269504088896341f - 0.5f, i8), f8);
  const f8 r = x - n * 0.693359375f + n * 2.12194440e-4f;
  f8 p = splat(1.9875691500e-4f);
  p = p * r + 1.3981999507e-3f;
  p = p * r + 8.3334519073e-3f;
  p = p * r + 4.1665795894e-2f;
  p = p * r + 1.6666665459e-1f;
  p = p * r + 5.0000001201e-1f;
  p = p * r * r + r + 1.0f;
  const i8 bits = (__builtin_convertvector(n, i8) + 127) << 23;
  return p * (f8)bits;
}

const f8 kLaneOffsets = {0.5f, 1.5f, 2.5f, 3.5f, 4.5f, 5.5f, 6.5f, 7.5f};  // pixel centres of a chunk
const i8 kLanes = {0, 1, 2, 3, 4, 5, 6, 7};

// Channels known at compile time let the channel loops unroll inside the pixel loop; 0 = any.
template <int kChannels>
struct Channels {
  static int count(int) { return kChannels; }
};
template <>
struct Channels<0> {
  static int count(int c) { return c; }
};

template <int kChannels>
void rasterize_forward_tiles(const float* mu, const float* con, const float* op, const float* val,
                             const int32_t* box, const int32_t* off, const int32_t* ids, int64_t width,
                             int64_t height, int channels, float* img, float* trans, int32_t* last_out) {
  const int C = Channels<kChannels>::count(channels);
  const int tiles_x = (int)((width + kTile - 1) / kTile), tiles_y = (int)((height + kTile - 1) / kTile);
#pragma omp parallel
  {
    std::vector<float> acc_buffer((size_t)C * kTilePixels);
    float* acc = acc_buffer.data();
    alignas(64) float T[kTilePixels];
    alignas(64) int32_t done[kTilePixels], last_idx[kTilePixels];
#pragma omp for schedule(dynamic, 1)
    for (int tile = 0; tile < tiles_x * tiles_y; ++tile) {
      const TileGeometry tg = tile_geometry(tile, tiles_x, width, height);
      std::fill(acc, acc + (size_t)C * kTilePixels, 0.f);
      int n_live = 0;
      for (int p = 0; p < kTilePixels; ++p) {
        const bool inside = (p % kTile) < tg.width && (p / kTile) < tg.height;
        T[p] = 1.f;
        done[p] = inside ? 0 : -1;
        last_idx[p] = -1;
        n_live += inside;
      }
      for (int k = off[tile]; k < off[tile + 1] && n_live > 0; ++k) {
        const int g = ids[k];
        int lx0, lx1, ly0, ly1;
        if (!box_in_tile(box + 4 * g, tg, lx0, lx1, ly0, ly1)) continue;
        const float mx = mu[2 * g], my = mu[2 * g + 1];
        const float a = con[3 * g], b = con[3 * g + 1], c = con[3 * g + 2], o = op[g];
        const float* vg = val + (size_t)g * C;
        for (int ly = ly0; ly < ly1; ++ly) {
          const float dy = my - (tg.y0 + ly + 0.5f);
          for (int cx0 = lx0 & ~(kChunk - 1); cx0 < lx1; cx0 += kChunk) {
            const int p = ly * kTile + cx0;
            const f8 dx = splat(mx - (float)(tg.x0 + cx0)) - kLaneOffsets;
            const f8 power = -0.5f * (a * dx * dx + c * dy * dy) - b * dx * dy;
            const f8 alpha = vmin(splat(kAlphaMax), o * exp8_nonpositive(vmin(power, splat(0.f))));
            const f8 T_old = load8(T + p);
            const i8 done_old = load8(done + p);
            const i8 valid = (kLanes >= lx0 - cx0) & (kLanes < lx1 - cx0) & (done_old == 0) & (power <= 0.f) &
                             (alpha >= kAlphaMin);
            if (!any8(valid)) continue;
            const f8 next_T = T_old * (1.f - alpha);
            const i8 stop = valid & (next_T < kTransmittanceMin);
            const i8 contributes = valid & ~stop;
            const f8 weight = select(contributes, alpha * T_old, splat(0.f));
            for (int ch = 0; ch < C; ++ch) store8(acc + ch * kTilePixels + p, load8(acc + ch * kTilePixels + p) + weight * vg[ch]);
            store8(T + p, select(contributes, next_T, T_old));
            store8(done + p, done_old | stop);
            store8(last_idx + p, contributes ? splat_int(k) : load8(last_idx + p));
            n_live -= count8(stop);
          }
        }
      }
      for (int ly = 0; ly < tg.height; ++ly)
        for (int lx = 0; lx < tg.width; ++lx) {
          const int p = ly * kTile + lx;
          const int64_t pix = (int64_t)(tg.y0 + ly) * width + tg.x0 + lx;
          for (int ch = 0; ch < C; ++ch) img[pix * C + ch] = acc[ch * kTilePixels + p];
          trans[pix] = T[p];
          last_out[pix] = last_idx[p];
        }
    }
  }
}

template <int kChannels>
void rasterize_backward_tiles(const float* mu, const float* con, const float* op, const float* val,
                              const int32_t* box, const int32_t* off, const int32_t* ids, const float* trans,
                              const int32_t* last_in, const float* gimg, const float* galpha, int64_t width,
                              int64_t height, int channels, int64_t n, float* grads, int n_threads) {
  const int C = Channels<kChannels>::count(channels);
  const int stride = 6 + C;  // per Gaussian: mean x, y, conic a, b, c, opacity, values
  const int tiles_x = (int)((width + kTile - 1) / kTile), tiles_y = (int)((height + kTile - 1) / kTile);
#pragma omp parallel num_threads(n_threads)
  {
    float* my_grads = grads + (size_t)omp_get_thread_num() * n * stride;
    std::vector<float> pixel_buffer(2 * (size_t)C * kTilePixels);
    float* v_pix = pixel_buffer.data();
    float* behind = v_pix + (size_t)C * kTilePixels;
    alignas(64) float T[kTilePixels], T_final[kTilePixels], v_alpha_pix[kTilePixels];
    alignas(64) int32_t last_idx[kTilePixels];
    std::vector<f8> s_val(C);
    // Round-robin, not dynamic: which thread's buffer a tile sums into must not depend on timing,
    // or the float sums (and a whole training run) change from run to run.
#pragma omp for schedule(static, 1)
    for (int tile = 0; tile < tiles_x * tiles_y; ++tile) {
      const TileGeometry tg = tile_geometry(tile, tiles_x, width, height);
      int max_last = -1;
      for (int p = 0; p < kTilePixels; ++p) {
        const int lx = p % kTile, ly = p / kTile;
        const bool inside = lx < tg.width && ly < tg.height;
        const int64_t pix = (int64_t)(tg.y0 + ly) * width + tg.x0 + lx;
        T[p] = inside ? trans[pix] : 1.f;
        T_final[p] = T[p];
        last_idx[p] = inside ? last_in[pix] : -1;
        v_alpha_pix[p] = inside ? galpha[pix] : 0.f;
        max_last = std::max(max_last, last_idx[p]);
        for (int ch = 0; ch < C; ++ch) {
          v_pix[ch * kTilePixels + p] = inside ? gimg[pix * C + ch] : 0.f;
          behind[ch * kTilePixels + p] = 0.f;
        }
      }
      for (int k = max_last; k >= off[tile]; --k) {
        const int g = ids[k];
        int lx0, lx1, ly0, ly1;
        if (!box_in_tile(box + 4 * g, tg, lx0, lx1, ly0, ly1)) continue;
        const float mx = mu[2 * g], my = mu[2 * g + 1];
        const float a = con[3 * g], b = con[3 * g + 1], c = con[3 * g + 2], o = op[g];
        const float* vg = val + (size_t)g * C;
        f8 s_mx{}, s_my{}, s_a{}, s_b{}, s_c{}, s_o{};
        for (int ch = 0; ch < C; ++ch) s_val[ch] = f8{};
        bool touched = false;
        for (int ly = ly0; ly < ly1; ++ly) {
          const float dy = my - (tg.y0 + ly + 0.5f);
          for (int cx0 = lx0 & ~(kChunk - 1); cx0 < lx1; cx0 += kChunk) {
            const int p = ly * kTile + cx0;
            const f8 dx = splat(mx - (float)(tg.x0 + cx0)) - kLaneOffsets;
            const f8 power = -0.5f * (a * dx * dx + c * dy * dy) - b * dx * dy;
            const f8 gval = exp8_nonpositive(vmin(power, splat(0.f)));
            const f8 raw = o * gval;
            const f8 alpha = vmin(splat(kAlphaMax), raw);
            const i8 contributes = (kLanes >= lx0 - cx0) & (kLanes < lx1 - cx0) & (splat_int(k) <= load8(last_idx + p)) &
                                   (power <= 0.f) & (alpha >= kAlphaMin);
            if (!any8(contributes)) continue;
            touched = true;
            const f8 inv = 1.f / (1.f - alpha);
            const f8 T_after = load8(T + p);
            const f8 T_before = select(contributes, T_after * inv, T_after);
            store8(T + p, T_before);
            const f8 weight = select(contributes, alpha * T_before, splat(0.f));
            // d alpha_image / d alpha_k = T_final / (1 - alpha_k)
            f8 v_alpha = load8(v_alpha_pix + p) * load8(T_final + p) * inv;
            for (int ch = 0; ch < C; ++ch) {
              const f8 vp = load8(v_pix + ch * kTilePixels + p);
              const f8 bh = load8(behind + ch * kTilePixels + p);
              s_val[ch] += weight * vp;
              // d pixel / d alpha_k = value_k T_k - (colour of the Gaussians behind) / (1 - alpha_k)
              v_alpha += (vg[ch] * T_before - bh * inv) * vp;
              store8(behind + ch * kTilePixels + p, bh + weight * vg[ch]);
            }
            // through alpha = min(0.99, opacity * exp(power)) to the 2D parameters
            const f8 v_raw = select(contributes & (raw <= kAlphaMax), v_alpha, splat(0.f));
            const f8 v_power = raw * v_raw;
            s_o += gval * v_raw;
            s_a += -0.5f * dx * dx * v_power;
            s_b += -dx * dy * v_power;
            s_c += -0.5f * dy * dy * v_power;
            s_mx += -(a * dx + b * dy) * v_power;
            s_my += -(b * dx + c * dy) * v_power;
          }
        }
        if (!touched) continue;
        float* out = my_grads + (size_t)g * stride;
        out[0] += sum8(s_mx); out[1] += sum8(s_my); out[2] += sum8(s_a); out[3] += sum8(s_b); out[4] += sum8(s_c);
        out[5] += sum8(s_o);
        for (int ch = 0; ch < C; ++ch) out[6 + ch] += sum8(s_val[ch]);
      }
    }
  }
}

}  // namespace

// Composites values [V,C] front to back. Returns image [H,W,C], transmittance [H,W] and the
// index (into tile_ids) of each pixel's last contributing Gaussian [H,W] (int32, -1: none).
std::vector<at::Tensor> rasterize_forward(at::Tensor means2d, at::Tensor conics, at::Tensor opacities,
                                          at::Tensor values, at::Tensor boxes, at::Tensor tile_offsets,
                                          at::Tensor tile_ids, int64_t width, int64_t height) {
  const int64_t n = means2d.size(0);
  check_rows(means2d, "means2d", n, 2);
  check_rows(conics, "conics", n, 3);
  check_cpu_float(opacities, "opacities");
  check_cpu_float(values, "values");
  TORCH_CHECK(values.dim() == 2 && values.size(0) == n, "values must have shape [", n, ", C]");
  const int C = (int)values.size(1);
  auto opts = values.options();
  auto image = at::empty({height, width, C}, opts);
  auto transmittance = at::empty({height, width}, opts);
  auto last = at::empty({height, width}, opts.dtype(at::kInt));
  const float *mu = means2d.data_ptr<float>(), *con = conics.data_ptr<float>(), *op = opacities.data_ptr<float>();
  const float* val = values.data_ptr<float>();
  const int32_t *box = boxes.data_ptr<int32_t>(), *off = tile_offsets.data_ptr<int32_t>(), *ids = tile_ids.data_ptr<int32_t>();
  float *img = image.data_ptr<float>(), *trans = transmittance.data_ptr<float>();
  int32_t* last_out = last.data_ptr<int32_t>();
  const auto run = [&](auto tag) {
    rasterize_forward_tiles<decltype(tag)::value>(mu, con, op, val, box, off, ids, width, height, C, img, trans,
                                                  last_out);
  };
  switch (C) {
    case 1: run(std::integral_constant<int, 1>{}); break;
    case 3: run(std::integral_constant<int, 3>{}); break;
    case 4: run(std::integral_constant<int, 4>{}); break;
    case 6: run(std::integral_constant<int, 6>{}); break;
    default: run(std::integral_constant<int, 0>{});
  }
  return {image, transmittance, last};
}

// Backward of rasterize_forward for the image and alpha = 1 - transmittance. Returns
// v_means2d [V,2], v_conics [V,3], v_opacities [V], v_values [V,C].
std::vector<at::Tensor> rasterize_backward(at::Tensor means2d, at::Tensor conics, at::Tensor opacities,
                                           at::Tensor values, at::Tensor boxes, at::Tensor tile_offsets,
                                           at::Tensor tile_ids, at::Tensor transmittance,
                                           at::Tensor last, at::Tensor v_image, at::Tensor v_alpha) {
  const int64_t n = means2d.size(0), height = transmittance.size(0), width = transmittance.size(1);
  const int C = (int)values.size(1);
  const int stride = 6 + C;
  const float *mu = means2d.data_ptr<float>(), *con = conics.data_ptr<float>(), *op = opacities.data_ptr<float>();
  const float* val = values.data_ptr<float>();
  const int32_t *box = boxes.data_ptr<int32_t>(), *off = tile_offsets.data_ptr<int32_t>(), *ids = tile_ids.data_ptr<int32_t>();
  const float *trans = transmittance.data_ptr<float>(), *gimg = v_image.data_ptr<float>(), *galpha = v_alpha.data_ptr<float>();
  const int32_t* last_in = last.data_ptr<int32_t>();
  const int n_threads = omp_get_max_threads();
  // Tiles run in parallel and share Gaussians: each thread sums into its own buffer.
  std::vector<float> grads((size_t)n_threads * n * stride, 0.f);
  const auto run = [&](auto tag) {
    rasterize_backward_tiles<decltype(tag)::value>(mu, con, op, val, box, off, ids, trans, last_in, gimg, galpha,
                                                   width, height, C, n, grads.data(), n_threads);
  };
  switch (C) {
    case 1: run(std::integral_constant<int, 1>{}); break;
    case 3: run(std::integral_constant<int, 3>{}); break;
    case 4: run(std::integral_constant<int, 4>{}); break;
    case 6: run(std::integral_constant<int, 6>{}); break;
    default: run(std::integral_constant<int, 0>{});
  }
  auto total = at::empty({n, stride}, values.options());
  float* tot = total.data_ptr<float>();
  const int64_t count = n * stride;
#pragma omp parallel for schedule(static)
  for (int64_t i = 0; i < count; ++i) {
    float s = 0.f;
    for (int t = 0; t < n_threads; ++t) s += grads[(size_t)t * count + i];
    tot[i] = s;
  }
  return {total.slice(1, 0, 2).contiguous(), total.slice(1, 2, 5).contiguous(), total.select(1, 5).contiguous(),
          total.slice(1, 6, stride).contiguous()};
}

TORCH_LIBRARY(TORCH_EXTENSION_NAME, m) {
  m.def("sh_forward", &sh_forward);  // spherical-harmonics colours of the visible Gaussians
  m.def("sh_backward", &sh_backward);  // backward of sh_forward
  m.def("project_forward", &project_forward);  // EWA projection of 3D Gaussians, culled and compacted
  m.def("project_backward", &project_backward);  // backward of project_forward
  m.def("bin_tiles", &bin_tiles);  // 16x16 tile lists sorted by depth
  m.def("rasterize_forward", &rasterize_forward);  // front-to-back compositing of C channels
  m.def("rasterize_backward", &rasterize_backward);  // backward of rasterize_forward
}
