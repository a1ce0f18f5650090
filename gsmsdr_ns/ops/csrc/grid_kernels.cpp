// Per-pixel K x K kernels predicted on a coarse grid, bilinearly resampled to
// every pixel on the fly and applied with replicate borders: forward and
// hand-written backward on CPU (Python entry point and PyTorch twin:
// gsmsdr_ns/ops/grid_kernels.py).
//
// With r the grid factor, the kernel of pixel (y, x) is
//   w[k](y, x) = bilinear(grid[k], (y + 0.5) / r - 0.5, (x + 0.5) / r - 0.5)
// (source coordinates clamped to the grid, as F.interpolate(scale_factor=r,
// mode="bilinear", align_corners=False) does), and the output is
//   out[b, c, y, x] = sum_k w[k](y, x) * image[b, c, clamp(y + i - p), clamp(x + j - p)]
// with k = i * K + j, p = K / 2, as in pixel_kernels.cpp. The full-resolution
// [B, K*K, H, W] weights are never stored: each row of them is interpolated
// from two grid rows resampled to the pixel columns (ResampledRows) when it is
// needed.
//
// Parallel loops (one OpenMP region per call, each output row owned by one
// iteration, so results do not depend on the thread schedule):
//   forward      : iteration (b, y)  writes out[b, :, y, :]
//   grad_image   : iteration (b, ys) gathers every (y, i) whose clamped source
//                  row is ys and writes grad_image[b, :, ys, :]
//   grad_grid    : iteration (b, gy) reduces the tap gradients of the pixel
//                  rows whose stencil starts at grid row gy into its own two
//                  [K*K, w] blocks (for grid rows gy and gy + 1); then
//                  iteration (b, gy) adds the two blocks of grid row gy into
//                  grad_grid[b, :, gy, :]

#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <torch/library.h>

#include "row_ops.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <optional>
#include <tuple>
#include <vector>

