// Per-pixel K x K kernels applied to an image with replicate borders, forward
// and hand-written backward, on CPU (see gsmsdr_ns/ops/pixel_kernels.py for the
// Python entry point and the PyTorch twin).
//
// Convention (row-major kernel index k = i * K + j, p = K / 2):
//   out[b, c, y, x] = sum_{i, j} weights[b, k, y, x]
//                     * image[b, c, clamp(y + i - p, 0, H - 1), clamp(x + j - p, 0, W - 1)]
// which is F.unfold's patch ordering on a replicate-padded image.
//
// Nothing of size K*K x image is ever allocated: the forward accumulates the
// K*K shifted rows into each output row, the backward recomputes them.
// All three loops run in a single at::parallel_for over the B*H rows (one
// OpenMP region per call, not one per kernel offset) and every output row is
// owned by exactly one iteration, so there are no races and the result does
// not depend on the thread schedule:
//   forward      : iteration (b, y)  writes out[b, :, y, :]
//   grad_weights : iteration (b, y)  writes grad_weights[b, :, y, :]
//   grad_image   : iteration (b, ys) gathers every (y, i, j) whose clamped
//                  source row is ys and writes grad_image[b, :, ys, :]
// The x loops are split into the left border (clamped to column 0), the
// interior (a plain shifted, vectorisable loop) and the right border.
//
// Only light torch headers are used (no torch/extension.h) to keep the JIT
// compile short; the ops are registered with TORCH_LIBRARY under the
// namespace gsmsdr_blur (gsmsdr_ns belongs to the rasterizer extension).

#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/zeros.h>
#include <torch/library.h>

#include "row_ops.h"

#include <algorithm>
#include <cstdint>
#include <optional>
#include <tuple>

