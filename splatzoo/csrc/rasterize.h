// Raw-pointer interface between the torch bindings (ext.cpp) and the tile loops (rasterize_cpu.cpp,
// rasterize_cuda.cu), and the small pieces both loops share. Kept free of torch headers so the tile loops compile
// fast and nvcc needs no torch.
//
// Surfels arrive compacted to the visible ones and sorted front to back by centre depth (stable), so a tile's
// list in increasing surfel index is its depth order. Shapes: M surfels, K waves, image H x W.
#pragma once

#include <cstdint>

#include "surfel_math.h"

namespace sz {

template <class S>
struct SurfelArgs {
    int M, K, W, H;
    const S* T;       // [M,3,3] rows m1, m2, m3
    const S* center;  // [M,2] projected centre (pixels)
    const S* depth;   // [M] camera depth of the centre
    const S* normal;  // [M,3] world normal facing the camera
    const S* opac;    // [M]
    const S* base;    // [M,3]
    const S* wv;      // [M,K,2]
    const S* wp;      // [M,K]
    const S* wa;      // [M,K,3]
    const S* boxes;   // [M,4] exact screen box (xmin, ymin, xmax, ymax), common.screen_boxes
    // [M] waves in use per surfel (its first wcount[i] of K), or nullptr for all K. The tile loops run the wave
    // loops to k < wcount[i], so removed waves cost nothing; the row stride stays K.
    const int* wcount;
};

template <class S>
struct FrameArgs {
    S* geom;                // [M,GEOM] per-surfel geometry (prepare)
    int* bounds;            // [M,4] pixel range x0, x1, y0, y1 (inclusive)
    const int* tile_start;  // [tiles+1] tile t's surfels are tile_list[tile_start[t] .. tile_start[t+1])
    const int* tile_list;   // [P] surfel index per (tile, surfel) pair, tile-major, depth order within a tile
    // outputs [H,W(,3)]
    S *rgb, *alpha, *depth, *median, *normal, *dist;
    // saved for the backward [H,W(,3)]
    S* Tfinal;
    S* tot;    // [H,W,3] sum w, sum w m, sum w m^2
    int* last;  // 1 + tile-list position (relative to the tile start) of the last blended contribution
    int* med;   // relative tile-list position of the median contribution, -1 if none
};

template <class S>
struct GradArgs {
    // cotangents of the outputs [H,W(,3)] (contiguous, zeros where the output was unused)
    const S *g_rgb, *g_alpha, *g_depth, *g_median, *g_normal, *g_dist;
    // gradients of the inputs, same shapes as SurfelArgs
    S *v_T, *v_center, *v_depth, *v_normal, *v_opac, *v_base, *v_wv, *v_wp, *v_wa;
};

inline int tiles_x(int W) { return (W + 15) / 16; }
inline int tiles_y(int H) { return (H + 15) / 16; }

// ---- shared by the CPU and CUDA tile loops ----
// One surfel's colour inputs (its rows of the SurfelArgs arrays) and how many of its K waves it uses.
template <class S>
struct SurfelColour {
    const S *normal, *base, *wv, *wp, *wa;
    int K;
};
template <class S>
SZ_HD SurfelColour<S> surfel_colour(const SurfelArgs<S>& s, int64_t i) {
    return {s.normal + 3 * i, s.base + 3 * i, s.wv + 2 * s.K * i, s.wp + s.K * i, s.wa + 3 * s.K * i,
            s.wcount ? s.wcount[i] : s.K};
}

// A pixel's finished forward state -> the outputs and the state the backward reads, at pixel index o.
template <class S>
SZ_HD void store_pixel(const FrameArgs<S>& f, int64_t o, const PixelFwd<S>& q) {
    const S acc = S(1) - q.T;
    for (int k = 0; k < 3; ++k) {
        f.rgb[3 * o + k] = q.rgb[k];
        f.normal[3 * o + k] = q.N[k];
    }
    f.alpha[o] = acc;
    f.depth[o] = acc > S(0) ? q.D / acc : S(0);
    f.median[o] = q.med >= 0 ? q.median : S(0);
    f.dist[o] = q.dist;
    f.Tfinal[o] = q.T;
    f.tot[3 * o] = q.A;
    f.tot[3 * o + 1] = q.M1;
    f.tot[3 * o + 2] = q.M2;
    f.last[o] = q.last;
    f.med[o] = q.med;
}

// ---- CPU (OpenMP) ----
// The camera-dependent set-up of N surfels (project_surfel): T [N,3,3], centre [N,2], depth [N], normal [N,3],
// boxes [N,4], visible [N]; and its backward (project_backward) to means [N,3], quats [N,4], scales [N,2].
template <class S>
void cpu_project(const CameraArgs<S>& cam, int64_t N, const S* means, const S* quats, const S* scales, const S* opac,
                 S* T, S* center, S* depth, S* normal, S* boxes, bool* visible, int threads);
template <class S>
void cpu_project_backward(const CameraArgs<S>& cam, int64_t N, const S* means, const S* quats, const S* scales,
                          const S* v_T, const S* v_center, const S* v_depth, const S* v_normal, S* v_means,
                          S* v_quats, S* v_scales, int threads);
// Fills geom and bounds; returns the number of (tile, surfel) pairs and writes surfel_off [M+1] (CSR of pairs by
// surfel, surfel-major order).
template <class S> int64_t cpu_prepare(const SurfelArgs<S>& s, S* geom, int* bounds, int64_t* surfel_off, int threads);
// Counting sort of the pairs by tile (stable, so depth order is kept): tile_start [tiles+1], tile_list [P], and
// pair_pos [P] (tile-list position of each pair in surfel-major order, to reduce gradients without atomics).
void cpu_bin(int M, int W, int H, const int* bounds, const int64_t* surfel_off, int* tile_start, int* tile_list,
             int* pair_pos);
template <class S> void cpu_forward(const SurfelArgs<S>& s, const FrameArgs<S>& f, int threads);
// partials: scratch [P, grad_width(K)] of the scalar type.
template <class S>
void cpu_backward(const SurfelArgs<S>& s, const FrameArgs<S>& f, const GradArgs<S>& g, const int64_t* surfel_off,
                  const int* pair_pos, S* partials, int threads);

// ---- CUDA ---- (stream is a cudaStream_t)
template <class S> void cuda_prepare(const SurfelArgs<S>& s, S* geom, int* bounds, int* tile_count, void* stream);
template <class S> void cuda_forward(const SurfelArgs<S>& s, const FrameArgs<S>& f, void* stream);
// gbuf: zeroed scratch [M, grad_width(K)] accumulated with atomics, then finalised into GradArgs.
template <class S>
void cuda_backward(const SurfelArgs<S>& s, const FrameArgs<S>& f, const GradArgs<S>& g, S* gbuf, void* stream);

}  // namespace sz
