// SSIM map of two images and its gradient with respect to the first, fused per channel.
//
// The torch twin (`ssim_map_reference` in mono_hdr_plugin/core/metrics.py) filters x, y, x^2, y^2
// and xy with two grouped convolutions and differentiates through them and a dozen elementwise
// maps: about 117 ms forward and backward at 512 x 512 px on one thread, most of it in the
// convolutions. Here the five statistics are filtered in one separable pass (11 taps, "valid"
// windows only, as the twin keeps), and the backward pass filters three gradient maps back.

// The few ATen headers these kernels use, not <torch/extension.h>: that one takes 28 s of a
// 35 s build (it parses all of libtorch's C++ API and pybind11); docs/gs_cpu.md, "Build time".
#include <ATen/core/Tensor.h>
#include <ATen/Dispatch.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/empty_like.h>
#include <torch/library.h>
#include <omp.h>

#include <memory>
#include <vector>

namespace {

constexpr int kTaps = 11;

// Five filtered statistics (mu_x, mu_y, E[x^2], E[y^2], E[xy]) of one channel, [5, h - 10, w - 10].
template <typename scalar_t>
void filtered_statistics(const scalar_t* x, const scalar_t* y, const scalar_t* g, int64_t h, int64_t w,
                         scalar_t* stats, scalar_t* rows) {
    const int64_t ow = w - kTaps + 1, oh = h - kTaps + 1;
    // horizontal pass: rows [5, h, ow]
    for (int64_t r = 0; r < h; ++r) {
        const scalar_t* xr = x + r * w;
        const scalar_t* yr = y + r * w;
        scalar_t* out0 = rows + (0 * h + r) * ow;
        scalar_t* out1 = rows + (1 * h + r) * ow;
        scalar_t* out2 = rows + (2 * h + r) * ow;
        scalar_t* out3 = rows + (3 * h + r) * ow;
        scalar_t* out4 = rows + (4 * h + r) * ow;
#pragma omp simd
        for (int64_t c = 0; c < ow; ++c) {
            scalar_t s0 = 0, s1 = 0, s2 = 0, s3 = 0, s4 = 0;
            for (int k = 0; k < kTaps; ++k) {
                const scalar_t a = xr[c + k], b = yr[c + k], gk = g[k];
                s0 += gk * a;
                s1 += gk * b;
                s2 += gk * a * a;
                s3 += gk * b * b;
                s4 += gk * a * b;
            }
            out0[c] = s0;
            out1[c] = s1;
            out2[c] = s2;
            out3[c] = s3;
            out4[c] = s4;
        }
    }
    // vertical pass: stats [5, oh, ow]
    for (int m = 0; m < 5; ++m) {
        for (int64_t r = 0; r < oh; ++r) {
            scalar_t* out = stats + (m * oh + r) * ow;
            const scalar_t* in = rows + (m * h + r) * ow;
#pragma omp simd
            for (int64_t c = 0; c < ow; ++c) out[c] = 0;
            for (int k = 0; k < kTaps; ++k) {
                const scalar_t gk = g[k];
                const scalar_t* src = in + k * ow;
#pragma omp simd
                for (int64_t c = 0; c < ow; ++c) out[c] += gk * src[c];
            }
        }
    }
}

// The transpose of the valid filter: a map [oh, ow] back onto [h, w] (full convolution).
template <typename scalar_t>
void filter_back(const scalar_t* in, const scalar_t* g, int64_t h, int64_t w, scalar_t* out, scalar_t* rows) {
    const int64_t ow = w - kTaps + 1, oh = h - kTaps + 1;
    // vertical: rows [h, ow], rows[r] = sum_k g[k] in[r - k]
    for (int64_t r = 0; r < h; ++r) {
        scalar_t* dst = rows + r * ow;
#pragma omp simd
        for (int64_t c = 0; c < ow; ++c) dst[c] = 0;
        for (int k = 0; k < kTaps; ++k) {
            const int64_t src_row = r - k;
            if (src_row < 0 || src_row >= oh) continue;
            const scalar_t gk = g[k];
            const scalar_t* src = in + src_row * ow;
#pragma omp simd
            for (int64_t c = 0; c < ow; ++c) dst[c] += gk * src[c];
        }
    }
    // horizontal: out[r, c] = sum_k g[k] rows[r, c - k], over a row padded with kTaps - 1 zeros each side
    std::vector<scalar_t> padded(ow + 2 * (kTaps - 1), scalar_t(0));
    scalar_t* pad = padded.data() + (kTaps - 1);
    for (int64_t r = 0; r < h; ++r) {
        const scalar_t* src = rows + r * ow;
        for (int64_t c = 0; c < ow; ++c) pad[c] = src[c];
        scalar_t* dst = out + r * w;
#pragma omp simd
        for (int64_t c = 0; c < w; ++c) {
            scalar_t sum = 0;
            for (int k = 0; k < kTaps; ++k) sum += g[k] * pad[c - k];
            dst[c] = sum;
        }
    }
}

void check_inputs(const at::Tensor& x, const at::Tensor& y, const at::Tensor& window) {
    TORCH_CHECK(x.dim() == 3 && x.is_contiguous() && y.sizes() == x.sizes() && y.is_contiguous(),
                "ssim: x and y must be contiguous [C, H, W] of one shape");
    TORCH_CHECK(x.size(1) >= kTaps && x.size(2) >= kTaps, "ssim: images need at least 11 pixels a side");
    TORCH_CHECK(window.numel() == kTaps && window.is_contiguous(), "ssim: the window has 11 taps");
    TORCH_CHECK(y.scalar_type() == x.scalar_type() && window.scalar_type() == x.scalar_type(), "ssim: one dtype");
}

// The four factors of one pixel's SSIM = (a1 a2) / (b1 b2), from its five filtered statistics.
template <typename scalar_t>
struct SsimFactors {
    scalar_t a1, a2, b1, b2;
    SsimFactors(scalar_t mx, scalar_t my, scalar_t xx, scalar_t yy, scalar_t xy, scalar_t k1, scalar_t k2)
        : a1(2 * mx * my + k1),
          a2(2 * (xy - mx * my) + k2),
          b1(mx * mx + my * my + k1),
          b2((xx - mx * mx) + (yy - my * my) + k2) {}
};

template <typename scalar_t>
void forward_channels(const scalar_t* xp, const scalar_t* yp, const scalar_t* g, scalar_t* mp, scalar_t* sp,
                      int64_t channels, int64_t h, int64_t w, scalar_t k1, scalar_t k2) {
    const int64_t oh = h - kTaps + 1, ow = w - kTaps + 1, n = oh * ow;
#pragma omp parallel for schedule(static)
    for (int64_t ch = 0; ch < channels; ++ch) {
        std::unique_ptr<scalar_t[]> rows(new scalar_t[5 * h * ow]);  // scratch, written before it is read
        scalar_t* stats = sp + ch * 5 * n;
        filtered_statistics(xp + ch * h * w, yp + ch * h * w, g, h, w, stats, rows.get());
        const scalar_t *mx = stats, *my = mx + n, *xx = my + n, *yy = xx + n, *xy = yy + n;
        scalar_t* out = mp + ch * n;
#pragma omp simd
        for (int64_t i = 0; i < n; ++i) {
            const SsimFactors<scalar_t> f(mx[i], my[i], xx[i], yy[i], xy[i], k1, k2);
            out[i] = (f.a1 * f.a2) / (f.b1 * f.b2);
        }
    }
}

template <typename scalar_t>
void backward_channels(const scalar_t* gm, const scalar_t* xp, const scalar_t* yp, const scalar_t* sp, const scalar_t* g,
                       scalar_t* gxp, int64_t channels, int64_t h, int64_t w, scalar_t k1, scalar_t k2) {
    const int64_t oh = h - kTaps + 1, ow = w - kTaps + 1, n = oh * ow;
#pragma omp parallel for schedule(static)
    for (int64_t ch = 0; ch < channels; ++ch) {
        // scratch, each written before it is read
        std::unique_ptr<scalar_t[]> rows(new scalar_t[h * ow]), partial(new scalar_t[3 * n]), back(new scalar_t[3 * h * w]);
        const scalar_t* xc = xp + ch * h * w;
        const scalar_t* yc = yp + ch * h * w;
        const scalar_t* stats = sp + ch * 5 * n;
        const scalar_t *mx = stats, *my = mx + n, *xx = my + n, *yy = xx + n, *xy = yy + n;
        scalar_t *d_mx = partial.get(), *d_xx = d_mx + n, *d_xy = d_xx + n;
        const scalar_t* gc = gm + ch * n;
#pragma omp simd
        for (int64_t i = 0; i < n; ++i) {
            const SsimFactors<scalar_t> f(mx[i], my[i], xx[i], yy[i], xy[i], k1, k2);
            const scalar_t s = (f.a1 * f.a2) / (f.b1 * f.b2);
            const scalar_t d_a1 = f.a2 / (f.b1 * f.b2), d_a2 = f.a1 / (f.b1 * f.b2);
            const scalar_t d_b1 = -s / f.b1, d_b2 = -s / f.b2;
            // a1, a2, b1, b2 as functions of mu_x, E[x^2], E[xy] (mu_y, E[y^2] belong to the constant y)
            d_mx[i] = gc[i] * (2 * my[i] * (d_a1 - d_a2) + 2 * mx[i] * (d_b1 - d_b2));
            d_xx[i] = gc[i] * d_b2;
            d_xy[i] = gc[i] * 2 * d_a2;
        }
        for (int m = 0; m < 3; ++m) filter_back(partial.get() + m * n, g, h, w, back.get() + m * h * w, rows.get());
        const scalar_t *b_mx = back.get(), *b_xx = b_mx + h * w, *b_xy = b_xx + h * w;
        scalar_t* out = gxp + ch * h * w;
#pragma omp simd
        for (int64_t i = 0; i < h * w; ++i) out[i] = b_mx[i] + 2 * xc[i] * b_xx[i] + yc[i] * b_xy[i];
    }
}

}  // namespace

