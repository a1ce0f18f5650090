// CPU rasterization of projected 2D Gaussians to pixels (step 3 of the render
// pipeline), forward and hand-written backward, with gsplat 1.4.0 semantics.
//
// Conventions (see notes/render spec):
//   means2d [C, N, 2], conics [C, N, 3] (a, b, c), colors [C, N, D],
//   opacities [C, N], backgrounds [C, D] (optional),
//   isect_offsets [C, th, tw] int32, flatten_ids [n_isects] int32 (indices into
//   the flattened [C * N] arrays, sorted front to back inside each tile).
//
// Work is split over (camera, tile) pairs with OpenMP dynamic scheduling.
// Inside a tile the loops are Gaussian-major: each Gaussian visits only the
// pixels of the box where it can pass the alpha >= 1/255 test, while every
// pixel keeps its own front-to-back state (same result as the spec's
// per-pixel walk, far fewer evaluations).
// The backward never divides by (1 - alpha): it recomputes the transmittance
// in front of each composited (pixel, Gaussian) pair front to back into a
// buffer, then runs suffix sums back to front. Gradients are summed per
// intersection (each intersection is owned by exactly one tile, so there are
// no races) and then reduced per Gaussian in a fixed order, which makes the
// backward deterministic regardless of the thread schedule.
//
// Only light torch headers are used (no torch/extension.h) to keep the JIT
// compile short; the ops are registered with TORCH_LIBRARY and reached from
// Python as torch.ops.gsmsdr_ns.*.

#include <ATen/Dispatch.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <optional>
#include <tuple>
#include <vector>

namespace gsmsdr {

using at::Tensor;

// Thresholds of the compositing loop, shared by forward and backward so both
// take exactly the same discrete decisions.
template <typename S> struct Thresh {
    static constexpr S alpha_max = S(0.999);
    static constexpr S alpha_min = S(1) / S(255);
    static constexpr S T_min = S(1e-4);
};

// Gaussians of one tile gathered into contiguous structure-of-arrays storage.
template <typename S> struct TileGaussians {
    std::vector<S> mx, my, ca, cb, cc, op, sig_cut, hx, hy, col;
    int64_t n = 0;

    void load(
        const S *means2d, const S *conics, const S *colors, const S *opacities,
        const int32_t *ids, int64_t len, int64_t D
    ) {
        n = len;
        for (auto *v : {&mx, &my, &ca, &cb, &cc, &op, &sig_cut, &hx, &hy})
            v->resize(len);
        col.resize(len * D);
        for (int64_t j = 0; j < len; ++j) {
            const int64_t g = ids[j];
            mx[j] = means2d[2 * g];
            my[j] = means2d[2 * g + 1];
            const S a = conics[3 * g], b = conics[3 * g + 1],
                    c = conics[3 * g + 2];
            ca[j] = a;
            cb[j] = b;
            cc[j] = c;
            const S o = opacities[g];
            op[j] = o;
            // alpha < 1/255 <=> sigma > log(255 * o). The cut has a margin so
            // it only skips exp() where the exact test surely fails; the exact
            // test stays the source of truth. (o <= 0 gives -inf / NaN: -inf
            // skips everything, NaN falls through to the exact test.)
            const S cut = std::log(S(255) * o) + S(1e-3);
            sig_cut[j] = cut;
            // Half extents of the ellipse {sigma <= cut}: only pixels inside
            // this box can pass the cut. For a non positive-definite conic or
            // a non-finite cut the box is the whole tile (infinite extents).
            const S det = a * c - b * b;
            if (cut < S(0)) {
                hx[j] = hy[j] = S(-1); // no pixel can pass
            } else if (a > S(0) && c > S(0) && det > S(0) && std::isfinite(cut)) {
                hx[j] = std::sqrt(S(2) * cut * c / det);
                hy[j] = std::sqrt(S(2) * cut * a / det);
            } else {
                hx[j] = hy[j] = std::numeric_limits<S>::infinity();
            }
            for (int64_t d = 0; d < D; ++d)
                col[j * D + d] = colors[g * D + d];
        }
    }

    // Pixel box [bx0, bx1) x [by0, by1) of Gaussian j clipped to the tile
    // [x0, x1) x [y0, y1); false when empty. Pixel x has centre x + 0.5.
    // NaN centres or extents give the whole tile (std::max/min keep their
    // first argument when the comparison with NaN is false).
    bool box(
        int64_t j, int64_t x0, int64_t x1, int64_t y0, int64_t y1,
        int64_t &bx0, int64_t &bx1, int64_t &by0, int64_t &by1
    ) const {
        if (hx[j] < S(0))
            return false;
        const S lx = std::max(S(x0), std::ceil(mx[j] - hx[j] - S(0.5)));
        const S ux = std::min(S(x1 - 1), std::floor(mx[j] + hx[j] - S(0.5)));
        const S ly = std::max(S(y0), std::ceil(my[j] - hy[j] - S(0.5)));
        const S uy = std::min(S(y1 - 1), std::floor(my[j] + hy[j] - S(0.5)));
        if (ux < lx || uy < ly)
            return false;
        bx0 = int64_t(lx);
        bx1 = int64_t(ux) + 1;
        by0 = int64_t(ly);
        by1 = int64_t(uy) + 1;
        return true;
    }

    // Alpha of Gaussian j at offset (dx, dy) = mean - pixel centre. Returns
    // false when the Gaussian is skipped (sigma < 0 or alpha < 1/255).
    inline bool eval(int64_t j, S dx, S dy, S &vis, S &alpha) const {
        const S sigma =
            S(0.5) * (ca[j] * dx * dx + cc[j] * dy * dy) + cb[j] * dx * dy;
        if (sigma < S(0) || sigma > sig_cut[j])
            return false;
        vis = std::exp(-sigma);
        alpha = op[j] * vis;
        // written this way (not std::min) so a NaN alpha propagates
        if (alpha > Thresh<S>::alpha_max)
            alpha = Thresh<S>::alpha_max;
        return !(alpha < Thresh<S>::alpha_min);
    }
};

// Geometry of the tile grid and the intersection range of one (camera, tile).
struct Grid {
    int64_t C, W, H, tile_size, tw, th, n_isects;
    const int32_t *offsets;

