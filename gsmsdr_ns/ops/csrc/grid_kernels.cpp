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
// needed. The loops run over blocks of columns (vector_block.h) that keep
// their sums in registers across all K*K taps, reading image rows padded once
// per call (PaddedRows) without bounds checks.
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
#include "vector_block.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <optional>
#include <tuple>
#include <utility>
#include <vector>

namespace gsmsdr_grid {

using at::Tensor;
using gsmsdr_vec::Block;

namespace {

using gsmsdr_rows::clamp_row;

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

// Column blocks summed side by side in the forward and the image gradient: independent sums hide the latency of each
// fused multiply-add.
constexpr int64_t NB = 2;
// Slack past a row that NB block loads may read.
constexpr int64_t BX = gsmsdr_vec::MAX_BLOCK * NB;

// Grid rows resampled to the pixel columns, built when a thread first needs them and kept for the rows after:
// row(b, gy)[k * W + x] = tap k of grid row gy, linearly interpolated to pixel column x. Direct-mapped on gy modulo
// the slot count, so that the grid rows a run of consecutive pixel rows reads stay cached (each grid row is then
// resampled about once per thread, instead of once per pixel row that reads it). The loops below read up to
// 2p + 2 BX values past a tap's row (into the next tap, slot or the zeroed tail): every value read is finite, and
// the products those lanes feed are discarded or multiplied by zero.
template <typename S> struct ResampledRows {
    ResampledRows(const Dims &s, const Columns<S> &cols, int64_t slots)
        : s(s), cols(cols), slots(slots), tag(slots, -1), data(slots * s.K * s.K * s.W + 2 * s.p + 2 * BX, S(0)) {}

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

// The image's rows padded for unclamped reads: replicate(b, c, y)[q] = image[b, c, y, clamp(q - p, 0, W - 1)] for
// q in [0, W + 2p + BX) (a tap at column offset j reads q = x + j), and zeros(b, c, y)[q] = image[b, c, y, q - K]
// for q - K in [0, W), else 0, for q in [0, W + 2K + 2 BX) (a product with a zero is no contribution).
template <typename S> struct PaddedRows {
    PaddedRows(const S *src, const Dims &s, bool replicate)
        : s(s), off(replicate ? 0 : s.K), len(replicate ? s.W + 2 * s.p + BX : s.W + 2 * s.K + 2 * BX),
          data(s.B * s.C * s.H * len, S(0)) {
        at::parallel_for(0, s.B * s.C * s.H, 64, [&](int64_t begin, int64_t end) {
            for (int64_t row = begin; row < end; ++row) {
                const S *in = src + row * s.W;
                S *out = data.data() + row * len;
                if (replicate) {
                    for (int64_t q = 0; q < len; ++q)
                        out[q] = in[std::min<int64_t>(std::max<int64_t>(q - s.p, 0), s.W - 1)];
                } else {
                    std::copy(in, in + s.W, out + off);
                }
            }
        });
    }
    // Row (b, c, y), shifted so that index x is image column x - p (replicate) or x (zeros).
    const S *row(int64_t b, int64_t c, int64_t y) const { return data.data() + ((b * s.C + c) * s.H + y) * len + off; }

  private:
    const Dims &s;
    const int64_t off, len;
    std::vector<S> data;
};

// Output row (b, y), channels [c0, c0 + NC): out[c, x] = sum_k w[k](y, x) * image[c, clamp(y + i - p), clamp(x + j
// - p)], the tap weights interpolated between the resampled grid rows lo / hi at row weight ty.
template <typename S, int NC>
void forward_row(S *out_row, const S *lo_rows, const S *hi_rows, S ty, const PaddedRows<S> &pad, int64_t b,
                 int64_t c0, int64_t y, const Dims &s) {
    std::vector<const S *> src(s.K * NC);
    for (int64_t i = 0; i < s.K; ++i)
        for (int c = 0; c < NC; ++c) src[i * NC + c] = pad.row(b, c0 + c, clamp_row(y + i - s.p, s.H));
    using V = typename Block<S>::type;
    constexpr int64_t L = Block<S>::n;
    for (int64_t xb = 0; xb < s.W; xb += NB * L) {
        V acc[NB][NC] = {};
        for (int64_t i = 0; i < s.K; ++i) {
            for (int64_t j = 0; j < s.K; ++j) {
                const int64_t k = (i * s.K + j) * s.W + xb;
                for (int64_t nb = 0; nb < NB; ++nb) {
                    const V a = Block<S>::load(lo_rows + k + nb * L);
                    const V w = a + ty * (Block<S>::load(hi_rows + k + nb * L) - a);
                    for (int c = 0; c < NC; ++c) acc[nb][c] += w * Block<S>::load(src[i * NC + c] + xb + nb * L + j);
                }
            }
        }
        for (int64_t nb = 0; nb < NB && xb + nb * L < s.W; ++nb) {
            const int64_t n = std::min<int64_t>(L, s.W - xb - nb * L);
            for (int c = 0; c < NC; ++c) Block<S>::store(out_row + c * s.HW + xb + nb * L, acc[nb][c], n);
        }
    }
}

template <typename S>
void forward_rows(const S *grid, const PaddedRows<S> &pad, S *out, const Dims &s, int64_t begin, int64_t end) {
    const Columns<S> cols(s);
    ResampledRows<S> rows(s, cols, 2);
    for (int64_t row = begin; row < end; ++row) {
        const int64_t b = row / s.H, y = row % s.H;
        const Stencil sy = stencil(y, s.r, s.h);
        const S ty = static_cast<S>(sy.t);
        const S *lo_rows = rows.row(grid, b, sy.lo), *hi_rows = rows.row(grid, b, sy.hi);
        S *out_row = out + b * s.C * s.HW + y * s.W;
        if (s.C == 3) {
            forward_row<S, 3>(out_row, lo_rows, hi_rows, ty, pad, b, 0, y, s);
        } else {
            for (int64_t c = 0; c < s.C; ++c)
                forward_row<S, 1>(out_row + c * s.HW, lo_rows, hi_rows, ty, pad, b, c, y, s);
        }
    }
}

// One output row y that reads source row ys through kernel row i: its interpolated tap rows and gradient rows.
template <typename S> struct ReadingRow {
    const S *lo, *hi;  // resampled grid rows of tap (i, 0)
    S ty;
    int64_t y;
};

// Source row (b, ys), channels [c0, c0 + NC), in padded columns X = x + j (x the output column, j the tap's
// column): acc[c, X] = sum over the reading rows and j of w[i, j](y, X - j) * g[c, y, X - j], then folded to the
// image columns (X - p clamped to [0, W - 1], the replicate border's adjoint).
template <typename S, int NC>
void grad_image_row(S *gi_row, const std::vector<ReadingRow<S>> &reading, const PaddedRows<S> &gz, int64_t b,
                    int64_t c0, std::vector<S> &acc_row, const Dims &s) {
    const int64_t Wx = s.W + 2 * s.p;
    std::vector<const S *> grows(reading.size() * NC);
    for (size_t n = 0; n < reading.size(); ++n)
        for (int c = 0; c < NC; ++c) grows[n * NC + c] = gz.row(b, c0 + c, reading[n].y);
    using V = typename Block<S>::type;
    constexpr int64_t L = Block<S>::n;
    for (int64_t Xb = 0; Xb < Wx; Xb += NB * L) {
        V acc[NB][NC] = {};
        for (size_t n = 0; n < reading.size(); ++n) {
            const ReadingRow<S> &rr = reading[n];
            for (int64_t j = 0; j < s.K; ++j) {
                const int64_t k = j * s.W + Xb - j;
                for (int64_t nb = 0; nb < NB; ++nb) {
                    const V a = Block<S>::load(rr.lo + k + nb * L);
                    const V w = a + rr.ty * (Block<S>::load(rr.hi + k + nb * L) - a);
                    for (int c = 0; c < NC; ++c) acc[nb][c] += w * Block<S>::load(grows[n * NC + c] + Xb + nb * L - j);
                }
            }
        }
        for (int64_t nb = 0; nb < NB && Xb + nb * L < Wx; ++nb) {
            const int64_t n = std::min<int64_t>(L, Wx - Xb - nb * L);
            for (int c = 0; c < NC; ++c) Block<S>::store(acc_row.data() + c * Wx + Xb + nb * L, acc[nb][c], n);
        }
    }
    for (int c = 0; c < NC; ++c) {
        const S *a = acc_row.data() + c * Wx;
        S *dst = gi_row + c * s.HW;
        for (int64_t x = 0; x < s.W; ++x) dst[x] = a[x + s.p];
        for (int64_t X = 0; X < s.p; ++X) dst[0] += a[X];
        for (int64_t X = s.W + s.p; X < Wx; ++X) dst[s.W - 1] += a[X];
    }
}

template <typename S>
void grad_image_rows(const S *grid, const PaddedRows<S> &gz, S *gi, const Dims &s, int64_t begin, int64_t end) {
    const Columns<S> cols(s);
    ResampledRows<S> rows(s, cols, window_slots(s));
    std::vector<ReadingRow<S>> reading;
    std::vector<S> acc_row(3 * (s.W + 2 * s.p));
    for (int64_t row = begin; row < end; ++row) {
        const int64_t b = row / s.H, ys = row % s.H;
        reading.clear();
        for (int64_t i = 0; i < s.K; ++i) {
            // output rows y with clamp(y + i - p) == ys; the first / last source row also collect the margin
            const int64_t y_lo = std::max<int64_t>(ys == 0 ? 0 : ys - i + s.p, 0);
            const int64_t y_hi = std::min<int64_t>(ys == s.H - 1 ? s.H - 1 : ys - i + s.p, s.H - 1);
            for (int64_t y = y_lo; y <= y_hi; ++y) {
                const Stencil sy = stencil(y, s.r, s.h);
                const int64_t k = i * s.K * s.W;
                reading.push_back({rows.row(grid, b, sy.lo) + k, rows.row(grid, b, sy.hi) + k,
                                   static_cast<S>(sy.t), y});
            }
        }
        S *gi_row = gi + b * s.C * s.HW + ys * s.W;
        if (s.C == 3) {
            grad_image_row<S, 3>(gi_row, reading, gz, b, 0, acc_row, s);
        } else {
            for (int64_t c = 0; c < s.C; ++c) grad_image_row<S, 1>(gi_row + c * s.HW, reading, gz, b, c, acc_row, s);
        }
    }
}

// The column interpolation's adjoint of one full-width row: dst[gx] = sum of src[x] over the columns x whose
// stencil reads grid column gx, times that stencil weight. Away from the borders every grid column sums the same
// pattern of columns, dst[gx] = sum_m c[m] * src[r gx + base + m]: there it is one filter over the row in column
// blocks, read every r columns; the border columns sum their runs (lo / hi stencils) one by one.
template <typename S> struct ColumnAdjoint {
    explicit ColumnAdjoint(const Columns<S> &cols, const Dims &s) : cols(cols), W(s.W), w(s.w), r(s.r) {
        const int64_t mid = w / 2;
        const std::vector<std::pair<int64_t, S>> pattern = terms(mid);
        if (pattern.empty()) return;
        base = pattern.front().first - r * mid;
        c.assign(pattern.back().first - pattern.front().first + 1, S(0));
        for (const auto &t : pattern) c[t.first - pattern.front().first] += t.second;
        // the regular columns: a contiguous range around the middle whose terms are the pattern's, shifted
        first = mid;
        while (first > 0 && regular(first - 1)) --first;
        last = mid + 1;
        while (last < w && regular(last)) ++last;
    }

    void apply(S *__restrict__ dst, const S *__restrict__ src, S *__restrict__ filtered) const {
        using V = typename Block<S>::type;
        constexpr int64_t L = Block<S>::n;
        const int64_t M = static_cast<int64_t>(c.size());
        if (first < last) {
            const int64_t x0 = r * first + base, x1 = r * (last - 1) + base + 1;
            for (int64_t xb = x0; xb < x1; xb += L) {
                V acc = {};
                for (int64_t m = 0; m < M; ++m) acc += c[m] * Block<S>::load(src + xb + m);
                Block<S>::store(filtered + (xb - x0), acc, L);
            }
            for (int64_t gx = first; gx < last; ++gx) dst[gx] = filtered[r * (gx - first)];
        }
        for (int64_t gx = 0; gx < w; ++gx) {
            if (gx == first) gx = std::max(last, gx);
            if (gx >= w) break;
            S acc = 0;
            for (int64_t x = cols.lo_begin[gx]; x < cols.lo_end[gx]; ++x) acc += cols.one_minus_t[x] * src[x];
            for (int64_t x = cols.hi_begin[gx]; x < cols.hi_end[gx]; ++x) acc += cols.t[x] * src[x];
            dst[gx] = acc;
        }
    }

  private:
    // (x, weight) of the columns grid column gx sums, in increasing x (a column read as lo and as hi: both terms)
    std::vector<std::pair<int64_t, S>> terms(int64_t gx) const {
        std::vector<std::pair<int64_t, S>> out;
        for (int64_t x = cols.hi_begin[gx]; x < cols.hi_end[gx]; ++x) out.emplace_back(x, cols.t[x]);
        for (int64_t x = cols.lo_begin[gx]; x < cols.lo_end[gx]; ++x) out.emplace_back(x, cols.one_minus_t[x]);
        std::sort(out.begin(), out.end(), [](const auto &a, const auto &b) { return a.first < b.first; });
        return out;
    }

    bool regular(int64_t gx) const {
        const int64_t x0 = r * gx + base, M = static_cast<int64_t>(c.size());
        if (x0 < 0 || x0 + M > W) return false;
        std::vector<S> got(M, S(0));
        for (const auto &t : terms(gx)) {
            if (t.first < x0 || t.first >= x0 + M) return false;
            got[t.first - x0] += t.second;
        }
        for (int64_t m = 0; m < M; ++m)
            if (std::abs(got[m] - c[m]) > 64 * std::numeric_limits<S>::epsilon() * std::abs(c[m])) return false;
        return true;
    }

    const Columns<S> &cols;
    const int64_t W, w, r;
    int64_t base = 0, first = 0, last = 0;  // regular grid columns: [first, last)
    std::vector<S> c;
};

// Pass 1 of grad_grid, iteration (b, gy): for each tap (i, j), the pixel rows y whose row stencil starts at grid row
// gy (the band [band_begin[gy], band_end[gy])) sum their tap gradients sum_c g[c, y, x] * image[c, clamp(y + i -
// p), clamp(x + j - p)] into two rows, one for grid row gy (weight 1 - t) and one for gy + 1 (t), each then
// column-interpolation-adjointed: part[b, gy, 0, k] (to grid row gy) and part[b, gy, 1, k] (to gy + 1), [w] each.
// NC: the channel count when known at compile time (3), 0 for s.C.
template <typename S, int NC>
void grad_band(S *out, const PaddedRows<S> &pad, const PaddedRows<S> &gz, int64_t b, int64_t y0, int64_t y1,
               const ColumnAdjoint<S> &adjoint, std::vector<S> &lo_row, std::vector<S> &hi_row,
               std::vector<S> &filtered, const Dims &s) {
    const int64_t KK = s.K * s.K, ny = y1 - y0;
    const int64_t C = NC > 0 ? NC : s.C;
    using V = typename Block<S>::type;
    constexpr int64_t L = Block<S>::n;
    std::vector<S> w_lo(ny), w_hi(ny);
    std::vector<const S *> grows(ny * C), src(ny * C);
    for (int64_t n = 0; n < ny; ++n) {
        const Stencil sy = stencil(y0 + n, s.r, s.h);
        w_hi[n] = sy.hi == sy.lo ? S(0) : static_cast<S>(sy.t);
        w_lo[n] = S(1) - w_hi[n];
        for (int64_t c = 0; c < C; ++c) grows[n * C + c] = gz.row(b, c, y0 + n);
    }
    for (int64_t i = 0; i < s.K; ++i) {
        for (int64_t n = 0; n < ny; ++n)
            for (int64_t c = 0; c < C; ++c) src[n * C + c] = pad.row(b, c, clamp_row(y0 + n + i - s.p, s.H));
        for (int64_t j = 0; j < s.K; ++j) {
            for (int64_t xb = 0; xb < s.W; xb += L) {
                V al = {}, ah = {};
                for (int64_t n = 0; n < ny; ++n) {
                    V prod = {};
                    for (int64_t c = 0; c < C; ++c)
                        prod += Block<S>::load(grows[n * C + c] + xb) * Block<S>::load(src[n * C + c] + xb + j);
                    al += w_lo[n] * prod;
                    ah += w_hi[n] * prod;
                }
                Block<S>::store(lo_row.data() + xb, al, L);
                Block<S>::store(hi_row.data() + xb, ah, L);
            }
            const int64_t k = i * s.K + j;
            adjoint.apply(out + k * s.w, lo_row.data(), filtered.data());
            adjoint.apply(out + (KK + k) * s.w, hi_row.data(), filtered.data());
        }
    }
}

template <typename S>
void grad_band_rows(const PaddedRows<S> &pad, const PaddedRows<S> &gz, S *part, const std::vector<int64_t> &band_begin,
                    const std::vector<int64_t> &band_end, const Dims &s, int64_t begin, int64_t end) {
    const Columns<S> cols(s);
    const int64_t KK = s.K * s.K;
    const ColumnAdjoint<S> adjoint(cols, s);
    std::vector<S> lo_row(s.W + BX), hi_row(s.W + BX), filtered(s.W + BX);
    for (int64_t row = begin; row < end; ++row) {
        const int64_t b = row / s.h, gy = row % s.h;
        S *out = part + row * 2 * KK * s.w;
        if (band_end[gy] <= band_begin[gy]) {  // no pixel row starts its stencil here
            std::fill(out, out + 2 * KK * s.w, S(0));
            continue;
        }
        if (s.C == 3) {
            grad_band<S, 3>(out, pad, gz, b, band_begin[gy], band_end[gy], adjoint, lo_row, hi_row, filtered, s);
        } else {
            grad_band<S, 0>(out, pad, gz, b, band_begin[gy], band_end[gy], adjoint, lo_row, hi_row, filtered, s);
        }
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
        const PaddedRows<scalar_t> pad(img, s, true);
        at::parallel_for(0, s.B * s.H, 1, [&](int64_t begin, int64_t end) {
            forward_rows<scalar_t>(grd, pad, o, s, begin, end);
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
        const PaddedRows<scalar_t> gz(grad_out.const_data_ptr<scalar_t>(), s, false);
        if (need_grid) {
            scalar_t *gg = grad_grid.mutable_data_ptr<scalar_t>();
            // [B, h, 2, K*K, w]: each row band's tap gradients for its two grid rows (twice the grid's size, far
            // smaller than the [B, K*K, H, W] weights)
            Tensor part = at::empty({s.B, s.h, 2, s.K * s.K, s.w}, grid.options());
            scalar_t *pt = part.mutable_data_ptr<scalar_t>();
            std::vector<int64_t> band_begin, band_end;
            row_bands(s, band_begin, band_end);
            const PaddedRows<scalar_t> pad(img, s, true);
            at::parallel_for(0, s.B * s.h, 1, [&](int64_t begin, int64_t end) {
                grad_band_rows<scalar_t>(pad, gz, pt, band_begin, band_end, s, begin, end);
            });
            at::parallel_for(0, s.B * s.h, 1, [&](int64_t begin, int64_t end) {
                grad_grid_rows<scalar_t>(pt, gg, s, begin, end);
            });
        }
        if (need_image) {
            scalar_t *gi = grad_image.mutable_data_ptr<scalar_t>();
            at::parallel_for(0, s.B * s.H, 1, [&](int64_t begin, int64_t end) {
                grad_image_rows<scalar_t>(grd, gz, gi, s, begin, end);
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
