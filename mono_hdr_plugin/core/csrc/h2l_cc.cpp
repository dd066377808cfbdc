// H2L-CC fused per pixel: out = sigmoid(relu(R) + tanh(B)), [R, B] = W2 relu(W1 x + b1) + b2.
//
// Autograd through the torch layers keeps a [pixels, hidden] latent, its ReLU and their gradients
// (six passes over 134 MB at 512 x 512 px, hidden 128): most of a whole-image 3DGS step. Here each
// pixel's latent lives in registers and a small buffer; the backward pass recomputes it instead of
// storing it. The torch twin is `h2l_cc_reference` in mono_hdr_plugin/core/converters.py.

// The few ATen headers these kernels use, not <torch/extension.h>: that one takes 28 s of a
// 35 s build (it parses all of libtorch's C++ API and pybind11); docs/gs_cpu.md, "Build time".
#include <ATen/core/Tensor.h>
#include <ATen/Dispatch.h>
#include <ATen/ops/empty_like.h>
#include <ATen/ops/zeros.h>
#include <torch/library.h>
#include <omp.h>

#include <cmath>
#include <vector>

namespace {

constexpr int kHeads = 6;  // R (3 channels) then B (3 channels)

template <typename scalar_t>
struct Pixel {
    // latent h (hidden), heads [R, B] and the output of one pixel
    std::vector<scalar_t> h;
    scalar_t heads[kHeads];
    scalar_t out[3];
    explicit Pixel(int64_t hidden) : h(hidden) {}

    void forward(const scalar_t* x, const scalar_t* w1t, const scalar_t* b1, const scalar_t* w2,
                 const scalar_t* b2, int64_t hidden) {
        const scalar_t x0 = x[0], x1 = x[1], x2 = x[2];
        const scalar_t* w1_0 = w1t;
        const scalar_t* w1_1 = w1t + hidden;
        const scalar_t* w1_2 = w1t + 2 * hidden;
        scalar_t* hp = h.data();
#pragma omp simd
        for (int64_t j = 0; j < hidden; ++j) {
            const scalar_t pre = b1[j] + w1_0[j] * x0 + w1_1[j] * x1 + w1_2[j] * x2;
            hp[j] = pre > 0 ? pre : scalar_t(0);
        }
        for (int c = 0; c < kHeads; ++c) {
            const scalar_t* row = w2 + c * hidden;
            scalar_t sum = 0;
#pragma omp simd reduction(+ : sum)
            for (int64_t j = 0; j < hidden; ++j) sum += row[j] * hp[j];
            heads[c] = sum + b2[c];
        }
        for (int k = 0; k < 3; ++k) {
            const scalar_t r = heads[k] > 0 ? heads[k] : scalar_t(0);
            out[k] = scalar_t(1) / (scalar_t(1) + std::exp(-(r + std::tanh(heads[3 + k]))));
        }
    }
};

// w1 [hidden, 3] -> w1t [3, hidden], so that the per-pixel loops over hidden units read contiguously
at::Tensor transposed_latent(const at::Tensor& w1) { return w1.t().contiguous(); }

void check_inputs(const at::Tensor& x, const at::Tensor& w1, const at::Tensor& b1, const at::Tensor& w2,
                  const at::Tensor& b2) {
    TORCH_CHECK(x.dim() == 2 && x.size(1) == 3 && x.is_contiguous(), "h2l_cc: x must be contiguous [N, 3]");
    TORCH_CHECK(w1.dim() == 2 && w1.size(1) == 3, "h2l_cc: latent weight must be [hidden, 3]");
    const int64_t hidden = w1.size(0);
    TORCH_CHECK(b1.numel() == hidden && b1.is_contiguous(), "h2l_cc: latent bias must be [hidden]");
    TORCH_CHECK(w2.dim() == 2 && w2.size(0) == kHeads && w2.size(1) == hidden && w2.is_contiguous(),
                "h2l_cc: head weights must be contiguous [6, hidden]");
    TORCH_CHECK(b2.numel() == kHeads && b2.is_contiguous(), "h2l_cc: head bias must be [6]");
    for (const auto* t : {&w1, &b1, &w2, &b2})
        TORCH_CHECK(t->scalar_type() == x.scalar_type() && t->device().is_cpu(), "h2l_cc: one dtype, CPU tensors");
}

template <typename scalar_t>
void forward_pixels(const scalar_t* xp, const scalar_t* w1p, const scalar_t* b1p, const scalar_t* w2p,
                    const scalar_t* b2p, scalar_t* op, int64_t n, int64_t hidden) {
#pragma omp parallel
    {
        Pixel<scalar_t> pixel(hidden);
#pragma omp for schedule(static)
        for (int64_t i = 0; i < n; ++i) {
            pixel.forward(xp + 3 * i, w1p, b1p, w2p, b2p, hidden);
            for (int k = 0; k < 3; ++k) op[3 * i + k] = pixel.out[k];
        }
    }
}

// Gradients of sum(grad_out * out) with respect to x, w1t, b1, w2, b2. Each thread sums the weight
// gradients of its pixels into its own row of `partial` [threads, 10 hidden + 6]: grad w1t [3, hidden],
// grad b1 [hidden], grad w2 [6, hidden], grad b2 [6]; the rows are added afterwards.
template <typename scalar_t>
void backward_pixels(const scalar_t* gop, const scalar_t* xp, const scalar_t* w1p, const scalar_t* b1p,
                     const scalar_t* w2p, const scalar_t* b2p, scalar_t* gxp, scalar_t* partial_p, int threads,
                     int64_t n, int64_t hidden) {
    const int64_t stride = 10 * hidden + kHeads;
#pragma omp parallel num_threads(threads)
    {
        scalar_t* acc = partial_p + omp_get_thread_num() * stride;
        scalar_t* g_w1t = acc;
        scalar_t* g_b1 = acc + 3 * hidden;
        scalar_t* g_w2 = acc + 4 * hidden;
        scalar_t* g_b2 = acc + 10 * hidden;
        Pixel<scalar_t> pixel(hidden);
        std::vector<scalar_t> g_pre(hidden);
        scalar_t* gp = g_pre.data();
#pragma omp for schedule(static)
        for (int64_t i = 0; i < n; ++i) {
            const scalar_t* xi = xp + 3 * i;
            pixel.forward(xi, w1p, b1p, w2p, b2p, hidden);
            const scalar_t* hp = pixel.h.data();
            scalar_t g_heads[kHeads];
            for (int k = 0; k < 3; ++k) {
                const scalar_t s = pixel.out[k];
                const scalar_t g_z = gop[3 * i + k] * s * (scalar_t(1) - s);
                g_heads[k] = pixel.heads[k] > 0 ? g_z : scalar_t(0);
                const scalar_t t = std::tanh(pixel.heads[3 + k]);
                g_heads[3 + k] = g_z * (scalar_t(1) - t * t);
            }
            for (int c = 0; c < kHeads; ++c) {
                const scalar_t gc = g_heads[c];
                scalar_t* row = g_w2 + c * hidden;
#pragma omp simd
                for (int64_t j = 0; j < hidden; ++j) row[j] += gc * hp[j];
                g_b2[c] += gc;
            }
#pragma omp simd
            for (int64_t j = 0; j < hidden; ++j) {
                scalar_t g_h = 0;
                for (int c = 0; c < kHeads; ++c) g_h += w2p[c * hidden + j] * g_heads[c];
                gp[j] = hp[j] > 0 ? g_h : scalar_t(0);  // ReLU: no gradient where its input was <= 0
            }
            scalar_t gx0 = 0, gx1 = 0, gx2 = 0;
            const scalar_t x0 = xi[0], x1 = xi[1], x2 = xi[2];
#pragma omp simd reduction(+ : gx0, gx1, gx2)
            for (int64_t j = 0; j < hidden; ++j) {
                const scalar_t g = gp[j];
                g_b1[j] += g;
                g_w1t[j] += g * x0;
                g_w1t[hidden + j] += g * x1;
                g_w1t[2 * hidden + j] += g * x2;
                gx0 += w1p[j] * g;
                gx1 += w1p[hidden + j] * g;
                gx2 += w1p[2 * hidden + j] * g;
            }
            gxp[3 * i] = gx0;
            gxp[3 * i + 1] = gx1;
            gxp[3 * i + 2] = gx2;
        }
    }
}

}  // namespace

