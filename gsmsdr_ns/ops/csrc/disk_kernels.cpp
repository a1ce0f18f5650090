// Thin-lens defocus (per-pixel disk kernels) applied to an image without ever
// materialising the kernels, forward and hand-written backward, on CPU (see
// gsmsdr_ns/ops/disk_defocus.py for the Python entry point and the PyTorch twin).
//
// It computes exactly apply_pixel_kernels(image, kernels) with kernels from
// occluding_disk_kernels(radius, inverse_depth, K, softness) (occlusion) or
// soft_disk_kernels(radius, K, softness) (no occlusion). With p = K / 2, tap
// k = i * K + j at distance d_k from the centre, q = clamp(pixel + (i - p, j - p)):
//   reach_k = (occlusion && z[q] < z[pix]) ? min(r[q], r[pix]) : (occlusion ? r[q] : r[pix])
//   cov_k   = d_k == 0 ? 1 : sigmoid((reach_k - d_k) / s) - sigmoid(-d_k / s)
//   u_k     = occlusion ? cov_k / (1 + pi r[q]^2) : cov_k
//   S       = sum_k u_k,  out[c] = sum_k (u_k / S) * image[c, q]
// S is returned too (the backward needs it).
//
// Backward, with G = grad_out at the pixel, beta = sum_c G[c] out[c] and
// dL/du_k = (sum_c G[c] image[c, q] - beta) / S:
//   grad_image[q]  += (u_k / S) * G                      (scattered to q)
//   grad_radius[q] += dL/du_k * du_k / dr[q]              (scattered to q)
//   grad_radius[pix] += sum_k dL/du_k * du_k / dr[pix]    (gathered)
// torch.minimum's tie rule is kept: on r[q] == r[pix] each side gets half.
//
// Nothing of size K*K x image is allocated: the forward keeps one row of the
// K*K weights per thread, the backward recomputes them. Each call opens one
// at::parallel_for over the B*H rows and every iteration owns its rows of the
// outputs, so there are no races and the result does not depend on the thread
// schedule:
//   forward  : iteration (b, y)  writes out[b, :, y, :] and S[b, 0, y, :]
//   backward : iteration (b, ys) gathers the pixels of row ys (their own radius
//              term) and every (pixel, tap) whose clamped source row is ys, and
//              writes grad_image[b, :, ys, :] and grad_radius[b, 0, ys, :]
//
// Only light torch headers are used (no torch/extension.h) to keep the JIT
// compile short; the ops are registered under the namespace gsmsdr_defocus.

#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <optional>
#include <tuple>
#include <vector>