    int64_t num_tiles() const { return tw * th; }
    // Small jobs run on one thread: waking the pool (and, on a busy machine,
    // waiting at its barrier for a descheduled worker) costs more than the
    // work itself.
    bool worth_threads(int num_threads) const {
        const int64_t work = n_isects * tile_size * tile_size + C * W * H;
        return num_threads > 1 && work > (int64_t(1) << 16);
    }
    void range(int64_t ct, int64_t &start, int64_t &end) const {
        // tile ct of the flattened [C * th * tw] array; the last tile of all
        // ends at n_isects. Clamped so corrupt offsets cannot read out of
        // bounds.
        start = offsets[ct];
        end = (ct == C * num_tiles() - 1) ? n_isects : offsets[ct + 1];
        start = std::clamp<int64_t>(start, 0, n_isects);
        end = std::clamp<int64_t>(end, start, n_isects);
    }
    // pixel rectangle [x0, x1) x [y0, y1) of tile t
    void pixels(int64_t t, int64_t &x0, int64_t &x1, int64_t &y0, int64_t &y1) const {
        y0 = (t / tw) * tile_size;
        x0 = (t % tw) * tile_size;
        y1 = std::min(y0 + tile_size, H);
        x1 = std::min(x0 + tile_size, W);
    }
};

/****************************************************************************
 * Forward
 *
 * Gaussian-major inside a tile: each Gaussian (front to back) updates only
 * the pixels of its box, every pixel keeps its own transmittance, colour and
 * done flag. Each pixel still sees the tile list in depth order, so this is
 * the per-pixel walk of the spec, without visiting pixels a Gaussian cannot
 * reach.
 ****************************************************************************/

template <typename S, int DT>
void fwd_kernel(
    const Grid &grid, int64_t Drt, const S *means2d, const S *conics,
    const S *colors, const S *opacities, const S *backgrounds,
    const int32_t *flatten_ids, S *out_colors, S *out_alphas,
    int32_t *last_ids, int num_threads
) {
    const int64_t D = DT > 0 ? DT : Drt;
    const int64_t n_tiles = grid.num_tiles();
    const int64_t W = grid.W, H = grid.H, ts = grid.tile_size;
#pragma omp parallel num_threads(num_threads) if (grid.worth_threads(num_threads))
    {
        TileGaussians<S> tg;
        // per-pixel state of one tile, indexed (y - y0) * ts + (x - x0)
        std::vector<S> T(ts * ts), acc(ts * ts * D);
        std::vector<int32_t> last(ts * ts);
        std::vector<uint8_t> done(ts * ts);

#pragma omp for schedule(dynamic, 1)
        for (int64_t ct = 0; ct < grid.C * n_tiles; ++ct) {
            const int64_t c = ct / n_tiles;
            int64_t start, end, x0, x1, y0, y1;
            grid.range(ct, start, end);
            grid.pixels(ct % n_tiles, x0, x1, y0, y1);
            tg.load(
                means2d, conics, colors, opacities, flatten_ids + start,
                end - start, D
            );
            std::fill(T.begin(), T.end(), S(1));
            std::fill(acc.begin(), acc.end(), S(0));
            std::fill(last.begin(), last.end(), -1);
            std::fill(done.begin(), done.end(), 0);
            int64_t n_active = (x1 - x0) * (y1 - y0);

            for (int64_t j = 0; j < tg.n && n_active > 0; ++j) {
                int64_t bx0, bx1, by0, by1;
                if (!tg.box(j, x0, x1, y0, y1, bx0, bx1, by0, by1))
                    continue;
                const S *cj = &tg.col[j * D];
                for (int64_t y = by0; y < by1; ++y) {
                    const S dy = tg.my[j] - (S(y) + S(0.5));
                    for (int64_t x = bx0; x < bx1; ++x) {
                        const int64_t p = (y - y0) * ts + (x - x0);
                        if (done[p])
                            continue;
                        S vis, alpha;
                        const S dx = tg.mx[j] - (S(x) + S(0.5));
                        if (!tg.eval(j, dx, dy, vis, alpha))
                            continue;
                        const S next_T = T[p] * (S(1) - alpha);
                        if (next_T <= Thresh<S>::T_min) {
                            // stop; this Gaussian is not composited
                            done[p] = 1;
                            --n_active;
                            continue;
                        }
                        const S w = alpha * T[p];
                        S *ap = &acc[p * D];
                        for (int64_t d = 0; d < D; ++d)
                            ap[d] += cj[d] * w;
                        T[p] = next_T;
                        last[p] = int32_t(j);
                    }
                }
            }

            const S *bg = backgrounds ? backgrounds + c * D : nullptr;
            for (int64_t y = y0; y < y1; ++y) {
                for (int64_t x = x0; x < x1; ++x) {
                    const int64_t p = (y - y0) * ts + (x - x0);
                    const int64_t pix = (c * H + y) * W + x;
                    S *oc = out_colors + pix * D;
                    const S *ap = &acc[p * D];
                    for (int64_t d = 0; d < D; ++d)
                        oc[d] = bg ? ap[d] + T[p] * bg[d] : ap[d];
                    out_alphas[pix] = S(1) - T[p];
                    last_ids[pix] = last[p] < 0 ? -1 : int32_t(start + last[p]);
                }
            }
        }
    }
}

// Defensive checks for direct callers of the ops (the Python wrapper raises
// friendlier ValueErrors first): everything the raw pointer loops rely on.
void check_inputs(
    const char *op, const Tensor &means2d, const Tensor &conics,
    const Tensor &colors, const Tensor &opacities,
    const std::optional<Tensor> &backgrounds, int64_t W, int64_t H,
    int64_t tile_size, const Tensor &isect_offsets, const Tensor &flatten_ids
) {
    TORCH_CHECK(means2d.dim() == 3 && means2d.size(2) == 2, op, ": means2d must be [C, N, 2]");
    const int64_t C = means2d.size(0), N = means2d.size(1);
    TORCH_CHECK(colors.dim() == 3 && colors.size(0) == C && colors.size(1) == N,
                op, ": colors must be [C, N, D]");
    const int64_t D = colors.size(2);
    TORCH_CHECK(conics.sizes() == at::IntArrayRef({C, N, 3}), op, ": conics must be [C, N, 3]");
    TORCH_CHECK(opacities.sizes() == at::IntArrayRef({C, N}), op, ": opacities must be [C, N]");
    TORCH_CHECK(tile_size > 0 && W > 0 && H > 0, op, ": sizes must be positive");
    TORCH_CHECK(isect_offsets.sizes() == at::IntArrayRef({C, (H + tile_size - 1) / tile_size,
                                                          (W + tile_size - 1) / tile_size}),
                op, ": isect_offsets must be [C, tile_height, tile_width]");
    TORCH_CHECK(isect_offsets.scalar_type() == at::kInt && flatten_ids.scalar_type() == at::kInt &&
                flatten_ids.dim() == 1, op, ": isect_offsets / flatten_ids must be int32, flatten_ids 1-D");
    std::vector<const Tensor *> floats = {&means2d, &conics, &colors, &opacities};
    if (backgrounds.has_value()) {
        TORCH_CHECK(backgrounds->sizes() == at::IntArrayRef({C, D}), op, ": backgrounds must be [C, D]");
        floats.push_back(&*backgrounds);
    }
    for (const Tensor *t : floats) {
        TORCH_CHECK(t->scalar_type() == means2d.scalar_type(), op, ": float inputs must share one dtype");
        TORCH_CHECK(t->is_contiguous() && t->device().is_cpu(), op, ": inputs must be contiguous CPU tensors");
    }
    TORCH_CHECK(isect_offsets.is_contiguous() && flatten_ids.is_contiguous(), op,
                ": isect_offsets / flatten_ids must be contiguous");
    const int32_t *ids = flatten_ids.data_ptr<int32_t>();
    for (int64_t i = 0; i < flatten_ids.numel(); ++i)
        TORCH_CHECK(ids[i] >= 0 && ids[i] < C * N, op, ": flatten_ids out of range [0, C * N)");
}

// at::zeros fills in parallel above a size threshold; waking the thread pool
// for a memset this small only costs time on a busy machine.
Tensor zeros_serial(at::IntArrayRef sizes, const at::TensorOptions &opts) {
    Tensor t = at::empty(sizes, opts);
    if (t.numel() > 0)
        std::memset(t.data_ptr(), 0, t.numel() * t.element_size());
    return t;
}

std::tuple<Tensor, Tensor, Tensor> rasterize_to_pixels_fwd(
    const Tensor &means2d, const Tensor &conics, const Tensor &colors,
    const Tensor &opacities, const std::optional<Tensor> &backgrounds,
    int64_t image_width, int64_t image_height, int64_t tile_size,
    const Tensor &isect_offsets, const Tensor &flatten_ids, int64_t num_threads
) {
    check_inputs(
        "rasterize_to_pixels_fwd", means2d, conics, colors, opacities,
        backgrounds, image_width, image_height, tile_size, isect_offsets,
        flatten_ids
    );
    const int64_t C = means2d.size(0), D = colors.size(2);
    Grid grid{C, image_width, image_height, tile_size, isect_offsets.size(2),
              isect_offsets.size(1), flatten_ids.numel(),
              isect_offsets.data_ptr<int32_t>()};

    auto opts = means2d.options();
    Tensor out_colors = at::empty({C, image_height, image_width, D}, opts);
    Tensor out_alphas = at::empty({C, image_height, image_width, 1}, opts);
    Tensor last_ids =
        at::empty({C, image_height, image_width}, opts.dtype(at::kInt));

    AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "rasterize_fwd", [&] {
        const scalar_t *bg = backgrounds.has_value()
                                 ? backgrounds->data_ptr<scalar_t>()
                                 : nullptr;
        auto run = [&](auto dt) {
            fwd_kernel<scalar_t, decltype(dt)::value>(
                grid, D, means2d.data_ptr<scalar_t>(),
                conics.data_ptr<scalar_t>(), colors.data_ptr<scalar_t>(),
                opacities.data_ptr<scalar_t>(), bg,
                flatten_ids.data_ptr<int32_t>(),
                out_colors.data_ptr<scalar_t>(),
                out_alphas.data_ptr<scalar_t>(), last_ids.data_ptr<int32_t>(),
                int(std::max<int64_t>(num_threads, 1))
            );
        };
        // fixed channel counts get unrolled inner loops
        switch (D) {
        case 1: run(std::integral_constant<int, 1>{}); break;
        case 3: run(std::integral_constant<int, 3>{}); break;
        case 4: run(std::integral_constant<int, 4>{}); break;
        default: run(std::integral_constant<int, 0>{}); break;
        }
    });
    return {out_colors, out_alphas, last_ids};
}

