// Row operations shared by the per-pixel kernel ops (pixel_kernels.cpp, grid_kernels.cpp): one image row
// shifted by d columns, with columns outside the row reading (or writing) its first / last pixel (replicate
// border). Header-only, included by each op's single source file.
#pragma once

#include <algorithm>
#include <cstdint>

namespace gsmsdr_rows {

// Interior columns [lo, hi) of a row for the column shift d: 0 <= x + d < W.
// Columns below lo read (or write) column 0, columns from hi on read column W-1.
inline void interior(int64_t W, int64_t d, int64_t &lo, int64_t &hi) {
    lo = std::min<int64_t>(std::max<int64_t>(-d, 0), W);
    hi = std::max<int64_t>(std::min<int64_t>(W - d, W), lo);
}

inline int64_t clamp_row(int64_t r, int64_t H) { return std::min<int64_t>(std::max<int64_t>(r, 0), H - 1); }

// dst[x] += w[x] * src[clamp(x + d)] for x in [0, W)
template <typename S>
inline void shifted_fma(S *__restrict__ dst, const S *__restrict__ w, const S *__restrict__ src, int64_t W,
                        int64_t d, int64_t lo, int64_t hi) {
    const S first = src[0], last = src[W - 1];
    for (int64_t x = 0; x < lo; ++x) dst[x] += w[x] * first;
    const S *s = src + lo + d;
    S *o = dst + lo;
    const S *ww = w + lo;
    const int64_t n = hi - lo;
    for (int64_t x = 0; x < n; ++x) o[x] += ww[x] * s[x];
    for (int64_t x = hi; x < W; ++x) dst[x] += w[x] * last;
}

// dst[x] = a[x] * src[clamp(x + d)] for x in [0, W)
template <typename S>
inline void shifted_mul(S *__restrict__ dst, const S *__restrict__ a, const S *__restrict__ src, int64_t W,
                        int64_t d, int64_t lo, int64_t hi) {
    const S first = src[0], last = src[W - 1];
    for (int64_t x = 0; x < lo; ++x) dst[x] = a[x] * first;
    const S *s = src + lo + d;
    S *o = dst + lo;
    const S *aa = a + lo;
    const int64_t n = hi - lo;
    for (int64_t x = 0; x < n; ++x) o[x] = aa[x] * s[x];
    for (int64_t x = hi; x < W; ++x) dst[x] = a[x] * last;
}

// Adjoint of shifted_fma with respect to src: dst[clamp(x + d)] += w[x] * g[x] for x in [0, W)
template <typename S>
inline void shifted_fma_adjoint(S *__restrict__ dst, const S *__restrict__ w, const S *__restrict__ g, int64_t W,
                                int64_t d, int64_t lo, int64_t hi) {
    S first = 0, last = 0;
    for (int64_t x = 0; x < lo; ++x) first += w[x] * g[x];
    for (int64_t x = hi; x < W; ++x) last += w[x] * g[x];
    S *o = dst + lo + d;
    const S *ww = w + lo;
    const S *gg = g + lo;
    const int64_t n = hi - lo;
    for (int64_t x = 0; x < n; ++x) o[x] += ww[x] * gg[x];
    dst[0] += first;
    dst[W - 1] += last;
}

}  // namespace gsmsdr_rows