namespace gsmsdr_defocus {

using at::Tensor;

namespace {

constexpr double kPi = 3.14159265358979323846;

struct Dims {
    int64_t B, C, H, W, K, p, HW;
};

inline int64_t clamp_index(int64_t v, int64_t n) { return std::min<int64_t>(std::max<int64_t>(v, 0), n - 1); }

template <typename S> inline S sigmoid(S x) { return S(1) / (S(1) + std::exp(-x)); }

// torch.minimum: NaN if either is NaN
template <typename S> inline S nan_min(S a, S b) {
    if (std::isnan(a) || std::isnan(b)) return a + b;
    return a < b ? a : b;
}

// The window's taps: distance to the centre and the constant sigmoid(-d / s), in the op's dtype as the reference.
template <typename S> struct Taps {
    std::vector<S> distance, base;
    Taps(int64_t K, S softness) : distance(K * K), base(K * K) {
        const int64_t p = K / 2;
        for (int64_t i = 0; i < K; ++i)
            for (int64_t j = 0; j < K; ++j) {
                const S di = S(i - p), dj = S(j - p);
                const S d = std::sqrt(di * di + dj * dj);
                distance[i * K + j] = d;
                base[i * K + j] = sigmoid<S>(-d / softness);
            }
    }
};

// One tap's weight and what its gradient needs.
template <typename S> struct Tap {
    S u;        // unnormalised weight
    S area;     // 1 / (1 + pi r_q^2) (1 without occlusion)
    S cov;      // coverage
    S dcov;     // d cov / d reach
    S dreach_q; // d reach / d r_q
    S dreach_p; // d reach / d r_p
};

template <typename S>
inline Tap<S> tap(S rq, S zq, S rp, S zp, S d, S base, S softness, bool occlusion, bool need_grad) {
    Tap<S> t;
    S reach;
    t.dreach_q = S(0);
    t.dreach_p = S(0);
    if (!occlusion) {
        reach = rp;
        t.dreach_p = S(1);
    } else if (zq < zp) {  // q behind: reaches no further than p's own disk
        reach = nan_min(rq, rp);
        if (need_grad) {
            t.dreach_q = rq < rp ? S(1) : (rq == rp ? S(0.5) : S(0));
            t.dreach_p = rp < rq ? S(1) : (rq == rp ? S(0.5) : S(0));
        }
    } else {
        reach = rq;
        t.dreach_q = S(1);
    }
    if (d == S(0)) {
        t.cov = S(1);
        t.dcov = S(0);
    } else {
        const S sg = sigmoid<S>((reach - d) / softness);
        t.cov = sg - base;
        t.dcov = need_grad ? sg * (S(1) - sg) / softness : S(0);
    }
    t.area = occlusion ? S(1) / (S(1) + S(kPi) * (rq * rq)) : S(1);
    t.u = occlusion ? t.cov / (S(1) + S(kPi) * (rq * rq)) : t.cov;
    return t;
}

template <typename S>
void forward_rows(const S *img, const S *rad, const S *invd, S *out, S *sum, const Dims &s, S softness,
                  bool occlusion, const Taps<S> &taps, int64_t begin, int64_t end) {
    const int64_t KK = s.K * s.K;
    std::vector<S> u(KK * s.W);  // this row's weights, tap-major
    for (int64_t row = begin; row < end; ++row) {
        const int64_t b = row / s.H, y = row % s.H;
        const S *r_b = rad + b * s.HW, *z_b = invd + b * s.HW;
        const S *img_b = img + b * s.C * s.HW;
        S *sum_row = sum + b * s.HW + y * s.W;
        std::fill(sum_row, sum_row + s.W, S(0));
        for (int64_t i = 0; i < s.K; ++i) {
            const int64_t ys = clamp_index(y + i - s.p, s.H);
            for (int64_t j = 0; j < s.K; ++j) {
                const int64_t k = i * s.K + j;
                S *u_k = u.data() + k * s.W;
                for (int64_t x = 0; x < s.W; ++x) {
                    const int64_t xs = clamp_index(x + j - s.p, s.W);
                    const Tap<S> t = tap<S>(r_b[ys * s.W + xs], z_b[ys * s.W + xs], r_b[y * s.W + x],
                                            z_b[y * s.W + x], taps.distance[k], taps.base[k], softness, occlusion,
                                            false);
                    u_k[x] = t.u;
                    sum_row[x] += t.u;
                }
            }
        }
        // normalise, then accumulate in the order apply_pixel_kernels does
        S *out_row = out + b * s.C * s.HW + y * s.W;
        for (int64_t c = 0; c < s.C; ++c) std::fill(out_row + c * s.HW, out_row + c * s.HW + s.W, S(0));
        for (int64_t i = 0; i < s.K; ++i) {
            const int64_t ys = clamp_index(y + i - s.p, s.H);
            for (int64_t j = 0; j < s.K; ++j) {
                S *u_k = u.data() + (i * s.K + j) * s.W;
                for (int64_t x = 0; x < s.W; ++x) u_k[x] = u_k[x] / sum_row[x];
                for (int64_t c = 0; c < s.C; ++c) {
                    const S *src = img_b + c * s.HW + ys * s.W;
                    S *dst = out_row + c * s.HW;
                    for (int64_t x = 0; x < s.W; ++x) dst[x] += u_k[x] * src[clamp_index(x + j - s.p, s.W)];
                }
            }
        }
    }
}

template <typename S>
void backward_rows(const S *grad_out, const S *img, const S *rad, const S *invd, const S *out, const S *sum,
                   S *grad_img, S *grad_rad, const Dims &s, S softness, bool occlusion, const Taps<S> &taps,
                   int64_t begin, int64_t end) {
    std::vector<S> beta(s.W);
    for (int64_t row = begin; row < end; ++row) {
        const int64_t b = row / s.H, ys = row % s.H;
        const S *r_b = rad + b * s.HW, *z_b = invd + b * s.HW, *sum_b = sum + b * s.HW;
        const S *img_b = img + b * s.C * s.HW, *g_b = grad_out + b * s.C * s.HW, *out_b = out + b * s.C * s.HW;
        S *gi_b = grad_img == nullptr ? nullptr : grad_img + b * s.C * s.HW;
        S *gr_row = grad_rad == nullptr ? nullptr : grad_rad + b * s.HW + ys * s.W;
        if (gi_b != nullptr)
            for (int64_t c = 0; c < s.C; ++c) {
                S *gi_row = gi_b + c * s.HW + ys * s.W;
                std::fill(gi_row, gi_row + s.W, S(0));
            }
        if (gr_row != nullptr) std::fill(gr_row, gr_row + s.W, S(0));
        auto fill_beta = [&](int64_t y) {
            for (int64_t x = 0; x < s.W; ++x) {
                S acc = S(0);
                for (int64_t c = 0; c < s.C; ++c) acc += g_b[c * s.HW + y * s.W + x] * out_b[c * s.HW + y * s.W + x];
                beta[x] = acc;
            }
        };
        // 1. the pixels of row ys: the taps whose reach depends on their own radius
        if (gr_row != nullptr) {
            fill_beta(ys);
            for (int64_t i = 0; i < s.K; ++i) {
                const int64_t yq = clamp_index(ys + i - s.p, s.H);
                for (int64_t j = 0; j < s.K; ++j) {
                    const int64_t k = i * s.K + j;
                    if (taps.distance[k] == S(0)) continue;  // the centre's coverage is constant
                    for (int64_t x = 0; x < s.W; ++x) {
                        const int64_t q = yq * s.W + clamp_index(x + j - s.p, s.W), pix = ys * s.W + x;
                        const S rq = r_b[q], zq = z_b[q], rp = r_b[pix], zp = z_b[pix];
                        if (occlusion && !(zq < zp && !(rp > rq))) continue;  // reach does not read r_p
                        const Tap<S> t = tap<S>(rq, zq, rp, zp, taps.distance[k], taps.base[k], softness, occlusion,
                                                true);
                        S g = S(0);
                        for (int64_t c = 0; c < s.C; ++c) g += g_b[c * s.HW + pix] * img_b[c * s.HW + q];
                        const S dl_du = (g - beta[x]) / sum_b[pix];
                        gr_row[x] += dl_du * t.dcov * t.dreach_p * t.area;
                    }
                }
            }
        }
        // 2. every (pixel, tap) reading source row ys: image gradient and the neighbour's radius term
        for (int64_t i = 0; i < s.K; ++i) {
            // output rows y with clamp(y + i - p) == ys; the first / last source row also collect the margin
            const int64_t y_lo = std::max<int64_t>(ys == 0 ? 0 : ys - i + s.p, 0);
            const int64_t y_hi = std::min<int64_t>(ys == s.H - 1 ? s.H - 1 : ys - i + s.p, s.H - 1);
            for (int64_t y = y_lo; y <= y_hi; ++y) {
                if (gr_row != nullptr && occlusion) fill_beta(y);
                for (int64_t j = 0; j < s.K; ++j) {
                    const int64_t k = i * s.K + j;
                    for (int64_t x = 0; x < s.W; ++x) {
                        const int64_t xs = clamp_index(x + j - s.p, s.W);
                        const int64_t q = ys * s.W + xs, pix = y * s.W + x;
                        const S rq = r_b[q], zq = z_b[q], rp = r_b[pix], zp = z_b[pix];
                        const Tap<S> t = tap<S>(rq, zq, rp, zp, taps.distance[k], taps.base[k], softness, occlusion,
                                                gr_row != nullptr);
                        const S w = t.u / sum_b[pix];
                        if (gi_b != nullptr)
                            for (int64_t c = 0; c < s.C; ++c) gi_b[c * s.HW + q] += w * g_b[c * s.HW + pix];
                        if (gr_row != nullptr && occlusion) {
                            S g = S(0);
                            for (int64_t c = 0; c < s.C; ++c) g += g_b[c * s.HW + pix] * img_b[c * s.HW + q];
                            const S dl_du = (g - beta[x]) / sum_b[pix];
                            const S darea = -S(2) * S(kPi) * rq * t.area * t.area;
                            gr_row[xs] += dl_du * (t.dcov * t.dreach_q * t.area + t.cov * darea);
                        }
                    }
                }
            }
        }
    }
}

Dims check(const Tensor &image, const Tensor &radius, const Tensor &inverse_depth, int64_t K, double softness) {
    TORCH_CHECK(image.dim() == 4 && radius.dim() == 4 && inverse_depth.dim() == 4,
                "image, radius and inverse_depth must be 4-D");
    TORCH_CHECK(K >= 1 && K % 2 == 1, "kernel_size must be odd and positive, got ", K);
    TORCH_CHECK(softness > 0, "softness must be > 0, got ", softness);
    TORCH_CHECK(image.is_contiguous() && radius.is_contiguous() && inverse_depth.is_contiguous(),
                "image, radius and inverse_depth must be contiguous");
    TORCH_CHECK(image.scalar_type() == radius.scalar_type() && image.scalar_type() == inverse_depth.scalar_type(),
                "image, radius and inverse_depth must share a dtype");
    const int64_t B = image.size(0), C = image.size(1), H = image.size(2), W = image.size(3);
    TORCH_CHECK(radius.size(0) == B && radius.size(1) == 1 && radius.size(2) == H && radius.size(3) == W,
                "radius: expected shape [", B, ", 1, ", H, ", ", W, "], got ", radius.sizes());
    TORCH_CHECK(inverse_depth.sizes() == radius.sizes(), "inverse_depth: expected the radius's shape ",
                radius.sizes(), ", got ", inverse_depth.sizes());
    TORCH_CHECK(H >= 1 && W >= 1, "image must have H >= 1 and W >= 1");
    return Dims{B, C, H, W, K, K / 2, H * W};
}

}  // namespace

std::tuple<Tensor, Tensor> disk_defocus_fwd(const Tensor &image, const Tensor &radius, const Tensor &inverse_depth,
                                            int64_t kernel_size, double softness, bool occlusion) {
    const Dims s = check(image, radius, inverse_depth, kernel_size, softness);
    Tensor out = at::empty(image.sizes(), image.options());
    Tensor sum = at::empty(radius.sizes(), radius.options());
    AT_DISPATCH_FLOATING_TYPES(image.scalar_type(), "disk_defocus_fwd", [&] {
        const scalar_t soft = scalar_t(softness);
        const Taps<scalar_t> taps(s.K, soft);
        const scalar_t *img = image.const_data_ptr<scalar_t>();
        const scalar_t *rad = radius.const_data_ptr<scalar_t>();
        const scalar_t *invd = inverse_depth.const_data_ptr<scalar_t>();
        scalar_t *o = out.mutable_data_ptr<scalar_t>();
        scalar_t *sm = sum.mutable_data_ptr<scalar_t>();
        at::parallel_for(0, s.B * s.H, 1, [&](int64_t begin, int64_t end) {
            forward_rows<scalar_t>(img, rad, invd, o, sm, s, soft, occlusion, taps, begin, end);
        });
    });
    return {out, sum};
}

std::tuple<std::optional<Tensor>, std::optional<Tensor>> disk_defocus_bwd(
    const Tensor &grad_out, const Tensor &image, const Tensor &radius, const Tensor &inverse_depth,
    const Tensor &out, const Tensor &sum, int64_t kernel_size, double softness, bool occlusion, bool need_image,
    bool need_radius
) {
    const Dims s = check(image, radius, inverse_depth, kernel_size, softness);
    TORCH_CHECK(grad_out.is_contiguous() && grad_out.sizes() == image.sizes() &&
                    grad_out.scalar_type() == image.scalar_type(),
                "grad_out must be contiguous with the image's shape and dtype");
    TORCH_CHECK(out.is_contiguous() && out.sizes() == image.sizes() && out.scalar_type() == image.scalar_type(),
                "out must be the forward's output");
    TORCH_CHECK(sum.is_contiguous() && sum.sizes() == radius.sizes() && sum.scalar_type() == image.scalar_type(),
                "sum must be the forward's weight sums");
    Tensor grad_image, grad_radius;
    if (need_image) grad_image = at::empty(image.sizes(), image.options());
    if (need_radius) grad_radius = at::empty(radius.sizes(), radius.options());
    AT_DISPATCH_FLOATING_TYPES(image.scalar_type(), "disk_defocus_bwd", [&] {
        const scalar_t soft = scalar_t(softness);
        const Taps<scalar_t> taps(s.K, soft);
        scalar_t *gi = need_image ? grad_image.mutable_data_ptr<scalar_t>() : nullptr;
        scalar_t *gr = need_radius ? grad_radius.mutable_data_ptr<scalar_t>() : nullptr;
        at::parallel_for(0, s.B * s.H, 1, [&](int64_t begin, int64_t end) {
            backward_rows<scalar_t>(grad_out.const_data_ptr<scalar_t>(), image.const_data_ptr<scalar_t>(),
                                    radius.const_data_ptr<scalar_t>(), inverse_depth.const_data_ptr<scalar_t>(),
                                    out.const_data_ptr<scalar_t>(), sum.const_data_ptr<scalar_t>(), gi, gr, s, soft,
                                    occlusion, taps, begin, end);
        });
    });
    std::optional<Tensor> gi_out, gr_out;
    if (need_image) gi_out = grad_image;
    if (need_radius) gr_out = grad_radius;
    return {gi_out, gr_out};
}

}  // namespace gsmsdr_defocus

TORCH_LIBRARY(gsmsdr_defocus, m) {
    m.def(
        "disk_defocus_fwd(Tensor image, Tensor radius, Tensor inverse_depth, int kernel_size, float softness, "
        "bool occlusion) -> (Tensor, Tensor)"
    );
    m.def(
        "disk_defocus_bwd(Tensor grad_out, Tensor image, Tensor radius, Tensor inverse_depth, Tensor out, "
        "Tensor sum, int kernel_size, float softness, bool occlusion, bool need_image, bool need_radius) "
        "-> (Tensor?, Tensor?)"
    );
}

TORCH_LIBRARY_IMPL(gsmsdr_defocus, CPU, m) {
    m.impl("disk_defocus_fwd", &gsmsdr_defocus::disk_defocus_fwd);
    m.impl("disk_defocus_bwd", &gsmsdr_defocus::disk_defocus_bwd);
}