namespace gsmsdr_blur {

using at::Tensor;

namespace {

using gsmsdr_rows::clamp_row;
using gsmsdr_rows::interior;
using gsmsdr_rows::shifted_fma;
using gsmsdr_rows::shifted_fma_adjoint;
using gsmsdr_rows::shifted_mul;

struct Dims {
    int64_t B, C, H, W, K, p, HW;
};

template <typename S> void forward_rows(const S *img, const S *wts, S *out, const Dims &s, int64_t begin, int64_t end) {
    for (int64_t row = begin; row < end; ++row) {
        const int64_t b = row / s.H, y = row % s.H;
        const S *img_b = img + b * s.C * s.HW;
        const S *w_row = wts + b * s.K * s.K * s.HW + y * s.W;
        S *out_row = out + b * s.C * s.HW + y * s.W;
        for (int64_t c = 0; c < s.C; ++c) std::fill(out_row + c * s.HW, out_row + c * s.HW + s.W, S(0));
        for (int64_t i = 0; i < s.K; ++i) {
            const int64_t ys = clamp_row(y + i - s.p, s.H);
            for (int64_t j = 0; j < s.K; ++j) {
                const int64_t d = j - s.p;
                int64_t lo, hi;
                interior(s.W, d, lo, hi);
                const S *w = w_row + (i * s.K + j) * s.HW;
                for (int64_t c = 0; c < s.C; ++c)
                    shifted_fma(out_row + c * s.HW, w, img_b + c * s.HW + ys * s.W, s.W, d, lo, hi);
            }
        }
    }
}

template <typename S>
void grad_weights_rows(const S *img, const S *g, S *gw, const Dims &s, int64_t begin, int64_t end) {
    for (int64_t row = begin; row < end; ++row) {
        const int64_t b = row / s.H, y = row % s.H;
        const S *img_b = img + b * s.C * s.HW;
        const S *g_row = g + b * s.C * s.HW + y * s.W;
        S *gw_row = gw + b * s.K * s.K * s.HW + y * s.W;
        for (int64_t i = 0; i < s.K; ++i) {
            const int64_t ys = clamp_row(y + i - s.p, s.H);
            for (int64_t j = 0; j < s.K; ++j) {
                const int64_t d = j - s.p;
                int64_t lo, hi;
                interior(s.W, d, lo, hi);
                S *dst = gw_row + (i * s.K + j) * s.HW;
                if (s.C == 0) {
                    std::fill(dst, dst + s.W, S(0));
                    continue;
                }
                shifted_mul(dst, g_row, img_b + ys * s.W, s.W, d, lo, hi);
                for (int64_t c = 1; c < s.C; ++c)
                    shifted_fma(dst, g_row + c * s.HW, img_b + c * s.HW + ys * s.W, s.W, d, lo, hi);
            }
        }
    }
}

template <typename S>
void grad_image_rows(const S *wts, const S *g, S *gi, const Dims &s, int64_t begin, int64_t end) {
    for (int64_t row = begin; row < end; ++row) {
        const int64_t b = row / s.H, ys = row % s.H;
        const S *w_b = wts + b * s.K * s.K * s.HW;
        const S *g_b = g + b * s.C * s.HW;
        S *gi_row = gi + b * s.C * s.HW + ys * s.W;
        for (int64_t c = 0; c < s.C; ++c) std::fill(gi_row + c * s.HW, gi_row + c * s.HW + s.W, S(0));
        for (int64_t i = 0; i < s.K; ++i) {
            // output rows y with clamp(y + i - p) == ys; the first / last source row also collect the margin
            const int64_t y_lo = std::max<int64_t>(ys == 0 ? 0 : ys - i + s.p, 0);
            const int64_t y_hi = std::min<int64_t>(ys == s.H - 1 ? s.H - 1 : ys - i + s.p, s.H - 1);
            for (int64_t y = y_lo; y <= y_hi; ++y) {
                for (int64_t j = 0; j < s.K; ++j) {
                    const int64_t d = j - s.p;
                    int64_t lo, hi;
                    interior(s.W, d, lo, hi);
                    const S *w = w_b + (i * s.K + j) * s.HW + y * s.W;
                    for (int64_t c = 0; c < s.C; ++c)
                        shifted_fma_adjoint(gi_row + c * s.HW, w, g_b + c * s.HW + y * s.W, s.W, d, lo, hi);
                }
            }
        }
    }
}

Dims check(const Tensor &image, const Tensor &weights, int64_t K) {
    TORCH_CHECK(image.dim() == 4 && weights.dim() == 4, "image and weights must be 4-D");
    TORCH_CHECK(K >= 1 && K % 2 == 1, "kernel_size must be odd and positive, got ", K);
    TORCH_CHECK(image.is_contiguous() && weights.is_contiguous(), "image and weights must be contiguous");
    TORCH_CHECK(image.scalar_type() == weights.scalar_type(), "image and weights must share a dtype");
    const int64_t B = image.size(0), C = image.size(1), H = image.size(2), W = image.size(3);
    TORCH_CHECK(weights.size(0) == B && weights.size(1) == K * K && weights.size(2) == H && weights.size(3) == W,
                "weights: expected shape [", B, ", ", K * K, ", ", H, ", ", W, "], got ", weights.sizes());
    TORCH_CHECK(H >= 1 && W >= 1, "image must have H >= 1 and W >= 1");
    return Dims{B, C, H, W, K, K / 2, H * W};
}

}  // namespace

Tensor pixel_kernels_fwd(const Tensor &image, const Tensor &weights, int64_t kernel_size) {
    const Dims s = check(image, weights, kernel_size);
    Tensor out = at::empty(image.sizes(), image.options());
    AT_DISPATCH_FLOATING_TYPES(image.scalar_type(), "pixel_kernels_fwd", [&] {
        const scalar_t *img = image.const_data_ptr<scalar_t>();
        const scalar_t *wts = weights.const_data_ptr<scalar_t>();
        scalar_t *o = out.mutable_data_ptr<scalar_t>();
        at::parallel_for(0, s.B * s.H, 1, [&](int64_t begin, int64_t end) {
            forward_rows<scalar_t>(img, wts, o, s, begin, end);
        });
    });
    return out;
}

std::tuple<std::optional<Tensor>, std::optional<Tensor>> pixel_kernels_bwd(
    const Tensor &grad_out, const Tensor &image, const Tensor &weights, int64_t kernel_size, bool need_image,
    bool need_weights
) {
    const Dims s = check(image, weights, kernel_size);
    TORCH_CHECK(grad_out.is_contiguous() && grad_out.sizes() == image.sizes() &&
                    grad_out.scalar_type() == image.scalar_type(),
                "grad_out must be contiguous with the image's shape and dtype");
    Tensor grad_image, grad_weights;
    if (need_image) grad_image = at::empty(image.sizes(), image.options());
    if (need_weights) grad_weights = at::empty(weights.sizes(), weights.options());
    AT_DISPATCH_FLOATING_TYPES(image.scalar_type(), "pixel_kernels_bwd", [&] {
        const scalar_t *img = image.const_data_ptr<scalar_t>();
        const scalar_t *wts = weights.const_data_ptr<scalar_t>();
        const scalar_t *g = grad_out.const_data_ptr<scalar_t>();
        scalar_t *gi = need_image ? grad_image.mutable_data_ptr<scalar_t>() : nullptr;
        scalar_t *gw = need_weights ? grad_weights.mutable_data_ptr<scalar_t>() : nullptr;
        // one parallel region for both gradients: each iteration owns one row of each
        at::parallel_for(0, s.B * s.H, 1, [&](int64_t begin, int64_t end) {
            if (gw != nullptr) grad_weights_rows<scalar_t>(img, g, gw, s, begin, end);
            if (gi != nullptr) grad_image_rows<scalar_t>(wts, g, gi, s, begin, end);
        });
    });
    std::optional<Tensor> gi_out, gw_out;
    if (need_image) gi_out = grad_image;
    if (need_weights) gw_out = grad_weights;
    return {gi_out, gw_out};
}

}  // namespace gsmsdr_blur

TORCH_LIBRARY(gsmsdr_blur, m) {
    m.def("pixel_kernels_fwd(Tensor image, Tensor weights, int kernel_size) -> Tensor");
    m.def(
        "pixel_kernels_bwd(Tensor grad_out, Tensor image, Tensor weights, int kernel_size, bool need_image, "
        "bool need_weights) -> (Tensor?, Tensor?)"
    );
}

TORCH_LIBRARY_IMPL(gsmsdr_blur, CPU, m) {
    m.impl("pixel_kernels_fwd", &gsmsdr_blur::pixel_kernels_fwd);
    m.impl("pixel_kernels_bwd", &gsmsdr_blur::pixel_kernels_bwd);
}
