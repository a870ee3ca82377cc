// CPU tile loop: OpenMP over 16x16 tiles. The per-pair maths is in surfel_math.h.
//
// Each (surfel, tile) pair is handled in two phases:
//   1. eval_rows: alpha (and u, v, z) of the surfel at every pixel of the rows its box covers, a pure float loop
//      that vectorises across pixels (no integer counters or early exits in it);
//   2. a scalar pass over the pixels with alpha > 0 that blends (forward) or back-propagates (backward). The
//      anti-aliased backward stops each pixel at the cotangents of the pair's alpha, depth and colour point and
//      takes them through the footprint in a third, vectorised pass (geom_rows_filtered) that reads the footprint's
//      per-pixel values from phase 1; the plain one does its short geometry pixel by pixel.
// Forward and backward call the same non-inlined eval_rows, so both see bit-identical alphas and agree on which
// pairs contributed. Per-surfel gradients are written per (surfel, tile) pair into a scratch row and summed per
// surfel at the end: no atomics, and the result does not depend on the thread count.
#include <omp.h>

#include <algorithm>
#include <cstring>
#include <vector>

#include "rasterize.h"
#include "surfel_math.h"

namespace sz {

namespace {

template <class S>
struct TileScratch {
    alignas(64) S xs[TILE];
    alignas(64) S alpha[TILE_PIXELS];
    alignas(64) S u[TILE_PIXELS];
    alignas(64) S v[TILE_PIXELS];
    alignas(64) S z[TILE_PIXELS];
    // the anti-aliased backward's per-pixel footprint values (PairEval)
    alignas(64) S ex[TILE_PIXELS], q[TILE_PIXELS], inv[TILE_PIXELS], xu[TILE_PIXELS], xv[TILE_PIXELS];
    alignas(64) S j00[TILE_PIXELS], j01[TILE_PIXELS], j10[TILE_PIXELS], j11[TILE_PIXELS];
    alignas(64) S p00[TILE_PIXELS], p01[TILE_PIXELS], p11[TILE_PIXELS], idet[TILE_PIXELS];
    // the anti-aliased backward's cotangents of each pair's alpha, depth and colour point (PairCotangents; 0 where
    // the pair did not contribute)
    alignas(64) S v_alpha[TILE_PIXELS], v_z[TILE_PIXELS], v_u[TILE_PIXELS], v_v[TILE_PIXELS];
};

// Rows r0..r1 (inclusive, tile-relative) of one surfel: alpha, u, v, z per pixel (KEEP: and the footprint values
// the anti-aliased backward needs). F: the surfel's falloff (with_falloff in surfel_math.h). GAIN: its appearance has
// an opacity gain (Appearance::has_gain), applied in a second loop over the rows (a kind's reads, a texture's, would
// keep the first from vectorising).
template <bool FILTERED, bool KEEP, class F, bool GAIN, class S>
__attribute__((noinline)) void eval_rows_impl(const Settings& settings, const Geom<S>& g, const Appearance<S>& ap,
                                              const S* xs, S y0, int r0, int r1, TileScratch<S>& sc) {
    const Geom<S> gl = g;  // local copies let the compiler keep every field in a register
    const Settings st = settings;
    for (int r = r0; r <= r1; ++r) {
        const S y = y0 + S(r);
        const int o = r * TILE;
#pragma omp simd
        for (int c = 0; c < TILE; ++c) {
            PairEval<S> e;
            if constexpr (FILTERED)
                eval_pair_filtered<F>(st, gl, xs[c], y, e);
            else
                eval_pair<F>(st, gl, xs[c], y, e);
            sc.alpha[o + c] = e.alpha;
            sc.u[o + c] = e.u;
            sc.v[o + c] = e.v;
            sc.z[o + c] = e.z;
            if constexpr (KEEP || GAIN) sc.ex[o + c] = e.ex;
            if constexpr (KEEP) {
                sc.q[o + c] = e.rho;
                sc.inv[o + c] = e.inv;
                sc.xu[o + c] = e.xu;
                sc.xv[o + c] = e.xv;
                sc.j00[o + c] = e.j00;
                sc.j01[o + c] = e.j01;
                sc.j10[o + c] = e.j10;
                sc.j11[o + c] = e.j11;
                sc.p00[o + c] = e.p00;
                sc.p01[o + c] = e.p01;
                sc.p11[o + c] = e.p11;
                sc.idet[o + c] = e.idet;
            }
        }
    }
    if constexpr (GAIN) {  // apply_opacity_gain, on the values kept
        const Appearance<S> al = ap;
        for (int r = r0; r <= r1; ++r) {
            const int o = r * TILE;
#pragma omp simd
            for (int c = 0; c < TILE; ++c) {
                const int p = o + c;
                const S ex = rmul(sc.ex[p], al.gain(sc.u[p], sc.v[p]));
                sc.ex[p] = ex;
                sc.alpha[p] = pair_alpha(st, rmul(gl.o, ex), sc.z[p]);
            }
        }
    }
}

// keep: the backward's call (anti-aliased, it keeps the footprint values).
template <bool GAIN, class S>
void eval_rows_kernel(const Settings& st, const Geom<S>& g, const Appearance<S>& ap, const S* xs, S y0, int r0,
                      int r1, TileScratch<S>& sc, bool keep) {
    with_falloff(g.s, [&](auto falloff) SZ_INLINE_LAMBDA {
        using F = decltype(falloff);
        if (st.pixel_filter > 0 && keep)
            eval_rows_impl<true, true, F, GAIN>(st, g, ap, xs, y0, r0, r1, sc);
        else if (st.pixel_filter > 0)
            eval_rows_impl<true, false, F, GAIN>(st, g, ap, xs, y0, r0, r1, sc);
        else
            eval_rows_impl<false, false, F, GAIN>(st, g, ap, xs, y0, r0, r1, sc);
    });
}
template <class S>
void eval_rows(const Settings& st, const Geom<S>& g, const Appearance<S>& ap, const S* xs, S y0, int r0, int r1,
               TileScratch<S>& sc, bool keep) {
    if (ap.has_gain())
        eval_rows_kernel<true>(st, g, ap, xs, y0, r0, r1, sc, keep);
    else
        eval_rows_kernel<false>(st, g, ap, xs, y0, r0, r1, sc, keep);
}

// The slots geom_backward_filtered writes (a prefix of the row, before the appearance block; G_NORMAL is a slot it
// leaves alone, G_ZC and G_CENTER it sets to 0: the screen filter's, unused when anti-aliased).
constexpr int GEOM_SLOTS = G_APPEARANCE;
constexpr bool filtered_geom_slot(int i) { return i < G_ZC || i == G_O || (i >= G_A && i < G_APPEARANCE); }

// Per-lane slot sums of a vectorised loop over one row's columns: lanes[slot][c] (one vector add per slot).
template <class S>
struct LaneAcc {
    S (*lanes)[TILE];
    int c;
    void operator()(int i, S v) {
        if (filtered_geom_slot(i)) lanes[i][c] += v;
    }
};

// The anti-aliased pairs' geometry over rows r0..r1 of one surfel: geom_backward_filtered at every pixel from the
// values eval_rows kept and the cotangents the scalar pass left (0 where the pair did not contribute), summed per
// slot into t[0, GEOM_SLOTS). Each row is one vectorised loop; the lanes are summed once per call. F: the surfel's
// falloff.
template <class F, class S>
__attribute__((noinline)) void geom_rows_filtered(const Settings& settings, const Geom<S>& g, const S* xs, S y0,
                                                  int r0, int r1, const TileScratch<S>& sc, S* t) {
    const Geom<S> gl = g;
    const Settings st = settings;
    alignas(64) S lanes[GEOM_SLOTS][TILE];
    for (int i = 0; i < GEOM_SLOTS; ++i)
        if (filtered_geom_slot(i))
            for (int c = 0; c < TILE; ++c) lanes[i][c] = S(0);
    for (int r = r0; r <= r1; ++r) {
        const S y = y0 + S(r);
        const int o = r * TILE;
#pragma omp simd
        for (int c = 0; c < TILE; ++c) {
            const int p = o + c;
            // a pair with alpha 0 may keep non-finite values (a ray that grazes the plane, a broken surfel): its
            // cotangents are 0, and so must everything they multiply be
            const bool on = sc.alpha[p] > S(0);
            PairEval<S> e;
            e.dx = on ? radd(xs[c], -gl.cx) : S(0);
            e.dy = on ? radd(y, -gl.cy) : S(0);
            e.inv = on ? sc.inv[p] : S(0);
            e.u = on ? sc.u[p] : S(0);
            e.v = on ? sc.v[p] : S(0);
            e.ex = on ? sc.ex[p] : S(0);
            e.rho = on ? sc.q[p] : S(0);
            e.raw = rmul(gl.o, e.ex);
            e.xu = on ? sc.xu[p] : S(0);
            e.xv = on ? sc.xv[p] : S(0);
            e.j00 = on ? sc.j00[p] : S(0);
            e.j01 = on ? sc.j01[p] : S(0);
            e.j10 = on ? sc.j10[p] : S(0);
            e.j11 = on ? sc.j11[p] : S(0);
            e.p00 = sc.p00[p];  // P and 1 / det are finite at every pixel (S is zeroed where the pair is culled)
            e.p01 = sc.p01[p];
            e.p11 = sc.p11[p];
            e.idet = sc.idet[p];
            LaneAcc<S> acc{lanes, c};
            geom_backward_filtered<F>(st, gl, e, sc.v_alpha[p], sc.v_z[p], sc.v_u[p], sc.v_v[p], acc);
        }
    }
    for (int i = 0; i < GEOM_SLOTS; ++i) {
        S sum = S(0);
        if (filtered_geom_slot(i))
            for (int c = 0; c < TILE; ++c) sum += lanes[i][c];
        t[i] = sum;  // 0 for the slots it does not write
    }
}

struct TileRect {
    int x0, y0, w, h;
};

inline TileRect tile_rect(int t, int W, int H) {
    int tx = t % tiles_x(W), ty = t / tiles_x(W);
    TileRect r{tx * TILE, ty * TILE, 0, 0};
    r.w = std::min(TILE, W - r.x0);
    r.h = std::min(TILE, H - r.y0);
    return r;
}

// The surfel's box clipped to the tile, tile-relative; false if empty.
inline bool clip_box(const int* b, const TileRect& tr, int& c0, int& c1, int& r0, int& r1) {
    c0 = std::max(b[0] - tr.x0, 0);
    c1 = std::min(b[1] - tr.x0, tr.w - 1);
    r0 = std::max(b[2] - tr.y0, 0);
    r1 = std::min(b[3] - tr.y0, tr.h - 1);
    return c0 <= c1 && r0 <= r1;
}

// gradient rows up to this width live on the stack (every wave count up to the sin/cos cache, textures up to 8x8)
constexpr int LOCAL_GW = grad_width(SINCOS_CACHE, 8);

template <class S>
struct RowAcc {
    S* g;
    void operator()(int i, S v) { g[i] += v; }
    void scatter(int i, S v) { g[i] += v; }
};

// Runs pass(acc) with acc summing into a zeroed slot row of width GW that ends up in row. Rows up to LOCAL_GW wide
// are accumulated on the stack, where the compiler knows they alias nothing.
template <class S, class Pass>
SZ_HD void with_row_acc(S* row, int GW, Pass&& pass) {
    if (GW <= LOCAL_GW) {
        alignas(64) S local[LOCAL_GW];
        std::memset(local, 0, sizeof(S) * GW);
        RowAcc<S> acc{local};
        pass(acc);
        std::memcpy(row, local, sizeof(S) * GW);
    } else {
        std::memset(row, 0, sizeof(S) * GW);
        RowAcc<S> acc{row};
        pass(acc);
    }
}

// One (surfel, tile) pair of the backward: the surfel, its clipped box (rows r0..r1, columns c0..c1, tile-relative),
// its position in the tile's list and what eval_rows left in the scratch.
template <class S>
struct PairPass {
    const Settings& st;
    const Geom<S>& g;
    const S* normal;
    const Appearance<S>& ap;  // as the pixels see it (anti-aliased: folded, Appearance::fold)
    int r0, r1, c0, c1, rel;
    S y0;
};

// The backward of one (surfel, tile) pair, back to front over the pixels that contributed: the colour part, then
// the pair's geometry pixel by pixel (plain) or, anti-aliased, for all pixels at once (geom_rows_filtered, whose
// chain through the footprint vectorises). Each path is its own instantiation, flattened: GCC otherwise keeps the
// wave loop's body, inlined in two places, out of line.
template <bool FILTERED, class S>
__attribute__((noinline, flatten)) void backward_pixels(const PairPass<S>& q, TileScratch<S>& sc, PixelBwd<S>* px,
                                                        S* row, int GW) {
    with_row_acc(row, GW, [&](RowAcc<S>& acc) {
        if constexpr (FILTERED)
            for (int p = q.r0 * TILE; p < (q.r1 + 1) * TILE; ++p)
                sc.v_alpha[p] = sc.v_z[p] = sc.v_u[p] = sc.v_v[p] = S(0);
        for (int r = q.r0; r <= q.r1; ++r)
            for (int c = q.c0; c <= q.c1; ++c) {
                const int p = r * TILE + c;
                const S a = sc.alpha[p];
                if (a == S(0) || q.rel >= px[p].last) continue;
                PairEval<S> e;
                if constexpr (!FILTERED) {
                    eval_pair_any(q.st, q.g, sc.xs[c], q.y0 + S(r), e);  // its hit or the filter
                    if (q.ap.has_gain()) apply_opacity_gain(q.st, q.g, q.ap.gain(e.u, e.v), e);
                } else {
                    e.raw = rmul(q.g.o, sc.ex[p]);  // o f g, as geom_rows_filtered takes it
                }
                // the decision and the values blended come from eval_rows, as in the forward
                e.alpha = a;
                e.u = sc.u[p];
                e.v = sc.v[p];
                e.z = sc.z[p];
                // anti-aliased, the appearance is folded: no blur here, and its slots are unfolded below
                const PairCotangents<S> v = blend_backward_colour(q.st, px[p], e, q.normal, q.ap, q.rel, acc,
                                                                  static_cast<const S*>(nullptr));
                if constexpr (FILTERED) {
                    sc.v_alpha[p] = v.alpha;
                    sc.v_z[p] = v.z;
                    sc.v_u[p] = v.u;
                    sc.v_v[p] = v.v;
                } else {
                    with_falloff(q.g.s, [&](auto falloff) SZ_INLINE_LAMBDA {
                        geom_backward<decltype(falloff)>(q.st, q.g, e, v.alpha, v.z, v.u, v.v, acc);
                    });
                }
            }
        if constexpr (FILTERED) {
            alignas(64) S t[GEOM_SLOTS];
            with_falloff(q.g.s, [&](auto falloff) SZ_INLINE_LAMBDA {
                geom_rows_filtered<decltype(falloff)>(q.st, q.g, sc.xs, q.y0, q.r0, q.r1, sc, t);
            });
            for (int j = 0; j < GEOM_SLOTS; ++j)
                if (filtered_geom_slot(j)) acc(j, t[j]);
            q.ap.unfold(acc.g);
        }
    });
}

}  // namespace

template <class S>
int64_t cpu_prepare(const SurfelArgs<S>& s, S* geom, int* bounds, int64_t* surfel_off, int threads) {
    const int M = s.M;
#pragma omp parallel for num_threads(threads) schedule(static)
    for (int r = 0; r < M; ++r) {
        const int64_t i = s.order[r];
        Geom<S>& g = *reinterpret_cast<Geom<S>*>(geom + GEOM * i);
        prepare_geom(s.st, s.T + 9 * i, s.center + 2 * i, s.depth[i], s.opacities[i], s.falloff[i], g);
        prepare_appearance(s, g, i);
        box_pixels(s.boxes + 4 * i, s.W, s.H, bounds + 4 * i);
    }
    surfel_off[0] = 0;
    for (int r = 0; r < M; ++r) surfel_off[r + 1] = surfel_off[r] + tile_range(bounds + 4 * int64_t(s.order[r])).count();
    return surfel_off[M];
}

void cpu_bin(int M, int W, int H, const int* order, const int* bounds, const int64_t* surfel_off, int* tile_start,
             int* tile_list, int* pair_pos) {
    const int ntx = tiles_x(W), nt = ntx * tiles_y(H);
    std::vector<int> count(nt + 1, 0);
    for (int k = 0; k < M; ++k) {
        const TileRange r = tile_range(bounds + 4 * int64_t(order[k]));
        for (int ty = r.y0; ty <= r.y1; ++ty)
            for (int tx = r.x0; tx <= r.x1; ++tx) ++count[ty * ntx + tx];
    }
    tile_start[0] = 0;
    for (int t = 0; t < nt; ++t) tile_start[t + 1] = tile_start[t] + count[t];
    std::vector<int> cursor(tile_start, tile_start + nt);
    // surfels by depth rank = front to back, so every tile list comes out in depth order
    for (int rank = 0; rank < M; ++rank) {
        const int i = order[rank];
        const TileRange r = tile_range(bounds + 4 * int64_t(i));
        int64_t k = surfel_off[rank];
        for (int ty = r.y0; ty <= r.y1; ++ty)
            for (int tx = r.x0; tx <= r.x1; ++tx) {
                int pos = cursor[ty * ntx + tx]++;
                tile_list[pos] = i;
                pair_pos[k++] = pos;
            }
    }
}

template <bool IMAGE_ONLY, class S>
void cpu_forward_impl(const SurfelArgs<S>& s, const FrameArgs<S>& f, int threads) {
    const int W = s.W, H = s.H;
    const int nt = tiles_x(W) * tiles_y(H);
    const Geom<S>* geom = reinterpret_cast<const Geom<S>*>(f.geom);
    const bool filtered = s.st.pixel_filter > 0;
#pragma omp parallel num_threads(threads)
    {
        TileScratch<S> sc;
        std::vector<PixelFwd<S>> px(TILE_PIXELS);
        // anti-aliased: what the surfel's appearance folds (Appearance::fold)
        std::vector<S> fold_values(std::max(Appearance<S>::fold_values(s.K), 1));
        std::vector<S> fold_factors(std::max(Appearance<S>::fold_factors(s.K), 1));
#pragma omp for schedule(dynamic, 1)
        for (int t = 0; t < nt; ++t) {
            const TileRect tr = tile_rect(t, W, H);
            for (int c = 0; c < TILE; ++c) sc.xs[c] = S(tr.x0 + c) + S(0.5);
            int active = 0;
            for (int p = 0; p < TILE_PIXELS; ++p) {
                bool inside = (p % TILE) < tr.w && (p / TILE) < tr.h;
                pixel_init(px[p], !inside);
                active += inside;
            }
            const int start = f.tile_start[t], end = f.tile_start[t + 1];
            const S y0 = S(tr.y0) + S(0.5);
            for (int pos = start; pos < end && active > 0; ++pos) {
                const int i = f.tile_list[pos];
                int c0, c1, r0, r1;
                if (!clip_box(f.bounds + 4 * i, tr, c0, c1, r0, r1)) continue;
                Appearance<S> ap = surfel_appearance(s, i);
                eval_rows(s.st, geom[i], ap, sc.xs, y0, r0, r1, sc, false);
                if (filtered) ap.fold(geom[i], fold_values.data(), fold_factors.data());
                const S* normal = s.normal + 3 * int64_t(i);
                const int rel = pos - start;
                for (int r = r0; r <= r1; ++r)
                    for (int c = c0; c <= c1; ++c) {
                        const int p = r * TILE + c;
                        const S a = sc.alpha[p];
                        if (a == S(0) || px[p].done) continue;
                        S col[3], pre[3];
                        ap.colour(sc.u[p], sc.v[p], col, pre);
                        blend_forward<IMAGE_ONLY>(s.st, px[p], a, sc.z[p], col, normal, rel);
                        active -= px[p].done;
                    }
            }
            for (int r = 0; r < tr.h; ++r)
                for (int c = 0; c < tr.w; ++c) store_pixel(f, int64_t(tr.y0 + r) * W + tr.x0 + c, px[r * TILE + c]);
        }
    }
}

template <class S>
void cpu_forward(const SurfelArgs<S>& s, const FrameArgs<S>& f, int threads) {
    if (f.image_only)
        cpu_forward_impl<true>(s, f, threads);
    else
        cpu_forward_impl<false>(s, f, threads);
}

template <class S>
void cpu_backward(const SurfelArgs<S>& s, const FrameArgs<S>& f, const GradArgs<S>& g, const int64_t* surfel_off,
                  const int* pair_pos, S* partials, int threads) {
    const int W = s.W, H = s.H, K = s.K, M = s.M;
    const int GW = grad_width(K, s.TS);
    const int nt = tiles_x(W) * tiles_y(H);
    const Geom<S>* geom = reinterpret_cast<const Geom<S>*>(f.geom);
    const bool filtered = s.st.pixel_filter > 0;
#pragma omp parallel num_threads(threads)
    {
        TileScratch<S> sc;
        std::vector<PixelBwd<S>> px(TILE_PIXELS);
        // anti-aliased: what the surfel's appearance folds (Appearance::fold)
        std::vector<S> fold_values(std::max(Appearance<S>::fold_values(K), 1));
        std::vector<S> fold_factors(std::max(Appearance<S>::fold_factors(K), 1));
#pragma omp for schedule(dynamic, 1)
        for (int t = 0; t < nt; ++t) {
            const TileRect tr = tile_rect(t, W, H);
            for (int c = 0; c < TILE; ++c) sc.xs[c] = S(tr.x0 + c) + S(0.5);
            const int start = f.tile_start[t], end = f.tile_start[t + 1];
            int maxlast = 0;
            for (int p = 0; p < TILE_PIXELS; ++p) {
                const int r = p / TILE, c = p % TILE;
                if (r >= tr.h || c >= tr.w) {
                    px[p].last = 0;
                    continue;
                }
                load_pixel_bwd(px[p], f, g, int64_t(tr.y0 + r) * W + tr.x0 + c);
                maxlast = std::max(maxlast, px[p].last);
            }
            // pairs behind every pixel's last contribution get no gradient
            if (start + maxlast < end)
                std::memset(partials + int64_t(start + maxlast) * GW, 0, sizeof(S) * int64_t(end - start - maxlast) * GW);
            const S y0 = S(tr.y0) + S(0.5);
            for (int pos = start + maxlast - 1; pos >= start; --pos) {
                const int i = f.tile_list[pos];
                S* row = partials + int64_t(pos) * GW;
                int c0, c1, r0, r1;
                if (!clip_box(f.bounds + 4 * i, tr, c0, c1, r0, r1)) {
                    std::memset(row, 0, sizeof(S) * GW);
                    continue;
                }
                const Geom<S>& gm = geom[i];
                Appearance<S> ap = surfel_appearance(s, i);
                eval_rows(s.st, gm, ap, sc.xs, y0, r0, r1, sc, true);
                if (filtered) ap.fold(gm, fold_values.data(), fold_factors.data());
                const int rel = pos - start;
                const PairPass<S> q{s.st, gm, s.normal + 3 * int64_t(i), ap, r0, r1, c0, c1, rel, y0};
                if (filtered)
                    backward_pixels<true>(q, sc, px.data(), row, GW);
                else
                    backward_pixels<false>(q, sc, px.data(), row, GW);
            }
        }
        // sum each surfel's pair rows (CSR by depth rank), then map the slots to input gradients
        std::vector<double> sum(GW);
#pragma omp for schedule(dynamic, 64)
        for (int r = 0; r < M; ++r) {
            std::fill(sum.begin(), sum.end(), 0.0);
            for (int64_t k = surfel_off[r]; k < surfel_off[r + 1]; ++k) {
                const S* row = partials + int64_t(pair_pos[k]) * GW;
                for (int j = 0; j < GW; ++j) sum[j] += double(row[j]);
            }
            finalize_surfel(s, g, s.order[r], sum.data());
        }
    }
}

template <class S>
void cpu_project(const ProjectArgs<S>& a, int threads) {
#pragma omp parallel for schedule(static) num_threads(threads) if (a.N > 4096)
    for (int64_t i = 0; i < a.N; ++i)
        a.visible[i] = project_surfel(a.st, a.cam, a.means + 3 * i, a.quats + 4 * i, a.scales + 2 * i, a.opac[i], a.falloff[i],
                                      a.T + 9 * i, a.center + 2 * i, a.depth + i, a.normal + 3 * i, a.boxes + 4 * i);
}

template <class S>
void cpu_project_backward(const ProjectGradArgs<S>& a, int threads) {
#pragma omp parallel for schedule(static) num_threads(threads) if (a.N > 4096)
    for (int64_t i = 0; i < a.N; ++i)
        project_backward(a.cam, a.means + 3 * i, a.quats + 4 * i, a.scales + 2 * i, a.v_T + 9 * i, a.v_center + 2 * i,
                         a.v_depth[i], a.v_normal + 3 * i, a.v_means + 3 * i, a.v_quats + 4 * i, a.v_scales + 2 * i);
}

#define SZ_INSTANTIATE(S)                                                                                           \
    template int64_t cpu_prepare<S>(const SurfelArgs<S>&, S*, int*, int64_t*, int);                                 \
    template void cpu_forward<S>(const SurfelArgs<S>&, const FrameArgs<S>&, int);                                  \
    template void cpu_backward<S>(const SurfelArgs<S>&, const FrameArgs<S>&, const GradArgs<S>&, const int64_t*,   \
                                  const int*, S*, int);                                                            \
    template void cpu_project<S>(const ProjectArgs<S>&, int);                                                       \
    template void cpu_project_backward<S>(const ProjectGradArgs<S>&, int);
SZ_INSTANTIATE(float)
SZ_INSTANTIATE(double)

}  // namespace sz
