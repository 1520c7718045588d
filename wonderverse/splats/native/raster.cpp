// The CPU rasteriser's inner loops, beside their vectorised torch versions in `render_torch`:
// - candidate pairs: each tile's depth-sorted list read pixel by pixel into (Gaussian, pixel) pairs
//   (`_candidate_pairs`: the same float64 chords, so the same pairs in the same order);
// - front-to-back compositing of those pairs and its analytic backward (`_Composite`), one pixel ("run") at a
//   time, as gsplat's CUDA kernel does one pixel per thread.
// The torch versions spend most of their time gathering and scattering pair-sized tensors; here every pair is
// touched in registers.
//
// Layout (all contiguous): per Gaussian mx, my (means2d), nha, nb, nhc (-a/2, -b, -c/2 of the conic), op
// (opacity), feat (N x F); per pair gid (int32); per run crow (S + 1, int32: run r's pairs are
// [crow[r], crow[r+1])), cx, cy (pixel centre). Runs are split among threads by pairs; each thread scatters its
// Gaussians' gradients into its own buffer, summed in thread order, so a result depends only on the thread count.
//
// Built by `native_raster.py` with -ffp-contract=off (no fused multiply-add: the same sums as the torch code).

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <thread>
#include <vector>

namespace {

constexpr double kAlphaThreshold = 1.0 / 255.0;
constexpr double kAlphaMax = 0.999;
constexpr double kTransmittanceMin = 1e-4;

template <typename R>
struct Gaussians {
    const R *mx, *my, *nha, *nb, *nhc, *op, *feat;
    int64_t n_feat;
};

template <typename R>
struct Pairs {
    const int32_t* gid;
    const int32_t* crow;
    const R *cx, *cy;
};

// One pair's alpha: false when it is skipped (alpha below 1/255 or a negative quadratic form).
template <typename R>
inline bool pair_alpha(const Gaussians<R>& gs, int32_t g, R cx, R cy, R& dx, R& dy, R& e, R& raw, R& alpha) {
    dx = gs.mx[g] - cx;
    dy = gs.my[g] - cy;
    R neg_sigma = gs.nha[g] * dx * dx;
    neg_sigma += gs.nhc[g] * dy * dy;
    neg_sigma += gs.nb[g] * dx * dy;
    if (!(neg_sigma <= R(0))) return false;
    e = std::exp(neg_sigma);
    raw = gs.op[g] * e;
    alpha = raw < R(kAlphaMax) ? raw : R(kAlphaMax);
    return alpha >= R(kAlphaThreshold);
}

template <typename Fn>
void parallel_runs(const int32_t* crow, int64_t n_runs, int n_threads, Fn fn) {
    if (n_threads <= 1 || n_runs < 2) {
        fn(0, int64_t(0), n_runs);
        return;
    }
    // Split by pairs (the work), on run boundaries.
    std::vector<int64_t> bounds(n_threads + 1, n_runs);
    bounds[0] = 0;
    const double total = double(crow[n_runs]);
    int64_t r = 0;
    for (int t = 1; t < n_threads; ++t) {
        const double target = total * t / n_threads;
        while (r < n_runs && double(crow[r]) < target) ++r;
        bounds[t] = r;
    }
    std::vector<std::thread> workers;
    for (int t = 1; t < n_threads; ++t) workers.emplace_back(fn, t, bounds[t], bounds[t + 1]);
    fn(0, bounds[0], bounds[1]);
    for (auto& w : workers) w.join();
}

template <typename R>
int64_t forward(const Gaussians<R>& gs, const Pairs<R>& ps, int64_t n_runs, R* acc, R* t_final, int n_threads) {
    const int64_t F = gs.n_feat;
    std::vector<int64_t> drawn(n_threads, 0);
    parallel_runs(ps.crow, n_runs, n_threads, [&](int t, int64_t r0, int64_t r1) {
        std::vector<double> sum(F);
        int64_t n_drawn = 0;
        for (int64_t r = r0; r < r1; ++r) {
            std::fill(sum.begin(), sum.end(), 0.0);
            double T = 1.0;
            for (int32_t p = ps.crow[r]; p < ps.crow[r + 1]; ++p) {
                const int32_t g = ps.gid[p];
                R dx, dy, e, raw, alpha;
                if (!pair_alpha(gs, g, ps.cx[r], ps.cy[r], dx, dy, e, raw, alpha)) continue;
                const double next_T = T * (1.0 - double(alpha));
                if (next_T <= kTransmittanceMin) break;  // gsplat's rule: this pair is not drawn, the pixel ends
                const double w = double(alpha) * T;
                const R* f = gs.feat + int64_t(g) * F;
                for (int64_t k = 0; k < F; ++k) sum[k] += w * double(f[k]);
                T = next_T;
                ++n_drawn;
            }
            for (int64_t k = 0; k < F; ++k) acc[r * F + k] = R(sum[k]);
            t_final[r] = R(T);
        }
        drawn[t] = n_drawn;
    });
    int64_t total = 0;
    for (int64_t d : drawn) total += d;
    return total;
}

// One drawn pair, as the backward needs it.
template <typename R>
struct Drawn {
    int32_t g;
    R dx, dy, e, raw, alpha;
    double T, w, fg;
};

// grad (n_threads x N x (F + 6)) receives, per Gaussian, dL/dfeat (F), dL/dopacity and the sums of g_sigma times
// dx, dy, dx^2, dx dy, dy^2 (from which the caller forms the means2d and conic gradients); thread t writes block t.
template <typename R>
void backward(const Gaussians<R>& gs, const Pairs<R>& ps, int64_t n_runs, int64_t n_gauss, const R* g_acc,
              const R* g_tf_t, R* grad, int n_threads) {
    const int64_t F = gs.n_feat;
    const int64_t stride = F + 6;
    parallel_runs(ps.crow, n_runs, n_threads, [&](int t, int64_t r0, int64_t r1) {
        R* out = grad + int64_t(t) * n_gauss * stride;
        std::vector<Drawn<R>> run;
        for (int64_t r = r0; r < r1; ++r) {
            const R* G = g_acc + r * F;
            run.clear();
            double T = 1.0;
            double total = double(g_tf_t[r]);  // Σ_j w_j (f_j . G) + g_T T_final
            for (int32_t p = ps.crow[r]; p < ps.crow[r + 1]; ++p) {
                Drawn<R> d;
                d.g = ps.gid[p];
                if (!pair_alpha(gs, d.g, ps.cx[r], ps.cy[r], d.dx, d.dy, d.e, d.raw, d.alpha)) continue;
                const double next_T = T * (1.0 - double(d.alpha));
                if (next_T <= kTransmittanceMin) break;
                d.T = T;
                d.w = double(d.alpha) * T;
                const R* f = gs.feat + int64_t(d.g) * F;
                double fg = 0.0;
                for (int64_t k = 0; k < F; ++k) fg += double(f[k]) * double(G[k]);
                d.fg = fg;
                total += d.w * fg;
                run.push_back(d);
                T = next_T;
            }
            double prefix = 0.0;
            for (const Drawn<R>& d : run) {
                R* o = out + int64_t(d.g) * stride;
                for (int64_t k = 0; k < F; ++k) o[k] += R(d.w * double(G[k]));
                prefix += d.w * d.fg;
                if (!(d.raw <= R(kAlphaMax))) continue;  // alpha clamped: no gradient through it
                const double suffix = total - prefix;  // Σ_{j>i} w_j (f_j . G) + g_T T_final
                const double g_raw = d.T * d.fg - suffix / (1.0 - double(d.alpha));
                o[F] += R(double(d.e) * g_raw);
                const double g_sigma = -g_raw * double(d.raw);
                const double gx = g_sigma * double(d.dx), gy = g_sigma * double(d.dy);
                o[F + 1] += R(gx);
                o[F + 2] += R(gy);
                o[F + 3] += R(gx * double(d.dx));
                o[F + 4] += R(gx * double(d.dy));
                o[F + 5] += R(gy * double(d.dy));
            }
        }
    });
}


// The chord of an entry's alpha >= 1/255 ellipse (widened for float32 rounding) on each of its tile's rows, as
// `render_torch._candidate_pairs` computes it; lo > hi where the row has none.
template <typename R>
void chords(const R* means2d, const R* conics, const R* opacities, int32_t g, int64_t tile, int ts, int64_t tiles_x,
            int64_t width, int64_t height, int32_t* lo, int32_t* hi) {
    const double x0 = double(tile % tiles_x * ts), y0 = double(tile / tiles_x * ts);
    double a = conics[3 * g], b = conics[3 * g + 1], c = conics[3 * g + 2];
    double ux = double(means2d[2 * g]) - x0 - 0.5, uy = double(means2d[2 * g + 1]) - y0 - 0.5;
    const double thr = std::log(double(opacities[g]) / kAlphaThreshold);
    const double dxm = std::max(std::fabs(ux), std::fabs(ux - (ts - 1)));
    const double dym = std::max(std::fabs(uy), std::fabs(uy - (ts - 1)));
    const double bound = 0.5 * std::fabs(a) * dxm * dxm + 0.5 * std::fabs(c) * dym * dym + std::fabs(b) * dxm * dym;
    double two_a_thr = 2.0 * a * (thr + 1e-4 + 1e-5 * bound);
    double det = a * c - b * b;
    double inv_a = 1.0, slope = 0.0;
    const bool ok = a > 0 && std::isfinite(two_a_thr) && std::isfinite(det) && std::isfinite(ux) && std::isfinite(uy);
    if (ok) {
        inv_a = 1.0 / a;
        slope = b * inv_a;
    } else {  // a degenerate conic: every pixel of the tile is a candidate
        det = 0.0;
        two_a_thr = double(ts * ts);
        ux = 0.5 * (ts - 1);
        uy = 0.0;
    }
    const double x_last = std::min(double(width - 1) - x0, double(ts - 1));
    for (int r = 0; r < ts; ++r) {
        const double dy = uy - r;
        const double half = std::sqrt(std::max(two_a_thr - det * dy * dy, 1e-300)) * inv_a;
        const double mid = ux + slope * dy;
        const double hi_cap = r < double(height) - y0 ? x_last : -1.0;
        const double l = std::max(std::ceil(mid - half), 0.0), h = std::min(std::floor(mid + half), hi_cap);
        const bool live = l <= h;  // false for NaN too
        lo[r] = live ? int32_t(l) : 1;
        hi[r] = live ? int32_t(std::min(h, double(ts - 1))) : 0;
    }
}

// Candidate pairs of the entries (gid, sorted by tile then depth; tile_start (n_tiles + 1) the tiles' ranges).
// With out_gid null, counts[t] = (pairs, runs) of tile t; otherwise fills the pairs at the offsets `counts` then
// holds (exclusive prefix sums): out_gid (pairs), out_crow (run ends: run k's pairs end at out_crow[k]) and
// out_pixel (v * width + u) of each run. Runs go tile by tile, row by row, column by column.
template <typename R>
void candidates(const R* means2d, const R* conics, const R* opacities, const int32_t* gid, const int32_t* tile_start,
                int64_t n_tiles, int ts, int64_t tiles_x, int64_t width, int64_t height, int64_t* counts,
                int32_t* out_gid, int32_t* out_crow, int64_t* out_pixel, int n_threads) {
    parallel_runs(tile_start, n_tiles, n_threads, [&](int, int64_t t0, int64_t t1) {
        std::vector<int32_t> lo, hi;
        std::vector<std::vector<int32_t>> column(ts);  // a row's entries at each pixel column, front to back
        for (int64_t t = t0; t < t1; ++t) {
            const int32_t e0 = tile_start[t], n = tile_start[t + 1] - e0;
            lo.resize(size_t(n) * ts);
            hi.resize(size_t(n) * ts);
            for (int32_t i = 0; i < n; ++i)
                chords(means2d, conics, opacities, gid[e0 + i], t, ts, tiles_x, width, height, &lo[size_t(i) * ts],
                       &hi[size_t(i) * ts]);
            int64_t pairs = out_gid ? counts[2 * t] : 0, runs = out_gid ? counts[2 * t + 1] : 0;
            const int64_t x0 = t % tiles_x * ts, y0 = t / tiles_x * ts;
            for (int r = 0; r < ts; ++r) {
                for (auto& c : column) c.clear();
                for (int32_t i = 0; i < n; ++i)
                    for (int32_t x = lo[size_t(i) * ts + r]; x <= hi[size_t(i) * ts + r]; ++x)
                        column[x].push_back(gid[e0 + i]);
                for (int x = 0; x < ts; ++x) {
                    if (column[x].empty()) continue;
                    if (out_gid) {
                        std::copy(column[x].begin(), column[x].end(), out_gid + pairs);
                        out_crow[runs] = int32_t(pairs + int64_t(column[x].size()));
                        out_pixel[runs] = (y0 + r) * width + x0 + x;
                    }
                    pairs += int64_t(column[x].size());
                    ++runs;
                }
            }
            if (!out_gid) {
                counts[2 * t] = pairs;
                counts[2 * t + 1] = runs;
            }
        }
    });
}

}  // namespace

