// Depthwise k x k convolution with dilation and zero padding (k / 2) * dilation (size-preserving), forward and
// hand-written backward on CPU (Python entry point and PyTorch twin: gsmsdr_ns/ops/depthwise_conv.py):
//   out[b, c, y, x] = sum_{i, j} weight[c, i, j] * image[b, c, y + (i - p) d, x + (j - p) d], p = k / 2,
// with image values outside the plane read as zero; the values of F.conv2d(image, weight, padding=p d,
// dilation=d, groups=C) without its bias.
//
// Each (b, c) plane is one iteration of one parallel loop. A plane is copied once into a zero-padded buffer, so the
// tap loops read without bounds checks, and the output is built in column blocks (vector_block.h) that keep their
// sums in registers across all k * k taps. The image gradient is the same convolution of the padded output gradient
// with the kernel flipped; the weight gradient sums, per tap, the output gradient times the shifted padded plane, one
// kernel row of taps at a time.

#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <torch/library.h>

#include "vector_block.h"

#include <algorithm>
#include <cstdint>
#include <optional>
#include <tuple>
#include <vector>

namespace gsmsdr_depthwise {

using at::Tensor;
using gsmsdr_vec::Block;

namespace {

// Column blocks summed side by side: independent sums hide the latency of each fused multiply-add.
constexpr int64_t NB = 4;
// Rows are padded to a whole number of BX-value groups (NB blocks, or more), plus BX.
constexpr int64_t BX = gsmsdr_vec::MAX_BLOCK * NB;

struct Dims {
    int64_t B, C, H, W, k, d, P, Hp, Wp;  // P: padding in pixels; Hp x Wp: the padded plane (with slack)
};

// plane [H, W] -> buf [Hp, Wp], zero outside, the plane at row P, column P.
template <typename S> void pad_plane(const S *plane, S *buf, const Dims &s) {
    std::fill(buf, buf + s.Hp * s.Wp, S(0));
    for (int64_t y = 0; y < s.H; ++y) std::copy(plane + y * s.W, plane + (y + 1) * s.W, buf + (y + s.P) * s.Wp + s.P);
}

// out[y, x] = sum_{i, j} w[i * k + j] * buf[y + i d, x + j d] over the plane (buf padded as pad_plane does).
template <typename S> void correlate(const S *buf, const S *w, S *out, const Dims &s) {
    using V = typename Block<S>::type;
    constexpr int64_t L = Block<S>::n;
    for (int64_t y = 0; y < s.H; ++y) {
        for (int64_t xb = 0; xb < s.W; xb += NB * L) {
            V acc[NB] = {};
            for (int64_t i = 0; i < s.k; ++i) {
                const S *row = buf + (y + i * s.d) * s.Wp + xb;
                for (int64_t j = 0; j < s.k; ++j) {
                    const S wv = w[i * s.k + j];
                    const S *r = row + j * s.d;
                    for (int64_t nb = 0; nb < NB; ++nb) acc[nb] += wv * Block<S>::load(r + nb * L);
                }
            }
            for (int64_t nb = 0; nb < NB && xb + nb * L < s.W; ++nb)
                Block<S>::store(out + y * s.W + xb + nb * L, acc[nb], std::min<int64_t>(L, s.W - xb - nb * L));
        }
    }
}

// gw[i * k + j] = sum_{y, x} g[y, x] * buf[y + i d, x + j d], with g read from gbuf, the output gradient padded as
// pad_plane does (zero past the plane's columns, so whole groups of blocks can be read).
template <typename S> void weight_grad(const S *buf, const S *gbuf, S *gw, const Dims &s) {
    const int64_t Wg = s.Wp - 2 * s.P - BX;  // the plane's columns, rounded up to whole groups of blocks
    using V = typename Block<S>::type;
    constexpr int64_t L = Block<S>::n;
    constexpr int64_t MAXJ = 8;  // taps of one kernel row summed together (k <= 8 per pass)
    for (int64_t i = 0; i < s.k; ++i) {
        for (int64_t j0 = 0; j0 < s.k; j0 += MAXJ) {
            const int64_t nj = std::min<int64_t>(MAXJ, s.k - j0);
            V acc[MAXJ] = {};
            for (int64_t y = 0; y < s.H; ++y) {
                const S *row = buf + (y + i * s.d) * s.Wp;
                const S *grow = gbuf + (y + s.P) * s.Wp + s.P;
                for (int64_t xb = 0; xb < Wg; xb += L) {
                    const V g = Block<S>::load(grow + xb);
                    for (int64_t jj = 0; jj < nj; ++jj) acc[jj] += g * Block<S>::load(row + xb + (j0 + jj) * s.d);
                }
            }
            for (int64_t jj = 0; jj < nj; ++jj) gw[i * s.k + j0 + jj] = Block<S>::sum(acc[jj]);
        }
    }
}

Dims check(const Tensor &image, const Tensor &weight, int64_t dilation) {
    TORCH_CHECK(image.dim() == 4, "image must be [B, C, H, W], got ", image.sizes());
    TORCH_CHECK(weight.dim() == 3, "weight must be [C, k, k], got ", weight.sizes());
    TORCH_CHECK(image.is_contiguous() && weight.is_contiguous(), "image and weight must be contiguous");
    TORCH_CHECK(image.scalar_type() == weight.scalar_type(), "image and weight must share a dtype");
    const int64_t B = image.size(0), C = image.size(1), H = image.size(2), W = image.size(3), k = weight.size(1);
    TORCH_CHECK(weight.size(0) == C && weight.size(2) == k && k >= 1 && k % 2 == 1,
                "weight: expected [", C, ", k, k] with odd k, got ", weight.sizes());
    TORCH_CHECK(dilation >= 1, "dilation must be >= 1, got ", dilation);
    TORCH_CHECK(H >= 1 && W >= 1, "image must have H >= 1 and W >= 1");
    const int64_t P = (k / 2) * dilation;
    const int64_t Wg = (W + BX - 1) / BX * BX;  // whole groups of blocks
    return Dims{B, C, H, W, k, dilation, P, H + 2 * P, Wg + 2 * P + BX};
}

}  // namespace

Tensor depthwise_conv_fwd(const Tensor &image, const Tensor &weight, int64_t dilation) {
    const Dims s = check(image, weight, dilation);
    Tensor out = at::empty(image.sizes(), image.options());
    AT_DISPATCH_FLOATING_TYPES(image.scalar_type(), "depthwise_conv_fwd", [&] {
        const scalar_t *img = image.const_data_ptr<scalar_t>();
        const scalar_t *w = weight.const_data_ptr<scalar_t>();
        scalar_t *o = out.mutable_data_ptr<scalar_t>();
        at::parallel_for(0, s.B * s.C, 1, [&](int64_t begin, int64_t end) {
            std::vector<scalar_t> buf(s.Hp * s.Wp);
            for (int64_t plane = begin; plane < end; ++plane) {
                pad_plane(img + plane * s.H * s.W, buf.data(), s);
                correlate(buf.data(), w + (plane % s.C) * s.k * s.k, o + plane * s.H * s.W, s);
            }
        });
    });
    return out;
}

std::tuple<std::optional<Tensor>, std::optional<Tensor>> depthwise_conv_bwd(
    const Tensor &grad_out, const Tensor &image, const Tensor &weight, int64_t dilation, bool need_image,
    bool need_weight
) {
    const Dims s = check(image, weight, dilation);
    TORCH_CHECK(grad_out.is_contiguous() && grad_out.sizes() == image.sizes() &&
                    grad_out.scalar_type() == image.scalar_type(),
                "grad_out must be contiguous with the image's shape and dtype");
    Tensor grad_image, grad_weight;
    if (need_image) grad_image = at::empty(image.sizes(), image.options());
    // per plane, summed over the batch below
    Tensor per_plane = need_weight ? at::empty({s.B, s.C, s.k, s.k}, weight.options()) : Tensor();
    AT_DISPATCH_FLOATING_TYPES(image.scalar_type(), "depthwise_conv_bwd", [&] {
        const scalar_t *img = image.const_data_ptr<scalar_t>();
        const scalar_t *w = weight.const_data_ptr<scalar_t>();
        const scalar_t *g = grad_out.const_data_ptr<scalar_t>();
        // the kernels flipped in both axes: the image gradient is the output gradient correlated with them
        std::vector<scalar_t> flipped(s.C * s.k * s.k);
        for (int64_t c = 0; c < s.C; ++c)
            for (int64_t t = 0; t < s.k * s.k; ++t) flipped[c * s.k * s.k + t] = w[c * s.k * s.k + s.k * s.k - 1 - t];
        at::parallel_for(0, s.B * s.C, 1, [&](int64_t begin, int64_t end) {
            std::vector<scalar_t> gbuf(s.Hp * s.Wp), ibuf(need_weight ? s.Hp * s.Wp : 0);
            for (int64_t plane = begin; plane < end; ++plane) {
                pad_plane(g + plane * s.H * s.W, gbuf.data(), s);  // read by both gradients
                if (need_weight) {
                    pad_plane(img + plane * s.H * s.W, ibuf.data(), s);
                    weight_grad(ibuf.data(), gbuf.data(), per_plane.mutable_data_ptr<scalar_t>() + plane * s.k * s.k,
                                s);
                }
                if (need_image) {
                    correlate(gbuf.data(), flipped.data() + (plane % s.C) * s.k * s.k,
                              grad_image.mutable_data_ptr<scalar_t>() + plane * s.H * s.W, s);
                }
            }
        });
    });
    if (need_weight) grad_weight = per_plane.sum(0);
    std::optional<Tensor> gi_out, gw_out;
    if (need_image) gi_out = grad_image;
    if (need_weight) gw_out = grad_weight;
    return {gi_out, gw_out};
}

}  // namespace gsmsdr_depthwise

TORCH_LIBRARY(gsmsdr_depthwise, m) {
    m.def("depthwise_conv_fwd(Tensor image, Tensor weight, int dilation) -> Tensor");
    m.def(
        "depthwise_conv_bwd(Tensor grad_out, Tensor image, Tensor weight, int dilation, bool need_image, "
        "bool need_weight) -> (Tensor?, Tensor?)"
    );
}

TORCH_LIBRARY_IMPL(gsmsdr_depthwise, CPU, m) {
    m.impl("depthwise_conv_fwd", &gsmsdr_depthwise::depthwise_conv_fwd);
    m.impl("depthwise_conv_bwd", &gsmsdr_depthwise::depthwise_conv_bwd);
}
