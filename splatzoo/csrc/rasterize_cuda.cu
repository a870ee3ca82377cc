// CUDA tile loop: one 16x16 thread block per tile, one thread per pixel, surfels staged through shared memory in
// batches of 256. The per-pair maths is the same surfel_math.h the CPU loop uses. Per-surfel gradients are summed
// with atomics into a [M, grad_width(K)] buffer, then mapped to input gradients by finalize_kernel.
//
// Binning (sorting (tile, surfel) pairs) happens in ext.cpp with ATen ops, so this file needs no torch headers.
#include <cuda_runtime.h>

#include <stdexcept>
#include <string>

#include "rasterize.h"
#include "surfel_math.h"

namespace sz {
namespace {

constexpr int BLOCK = TILE_PIXELS;

void check(cudaError_t err, const char* what) {
    if (err != cudaSuccess)
        throw std::runtime_error(std::string("splatzoo cuda rasterizer: ") + what + ": " + cudaGetErrorString(err));
}

template <class S>
struct AtomicAcc {
    S* g;
    __device__ void operator()(int i, S v) { atomicAdd(g + i, v); }
};

template <class S>
__global__ void prepare_kernel(SurfelArgs<S> s, S* geom, int* bounds, int* count) {
    const int i = blockIdx.x * blockDim.x + threadIdx.x;
    if (i >= s.M) return;
    prepare_geom(s.T + 9 * i, s.center + 2 * i, s.depth[i], s.opac[i], *reinterpret_cast<Geom<S>*>(geom + GEOM * i));
    int* b = bounds + 4 * i;
    box_pixels(s.boxes + 4 * i, s.W, s.H, b);
    count[i] = (b[0] <= b[1] && b[2] <= b[3]) ? (b[1] / TILE - b[0] / TILE + 1) * (b[3] / TILE - b[2] / TILE + 1) : 0;
}

// Shared-memory batch of surfels: geometry, pixel bounds and index.
template <class S>
struct Batch {
    Geom<S> g[BLOCK];
    int4 b[BLOCK];
    int id[BLOCK];
};

template <class S>
__device__ __forceinline__ void stage(Batch<S>& sh, const FrameArgs<S>& f, int k) {
    const int i = f.tile_list[k];
    sh.id[threadIdx.x] = i;
    sh.g[threadIdx.x] = reinterpret_cast<const Geom<S>*>(f.geom)[i];
    sh.b[threadIdx.x] = reinterpret_cast<const int4*>(f.bounds)[i];
}

// The CPU loop evaluates a surfel only on pixels inside its box; do the same so both backends agree exactly.
__device__ __forceinline__ bool in_box(const int4& b, int x, int y) {
    return x >= b.x && x <= b.y && y >= b.z && y <= b.w;
}

// This thread's pixel: block t is tile t (row-major), thread i is pixel i of the tile (row-major).
struct ThreadPixel {
    int t, x, y;
    bool inside;
};
__device__ __forceinline__ ThreadPixel thread_pixel(int W, int H) {
    const int ntx = (W + TILE - 1) / TILE;
    const int t = blockIdx.x;
    const int x = (t % ntx) * TILE + int(threadIdx.x) % TILE;
    const int y = (t / ntx) * TILE + int(threadIdx.x) / TILE;
    return {t, x, y, x < W && y < H};
}

template <class S>
__global__ void __launch_bounds__(BLOCK) forward_kernel(SurfelArgs<S> s, FrameArgs<S> f) {
    const auto [t, x, y, inside] = thread_pixel(s.W, s.H);
    const S px = S(x) + S(0.5), py = S(y) + S(0.5);
    const int start = f.tile_start[t], end = f.tile_start[t + 1];
    __shared__ Batch<S> sh;
    PixelFwd<S> p;
    pixel_init(p, !inside);
    for (int base = start; base < end; base += BLOCK) {
        // the barrier also protects `sh` from being overwritten while other threads still read it
        if (__syncthreads_count(p.done ? 1 : 0) == BLOCK) break;
        if (base + int(threadIdx.x) < end) stage(sh, f, base + threadIdx.x);
        __syncthreads();
        const int n = min(BLOCK, end - base);
        for (int j = 0; j < n && !p.done; ++j) {
            if (!in_box(sh.b[j], x, y)) continue;
            PairEval<S> e;
            eval_pair(sh.g[j], px, py, e);
            if (e.alpha == S(0)) continue;
            const SurfelColour<S> sf = surfel_colour(s, sh.id[j]);
            S col[3], pre[3];
            wave_color(sf.base, sf.wv, sf.wp, sf.wa, sf.K, e.u, e.v, col, pre);
            blend_forward(p, e.alpha, e.z, col, sf.normal, base + j - start);
        }
    }
    if (inside) store_pixel(f, int64_t(y) * s.W + x, p);
}

template <class S>
__global__ void __launch_bounds__(BLOCK) backward_kernel(SurfelArgs<S> s, FrameArgs<S> f, GradArgs<S> g, S* gbuf) {
    const auto [t, x, y, inside] = thread_pixel(s.W, s.H);
    const S px = S(x) + S(0.5), py = S(y) + S(0.5);
    const int start = f.tile_start[t];
    const int GW = grad_width(s.K);
    __shared__ Batch<S> sh;
    __shared__ int max_last;
    PixelBwd<S> p;
    p.last = 0;
    if (inside) {
        const int64_t o = int64_t(y) * s.W + x;
        pixel_bwd_init(p, f.Tfinal[o], f.tot + 3 * o, f.last[o], f.med[o], f.depth[o], g.g_rgb + 3 * o, g.g_alpha[o],
                       g.g_depth[o], g.g_median[o], g.g_normal + 3 * o, g.g_dist[o]);
    }
    if (threadIdx.x == 0) max_last = 0;
    __syncthreads();
    if (p.last > 0) atomicMax(&max_last, p.last);
    __syncthreads();
    // back to front over the tile list, from the last contribution any pixel of the tile blended
    for (int top = start + max_last; top > start; top -= BLOCK) {
        const int lo = max(start, top - BLOCK);
        __syncthreads();
        if (top - 1 - int(threadIdx.x) >= lo) stage(sh, f, top - 1 - threadIdx.x);
        __syncthreads();
        const int n = top - lo;
        for (int j = 0; j < n; ++j) {
            const int rel = top - 1 - j - start;
            if (rel >= p.last || !in_box(sh.b[j], x, y)) continue;
            PairEval<S> e;
            eval_pair(sh.g[j], px, py, e);
            if (e.alpha == S(0)) continue;
            const int64_t i = sh.id[j];
            const SurfelColour<S> sf = surfel_colour(s, i);
            AtomicAcc<S> acc{gbuf + i * GW};
            blend_backward(p, sh.g[j], e, sf.normal, sf.base, sf.wv, sf.wp, sf.wa, sf.K, rel, acc);
        }
    }
}

template <class S>
__global__ void finalize_kernel(SurfelArgs<S> s, GradArgs<S> g, const S* gbuf) {
    const int64_t i = blockIdx.x * int64_t(blockDim.x) + threadIdx.x;
    if (i >= s.M) return;
    const int K = s.K;
    finalize_grads(s.T + 9 * i, s.center + 2 * i, gbuf + i * grad_width(K), K, g.v_T + 9 * i, g.v_center + 2 * i,
                   g.v_depth + i, g.v_normal + 3 * i, g.v_opac + i, g.v_base + 3 * i, g.v_wv + 2 * K * i,
                   g.v_wp + K * i, g.v_wa + 3 * K * i);
}

}  // namespace

template <class S>
void cuda_prepare(const SurfelArgs<S>& s, S* geom, int* bounds, int* count, void* stream) {
    if (s.M == 0) return;
    prepare_kernel<S><<<(s.M + 255) / 256, 256, 0, static_cast<cudaStream_t>(stream)>>>(s, geom, bounds, count);
    check(cudaGetLastError(), "prepare kernel launch");
}

template <class S>
void cuda_forward(const SurfelArgs<S>& s, const FrameArgs<S>& f, void* stream) {
    const int nt = tiles_x(s.W) * tiles_y(s.H);
    forward_kernel<S><<<nt, BLOCK, 0, static_cast<cudaStream_t>(stream)>>>(s, f);
    check(cudaGetLastError(), "forward kernel launch");
}

template <class S>
void cuda_backward(const SurfelArgs<S>& s, const FrameArgs<S>& f, const GradArgs<S>& g, S* gbuf, void* stream) {
    if (s.M == 0) return;
    const int nt = tiles_x(s.W) * tiles_y(s.H);
    auto st = static_cast<cudaStream_t>(stream);
    backward_kernel<S><<<nt, BLOCK, 0, st>>>(s, f, g, gbuf);
    check(cudaGetLastError(), "backward kernel launch");
    finalize_kernel<S><<<(s.M + 255) / 256, 256, 0, st>>>(s, g, gbuf);
    check(cudaGetLastError(), "finalize kernel launch");
}

#define SZ_INSTANTIATE_CUDA(S)                                                                                    \
    template void cuda_prepare<S>(const SurfelArgs<S>&, S*, int*, int*, void*);                                   \
    template void cuda_forward<S>(const SurfelArgs<S>&, const FrameArgs<S>&, void*);                              \
    template void cuda_backward<S>(const SurfelArgs<S>&, const FrameArgs<S>&, const GradArgs<S>&, S*, void*);
SZ_INSTANTIATE_CUDA(float)
SZ_INSTANTIATE_CUDA(double)

}  // namespace sz