#define WV_EXPORTS(R, SUFFIX)                                                                                     \
    extern "C" int64_t wv_composite_forward_##SUFFIX(const R* mx, const R* my, const R* nha, const R* nb,          \
                                                     const R* nhc, const R* op, const R* feat, int64_t n_feat,    \
                                                     const int32_t* gid, const int32_t* crow, const R* cx,        \
                                                     const R* cy, int64_t n_runs, R* acc, R* t_final,             \
                                                     int n_threads) {                                             \
        return forward<R>({mx, my, nha, nb, nhc, op, feat, n_feat}, {gid, crow, cx, cy}, n_runs, acc, t_final,   \
                          n_threads);                                                                             \
    }                                                                                                             \
    extern "C" void wv_composite_backward_##SUFFIX(const R* mx, const R* my, const R* nha, const R* nb,            \
                                                   const R* nhc, const R* op, const R* feat, int64_t n_feat,      \
                                                   const int32_t* gid, const int32_t* crow, const R* cx,          \
                                                   const R* cy, int64_t n_runs, int64_t n_gauss, const R* g_acc,  \
                                                   const R* g_tf_t, R* grad, int n_threads) {                     \
        backward<R>({mx, my, nha, nb, nhc, op, feat, n_feat}, {gid, crow, cx, cy}, n_runs, n_gauss, g_acc, g_tf_t, \
                    grad, n_threads);                                                                             \
    }                                                                                                             \
    extern "C" void wv_candidates_##SUFFIX(const R* means2d, const R* conics, const R* opacities,                  \
                                           const int32_t* gid, const int32_t* tile_start, int64_t n_tiles, int ts, \
                                           int64_t tiles_x, int64_t width, int64_t height, int64_t* counts,       \
                                           int32_t* out_gid, int32_t* out_crow, int64_t* out_pixel,               \
                                           int n_threads) {                                                      \
        candidates<R>(means2d, conics, opacities, gid, tile_start, n_tiles, ts, tiles_x, width, height, counts,  \
                      out_gid, out_crow, out_pixel, n_threads);                                                   \
    }

WV_EXPORTS(float, f32)
WV_EXPORTS(double, f64)