/****************************************************************************
 * Backward
 ****************************************************************************/

// Per-intersection gradient row layout: [mx, my, a, b, c, opacity, color[D],
// (|mx|, |my| when absgrad)].
constexpr int64_t kMx = 0, kMy = 1, kA = 2, kB = 3, kC = 4, kOp = 5, kCol = 6;

// A composited (pixel, Gaussian) pair: tile-local pixel, transmittance in
// front of the Gaussian, its alpha and exp(-sigma).
template <typename S> struct Pair {
    int32_t lx, ly;
    S T, alpha, vis;
};

template <typename S, int DT>
void bwd_kernel(
    const Grid &grid, int64_t Drt, bool absgrad, const S *means2d,
    const S *conics, const S *colors, const S *opacities,
    const S *backgrounds, const int32_t *flatten_ids, const int32_t *last_ids,
    const S *v_out_colors, const S *v_out_alphas,
    S *v_isect,   // [n_isects, K], rows of each tile written by that tile
    S *v_bg_tile, // [C * th * tw, D] or nullptr
    int num_threads
) {
    const int64_t D = DT > 0 ? DT : Drt;
    const int64_t K = kCol + D + (absgrad ? 2 : 0);
    const int64_t n_tiles = grid.num_tiles();
    const int64_t W = grid.W, H = grid.H, ts = grid.tile_size;
#pragma omp parallel num_threads(num_threads) if (grid.worth_threads(num_threads))
    {
        TileGaussians<S> tg;
        // per-pixel state, indexed (y - y0) * ts + (x - x0)
        std::vector<int32_t> last(ts * ts);
        std::vector<S> T(ts * ts), P(ts * ts), bg_dot(ts * ts), R(ts * ts * D);
        // composited (pixel, Gaussian) pairs of the tile, grouped by Gaussian:
        // pairs of Gaussian j are rec_*[rec_begin[j] : rec_begin[j + 1]]
        std::vector<int64_t> rec_begin;
        std::vector<Pair<S>> rec;
        std::vector<S> gcol_dyn(DT > 0 ? 0 : D);
        S gcol_fixed[DT > 0 ? DT : 1];
        S *gcol = DT > 0 ? gcol_fixed : gcol_dyn.data();

#pragma omp for schedule(dynamic, 1)
        for (int64_t ct = 0; ct < grid.C * n_tiles; ++ct) {
            const int64_t c = ct / n_tiles;
            int64_t start, end, x0, x1, y0, y1;
            grid.range(ct, start, end);
            grid.pixels(ct % n_tiles, x0, x1, y0, y1);
            const int64_t len = end - start;
            const S *bg = backgrounds ? backgrounds + c * D : nullptr;

            int32_t max_last = -1;
            for (int64_t y = y0; y < y1; ++y) {
                for (int64_t x = x0; x < x1; ++x) {
                    const int64_t p = (y - y0) * ts + (x - x0);
                    const int64_t l = last_ids[(c * H + y) * W + x];
                    last[p] = l < 0 ? -1
                                    : int32_t(std::clamp<int64_t>(
                                          l - start, -1, len - 1));
                    max_last = std::max(max_last, last[p]);
                    T[p] = S(1);
                }
            }
            tg.load(
                means2d, conics, colors, opacities, flatten_ids + start,
                max_last + 1, D // nothing behind the last composited one matters
            );

            // Front to back: the transmittance in front of every composited
            // pair. No stop test: the forward composited all up to last[p].
            rec_begin.assign(max_last + 2, 0);
            rec.clear();
            for (int64_t j = 0; j <= max_last; ++j) {
                rec_begin[j] = int64_t(rec.size());
                int64_t bx0, bx1, by0, by1;
                if (!tg.box(j, x0, x1, y0, y1, bx0, bx1, by0, by1))
                    continue;
                for (int64_t y = by0; y < by1; ++y) {
                    const S dy = tg.my[j] - (S(y) + S(0.5));
                    for (int64_t x = bx0; x < bx1; ++x) {
                        const int64_t p = (y - y0) * ts + (x - x0);
                        if (j > last[p])
                            continue;
                        S vis, alpha;
                        const S dx = tg.mx[j] - (S(x) + S(0.5));
                        if (!tg.eval(j, dx, dy, vis, alpha))
                            continue;
                        rec.push_back({int32_t(x - x0), int32_t(y - y0),
                                       T[p], alpha, vis});
                        T[p] *= S(1) - alpha;
                    }
                }
            }
            rec_begin[max_last + 1] = int64_t(rec.size());

            // T[p] is now the final transmittance: background gradient, and
            // the start of the back-to-front sums.
            S *vbg = v_bg_tile ? v_bg_tile + ct * D : nullptr;
            for (int64_t y = y0; y < y1; ++y) {
                for (int64_t x = x0; x < x1; ++x) {
                    const int64_t p = (y - y0) * ts + (x - x0);
                    const S *vC = v_out_colors + ((c * H + y) * W + x) * D;
                    S dot = S(0);
                    if (bg) {
                        for (int64_t d = 0; d < D; ++d) {
                            vbg[d] += vC[d] * T[p];
                            dot += vC[d] * bg[d];
                        }
                    }
                    bg_dot[p] = dot;
                    P[p] = S(1);
                    for (int64_t d = 0; d < D; ++d)
                        R[p * D + d] = S(0);
                }
            }

            // Back to front. Per pixel, R: colour composited behind the
            // current Gaussian with transmittance 1 right behind it, P: product
            // of (1 - alpha) behind it. Then, without any division,
            //   d color / d alpha_k = T_k (c_k - R_k - P_k bg)
            //   d alpha_out / d alpha_k = T_k P_k
            std::fill(v_isect + start * K, v_isect + end * K, S(0));
            for (int64_t j = max_last; j >= 0; --j) {
                const int64_t r0 = rec_begin[j], r1 = rec_begin[j + 1];
                if (r0 == r1)
                    continue;
                const S *cj = &tg.col[j * D];
                const S a = tg.ca[j], b = tg.cb[j], cz = tg.cc[j], o = tg.op[j];
                S g_mx = 0, g_my = 0, g_a = 0, g_b = 0, g_c = 0, g_op = 0;
                S g_absx = 0, g_absy = 0;
                for (int64_t d = 0; d < D; ++d)
                    gcol[d] = S(0);
                for (int64_t r = r0; r < r1; ++r) {
                    const Pair<S> &q = rec[r];
                    const int64_t p = int64_t(q.ly) * ts + q.lx;
                    const int64_t y = y0 + q.ly, x = x0 + q.lx;
                    const int64_t pix = (c * H + y) * W + x;
                    const S *vC = v_out_colors + pix * D;
                    const S alpha = q.alpha, vis = q.vis;
                    const S Tk = q.T, one_m_a = S(1) - alpha;
                    const S w = alpha * Tk;
                    S *Rp = &R[p * D];
                    S dot = S(0);
                    for (int64_t d = 0; d < D; ++d) {
                        gcol[d] += w * vC[d];
                        dot += vC[d] * (cj[d] - Rp[d]);
                        Rp[d] = cj[d] * alpha + one_m_a * Rp[d];
                    }
                    const S v_alpha =
                        Tk * (dot + P[p] * (v_out_alphas[pix] - bg_dot[p]));
                    P[p] *= one_m_a;

                    // a clamped alpha (0.999) passes no gradient
                    const S ov = o * vis;
                    if (!(ov <= Thresh<S>::alpha_max))
                        continue;
                    const S v_sigma = -ov * v_alpha;
                    const S dx = tg.mx[j] - (S(x) + S(0.5));
                    const S dy = tg.my[j] - (S(y) + S(0.5));
                    const S gx = v_sigma * (a * dx + b * dy);
                    const S gy = v_sigma * (b * dx + cz * dy);
                    g_mx += gx;
                    g_my += gy;
                    g_a += S(0.5) * v_sigma * dx * dx;
                    g_b += v_sigma * dx * dy;
                    g_c += S(0.5) * v_sigma * dy * dy;
                    g_op += vis * v_alpha;
                    g_absx += std::abs(gx);
                    g_absy += std::abs(gy);
                }
                // row start + j belongs to this tile only
                S *row = v_isect + (start + j) * K;
                row[kMx] = g_mx;
                row[kMy] = g_my;
                row[kA] = g_a;
                row[kB] = g_b;
                row[kC] = g_c;
                row[kOp] = g_op;
                for (int64_t d = 0; d < D; ++d)
                    row[kCol + d] = gcol[d];
                if (absgrad) {
                    row[kCol + D] = g_absx;
                    row[kCol + D + 1] = g_absy;
                }
            }
        }
    }
}