// The SSIM map [C, H - 10, W - 10] and the filtered statistics [C, 5, H - 10, W - 10] the backward pass reads.
std::vector<at::Tensor> ssim_forward(at::Tensor x, at::Tensor y, at::Tensor window, double c1, double c2) {
    check_inputs(x, y, window);
    const int64_t channels = x.size(0), h = x.size(1), w = x.size(2);
    auto map = at::empty({channels, h - kTaps + 1, w - kTaps + 1}, x.options());
    auto stats = at::empty({channels, 5, h - kTaps + 1, w - kTaps + 1}, x.options());
    AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "ssim_forward", [&] {
        forward_channels<scalar_t>(x.data_ptr<scalar_t>(), y.data_ptr<scalar_t>(), window.data_ptr<scalar_t>(),
                                   map.data_ptr<scalar_t>(), stats.data_ptr<scalar_t>(), channels, h, w,
                                   static_cast<scalar_t>(c1), static_cast<scalar_t>(c2));
    });
    return {map, stats};
}

// d(sum(grad_map * map)) / dx. y is a constant (a training target).
at::Tensor ssim_backward(at::Tensor grad_map, at::Tensor x, at::Tensor y, at::Tensor stats,
                         at::Tensor window, double c1, double c2) {
    check_inputs(x, y, window);
    TORCH_CHECK(stats.is_contiguous() && stats.dim() == 4 && stats.size(0) == x.size(0) && stats.size(1) == 5,
                "ssim: stats must be the forward pass's [C, 5, H - 10, W - 10]");
    grad_map = grad_map.contiguous();
    const int64_t channels = x.size(0), h = x.size(1), w = x.size(2);
    TORCH_CHECK(grad_map.dim() == 3 && grad_map.size(0) == channels && grad_map.size(1) == h - kTaps + 1 &&
                    grad_map.size(2) == w - kTaps + 1,
                "ssim: grad_map must be [C, H - 10, W - 10]");
    auto grad_x = at::empty_like(x);
    AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "ssim_backward", [&] {
        backward_channels<scalar_t>(grad_map.data_ptr<scalar_t>(), x.data_ptr<scalar_t>(), y.data_ptr<scalar_t>(),
                                    stats.data_ptr<scalar_t>(), window.data_ptr<scalar_t>(), grad_x.data_ptr<scalar_t>(), channels, h, w,
                                    static_cast<scalar_t>(c1), static_cast<scalar_t>(c2));
    });
    return grad_x;
}

TORCH_LIBRARY(TORCH_EXTENSION_NAME, m) {
    m.def("ssim_forward", &ssim_forward);  // SSIM map [C, H - 10, W - 10] of two images [C, H, W], and its filtered statistics
    m.def("ssim_backward", &ssim_backward);  // gradient of the SSIM map with respect to the first image
}
