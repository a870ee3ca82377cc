// Raw-pointer interface between the torch bindings (ext.cpp) and the tile rasterizers: the C++ loops
// (rasterize_cpu.cpp) and the CUDA kernels (rasterize_cuda.cu, compiled by nvcc into namespace sz::gpu and, for the
// host emulation that runs them without a GPU, into sz::emu). Free of torch headers so the loops compile fast and
// nvcc needs no torch.
//
// One pipeline on every device: project every surfel (project_surfel), sort the visible ones front to back by
// centre depth (`order`, in ext.cpp), prepare their pixel geometry and count their tiles, bin (tile, surfel) pairs
// tile-major in depth order, run the tile loop; the backward runs the tile loop back to front, sums each surfel's
// slot row and maps it to input gradients (finalize_grads), then back through the projection. Per-surfel arrays
// stay in input order (no gathers): the order and the tile lists hold surfel indices.
// Shapes: N surfels in, M visible, K waves, TS texels a side (0: no texture), image H x W, P (tile, surfel) pairs.
#pragma once

#include <cstdint>

#include "surfel_fields.h"
#include "surfel_math.h"

namespace sz {

// Per-surfel projection for one camera: inputs [N,...], outputs [N,...] (see project_surfel).
template <class S>
struct ProjectArgs {
    Settings st;
    CameraArgs<S> cam;
    int64_t N;
    const S *means, *quats, *scales, *opac, *falloff;
    S *T, *center, *depth, *normal, *boxes;
    bool* visible;
};

// Its backward: cotangents of T, centre, depth, normal -> v_means, v_quats, v_scales.
template <class S>
struct ProjectGradArgs {
    Settings st;
    CameraArgs<S> cam;
    int64_t N;
    const S *means, *quats, *scales;
    const S *v_T, *v_center, *v_depth, *v_normal;
    S *v_means, *v_quats, *v_scales;
};

// The surfels with their projection, in input order; order[0..M) lists the visible ones front to back (stable in
// the index), which is the order of every tile's list.
template <class S>
struct SurfelArgs {
    Settings st;
    int N, M, K, TS, W, H;
    const int* order;  // [M] visible surfel indices, front to back
    const S* T;        // [N,3,3] rows m1, m2, m3
    const S* center;   // [N,2] projected centre (pixels)
    const S* depth;    // [N] camera depth of the centre
    const S* normal;   // [N,3] world normal facing the camera
    const S* boxes;    // [N,4] exact screen box (xmin, ymin, xmax, ymax)
    // the fields read per pair, by their table names (surfel_fields.h): opacities [N], base_color [N,3],
    // wave_vectors [N,K,2], wave_phases [N,K], wave_amplitudes [N,K,3], falloff [N], texture [N,TS,TS,4]
#define SZ_FIELD_POINTER(name) const S* name;
    SZ_PAIR_FIELDS(SZ_FIELD_POINTER)
#undef SZ_FIELD_POINTER
    // [N,prepared_width] the appearance's per-surfel set-up (Appearance::prepare: anti-aliased, the prefiltered
    // textures), written by the prepare step for the visible surfels; nullptr where prepared_width is 0
    S* prepared;
    int prepared_width;
    // [N] waves in use per surfel (its first wcount[i] of K), or nullptr for all K. The tile loops run the wave
    // loops to k < wcount[i], so removed waves cost nothing; the row stride stays K.
    const int* wcount;
};

template <class S>
struct FrameArgs {
    S* geom;                // [N,GEOM] per-surfel pixel geometry (prepare_geom; visible surfels only)
    int* bounds;            // [N,4] pixel range x0, x1, y0, y1 (inclusive; visible surfels only)
    const int* tile_start;  // [tiles+1] tile t's surfels are tile_list[tile_start[t] .. tile_start[t+1])
    const int* tile_list;   // [P] surfel index per (tile, surfel) pair, tile-major, depth order within a tile
    // outputs [H,W(,3)]
    S *rgb, *alpha, *depth, *median, *normal, *dist;
    // saved for the backward [H,W(,3)]
    S* T_final;
    S* totals;          // [H,W,3] sum w, sum w m, sum w m^2
    int* last;          // 1 + tile-list position (relative to the tile start) of the last blended contribution
    int* median_index;  // relative tile-list position of the median contribution, -1 if none
    // a render to look at: rgb and alpha only; the other outputs and the saved state are not written (nullptr)
    bool image_only;
};

template <class S>
struct GradArgs {
    // cotangents of the outputs [H,W(,3)] (contiguous, zeros where an output was unused)
    const S *v_rgb, *v_alpha, *v_depth, *v_median, *v_normal, *v_dist;
    // gradients of the per-surfel inputs, same shapes as in SurfelArgs (written for visible surfels only): the
    // projection's outputs, then v_<name> for every per-pair field
    S *v_T, *v_center, *v_depth_c, *v_normal_c;
#define SZ_FIELD_GRADIENT(name) S* v_##name;
    SZ_PAIR_FIELDS(SZ_FIELD_GRADIENT)
#undef SZ_FIELD_GRADIENT
};

inline int tiles_x(int W) { return (W + TILE - 1) / TILE; }
inline int tiles_y(int H) { return (H + TILE - 1) / TILE; }

// ---- shared by the CPU loops and the CUDA kernels ----
// Surfel i's appearance as its pairs see it: its rows of the kinds' fields, the waves it uses, its prepared row
// (anti-aliased: the prefiltered texture). Appearance::bind, for SurfelArgs.
template <class S>
SZ_HD Appearance<S> surfel_appearance(const SurfelArgs<S>& s, int64_t i) {
    return Appearance<S>::bind(s, i);
}

// The per-surfel appearance set-up of a prepare step (visible surfel i, its Geom done).
template <class S>
SZ_HD void prepare_appearance(const SurfelArgs<S>& s, const Geom<S>& g, int64_t i) {
    Appearance<S>::prepare(s, g.blur, i);
}

// A pixel's finished forward state -> the outputs and the state the backward reads, at pixel index o.
template <class S>
SZ_HD void store_pixel(const FrameArgs<S>& f, int64_t o, const PixelFwd<S>& q) {
    const S acc = S(1) - q.T;
    if (f.image_only) {
        for (int k = 0; k < 3; ++k) f.rgb[3 * o + k] = q.rgb[k];
        f.alpha[o] = acc;
        return;
    }
    for (int k = 0; k < 3; ++k) {
        f.rgb[3 * o + k] = q.rgb[k];
        f.normal[3 * o + k] = q.N[k];
    }
    f.alpha[o] = acc;
    f.depth[o] = acc > S(0) ? q.D / acc : S(0);
    f.median[o] = q.med >= 0 ? q.median : S(0);
    f.dist[o] = q.dist;
    f.T_final[o] = q.T;
    f.totals[3 * o] = q.A;
    f.totals[3 * o + 1] = q.M1;
    f.totals[3 * o + 2] = q.M2;
    f.last[o] = q.last;
    f.median_index[o] = q.med;
}

// A pixel's backward state from the forward's saved state and the output cotangents, at pixel index o.
template <class S>
SZ_HD void load_pixel_bwd(PixelBwd<S>& p, const FrameArgs<S>& f, const GradArgs<S>& g, int64_t o) {
    pixel_bwd_init(p, f.T_final[o], f.totals + 3 * o, f.last[o], f.median_index[o], f.depth[o], g.v_rgb + 3 * o,
                   g.v_alpha[o], g.v_depth[o], g.v_median[o], g.v_normal + 3 * o, g.v_dist[o]);
}

// A surfel's summed slot row -> its input gradients (row R: float or double).
template <class S, class R>
SZ_HD void finalize_surfel(const SurfelArgs<S>& s, const GradArgs<S>& g, int64_t i, const R* row) {
    const SurfelGrads<S> v{g.v_T + 9 * i,           g.v_center + 2 * i, g.v_depth_c + i,
                           g.v_normal_c + 3 * i,    g.v_opacities + i,  g.v_falloff + i,
                           Appearance<S>::bind_grads(g, s, i)};
    finalize_grads(s.st, s.T + 9 * i, s.center + 2 * i, surfel_appearance(s, i), row, v);
}

// ---- CPU (OpenMP) ----
template <class S> void cpu_project(const ProjectArgs<S>& a, int threads);
template <class S> void cpu_project_backward(const ProjectGradArgs<S>& a, int threads);
// Fills geom and bounds; returns the number of (tile, surfel) pairs and writes surfel_off [M+1] (CSR of pairs by
// depth rank, rank-major order).
template <class S> int64_t cpu_prepare(const SurfelArgs<S>& s, S* geom, int* bounds, int64_t* surfel_off, int threads);
// Counting sort of the pairs by tile (stable, so depth order is kept): tile_start [tiles+1], tile_list [P], and
// pair_pos [P] (tile-list position of each pair, in depth-rank-major order, to reduce gradients without atomics).
void cpu_bin(int M, int W, int H, const int* order, const int* bounds, const int64_t* surfel_off, int* tile_start,
             int* tile_list, int* pair_pos);
template <class S> void cpu_forward(const SurfelArgs<S>& s, const FrameArgs<S>& f, int threads);
// partials: scratch [P, grad_width(K, TS)]; rows are summed per surfel in a fixed order (deterministic).
template <class S>
void cpu_backward(const SurfelArgs<S>& s, const FrameArgs<S>& f, const GradArgs<S>& g, const int64_t* surfel_off,
                  const int* pair_pos, S* partials, int threads);

// ---- CUDA kernels (stream: a cudaStream_t; nullptr under the host emulation) ----
// The same entry points, compiled by nvcc (sz::gpu) and for the host emulation (sz::emu).
#define SZ_GPU_ENTRY_POINTS                                                                                        \
    template <class S> void project(const ProjectArgs<S>& a, void* stream);                                        \
    template <class S> void project_backward(const ProjectGradArgs<S>& a, void* stream);                           \
    /* geom, bounds, and the tile count [M] of each visible surfel by depth rank */                                \
    template <class S> void prepare(const SurfelArgs<S>& s, S* geom, int* bounds, int* tile_count, void* stream);  \
    /* one key (tile << 32 | depth rank) per pair; pair_end [M] = inclusive cumulative tile counts by rank */       \
    void emit_pairs(int M, int W, const int* order, const int* bounds, const int64_t* pair_end, int64_t* keys,     \
                    void* stream);                                                                                 \
    /* tile_list [P] (surfel indices) and tile_start [tiles+1] from the sorted keys [P] */                         \
    void tile_starts(int64_t P, int tiles, const int* order, const int64_t* keys, int* tile_list, int* tile_start, \
                     void* stream);                                                                                \
    template <class S> void forward(const SurfelArgs<S>& s, const FrameArgs<S>& f, void* stream);                  \
    /* rows: zeroed scratch [N, grad_width(K, TS)], summed into per warp (one atomic per slot per warp) */             \
    template <class S>                                                                                             \
    void backward(const SurfelArgs<S>& s, const FrameArgs<S>& f, const GradArgs<S>& g, S* rows, void* stream);

namespace gpu {
SZ_GPU_ENTRY_POINTS
}
namespace emu {
SZ_GPU_ENTRY_POINTS
}

}  // namespace sz