// Sums the per-intersection rows into per-Gaussian gradients. Serial and in
// intersection order, so the result does not depend on the thread schedule.
template <typename S>
void reduce_isects(
    int64_t n_isects, int64_t D, bool absgrad, const int32_t *flatten_ids,
    const S *v_isect, S *v_means2d, S *v_conics, S *v_colors, S *v_opacities,
    S *v_abs
) {
    const int64_t K = kCol + D + (absgrad ? 2 : 0);
    for (int64_t i = 0; i < n_isects; ++i) {
        const int64_t g = flatten_ids[i];
        const S *r = v_isect + i * K;
        v_means2d[2 * g] += r[kMx];
        v_means2d[2 * g + 1] += r[kMy];
        v_conics[3 * g] += r[kA];
        v_conics[3 * g + 1] += r[kB];
        v_conics[3 * g + 2] += r[kC];
        v_opacities[g] += r[kOp];
        for (int64_t d = 0; d < D; ++d)
            v_colors[g * D + d] += r[kCol + d];
        if (absgrad) {
            v_abs[2 * g] += r[kCol + D];
            v_abs[2 * g + 1] += r[kCol + D + 1];
        }
    }
}

std::tuple<Tensor, Tensor, Tensor, Tensor, Tensor, Tensor>
rasterize_to_pixels_bwd(
    const Tensor &means2d, const Tensor &conics, const Tensor &colors,
    const Tensor &opacities, const std::optional<Tensor> &backgrounds,
    int64_t image_width, int64_t image_height, int64_t tile_size,
    const Tensor &isect_offsets, const Tensor &flatten_ids,
    const Tensor &last_ids, const Tensor &v_render_colors,
    const Tensor &v_render_alphas, bool absgrad, int64_t num_threads
) {
    check_inputs(
        "rasterize_to_pixels_bwd", means2d, conics, colors, opacities,
        backgrounds, image_width, image_height, tile_size, isect_offsets,
        flatten_ids
    );
    const int64_t C = means2d.size(0), D = colors.size(2);
    const auto dtype = means2d.scalar_type();
    TORCH_CHECK(last_ids.sizes() == at::IntArrayRef({C, image_height, image_width}) &&
                last_ids.scalar_type() == at::kInt && last_ids.is_contiguous(),
                "rasterize_to_pixels_bwd: last_ids must be contiguous int32 [C, H, W]");
    TORCH_CHECK(v_render_colors.sizes() == at::IntArrayRef({C, image_height, image_width, D}) &&
                v_render_alphas.sizes() == at::IntArrayRef({C, image_height, image_width, 1}) &&
                v_render_colors.scalar_type() == dtype && v_render_alphas.scalar_type() == dtype &&
                v_render_colors.is_contiguous() && v_render_alphas.is_contiguous(),
                "rasterize_to_pixels_bwd: output gradients must be contiguous [C, H, W, D] / [C, H, W, 1]");
    const int64_t n_isects = flatten_ids.numel();
    Grid grid{C, image_width, image_height, tile_size, isect_offsets.size(2),
              isect_offsets.size(1), n_isects,
              isect_offsets.data_ptr<int32_t>()};
    const int64_t K = kCol + D + (absgrad ? 2 : 0);

    auto opts = means2d.options();
    Tensor v_means2d = zeros_serial(means2d.sizes(), opts);
    Tensor v_conics = zeros_serial(conics.sizes(), opts);
    Tensor v_colors = zeros_serial(colors.sizes(), opts);
    Tensor v_opacities = zeros_serial(opacities.sizes(), opts);
    Tensor v_abs = absgrad ? zeros_serial(means2d.sizes(), opts) : Tensor();
    // every row inside a tile range is written by its tile; only rows before
    // the first tile (not produced by isect_offset_encode) need zeros
    Tensor v_isect = at::empty({n_isects, K}, opts);
    if (n_isects > 0) {
        const int64_t first =
            std::clamp<int64_t>(grid.offsets[0], 0, n_isects);
        std::memset(v_isect.data_ptr(), 0, first * K * v_isect.element_size());
    }
    const bool has_bg = backgrounds.has_value();
    Tensor v_bg_tile =
        has_bg ? zeros_serial({C * grid.num_tiles(), D}, opts) : Tensor();
    Tensor v_backgrounds = has_bg ? zeros_serial({C, D}, opts) : Tensor();

    AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "rasterize_bwd", [&] {
        auto run = [&](auto dt) {
            bwd_kernel<scalar_t, decltype(dt)::value>(
                grid, D, absgrad, means2d.data_ptr<scalar_t>(),
                conics.data_ptr<scalar_t>(), colors.data_ptr<scalar_t>(),
                opacities.data_ptr<scalar_t>(),
                has_bg ? backgrounds->data_ptr<scalar_t>() : nullptr,
                flatten_ids.data_ptr<int32_t>(), last_ids.data_ptr<int32_t>(),
                v_render_colors.data_ptr<scalar_t>(),
                v_render_alphas.data_ptr<scalar_t>(),
                v_isect.data_ptr<scalar_t>(),
                has_bg ? v_bg_tile.data_ptr<scalar_t>() : nullptr,
                int(std::max<int64_t>(num_threads, 1))
            );
        };
        switch (D) {
        case 1: run(std::integral_constant<int, 1>{}); break;
        case 3: run(std::integral_constant<int, 3>{}); break;
        case 4: run(std::integral_constant<int, 4>{}); break;
        default: run(std::integral_constant<int, 0>{}); break;
        }
        reduce_isects<scalar_t>(
            n_isects, D, absgrad, flatten_ids.data_ptr<int32_t>(),
            v_isect.data_ptr<scalar_t>(), v_means2d.data_ptr<scalar_t>(),
            v_conics.data_ptr<scalar_t>(), v_colors.data_ptr<scalar_t>(),
            v_opacities.data_ptr<scalar_t>(),
            absgrad ? v_abs.data_ptr<scalar_t>() : nullptr
        );
        if (has_bg) {
            // per-tile partial sums, reduced in tile order (deterministic)
            const scalar_t *src = v_bg_tile.data_ptr<scalar_t>();
            scalar_t *dst = v_backgrounds.data_ptr<scalar_t>();
            for (int64_t ct = 0; ct < C * grid.num_tiles(); ++ct) {
                const int64_t c = ct / grid.num_tiles();
                for (int64_t d = 0; d < D; ++d)
                    dst[c * D + d] += src[ct * D + d];
            }
        }
    });
    return {v_means2d, v_conics, v_colors, v_opacities, v_backgrounds, v_abs};
}

} // namespace gsmsdr

TORCH_LIBRARY(gsmsdr_ns, m) {
    m.def(
        "rasterize_to_pixels_fwd(Tensor means2d, Tensor conics, Tensor colors, "
        "Tensor opacities, Tensor? backgrounds, int image_width, "
        "int image_height, int tile_size, Tensor isect_offsets, "
        "Tensor flatten_ids, int num_threads) -> (Tensor, Tensor, Tensor)"
    );
    m.def(
        "rasterize_to_pixels_bwd(Tensor means2d, Tensor conics, Tensor colors, "
        "Tensor opacities, Tensor? backgrounds, int image_width, "
        "int image_height, int tile_size, Tensor isect_offsets, "
        "Tensor flatten_ids, Tensor last_ids, Tensor v_render_colors, "
        "Tensor v_render_alphas, bool absgrad, int num_threads) "
        "-> (Tensor, Tensor, Tensor, Tensor, Tensor, Tensor)"
    );
}

TORCH_LIBRARY_IMPL(gsmsdr_ns, CPU, m) {
    m.impl("rasterize_to_pixels_fwd", &gsmsdr::rasterize_to_pixels_fwd);
    m.impl("rasterize_to_pixels_bwd", &gsmsdr::rasterize_to_pixels_bwd);
}
