// CUDA kernels of the tile rasterizer: per-surfel projection and its backward, pixel geometry and tile counts, pair
// emission and tile ranges for the binning, and the tile loops (one 16x16 block per tile, one thread per pixel,
// surfels staged through shared memory in batches of 256). The per-pair maths is surfel_math.h, as on the CPU.
//
// The same source also compiles for the host against cuda_emulation.h (rasterize_cuda_emulated.cpp defines
// SZ_CUDA_EMULATION): blocks run one after another, their threads as fibers that meet at barriers and warp
// collectives. That build is the test-only "cuda-emulated" backend, which runs these kernels on machines without a GPU.
#ifdef SZ_CUDA_EMULATION
#include "cuda_emulation.h"
#define SZ_GPU_NAMESPACE emu
#else
#include <cuda_runtime.h>
#define SZ_GPU_NAMESPACE gpu
#define SZ_LAUNCH(kernel, grid, block, stream) kernel<<<(grid), (block), 0, (stream)>>>
#endif

#include <stdexcept>
#include <string>

#include "rasterize.h"
#include "surfel_math.h"

namespace sz {
namespace SZ_GPU_NAMESPACE {
namespace {

constexpr int BLOCK = TILE_PIXELS;  // one thread per pixel of a tile
constexpr int PER_SURFEL = 256;     // threads per block of the per-surfel kernels
constexpr unsigned FULL_WARP = 0xffffffffu;

void check(cudaError_t err, const char* what) {
    if (err != cudaSuccess)
        throw std::runtime_error(std::string("splatzoo cuda rasterizer: ") + what + ": " + cudaGetErrorString(err));
}

int blocks_for(int64_t n) { return int((n + PER_SURFEL - 1) / PER_SURFEL); }

// ---- per surfel ------------------------------------------------------------------------------------------------

template <class S>
__global__ void project_kernel(ProjectArgs<S> a) {
    const int64_t i = blockIdx.x * int64_t(blockDim.x) + threadIdx.x;
    if (i >= a.N) return;
    a.visible[i] = project_surfel(a.st, a.cam, a.means + 3 * i, a.quats + 4 * i, a.scales + 2 * i, a.opac[i], a.falloff[i],
                                  a.T + 9 * i, a.center + 2 * i, a.depth + i, a.normal + 3 * i, a.boxes + 4 * i);
}

template <class S>
__global__ void project_backward_kernel(ProjectGradArgs<S> a) {
    const int64_t i = blockIdx.x * int64_t(blockDim.x) + threadIdx.x;
    if (i >= a.N) return;
    project_backward(a.cam, a.means + 3 * i, a.quats + 4 * i, a.scales + 2 * i, a.v_T + 9 * i, a.v_center + 2 * i,
                     a.v_depth[i], a.v_normal + 3 * i, a.v_means + 3 * i, a.v_quats + 4 * i, a.v_scales + 2 * i);
}

// Thread r prepares the visible surfel of depth rank r.
template <class S>
__global__ void prepare_kernel(SurfelArgs<S> s, S* geom, int* bounds, int* tile_count) {
    const int r = blockIdx.x * blockDim.x + threadIdx.x;
    if (r >= s.M) return;
    const int64_t i = s.order[r];
    Geom<S>& g = *reinterpret_cast<Geom<S>*>(geom + GEOM * i);
    prepare_geom(s.st, s.T + 9 * i, s.center + 2 * i, s.depth[i], s.opacities[i], s.falloff[i], g);
    prepare_appearance(s, g, i);
    box_pixels(s.boxes + 4 * i, s.W, s.H, bounds + 4 * i);
    tile_count[r] = int(tile_range(bounds + 4 * i).count());
}

// The surfel of depth rank r writes its pairs at [pair_end[r-1], pair_end[r]): key = tile << 32 | r. Sorting the
// keys orders the pairs by tile and, within a tile, front to back.
__global__ void emit_pairs_kernel(int M, int W, const int* order, const int* bounds, const int64_t* pair_end,
                                  int64_t* keys) {
    const int rank = blockIdx.x * blockDim.x + threadIdx.x;
    if (rank >= M) return;
    const TileRange r = tile_range(bounds + 4 * int64_t(order[rank]));
    const int ntx = (W + TILE - 1) / TILE;
    int64_t k = rank > 0 ? pair_end[rank - 1] : 0;
    for (int ty = r.y0; ty <= r.y1; ++ty)
        for (int tx = r.x0; tx <= r.x1; ++tx) keys[k++] = (int64_t(ty * ntx + tx) << 32) | int64_t(rank);
}

// tile_list (surfel indices) from the sorted keys, and tile_start: where each tile's run of keys begins (empty
// tiles included).
__global__ void tile_starts_kernel(int64_t P, int tiles, const int* order, const int64_t* keys, int* tile_list,
                                   int* tile_start) {
    const int64_t k = blockIdx.x * int64_t(blockDim.x) + threadIdx.x;
    if (k >= P) return;
    tile_list[k] = order[keys[k] & 0xffffffff];
    const int tile = int(keys[k] >> 32);
    const int prev = k > 0 ? int(keys[k - 1] >> 32) : -1;
    for (int t = prev + 1; t <= tile; ++t) tile_start[t] = int(k);
    if (k == P - 1)
        for (int t = tile + 1; t <= tiles; ++t) tile_start[t] = int(P);
}

// ---- tile loops ------------------------------------------------------------------------------------------------

// Shared-memory batch of surfels: pixel geometry, pixel bounds and index.
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

template <class S, bool IMAGE_ONLY>
__global__ void __launch_bounds__(BLOCK) forward_kernel(SurfelArgs<S> s, FrameArgs<S> f) {
    const Settings st = s.st;
    const auto [t, x, y, inside] = thread_pixel(s.W, s.H);
    const S px = S(x) + S(0.5), py = S(y) + S(0.5);
    const int start = f.tile_start[t], end = f.tile_start[t + 1];
    __shared__ Batch<S> sh;
    PixelFwd<S> p;
    pixel_init(p, !inside);
    for (int base = start; base < end; base += BLOCK) {
        // the barrier also keeps `sh` from being overwritten while other threads still read it
        if (__syncthreads_count(p.done ? 1 : 0) == BLOCK) break;
        if (base + int(threadIdx.x) < end) stage(sh, f, base + threadIdx.x);
        __syncthreads();
        const int n = min(BLOCK, end - base);
        for (int j = 0; j < n && !p.done; ++j) {
            if (!in_box(sh.b[j], x, y)) continue;
            PairEval<S> e;
            eval_pair_any(st, sh.g[j], px, py, e);
            const int64_t i = sh.id[j];
            const Appearance<S> ap = surfel_appearance(s, i);
            if (ap.has_gain()) apply_opacity_gain(st, sh.g[j], ap.gain(e.u, e.v), e);
            if (e.alpha == S(0)) continue;
            S col[3], pre[3];
            ap.colour(e.u, e.v, col, pre, st.pixel_filter > 0 ? sh.g[j].blur : nullptr);
            blend_forward<IMAGE_ONLY>(st, p, e.alpha, e.z, col, s.normal + 3 * i, base + j - start);
        }
    }
    if (inside) store_pixel(f, int64_t(y) * s.W + x, p);
}

// Sums one gradient slot over the warp, then lane 0 adds it to the surfel's row: one atomic per slot per warp
// instead of one per pixel. Lanes whose pair did not contribute take part with zero. (Any wave count.) scatter: a
// slot that differs from lane to lane (a kind's scatter slot: a texel), one atomic per lane.
template <class S>
struct WarpSum {
    S* row;
    bool valid;
    __device__ __forceinline__ void operator()(int slot, S v) {
        v = valid ? v : S(0);
#pragma unroll
        for (int offset = 16; offset > 0; offset >>= 1) v += __shfl_xor_sync(FULL_WARP, v, offset);
        if ((threadIdx.x & 31) == 0 && v != S(0)) atomicAdd(row + slot, v);
    }
    __device__ __forceinline__ void scatter(int slot, S v) {
        if (valid && v != S(0)) atomicAdd(row + slot, v);
    }
};

// Accumulates a pair's dense slots into a register row (compile-time slot indices: see for_each_wave); scatter (a
// kind's scatter slots: texels) adds to the surfel's row in global memory, one atomic per lane.
template <class S>
struct RowAcc {
    S* row;
    bool valid;
    S* surfel_row;
    __device__ __forceinline__ void operator()(int slot, S v) { row[slot] += valid ? v : S(0); }
    __device__ __forceinline__ void scatter(int slot, S v) {
        if (valid && v != S(0)) atomicAdd(surfel_row + slot, v);
    }
};

// One halving step of a warp reduce-scatter: lanes with BIT set keep the upper HALF of their values, the others
// the lower half, and each adds its partner's partial sums of the half it keeps.
template <class S, int HALF, int BIT>
__device__ __forceinline__ void reduce_scatter_step(S* v) {
    const bool upper = (threadIdx.x & BIT) != 0;
#pragma unroll
    for (int i = 0; i < HALF; ++i) {
        const S send = upper ? v[i] : v[i + HALF];
        const S keep = upper ? v[i + HALF] : v[i];
        v[i] = keep + __shfl_xor_sync(FULL_WARP, send, BIT);
    }
}

// Sums N values (N a multiple of 32) over the warp in N - N/32 shuffles (a shuffle per value and level would take
// 5N): afterwards lane l holds the sums of values [l N/32, (l + 1) N/32) in v[0 .. N/32).
template <class S, int N>
__device__ __forceinline__ void warp_reduce_scatter(S* v) {
    static_assert(N % 32 == 0, "pad the row to a multiple of 32");
    reduce_scatter_step<S, N / 2, 16>(v);
    reduce_scatter_step<S, N / 4, 8>(v);
    reduce_scatter_step<S, N / 8, 4>(v);
    reduce_scatter_step<S, N / 16, 2>(v);
    reduce_scatter_step<S, N / 32, 1>(v);
}

// KMAX >= 0 (every surfel has at most KMAX waves): each lane keeps the pair's slot row in registers and the warp
// sums the rows with a reduce-scatter, then each lane adds its share of the slots with atomics. KMAX < 0: any wave
// count, one warp sum and one atomic per slot (WarpSum).
template <class S, int KMAX>
__global__ void __launch_bounds__(BLOCK) backward_kernel(SurfelArgs<S> s, FrameArgs<S> f, GradArgs<S> g, S* rows) {
    const Settings st = s.st;
    const auto [t, x, y, inside] = thread_pixel(s.W, s.H);
    const S px = S(x) + S(0.5), py = S(y) + S(0.5);
    const int start = f.tile_start[t];
    const int GW = grad_width(s.K, s.TS);  // the row's stride; the register row holds its dense slots
    const int GWR = dense_width(s.K);
    __shared__ Batch<S> sh;
    __shared__ int max_last;
    PixelBwd<S> p{};  // a pixel outside the image keeps last = 0: it never contributes
    if (inside) load_pixel_bwd(p, f, g, int64_t(y) * s.W + x);
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
        for (int j = 0; j < n; ++j) {  // every lane of a warp runs the same j: the warp sums below need them all
            const int rel = top - 1 - j - start;
            const bool candidate = rel < p.last && in_box(sh.b[j], x, y);
            if (!__any_sync(FULL_WARP, candidate)) continue;
            PairEval<S> e;
            eval_pair_any(st, sh.g[j], px, py, e);  // rounds as in the forward: the same pairs contribute
            const int64_t i = sh.id[j];
            const Appearance<S> ap = surfel_appearance(s, i);
            if (ap.has_gain()) apply_opacity_gain(st, sh.g[j], ap.gain(e.u, e.v), e);
            const bool valid = candidate && e.alpha != S(0);
            if (!__any_sync(FULL_WARP, valid)) continue;
            S* surfel_row = rows + i * GW;
            PixelBwd<S> q = p;
            if constexpr (KMAX >= 0) {
                constexpr int ROW = (dense_width(KMAX) + 31) / 32 * 32;
                S row[ROW];
#pragma unroll
                for (int k = 0; k < ROW; ++k) row[k] = S(0);
                RowAcc<S> acc{row, valid, surfel_row};
                blend_backward<KMAX>(st, q, sh.g[j], e, s.normal + 3 * i, ap, rel, acc);
                warp_reduce_scatter<S, ROW>(row);
                const int first = int(threadIdx.x & 31) * (ROW / 32);
#pragma unroll
                for (int k = 0; k < ROW / 32; ++k)
                    if (first + k < GWR && row[k] != S(0)) atomicAdd(surfel_row + first + k, row[k]);
            } else {
                WarpSum<S> acc{surfel_row, valid};
                blend_backward(st, q, sh.g[j], e, s.normal + 3 * i, ap, rel, acc);
            }
            if (valid) p = q;
        }
    }
}

template <class S>
__global__ void finalize_kernel(SurfelArgs<S> s, GradArgs<S> g, const S* rows) {
    const int r = blockIdx.x * blockDim.x + threadIdx.x;
    if (r >= s.M) return;
    const int64_t i = s.order[r];
    finalize_surfel(s, g, i, rows + i * grad_width(s.K, s.TS));
}

template <class S, int KMAX>
void launch_backward(const SurfelArgs<S>& s, const FrameArgs<S>& f, const GradArgs<S>& g, S* rows, int tiles,
                     cudaStream_t stream) {
    constexpr auto kernel = &backward_kernel<S, KMAX>;  // one name: a template-id's comma would split the macro
    SZ_LAUNCH(kernel, tiles, BLOCK, stream)(s, f, g, rows);
}

}  // namespace

template <class S>
void project(const ProjectArgs<S>& a, void* stream) {
    if (a.N == 0) return;
    SZ_LAUNCH(project_kernel<S>, blocks_for(a.N), PER_SURFEL, static_cast<cudaStream_t>(stream))(a);
    check(cudaGetLastError(), "project kernel launch");
}

template <class S>
void project_backward(const ProjectGradArgs<S>& a, void* stream) {
    if (a.N == 0) return;
    SZ_LAUNCH(project_backward_kernel<S>, blocks_for(a.N), PER_SURFEL, static_cast<cudaStream_t>(stream))(a);
    check(cudaGetLastError(), "project backward kernel launch");
}

template <class S>
void prepare(const SurfelArgs<S>& s, S* geom, int* bounds, int* tile_count, void* stream) {
    if (s.M == 0) return;
    SZ_LAUNCH(prepare_kernel<S>, blocks_for(s.M), PER_SURFEL, static_cast<cudaStream_t>(stream))(s, geom, bounds,
                                                                                                   tile_count);
    check(cudaGetLastError(), "prepare kernel launch");
}

void emit_pairs(int M, int W, const int* order, const int* bounds, const int64_t* pair_end, int64_t* keys,
                void* stream) {
    if (M == 0) return;
    SZ_LAUNCH(emit_pairs_kernel, blocks_for(M), PER_SURFEL, static_cast<cudaStream_t>(stream))(M, W, order, bounds,
                                                                                                pair_end, keys);
    check(cudaGetLastError(), "emit pairs kernel launch");
}

void tile_starts(int64_t P, int tiles, const int* order, const int64_t* keys, int* tile_list, int* tile_start,
                 void* stream) {
    if (P == 0) return;
    SZ_LAUNCH(tile_starts_kernel, blocks_for(P), PER_SURFEL, static_cast<cudaStream_t>(stream))(P, tiles, order, keys,
                                                                                                 tile_list, tile_start);
    check(cudaGetLastError(), "tile starts kernel launch");
}

template <class S>
void forward(const SurfelArgs<S>& s, const FrameArgs<S>& f, void* stream) {
    const int nt = tiles_x(s.W) * tiles_y(s.H);
    constexpr auto full = &forward_kernel<S, false>;  // one name: a template-id's comma would split the macro
    constexpr auto image = &forward_kernel<S, true>;
    if (f.image_only)
        SZ_LAUNCH(image, nt, BLOCK, static_cast<cudaStream_t>(stream))(s, f);
    else
        SZ_LAUNCH(full, nt, BLOCK, static_cast<cudaStream_t>(stream))(s, f);
    check(cudaGetLastError(), "forward kernel launch");
}

template <class S>
void backward(const SurfelArgs<S>& s, const FrameArgs<S>& f, const GradArgs<S>& g, S* rows, void* stream) {
    if (s.M == 0) return;
    const int nt = tiles_x(s.W) * tiles_y(s.H);
    auto st = static_cast<cudaStream_t>(stream);
    // the register row for the common wave counts; any count through the per-slot warp sums
    if (s.K == 0)
        launch_backward<S, 0>(s, f, g, rows, nt, st);
    else if (s.K <= 4)
        launch_backward<S, 4>(s, f, g, rows, nt, st);
    else
        launch_backward<S, -1>(s, f, g, rows, nt, st);
    check(cudaGetLastError(), "backward kernel launch");
    SZ_LAUNCH(finalize_kernel<S>, blocks_for(s.M), PER_SURFEL, st)(s, g, rows);
    check(cudaGetLastError(), "finalize kernel launch");
}

#define SZ_INSTANTIATE_GPU(S)                                                                                     \
    template void project<S>(const ProjectArgs<S>&, void*);                                                       \
    template void project_backward<S>(const ProjectGradArgs<S>&, void*);                                          \
    template void prepare<S>(const SurfelArgs<S>&, S*, int*, int*, void*);                                        \
    template void forward<S>(const SurfelArgs<S>&, const FrameArgs<S>&, void*);                                   \
    template void backward<S>(const SurfelArgs<S>&, const FrameArgs<S>&, const GradArgs<S>&, S*, void*);
SZ_INSTANTIATE_GPU(float)
SZ_INSTANTIATE_GPU(double)

}  // namespace SZ_GPU_NAMESPACE
}  // namespace sz