at::Tensor h2l_forward(at::Tensor x, at::Tensor w1, at::Tensor b1, at::Tensor w2, at::Tensor b2) {
    check_inputs(x, w1, b1, w2, b2);
    const int64_t n = x.size(0), hidden = w1.size(0);
    auto w1t = transposed_latent(w1);
    auto out = at::empty_like(x);
    AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "h2l_forward", [&] {
        forward_pixels<scalar_t>(x.data_ptr<scalar_t>(), w1t.data_ptr<scalar_t>(), b1.data_ptr<scalar_t>(),
                                 w2.data_ptr<scalar_t>(), b2.data_ptr<scalar_t>(), out.data_ptr<scalar_t>(), n,
                                 hidden);
    });
    return out;
}

std::vector<at::Tensor> h2l_backward(at::Tensor grad_out, at::Tensor x, at::Tensor w1, at::Tensor b1,
                                     at::Tensor w2, at::Tensor b2) {
    check_inputs(x, w1, b1, w2, b2);
    grad_out = grad_out.contiguous();
    TORCH_CHECK(grad_out.sizes() == x.sizes(), "h2l_cc: grad_out must have the shape of x");
    const int64_t n = x.size(0), hidden = w1.size(0);
    auto w1t = transposed_latent(w1);
    auto grad_x = at::empty_like(x);
    const int threads = omp_get_max_threads();
    auto partial = at::zeros({threads, 10 * hidden + kHeads}, x.options());
    AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "h2l_backward", [&] {
        backward_pixels<scalar_t>(grad_out.data_ptr<scalar_t>(), x.data_ptr<scalar_t>(), w1t.data_ptr<scalar_t>(),
                                  b1.data_ptr<scalar_t>(), w2.data_ptr<scalar_t>(), b2.data_ptr<scalar_t>(),
                                  grad_x.data_ptr<scalar_t>(), partial.data_ptr<scalar_t>(), threads, n, hidden);
    });
    auto total = partial.sum(0);
    auto grad_w1 = total.narrow(0, 0, 3 * hidden).view({3, hidden}).t().contiguous();
    auto grad_b1 = total.narrow(0, 3 * hidden, hidden).clone();
    auto grad_w2 = total.narrow(0, 4 * hidden, kHeads * hidden).view({kHeads, hidden}).clone();
    auto grad_b2 = total.narrow(0, 10 * hidden, kHeads).clone();
    return {grad_x, grad_w1, grad_b1, grad_w2, grad_b2};
}

TORCH_LIBRARY(TORCH_EXTENSION_NAME, m) {
    m.def("h2l_forward", &h2l_forward);  // H2L-CC forward, fused per pixel
    m.def("h2l_backward", &h2l_backward);  // H2L-CC backward, recomputing each pixel's latent
}
