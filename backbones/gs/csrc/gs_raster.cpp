// CPU kernels of the 3D Gaussian Splatting rasteriser: projection, tile binning,
// front-to-back compositing of any number of channels, and their analytic backward passes.
//
// The compositing loops run Gaussian-outer, pixel-inner inside each 16 x 16 tile: a
// Gaussian's parameters stay in registers while the compiler vectorises the pixel loop,
// and the per-channel work is one multiply-add per pixel, so 6 channels cost little more
// than 3. Per pixel, Gaussians are still visited in depth order, so every pixel sees the
// exact 3DGS rules (alpha clamp 0.99, skip alpha < 1/255, stop before T < 1e-4).
// The Python twin in backbones/gs/reference.py defines the same semantics in plain torch.

#include <torch/extension.h>
#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <utility>
#include <vector>

namespace {

constexpr int kTile = 16;
constexpr int kTilePixels = kTile * kTile;
constexpr float kAlphaMax = 0.99f;
constexpr float kAlphaMin = 1.0f / 255.0f;
constexpr float kTransmittanceMin = 1e-4f;
constexpr float kDilation = 0.3f;
constexpr float kQuatNormMin2 = 1e-20f;

// exp(x) for the x <= 0 this rasteriser needs, in a form the compiler vectorises
// (Cephes range reduction and polynomial, within 2 ulp of expf).
inline float exp_nonpositive(float x) {
  x = x < -87.0f ? -87.0f : x;
  const float n = std::floor(x * 1.44269504088896341f + 0.5f);
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

inline void project_one(const float* m, const float* q, const float* s, const float* view,
                        const Intrinsics& k, Projected& p) {
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

void check_cpu_float(const torch::Tensor& t, const char* name, int64_t last_dim) {
  TORCH_CHECK(t.device().is_cpu() && t.scalar_type() == torch::kFloat32 && t.is_contiguous(),
              name, " must be a contiguous float32 CPU tensor");
  if (last_dim > 0) TORCH_CHECK(t.dim() == 2 && t.size(1) == last_dim, name, " must have shape [N, ", last_dim, "]");
}

}  // namespace

// Returns means2d [N,2], conics [N,3], depths [N], radii [N] (int32, 3 sigma, 0 when culled)
// and boxes [N,4] (int32 x0, y0, x1, y1, end-exclusive: the pixels where alpha can reach 1/255).
std::vector<torch::Tensor> project_forward(torch::Tensor means, torch::Tensor quats, torch::Tensor scales,
                                           torch::Tensor opacities, torch::Tensor viewmat, double fx,
                                           double fy, double cx, double cy, int64_t width, int64_t height,
                                           double near_plane) {
  check_cpu_float(means, "means", 3);
  check_cpu_float(quats, "quats", 4);
  check_cpu_float(scales, "scales", 3);
  check_cpu_float(opacities, "opacities", 0);
  check_cpu_float(viewmat, "viewmat", 0);
  const int64_t n = means.size(0);
  const Intrinsics k{(float)fx, (float)fy, (float)cx, (float)cy, (int)width, (int)height, (float)near_plane};
  auto opts = means.options();
  auto means2d = torch::zeros({n, 2}, opts);
  auto conics = torch::zeros({n, 3}, opts);
  auto depths = torch::zeros({n}, opts);
  auto radii = torch::zeros({n}, opts.dtype(torch::kInt32));
  auto boxes = torch::zeros({n, 4}, opts.dtype(torch::kInt32));
  const float *m = means.data_ptr<float>(), *q = quats.data_ptr<float>(), *s = scales.data_ptr<float>();
  const float *o = opacities.data_ptr<float>(), *view = viewmat.data_ptr<float>();
  float *out_m = means2d.data_ptr<float>(), *out_c = conics.data_ptr<float>(), *out_d = depths.data_ptr<float>();
  int32_t *out_r = radii.data_ptr<int32_t>(), *out_b = boxes.data_ptr<int32_t>();

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
    out_m[2 * g] = p.mean2d[0];
    out_m[2 * g + 1] = p.mean2d[1];
    for (int i = 0; i < 3; ++i) out_c[3 * g + i] = p.conic[i];
    out_d[g] = p.t[2];
    out_r[g] = (int32_t)std::min(1e9f, std::ceil(3.0f * sigma));
    out_b[4 * g] = x0; out_b[4 * g + 1] = y0; out_b[4 * g + 2] = x1; out_b[4 * g + 3] = y1;
  }
  return {means2d, conics, depths, radii, boxes};
}

// Gradients of project_forward's means2d, conics and depths with respect to means, quats, scales.
std::vector<torch::Tensor> project_backward(torch::Tensor means, torch::Tensor quats, torch::Tensor scales,
                                            torch::Tensor viewmat, torch::Tensor radii, double fx, double fy,
                                            double cx, double cy, int64_t width, int64_t height,
                                            double near_plane, torch::Tensor v_means2d, torch::Tensor v_conics,
                                            torch::Tensor v_depths) {
  const int64_t n = means.size(0);
  const Intrinsics k{(float)fx, (float)fy, (float)cx, (float)cy, (int)width, (int)height, (float)near_plane};
  auto v_means = torch::zeros_like(means);
  auto v_quats = torch::zeros_like(quats);
  auto v_scales = torch::zeros_like(scales);
  const float *m = means.data_ptr<float>(), *q = quats.data_ptr<float>(), *s = scales.data_ptr<float>();
  const float* view = viewmat.data_ptr<float>();
  const int32_t* r = radii.data_ptr<int32_t>();
  const float *vm2 = v_means2d.data_ptr<float>(), *vc = v_conics.data_ptr<float>(), *vd = v_depths.data_ptr<float>();
  float *gm = v_means.data_ptr<float>(), *gq = v_quats.data_ptr<float>(), *gs = v_scales.data_ptr<float>();

#pragma omp parallel for schedule(static)
  for (int64_t g = 0; g < n; ++g) {
    if (r[g] <= 0) continue;
    Projected p;
    project_one(m + 3 * g, q + 4 * g, s + 3 * g, view, k, p);
    const float tz = p.t[2];
    float vt[3];
    vt[0] = k.fx / tz * vm2[2 * g];
    vt[1] = k.fy / tz * vm2[2 * g + 1];
    vt[2] = -(k.fx * p.t[0] * vm2[2 * g] + k.fy * p.t[1] * vm2[2 * g + 1]) / (tz * tz) + vd[g];

    // conic = cov^-1: dL/dcov = -A G A, with G the symmetric gradient of the conic matrix
    const float A[4] = {p.conic[0], p.conic[1], p.conic[1], p.conic[2]};
    const float G[4] = {vc[3 * g], 0.5f * vc[3 * g + 1], 0.5f * vc[3 * g + 1], vc[3 * g + 2]};
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

// Tile lists: tile_offsets [T+1] and gaussian ids [M], each tile's ids sorted front to back
// (ties by id). Tiles are row-major, ceil(width/16) per row.
std::vector<torch::Tensor> bin_tiles(torch::Tensor boxes, torch::Tensor depths, int64_t width, int64_t height) {
  const int64_t n = boxes.size(0);
  const int tiles_x = (int)((width + kTile - 1) / kTile), tiles_y = (int)((height + kTile - 1) / kTile);
  const int n_tiles = tiles_x * tiles_y;
  const int32_t* b = boxes.data_ptr<int32_t>();
  const float* d = depths.data_ptr<float>();
  auto offsets = torch::zeros({n_tiles + 1}, boxes.options());
  int32_t* off = offsets.data_ptr<int32_t>();
  for (int64_t g = 0; g < n; ++g) {
    const int32_t* bg = b + 4 * g;
    if (bg[0] >= bg[2] || bg[1] >= bg[3]) continue;
    for (int ty = bg[1] / kTile; ty < (bg[3] + kTile - 1) / kTile; ++ty)
      for (int tx = bg[0] / kTile; tx < (bg[2] + kTile - 1) / kTile; ++tx) ++off[ty * tiles_x + tx + 1];
  }
  for (int t = 0; t < n_tiles; ++t) off[t + 1] += off[t];
  auto ids = torch::empty({(int64_t)off[n_tiles]}, boxes.options());
  int32_t* id = ids.data_ptr<int32_t>();
  std::vector<int32_t> cursor(off, off + n_tiles);
  for (int64_t g = 0; g < n; ++g) {
    const int32_t* bg = b + 4 * g;
    if (bg[0] >= bg[2] || bg[1] >= bg[3]) continue;
    for (int ty = bg[1] / kTile; ty < (bg[3] + kTile - 1) / kTile; ++ty)
      for (int tx = bg[0] / kTile; tx < (bg[2] + kTile - 1) / kTile; ++tx) id[cursor[ty * tiles_x + tx]++] = (int32_t)g;
  }
#pragma omp parallel
  {
    std::vector<std::pair<float, int32_t>> keys;
#pragma omp for schedule(dynamic, 4)
    for (int t = 0; t < n_tiles; ++t) {
      keys.clear();
      for (int i = off[t]; i < off[t + 1]; ++i) keys.emplace_back(d[id[i]], id[i]);
      std::sort(keys.begin(), keys.end());
      for (int i = off[t]; i < off[t + 1]; ++i) id[i] = keys[i - off[t]].second;
    }
  }
  return {offsets, ids};
}

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

}  // namespace

// Composites values [N,C] front to back. Returns image [H,W,C], transmittance [H,W] and the
// index (into tile_ids) of each pixel's last contributing Gaussian [H,W] (int32, -1: none).
std::vector<torch::Tensor> rasterize_forward(torch::Tensor means2d, torch::Tensor conics, torch::Tensor opacities,
                                             torch::Tensor values, torch::Tensor boxes, torch::Tensor tile_offsets,
                                             torch::Tensor tile_ids, int64_t width, int64_t height) {
  check_cpu_float(means2d, "means2d", 2);
  check_cpu_float(conics, "conics", 3);
  check_cpu_float(values, "values", 0);
  const int C = (int)values.size(1);
  const int tiles_x = (int)((width + kTile - 1) / kTile), tiles_y = (int)((height + kTile - 1) / kTile);
  auto opts = values.options();
  auto image = torch::zeros({height, width, C}, opts);
  auto transmittance = torch::ones({height, width}, opts);
  auto last = torch::full({height, width}, -1, opts.dtype(torch::kInt32));
  const float *mu = means2d.data_ptr<float>(), *con = conics.data_ptr<float>(), *op = opacities.data_ptr<float>();
  const float* val = values.data_ptr<float>();
  const int32_t *box = boxes.data_ptr<int32_t>(), *off = tile_offsets.data_ptr<int32_t>(), *ids = tile_ids.data_ptr<int32_t>();
  float *img = image.data_ptr<float>(), *trans = transmittance.data_ptr<float>();
  int32_t* last_out = last.data_ptr<int32_t>();

#pragma omp parallel
  {
    std::vector<float> acc((size_t)C * kTilePixels);
    alignas(64) float T[kTilePixels], live[kTilePixels], weight[kTilePixels];
    alignas(64) int32_t last_idx[kTilePixels];
#pragma omp for schedule(dynamic, 1)
    for (int tile = 0; tile < tiles_x * tiles_y; ++tile) {
      const TileGeometry tg = tile_geometry(tile, tiles_x, width, height);
      std::fill(acc.begin(), acc.end(), 0.f);
      int n_live = 0;
      for (int p = 0; p < kTilePixels; ++p) {
        const bool inside = (p % kTile) < tg.width && (p / kTile) < tg.height;
        T[p] = 1.f;
        live[p] = inside ? 1.f : 0.f;
        last_idx[p] = -1;
        n_live += inside;
      }
      for (int k = off[tile]; k < off[tile + 1] && n_live > 0; ++k) {
        const int g = ids[k];
        int lx0, lx1, ly0, ly1;
        if (!box_in_tile(box + 4 * g, tg, lx0, lx1, ly0, ly1)) continue;
        const float mx = mu[2 * g], my = mu[2 * g + 1];
        const float a = con[3 * g], b = con[3 * g + 1], c = con[3 * g + 2], o = op[g];
        int n_stopped = 0;
        for (int ly = ly0; ly < ly1; ++ly) {
          const float dy = my - (tg.y0 + ly + 0.5f);
          const int row = ly * kTile;
#pragma omp simd reduction(+ : n_stopped)
          for (int lx = lx0; lx < lx1; ++lx) {
            const int p = row + lx;
            const float dx = mx - (tg.x0 + lx + 0.5f);
            const float power = -0.5f * (a * dx * dx + c * dy * dy) - b * dx * dy;
            const float alpha = std::min(kAlphaMax, o * exp_nonpositive(std::min(power, 0.f)));
            const bool valid = live[p] > 0.f && power <= 0.f && alpha >= kAlphaMin;
            const float next_T = T[p] * (1.f - alpha);
            const bool stop = valid && next_T < kTransmittanceMin;
            const bool contributes = valid && !stop;
            weight[p] = contributes ? alpha * T[p] : 0.f;
            T[p] = contributes ? next_T : T[p];
            live[p] = stop ? 0.f : live[p];
            last_idx[p] = contributes ? k : last_idx[p];
            n_stopped += stop ? 1 : 0;
          }
        }
        n_live -= n_stopped;
        const float* vg = val + (size_t)g * C;
        for (int ch = 0; ch < C; ++ch) {
          const float v = vg[ch];
          float* acc_c = acc.data() + (size_t)ch * kTilePixels;
          for (int ly = ly0; ly < ly1; ++ly) {
            const int row = ly * kTile;
#pragma omp simd
            for (int lx = lx0; lx < lx1; ++lx) acc_c[row + lx] += weight[row + lx] * v;
          }
        }
      }
      for (int ly = 0; ly < tg.height; ++ly)
        for (int lx = 0; lx < tg.width; ++lx) {
          const int p = ly * kTile + lx;
          const int64_t pix = (int64_t)(tg.y0 + ly) * width + tg.x0 + lx;
          for (int ch = 0; ch < C; ++ch) img[pix * C + ch] = acc[(size_t)ch * kTilePixels + p];
          trans[pix] = T[p];
          last_out[pix] = last_idx[p];
        }
    }
  }
  return {image, transmittance, last};
}

// Backward of rasterize_forward for the image and alpha = 1 - transmittance. Returns
// v_means2d [N,2], v_conics [N,3], v_opacities [N], v_values [N,C].
std::vector<torch::Tensor> rasterize_backward(torch::Tensor means2d, torch::Tensor conics, torch::Tensor opacities,
                                              torch::Tensor values, torch::Tensor boxes, torch::Tensor tile_offsets,
                                              torch::Tensor tile_ids, torch::Tensor transmittance,
                                              torch::Tensor last, torch::Tensor v_image, torch::Tensor v_alpha) {
  const int64_t n = means2d.size(0), height = transmittance.size(0), width = transmittance.size(1);
  const int C = (int)values.size(1);
  const int stride = 6 + C;  // per Gaussian: mean x, y, conic a, b, c, opacity, values
  const int tiles_x = (int)((width + kTile - 1) / kTile), tiles_y = (int)((height + kTile - 1) / kTile);
  const float *mu = means2d.data_ptr<float>(), *con = conics.data_ptr<float>(), *op = opacities.data_ptr<float>();
  const float* val = values.data_ptr<float>();
  const int32_t *box = boxes.data_ptr<int32_t>(), *off = tile_offsets.data_ptr<int32_t>(), *ids = tile_ids.data_ptr<int32_t>();
  const float *trans = transmittance.data_ptr<float>(), *gimg = v_image.data_ptr<float>(), *galpha = v_alpha.data_ptr<float>();
  const int32_t* last_in = last.data_ptr<int32_t>();
  const int n_threads = omp_get_max_threads();
  // Tiles run in parallel and share Gaussians: each thread sums into its own buffer.
  std::vector<float> grads((size_t)n_threads * n * stride, 0.f);

#pragma omp parallel
  {
    float* my_grads = grads.data() + (size_t)omp_get_thread_num() * n * stride;
    std::vector<float> v_pix((size_t)C * kTilePixels), behind((size_t)C * kTilePixels);
    alignas(64) float T[kTilePixels], T_final_over[kTilePixels], v_alpha_pix[kTilePixels];
    alignas(64) float weight[kTilePixels], inv_one_minus[kTilePixels], v_alpha_g[kTilePixels], raw[kTilePixels];
    alignas(64) float gauss[kTilePixels], mask[kTilePixels];
    alignas(64) int32_t last_idx[kTilePixels];
    std::vector<float> v_val(C);
#pragma omp for schedule(dynamic, 1)
    for (int tile = 0; tile < tiles_x * tiles_y; ++tile) {
      const TileGeometry tg = tile_geometry(tile, tiles_x, width, height);
      int max_last = -1;
      for (int p = 0; p < kTilePixels; ++p) {
        const int lx = p % kTile, ly = p / kTile;
        const bool inside = lx < tg.width && ly < tg.height;
        const int64_t pix = (int64_t)(tg.y0 + ly) * width + tg.x0 + lx;
        T[p] = inside ? trans[pix] : 1.f;
        T_final_over[p] = T[p];
        last_idx[p] = inside ? last_in[pix] : -1;
        v_alpha_pix[p] = inside ? galpha[pix] : 0.f;
        max_last = std::max(max_last, last_idx[p]);
        for (int ch = 0; ch < C; ++ch) {
          v_pix[(size_t)ch * kTilePixels + p] = inside ? gimg[pix * C + ch] : 0.f;
          behind[(size_t)ch * kTilePixels + p] = 0.f;
        }
      }
      for (int k = max_last; k >= off[tile]; --k) {
        const int g = ids[k];
        int lx0, lx1, ly0, ly1;
        if (!box_in_tile(box + 4 * g, tg, lx0, lx1, ly0, ly1)) continue;
        const float mx = mu[2 * g], my = mu[2 * g + 1];
        const float a = con[3 * g], b = con[3 * g + 1], c = con[3 * g + 2], o = op[g];
        // Pass 1: which pixels this Gaussian reached, with what weight; step T back past it.
        for (int ly = ly0; ly < ly1; ++ly) {
          const float dy = my - (tg.y0 + ly + 0.5f);
          const int row = ly * kTile;
#pragma omp simd
          for (int lx = lx0; lx < lx1; ++lx) {
            const int p = row + lx;
            const float dx = mx - (tg.x0 + lx + 0.5f);
            const float power = -0.5f * (a * dx * dx + c * dy * dy) - b * dx * dy;
            const float gval = exp_nonpositive(std::min(power, 0.f));
            const float raw_alpha = o * gval;
            const float alpha = std::min(kAlphaMax, raw_alpha);
            const bool contributes = k <= last_idx[p] && power <= 0.f && alpha >= kAlphaMin;
            const float inv = 1.f / (1.f - alpha);
            const float T_before = contributes ? T[p] * inv : T[p];
            T[p] = T_before;
            weight[p] = contributes ? alpha * T_before : 0.f;
            mask[p] = contributes ? 1.f : 0.f;
            inv_one_minus[p] = inv;
            gauss[p] = gval;
            raw[p] = raw_alpha;
            // d alpha_image / d alpha_k = T_final / (1 - alpha_k)
            v_alpha_g[p] = contributes ? v_alpha_pix[p] * T_final_over[p] * inv : 0.f;
          }
        }
        // Pass 2, per channel: value gradient and d pixel / d alpha.
        const float* vg = val + (size_t)g * C;
        for (int ch = 0; ch < C; ++ch) {
          const float v = vg[ch];
          const float* vp = v_pix.data() + (size_t)ch * kTilePixels;
          float* bh = behind.data() + (size_t)ch * kTilePixels;
          float v_value = 0.f;
          for (int ly = ly0; ly < ly1; ++ly) {
            const int row = ly * kTile;
#pragma omp simd reduction(+ : v_value)
            for (int lx = lx0; lx < lx1; ++lx) {
              const int p = row + lx;
              v_value += weight[p] * vp[p];
              v_alpha_g[p] += mask[p] * (v * T[p] - bh[p] * inv_one_minus[p]) * vp[p];
              bh[p] += weight[p] * v;
            }
          }
          v_val[ch] = v_value;
        }
        // Pass 3: through alpha = min(0.99, opacity * exp(power)) to the 2D parameters.
        float v_mx = 0.f, v_my = 0.f, v_a = 0.f, v_b = 0.f, v_c = 0.f, v_o = 0.f;
        for (int ly = ly0; ly < ly1; ++ly) {
          const float dy = my - (tg.y0 + ly + 0.5f);
          const int row = ly * kTile;
#pragma omp simd reduction(+ : v_mx, v_my, v_a, v_b, v_c, v_o)
          for (int lx = lx0; lx < lx1; ++lx) {
            const int p = row + lx;
            const float dx = mx - (tg.x0 + lx + 0.5f);
            const float v_raw = raw[p] <= kAlphaMax ? v_alpha_g[p] : 0.f;
            const float v_power = raw[p] * v_raw;
            v_o += gauss[p] * v_raw;
            v_a += -0.5f * dx * dx * v_power;
            v_b += -dx * dy * v_power;
            v_c += -0.5f * dy * dy * v_power;
            v_mx += -(a * dx + b * dy) * v_power;
            v_my += -(b * dx + c * dy) * v_power;
          }
        }
        float* out = my_grads + (size_t)g * stride;
        out[0] += v_mx; out[1] += v_my; out[2] += v_a; out[3] += v_b; out[4] += v_c; out[5] += v_o;
        for (int ch = 0; ch < C; ++ch) out[6 + ch] += v_val[ch];
      }
    }
  }
  auto total = torch::zeros({n, stride}, values.options());
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

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("project_forward", &project_forward, "EWA projection of 3D Gaussians");
  m.def("project_backward", &project_backward, "backward of project_forward");
  m.def("bin_tiles", &bin_tiles, "16x16 tile lists sorted by depth");
  m.def("rasterize_forward", &rasterize_forward, "front-to-back compositing of C channels");
  m.def("rasterize_backward", &rasterize_backward, "backward of rasterize_forward");
}