namespace gsmsdr_grid {

using at::Tensor;

namespace {

using gsmsdr_rows::clamp_row;
using gsmsdr_rows::interior;
using gsmsdr_rows::shifted_fma;
using gsmsdr_rows::shifted_fma_adjoint;

struct Dims {
    int64_t B, C, H, W, K, p, HW, h, w, hw, r;
};

// Bilinear stencil along one axis: output index o reads grid cells lo and hi with weights 1 - t and t.
struct Stencil {
    int64_t lo, hi;
    double t;
};

inline Stencil stencil(int64_t o, int64_t r, int64_t n) {
    double src = (static_cast<double>(o) + 0.5) / static_cast<double>(r) - 0.5;
    if (src < 0.0) src = 0.0;
    int64_t lo = std::min<int64_t>(static_cast<int64_t>(std::floor(src)), n - 1);
    int64_t hi = std::min<int64_t>(lo + 1, n - 1);
    return Stencil{lo, hi, src - static_cast<double>(lo)};
}

// The column stencils of a row, and their adjoint as runs: lo and hi are non-decreasing in x, so the columns that
// read grid column gx as lo (as hi) form one run [lo_begin[gx], lo_end[gx]) ([hi_begin[gx], hi_end[gx])).
template <typename S> struct Columns {
    std::vector<int64_t> lo, hi, lo_begin, lo_end, hi_begin, hi_end;
    std::vector<S> t, one_minus_t;
    explicit Columns(const Dims &s)
        : lo(s.W), hi(s.W), lo_begin(s.w, 0), lo_end(s.w, 0), hi_begin(s.w, 0), hi_end(s.w, 0), t(s.W),
          one_minus_t(s.W) {
        for (int64_t x = 0; x < s.W; ++x) {
            const Stencil st = stencil(x, s.r, s.w);
            lo[x] = st.lo;
            hi[x] = st.hi;
            t[x] = static_cast<S>(st.t);
            one_minus_t[x] = S(1) - t[x];
        }
        runs(lo, lo_begin, lo_end);
        runs(hi, hi_begin, hi_end);
    }

  private:
    static void runs(const std::vector<int64_t> &cell, std::vector<int64_t> &begin, std::vector<int64_t> &end) {
        const int64_t W = static_cast<int64_t>(cell.size());
        for (int64_t x = 0; x < W; ++x) {
            if (x == 0 || cell[x] != cell[x - 1]) begin[cell[x]] = x;
            end[cell[x]] = x + 1;
        }
    }
};

// Grid rows resampled to the pixel columns, built when a thread first needs them and kept for the rows after:
// row(b, gy)[k * W + x] = tap k of grid row gy, linearly interpolated to pixel column x. Direct-mapped on gy modulo
// the slot count, so that the grid rows a run of consecutive pixel rows reads stay cached (each grid row is then
// resampled about once per thread, instead of once per pixel row that reads it).
template <typename S> struct ResampledRows {
    ResampledRows(const Dims &s, const Columns<S> &cols, int64_t slots)
        : s(s), cols(cols), slots(slots), tag(slots, -1), data(slots * s.K * s.K * s.W) {}

    const S *row(const S *grid, int64_t b, int64_t gy) {
        const int64_t slot = gy % slots;
        S *dst = data.data() + slot * s.K * s.K * s.W;
        if (tag[slot] != b * s.h + gy) {
            const S *src = grid + b * s.K * s.K * s.hw + gy * s.w;
            for (int64_t k = 0; k < s.K * s.K; ++k, src += s.hw, dst += s.W) {
                for (int64_t x = 0; x < s.W; ++x) {
                    const S l = src[cols.lo[x]];
                    dst[x] = l + cols.t[x] * (src[cols.hi[x]] - l);
                }
            }
            tag[slot] = b * s.h + gy;
            dst = data.data() + slot * s.K * s.K * s.W;
        }
        return dst;
    }

  private:
    const Dims &s;
    const Columns<S> &cols;
    const int64_t slots;
    std::vector<int64_t> tag;
    std::vector<S> data;
};

// Slots that keep every grid row read by K consecutive pixel rows (grad_image's window), plus the two rows of the
// stencil's interpolation.
inline int64_t window_slots(const Dims &s) { return (s.K + s.r - 1) / s.r + 3; }

// dst[x] = the bilinear weight of the tap whose resampled grid rows are a (stencil lo) and b (hi), at pixel row
// stencil weight ty
template <typename S>
inline void weight_row(S *__restrict__ dst, const S *__restrict__ a, const S *__restrict__ b, S ty, int64_t W) {
    for (int64_t x = 0; x < W; ++x) dst[x] = a[x] + ty * (b[x] - a[x]);
}

template <typename S>
void forward_rows(const S *img, const S *grid, S *out, const Dims &s, int64_t begin, int64_t end) {
    const Columns<S> cols(s);
    ResampledRows<S> rows(s, cols, 2);
    std::vector<S> wrow(s.W);
    for (int64_t row = begin; row < end; ++row) {
        const int64_t b = row / s.H, y = row % s.H;
        const Stencil sy = stencil(y, s.r, s.h);
        const S ty = static_cast<S>(sy.t);
        const S *lo_rows = rows.row(grid, b, sy.lo), *hi_rows = rows.row(grid, b, sy.hi);
        const S *img_b = img + b * s.C * s.HW;
        S *out_row = out + b * s.C * s.HW + y * s.W;
        for (int64_t c = 0; c < s.C; ++c) std::fill(out_row + c * s.HW, out_row + c * s.HW + s.W, S(0));
        for (int64_t i = 0; i < s.K; ++i) {
            const int64_t ys = clamp_row(y + i - s.p, s.H);
            for (int64_t j = 0; j < s.K; ++j) {
                const int64_t d = j - s.p;
                int64_t lo, hi;
                interior(s.W, d, lo, hi);
                const int64_t k = (i * s.K + j) * s.W;
                weight_row(wrow.data(), lo_rows + k, hi_rows + k, ty, s.W);
                for (int64_t c = 0; c < s.C; ++c)
                    shifted_fma(out_row + c * s.HW, wrow.data(), img_b + c * s.HW + ys * s.W, s.W, d, lo, hi);
            }
        }
    }
}

template <typename S>
void grad_image_rows(const S *grid, const S *g, S *gi, const Dims &s, int64_t begin, int64_t end) {
    const Columns<S> cols(s);
    ResampledRows<S> rows(s, cols, window_slots(s));
    std::vector<S> wrow(s.W);
    for (int64_t row = begin; row < end; ++row) {
        const int64_t b = row / s.H, ys = row % s.H;
        const S *g_b = g + b * s.C * s.HW;
        S *gi_row = gi + b * s.C * s.HW + ys * s.W;
        for (int64_t c = 0; c < s.C; ++c) std::fill(gi_row + c * s.HW, gi_row + c * s.HW + s.W, S(0));
        for (int64_t i = 0; i < s.K; ++i) {
            // output rows y with clamp(y + i - p) == ys; the first / last source row also collect the margin
            const int64_t y_lo = std::max<int64_t>(ys == 0 ? 0 : ys - i + s.p, 0);
            const int64_t y_hi = std::min<int64_t>(ys == s.H - 1 ? s.H - 1 : ys - i + s.p, s.H - 1);
            for (int64_t y = y_lo; y <= y_hi; ++y) {
                const Stencil sy = stencil(y, s.r, s.h);
                const S ty = static_cast<S>(sy.t);
                const S *lo_rows = rows.row(grid, b, sy.lo), *hi_rows = rows.row(grid, b, sy.hi);
                for (int64_t j = 0; j < s.K; ++j) {
                    const int64_t d = j - s.p;
                    int64_t lo, hi;
                    interior(s.W, d, lo, hi);
                    const int64_t k = (i * s.K + j) * s.W;
                    weight_row(wrow.data(), lo_rows + k, hi_rows + k, ty, s.W);
                    for (int64_t c = 0; c < s.C; ++c)
                        shifted_fma_adjoint(gi_row + c * s.HW, wrow.data(), g_b + c * s.HW + y * s.W, s.W, d, lo, hi);
                }
            }
        }
    }
}

// The column interpolation's adjoint of one full-width row: dst[gx] = sum of src[x] over the columns x whose
// stencil reads grid column gx, times that stencil weight (runs, not a scatter: no store waits for the previous one).
template <typename S>
inline void column_adjoint(S *__restrict__ dst, const S *__restrict__ src, const Columns<S> &cols, int64_t w) {
    for (int64_t gx = 0; gx < w; ++gx) {
        S acc = 0;
        for (int64_t x = cols.lo_begin[gx]; x < cols.lo_end[gx]; ++x) acc += cols.one_minus_t[x] * src[x];
        for (int64_t x = cols.hi_begin[gx]; x < cols.hi_end[gx]; ++x) acc += cols.t[x] * src[x];
        dst[gx] = acc;
    }
}

// Pass 1 of grad_grid, iteration (b, gy): the pixel rows y whose row stencil starts at grid row gy (the band
// [band_begin[gy], band_end[gy])) reduce their tap gradients sum_c g[c, y, x] * image[c, clamp(y + i - p),
// clamp(x + j - p)] into two full-width accumulators, one for grid row gy (weight 1 - t) and one for gy + 1 (t);
// each is then column-interpolation-adjointed once: part[b, gy, 0] (to grid row gy) and part[b, gy, 1] (to gy + 1),
// both [K*K, w].
template <typename S>
void grad_band_rows(const S *img, const S *g, S *part, const std::vector<int64_t> &band_begin,
                    const std::vector<int64_t> &band_end, const Dims &s, int64_t begin, int64_t end) {
    const Columns<S> cols(s);
    const int64_t KK = s.K * s.K;
    std::vector<S> acc(2 * KK * s.W), prod(s.W);
    for (int64_t row = begin; row < end; ++row) {
        const int64_t b = row / s.h, gy = row % s.h;
        const S *img_b = img + b * s.C * s.HW;
        std::fill(acc.begin(), acc.end(), S(0));
        for (int64_t y = band_begin[gy]; y < band_end[gy]; ++y) {
            const Stencil sy = stencil(y, s.r, s.h);
            const S w_hi = sy.hi == sy.lo ? S(0) : static_cast<S>(sy.t);
            const S w_lo = S(1) - w_hi;
            const S *g_row = g + b * s.C * s.HW + y * s.W;
            for (int64_t i = 0; i < s.K; ++i) {
                const int64_t ys = clamp_row(y + i - s.p, s.H);
                for (int64_t j = 0; j < s.K; ++j) {
                    const int64_t d = j - s.p;
                    int64_t lo, hi;
                    interior(s.W, d, lo, hi);
                    std::fill(prod.begin(), prod.end(), S(0));
                    for (int64_t c = 0; c < s.C; ++c)
                        shifted_fma(prod.data(), g_row + c * s.HW, img_b + c * s.HW + ys * s.W, s.W, d, lo, hi);
                    S *acc_lo = acc.data() + (i * s.K + j) * s.W;
                    S *acc_hi = acc_lo + KK * s.W;
                    for (int64_t x = 0; x < s.W; ++x) {
                        acc_lo[x] += w_lo * prod[x];
                        acc_hi[x] += w_hi * prod[x];
                    }
                }
            }
        }
        S *out = part + row * 2 * KK * s.w;
        for (int64_t k = 0; k < 2 * KK; ++k) column_adjoint(out + k * s.w, acc.data() + k * s.W, cols, s.w);
    }
}

// Pass 2 of grad_grid, iteration (b, gy): grad_grid[b, :, gy, :] = part[b, gy, 0] + part[b, gy - 1, 1].
template <typename S> void grad_grid_rows(const S *part, S *gg, const Dims &s, int64_t begin, int64_t end) {
    const int64_t KK = s.K * s.K;
    for (int64_t row = begin; row < end; ++row) {
        const int64_t b = row / s.h, gy = row % s.h;
        const S *own = part + row * 2 * KK * s.w;
        const S *above = gy > 0 ? part + ((row - 1) * 2 + 1) * KK * s.w : nullptr;
        S *gg_b = gg + b * KK * s.hw + gy * s.w;
        for (int64_t k = 0; k < KK; ++k) {
            S *dst = gg_b + k * s.hw;
            for (int64_t gx = 0; gx < s.w; ++gx) dst[gx] = own[k * s.w + gx] + (above ? above[k * s.w + gx] : S(0));
        }
    }
}

// Pixel rows [band_begin[gy], band_end[gy]) have row stencils starting at grid row gy (lo is non-decreasing in y).
void row_bands(const Dims &s, std::vector<int64_t> &band_begin, std::vector<int64_t> &band_end) {
    band_begin.assign(s.h, 0);
    band_end.assign(s.h, 0);
    for (int64_t y = 0; y < s.H; ++y) {
        const int64_t lo = stencil(y, s.r, s.h).lo;
        if (y == 0 || lo != stencil(y - 1, s.r, s.h).lo) band_begin[lo] = y;
        band_end[lo] = y + 1;
    }
}

Dims check(const Tensor &image, const Tensor &grid, int64_t K, int64_t r) {
    TORCH_CHECK(image.dim() == 4 && grid.dim() == 4, "image and grid weights must be 4-D");
    TORCH_CHECK(K >= 1 && K % 2 == 1, "kernel_size must be odd and positive, got ", K);
    TORCH_CHECK(r >= 1, "factor must be >= 1, got ", r);
    TORCH_CHECK(image.is_contiguous() && grid.is_contiguous(), "image and grid weights must be contiguous");
    TORCH_CHECK(image.scalar_type() == grid.scalar_type(), "image and grid weights must share a dtype");
    const int64_t B = image.size(0), C = image.size(1), H = image.size(2), W = image.size(3);
    const int64_t h = grid.size(2), w = grid.size(3);
    TORCH_CHECK(grid.size(0) == B && grid.size(1) == K * K && h >= 1 && w >= 1,
                "grid weights: expected shape [", B, ", ", K * K, ", h, w], got ", grid.sizes());
    TORCH_CHECK(H >= 1 && W >= 1, "image must have H >= 1 and W >= 1");
    return Dims{B, C, H, W, K, K / 2, H * W, h, w, h * w, r};
}

}  // namespace

Tensor grid_kernels_fwd(const Tensor &image, const Tensor &grid, int64_t kernel_size, int64_t factor) {
    const Dims s = check(image, grid, kernel_size, factor);
    Tensor out = at::empty(image.sizes(), image.options());
    AT_DISPATCH_FLOATING_TYPES(image.scalar_type(), "grid_kernels_fwd", [&] {
        const scalar_t *img = image.const_data_ptr<scalar_t>();
        const scalar_t *grd = grid.const_data_ptr<scalar_t>();
        scalar_t *o = out.mutable_data_ptr<scalar_t>();
        at::parallel_for(0, s.B * s.H, 1, [&](int64_t begin, int64_t end) {
            forward_rows<scalar_t>(img, grd, o, s, begin, end);
        });
    });
    return out;
}

std::tuple<std::optional<Tensor>, std::optional<Tensor>> grid_kernels_bwd(
    const Tensor &grad_out, const Tensor &image, const Tensor &grid, int64_t kernel_size, int64_t factor,
    bool need_image, bool need_grid
) {
    const Dims s = check(image, grid, kernel_size, factor);
    TORCH_CHECK(grad_out.is_contiguous() && grad_out.sizes() == image.sizes() &&
                    grad_out.scalar_type() == image.scalar_type(),
                "grad_out must be contiguous with the image's shape and dtype");
    Tensor grad_image, grad_grid;
    if (need_image) grad_image = at::empty(image.sizes(), image.options());
    if (need_grid) grad_grid = at::empty(grid.sizes(), grid.options());
    AT_DISPATCH_FLOATING_TYPES(image.scalar_type(), "grid_kernels_bwd", [&] {
        const scalar_t *img = image.const_data_ptr<scalar_t>();
        const scalar_t *grd = grid.const_data_ptr<scalar_t>();
        const scalar_t *g = grad_out.const_data_ptr<scalar_t>();
        if (need_grid) {
            scalar_t *gg = grad_grid.mutable_data_ptr<scalar_t>();
            // [B, h, 2, K*K, w]: each row band's tap gradients for its two grid rows (twice the grid's size, far
            // smaller than the [B, K*K, H, W] weights)
            Tensor part = at::empty({s.B, s.h, 2, s.K * s.K, s.w}, grid.options());
            scalar_t *pt = part.mutable_data_ptr<scalar_t>();
            std::vector<int64_t> band_begin, band_end;
            row_bands(s, band_begin, band_end);
            at::parallel_for(0, s.B * s.h, 1, [&](int64_t begin, int64_t end) {
                grad_band_rows<scalar_t>(img, g, pt, band_begin, band_end, s, begin, end);
            });
            at::parallel_for(0, s.B * s.h, 1, [&](int64_t begin, int64_t end) {
                grad_grid_rows<scalar_t>(pt, gg, s, begin, end);
            });
        }
        if (need_image) {
            scalar_t *gi = grad_image.mutable_data_ptr<scalar_t>();
            at::parallel_for(0, s.B * s.H, 1, [&](int64_t begin, int64_t end) {
                grad_image_rows<scalar_t>(grd, g, gi, s, begin, end);
            });
        }
    });
    std::optional<Tensor> gi_out, gg_out;
    if (need_image) gi_out = grad_image;
    if (need_grid) gg_out = grad_grid;
    return {gi_out, gg_out};
}

}  // namespace gsmsdr_grid

TORCH_LIBRARY(gsmsdr_grid, m) {
    m.def("grid_kernels_fwd(Tensor image, Tensor grid, int kernel_size, int factor) -> Tensor");
    m.def(
        "grid_kernels_bwd(Tensor grad_out, Tensor image, Tensor grid, int kernel_size, int factor, bool need_image, "
        "bool need_grid) -> (Tensor?, Tensor?)"
    );
}

TORCH_LIBRARY_IMPL(gsmsdr_grid, CPU, m) {
    m.impl("grid_kernels_fwd", &gsmsdr_grid::grid_kernels_fwd);
    m.impl("grid_kernels_bwd", &gsmsdr_grid::grid_kernels_bwd);
}
