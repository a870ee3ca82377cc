// Checks of splatzoo/csrc/cuda_emulation.h: kernels written as CUDA, compiled with a host compiler.
//   g++ -O2 -std=c++17 -Wall -Wextra -o /tmp/tce tests/csrc/test_cuda_emulation.cpp -I splatzoo/csrc && /tmp/tce
// Prints "ok <name>" per check and exits non-zero if any fails.
#include <algorithm>
#include <cmath>

#define SZ_CUDA_EMULATION 1
#include "cuda_emulation.h"

#include <sys/wait.h>
#include <ucontext.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <string>
#include <vector>

static int failures = 0;
static void check(bool ok, const char* name) {
    std::printf("%s %s\n", ok ? "ok" : "FAIL", name);
    if (!ok) ++failures;
}
constexpr unsigned FULL = 0xffffffffu;

// ---- 1. block reduction ----
__global__ void __launch_bounds__(256) reduce_kernel(const int* in, int n, long long* partial) {
    __shared__ long long buf[256];
    const int t = threadIdx.x;
    const int i = blockIdx.x * blockDim.x + t;
    buf[t] = i < n ? in[i] : 0;
    __syncthreads();
    for (int s = blockDim.x / 2; s > 0; s >>= 1) {
        if (t < s) buf[t] += buf[t + s];
        __syncthreads();
    }
    if (t == 0) partial[blockIdx.x] = buf[0];
}

__global__ void index_kernel(int* out) {
    const int bx = blockIdx.x + gridDim.x * blockIdx.y;
    const int tx = threadIdx.x + blockDim.x * (threadIdx.y + blockDim.y * threadIdx.z);
    const int nt = blockDim.x * blockDim.y * blockDim.z;
    out[bx * nt + tx] = 1000 * bx + 100 * threadIdx.z + 10 * threadIdx.y + threadIdx.x;
}

// ---- 2. shuffles ----
template <class T>
__global__ void warp_sum_kernel(const T* in, T* out) {
    const int i = blockIdx.x * blockDim.x + threadIdx.x;
    T v = in[i];
    for (int m = 16; m > 0; m >>= 1) v += __shfl_xor_sync(FULL, v, m);
    out[i] = v;
}

__global__ void shfl_edges_kernel(int* out) {  // 32 threads, 8 results each
    const int lane = threadIdx.x % 32;
    int* o = out + 8 * lane;
    o[0] = __shfl_down_sync(FULL, lane, 5);
    o[1] = __shfl_up_sync(FULL, lane, 5);
    o[2] = __shfl_sync(FULL, lane * 10, 37);            // srcLane modulo 32
    o[3] = __shfl_sync(FULL, lane, (lane + 1) % 32);    // rotation
    o[4] = __shfl_down_sync(FULL, lane, 2, 8);          // segments of 8
    o[5] = __shfl_sync(FULL, lane, 3, 8);
    const unsigned long long big = (1ull << 40) + lane;
    o[6] = int(__shfl_xor_sync(FULL, big, 1) - (1ull << 40));
    const double d = 0.5 + lane;
    o[7] = int(__shfl_up_sync(FULL, d, 1) * 2);
}

// ---- 3. votes (block of 80: the last warp has 16 lanes) ----
__global__ void vote_kernel(unsigned* out) {
    const int t = threadIdx.x, lane = t % 32, w = t / 32;
    unsigned* o = out + 8 * w;
    const unsigned b = __ballot_sync(FULL, lane % 3 == 0);
    const int any_last = __any_sync(FULL, lane == 31);
    const int any_none = __any_sync(FULL, 0);
    const int all_true = __all_sync(FULL, 1);
    const int all_most = __all_sync(FULL, lane < 31);
    const unsigned all_b = __ballot_sync(FULL, 1);
    __syncwarp();
    const unsigned active = __activemask();
    if (lane == 0) {
        o[0] = b, o[1] = unsigned(any_last), o[2] = unsigned(any_none), o[3] = unsigned(all_true);
        o[4] = unsigned(all_most), o[5] = all_b, o[6] = active;
    }
}

// ---- 4. __syncthreads_count/or/and ----
__global__ void sync_pred_kernel(int* out) {
    const int t = threadIdx.x;
    const int c = __syncthreads_count(t % 5 == 0);
    const int o1 = __syncthreads_or(t == 200);
    const int o0 = __syncthreads_or(0);
    const int a1 = __syncthreads_and(t < 256);
    const int a0 = __syncthreads_and(t != 7);
    bool loop_ok = true;
    for (int k = 0; k < 10; ++k) loop_ok &= __syncthreads_count(t < 30 * k) == min(30 * k, 256);
    if (t == 0) out[0] = c, out[1] = o1, out[2] = o0, out[3] = a1, out[4] = a0;
    out[8 + t] = loop_ok;
    if (t >= 100) return;  // finished threads leave later barriers
    const int rest = __syncthreads_count(1);
    const int rest_and = __syncthreads_and(1);
    if (t == 0) out[5] = rest, out[6] = rest_and;
}

// ---- 5. atomics ----
__global__ void atomic_kernel(float* fsum, int* isum, int* olds, int* maxes) {
    const int i = blockIdx.x * blockDim.x + threadIdx.x;
    __shared__ int m;
    if (threadIdx.x == 0) m = -1;
    __syncthreads();
    atomicAdd(fsum, 1.0f);
    olds[i] = atomicAdd(isum, i + 1);
    atomicMax(&m, int(threadIdx.x * 37 % 256) + int(blockIdx.x));
    __syncthreads();
    if (threadIdx.x == 0) maxes[blockIdx.x] = m;
}

// ---- 6. early return and deadlocks ----
__global__ void early_return_kernel(int n, int* out) {
    const int i = blockIdx.x * blockDim.x + threadIdx.x;
    if (i >= n) return;
    out[i] = 2 * i;
}
// Half of every warp waits at __syncthreads, the other half at a warp collective: neither can ever be released.
__global__ void divergent_sync_kernel(int* out) {
    int v = threadIdx.x;
    if (threadIdx.x % 32 < 16)
        __syncthreads();
    else
        v = __shfl_xor_sync(FULL, v, 1);
    out[threadIdx.x] = v;
}
// Threads that finished do not take part in later barriers (as on current GPUs): this one completes.
__global__ void half_exit_kernel(int* out) {
    if (threadIdx.x >= 128) return;
    out[threadIdx.x] = __syncthreads_count(1);
}
__global__ void exited_lane_kernel(int* out) {
    if (threadIdx.x % 32 < 16) return;
    out[threadIdx.x] = __shfl_xor_sync(FULL, int(threadIdx.x), 1);
}
__global__ void bad_mask_kernel(int* out) { out[threadIdx.x] = __shfl_sync(0x0000ffffu, int(threadIdx.x), 0); }

// ---- 7. struct by value, templates ----
struct Params {
    int n;
    float scale;
    const float* in;
    float* out;
};
template <class T>
__global__ void scale_kernel(Params p, T bias) {
    const int i = blockIdx.x * blockDim.x + threadIdx.x;
    p.scale *= 2;  // this thread's copy only
    if (i < p.n) p.out[i] = p.in[i] * p.scale + T(bias);
}
template <class A, class B>
__global__ void pair_kernel(A a, B b, double* out) { out[threadIdx.x] = double(a) * threadIdx.x + double(b); }

// ---- 8. timing ----
__global__ void shuffle_heavy_kernel(int iters, float* out) {
    float v = float(threadIdx.x % 32);
    for (int k = 0; k < iters; ++k) v = __shfl_xor_sync(FULL, v, 1 + k % 31) * 0.5f + 1.0f;
    out[threadIdx.x] = v;
}

// floating-point intrinsics: values through volatile so nothing is folded at compile time
__global__ void rn_kernel(const float* in, float* out) {
    const float a = in[0], c = in[1];
    out[0] = __fadd_rn(__fmul_rn(a, a), c);
    out[1] = __fmaf_rn(a, a, c);
    out[2] = __fadd_rn(a * a, c);
}

// min/max next to std::min/std::max
static bool minmax_ok() {
    int a = 3, b = -2;
    float x = 1.5f, y = -0.5f;
    bool ok = std::min(a, b) == -2 && std::max(a, b) == 3 && std::min(x, y) == -0.5f && std::max(x, y) == 1.5f;
    ok &= min(a, b) == -2 && max(a, b) == 3 && min(x, y) == -0.5f && max(x, y) == 1.5f;
    ok &= min(int64_t(5), int64_t(7)) == 5 && max(2u, 9u) == 9u && min(1.0, 2.0) == 1.0;
    using namespace std;
    ok &= min(a, b) == -2 && max(x, y) == 1.5f && std::min<long>(4, 6) == 4;
    return ok;
}

// Runs fn in a child; the child's stderr comes back through a pipe. Returns the exit status.
template <class F>
static int in_child(F fn, std::string& err) {
    int fd[2];
    if (pipe(fd) != 0) return -1;
    std::fflush(stdout);
    const pid_t pid = fork();
    if (pid == 0) {
        close(fd[0]);
        dup2(fd[1], 2);
        fn();
        std::_Exit(0);
    }
    close(fd[1]);
    char buf[4096];
    ssize_t k;
    err.clear();
    while ((k = read(fd[0], buf, sizeof buf)) > 0) err.append(buf, size_t(k));
    close(fd[0]);
    int status = 0;
    waitpid(pid, &status, 0);
    return status;
}
static bool has(const std::string& s, const char* what) { return s.find(what) != std::string::npos; }

// context switch micro-benchmarks: two contexts passing control back and forth
namespace pingpong {
sz_emu::detail::Context main_ctx, fiber_ctx;
ucontext_t main_uc, fiber_uc;
void fiber() {
    for (;;) sz_emu::detail::ctx_switch(fiber_ctx, main_ctx);
}
void fiber_uc_fn() {
    for (;;) swapcontext(&fiber_uc, &main_uc);
}
}  // namespace pingpong

static double seconds_since(std::chrono::steady_clock::time_point t0) {
    return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

int main() {
    using clk = std::chrono::steady_clock;
    // 1
    {
        const int n = 7 * 256 - 100;
        std::vector<int> in(n);
        for (int i = 0; i < n; ++i) in[i] = i;
        std::vector<long long> partial(7, -1);
        SZ_LAUNCH(reduce_kernel, 7, 256, nullptr)(in.data(), n, partial.data());
        bool ok = cudaGetLastError() == cudaSuccess;
        long long total = 0;
        for (int b = 0; b < 7; ++b) {
            long long want = 0;
            for (int i = 256 * b; i < std::min(n, 256 * b + 256); ++i) want += i;
            ok &= partial[b] == want;
            total += partial[b];
        }
        check(ok && total == 1ll * n * (n - 1) / 2, "block_reduction");

        std::vector<int> idx(6 * 32, -1);
        SZ_LAUNCH(index_kernel, dim3(3, 2), dim3(8, 2, 2), 0)(idx.data());
        bool iok = true;
        for (int b = 0; b < 6; ++b)
            for (int z = 0; z < 2; ++z)
                for (int y = 0; y < 2; ++y)
                    for (int x = 0; x < 8; ++x) iok &= idx[b * 32 + x + 8 * (y + 2 * z)] == 1000 * b + 100 * z + 10 * y + x;
        check(iok, "index_3d");
    }
    // 2
    {
        const int n = 3 * 256;
        std::vector<int> in(n), out(n);
        std::vector<double> din(n), dout(n);
        for (int i = 0; i < n; ++i) in[i] = i * 7 % 101 - 50, din[i] = 0.25 * in[i];
        SZ_LAUNCH(warp_sum_kernel<int>, 3, 256, nullptr)(in.data(), out.data());
        SZ_LAUNCH(warp_sum_kernel<double>, 3, 256, nullptr)(din.data(), dout.data());
        bool ok = true;
        for (int w = 0; w < n / 32; ++w) {
            int s = 0;
            for (int l = 0; l < 32; ++l) s += in[32 * w + l];
            for (int l = 0; l < 32; ++l) ok &= out[32 * w + l] == s && dout[32 * w + l] == 0.25 * s;
        }
        check(ok, "warp_sum_shfl_xor");

        std::vector<int> e(8 * 32);
        SZ_LAUNCH(shfl_edges_kernel, 1, 32, nullptr)(e.data());
        bool eok = true;
        for (int l = 0; l < 32; ++l) {
            const int* o = &e[8 * l];
            eok &= o[0] == (l + 5 < 32 ? l + 5 : l) && o[1] == (l >= 5 ? l - 5 : l) && o[2] == 50 &&
                   o[3] == (l + 1) % 32 && o[4] == (l % 8 + 2 < 8 ? l + 2 : l) && o[5] == (l & ~7) + 3 &&
                   o[6] == (l ^ 1) && o[7] == (l >= 1 ? 2 * l - 1 : 1);
        }
        check(eok, "shfl_down_up_idx_edges");
    }
    // 3
    {
        std::vector<unsigned> o(3 * 8, 7);
        SZ_LAUNCH(vote_kernel, 1, 80, nullptr)(o.data());
        const unsigned b = 0x49249249u;
        bool ok = true;
        for (int w = 0; w < 2; ++w)
            ok &= o[8 * w] == b && o[8 * w + 1] == 1 && o[8 * w + 2] == 0 && o[8 * w + 3] == 1 && o[8 * w + 4] == 0 &&
                  o[8 * w + 5] == FULL && o[8 * w + 6] == FULL;
        // partial warp: lanes 16-31 do not exist
        ok &= o[16] == (b & 0xffffu) && o[17] == 0 && o[18] == 0 && o[19] == 1 && o[20] == 1 && o[21] == 0xffffu &&
              o[22] == 0xffffu;
        check(ok, "ballot_any_all");
    }
    // 4
    {
        std::vector<int> o(8 + 256, -1);
        SZ_LAUNCH(sync_pred_kernel, 1, 256, nullptr)(o.data());
        bool ok = o[0] == 52 && o[1] == 1 && o[2] == 0 && o[3] == 1 && o[4] == 0 && o[5] == 100 && o[6] == 1;
        for (int t = 0; t < 256; ++t) ok &= o[8 + t] == 1;
        check(ok, "syncthreads_count_or_and");
    }
    // 5
    {
        float fsum = 0;
        int isum = 0;
        std::vector<int> olds(4 * 256), maxes(4);
        SZ_LAUNCH(atomic_kernel, 4, 256, nullptr)(&fsum, &isum, olds.data(), maxes.data());
        bool ok = fsum == 1024.0f && isum == 1024 * 1025 / 2;
        std::vector<int> sorted(olds);
        std::sort(sorted.begin(), sorted.end());
        ok &= std::adjacent_find(sorted.begin(), sorted.end()) == sorted.end();  // every old value distinct
        for (int b = 0; b < 4; ++b) ok &= maxes[b] == 255 + b;
        int x = 5;
        unsigned long long u = 9;
        float f = 1.f;
        ok &= atomicCAS(&x, 5, 8) == 5 && x == 8 && atomicCAS(&x, 5, 9) == 8 && x == 8;
        ok &= atomicExch(&f, 2.f) == 1.f && f == 2.f && atomicMin(&x, 3) == 8 && x == 3;
        ok &= atomicAdd(&u, 1ull) == 9 && atomicCAS(&u, 10ull, 1ull) == 10 && u == 1;
        check(ok, "atomics");
    }
    // 6
    {
        std::vector<int> o(300, -1);
        SZ_LAUNCH(early_return_kernel, 3, 128, nullptr)(250, o.data());
        bool ok = true;
        for (int i = 0; i < 300; ++i) ok &= o[i] == (i < 250 ? 2 * i : -1);
        std::vector<int> h(256, -1);
        SZ_LAUNCH(half_exit_kernel, 1, 256, nullptr)(h.data());
        for (int i = 0; i < 256; ++i) ok &= h[i] == (i < 128 ? 128 : -1);
        check(ok, "early_return");

        std::string err;
        std::vector<int> d(256);
        int st = in_child([&] { SZ_LAUNCH(divergent_sync_kernel, 2, 256, nullptr)(d.data()); }, err);
        check(WIFSIGNALED(st) && WTERMSIG(st) == SIGABRT && has(err, "deadlock in kernel divergent_sync_kernel") &&
                  has(err, "block (0,0,0)") && has(err, "__syncthreads: 0-15,32-47,64-79") &&
                  has(err, "collective: 16-31,48-63,80-95") && has(err, "(128 threads)"),
              "divergent_syncthreads_aborts");
        if (failures) std::fprintf(stderr, "child stderr: %s\n", err.c_str());

        st = in_child(
            [&] {
                try {
                    SZ_LAUNCH(exited_lane_kernel, 1, 64, nullptr)(d.data());
                } catch (const std::runtime_error& e) {
                    std::fprintf(stderr, "caught: %s\n", e.what());
                }
                // the emulator is usable again after a failed launch
                std::vector<int> o2(64, -1);
                SZ_LAUNCH(early_return_kernel, 1, 64, nullptr)(64, o2.data());
                std::_Exit(o2[63] == 126 ? 0 : 3);
            },
            err);
        check(WIFEXITED(st) && WEXITSTATUS(st) == 0 && has(err, "caught: sz_emu: deadlock") &&
                  has(err, "warp collective: 16-31,48-63 (32 threads)") && has(err, "finished: 0-15,32-47 (32 threads)"),
              "collective_with_finished_lanes_throws");

        st = in_child([&] { SZ_LAUNCH(bad_mask_kernel, 1, 32, nullptr)(d.data()); }, err);
        check(WIFSIGNALED(st) && has(err, "__shfl_sync with mask 0x0000ffff") && has(err, "thread 0"), "bad_mask");

        SZ_LAUNCH(early_return_kernel, 1, 2048, nullptr)(1, d.data());
        const cudaError_t e1 = cudaGetLastError(), e2 = cudaGetLastError();
        check(e1 == cudaErrorInvalidConfiguration && e2 == cudaSuccess &&
                  std::string(cudaGetErrorString(e1)) == "invalid configuration argument",
              "invalid_configuration");
    }
    // 7
    {
        std::vector<float> in(100), out(100, -1);
        for (int i = 0; i < 100; ++i) in[i] = float(i);
        const Params p{100, 1.5f, in.data(), out.data()};
        SZ_LAUNCH(scale_kernel<float>, 2, 64, static_cast<cudaStream_t>(nullptr))(p, 1);
        bool ok = true;
        for (int i = 0; i < 100; ++i) ok &= out[i] == 3.0f * i + 1;
        std::vector<double> pd(32);
        SZ_LAUNCH((pair_kernel<int, float>), 1, 32, nullptr)(3, 0.5f, pd.data());
        for (int t = 0; t < 32; ++t) ok &= pd[t] == 3.0 * t + 0.5;
        check(ok && p.scale == 1.5f, "struct_by_value_template_kernel");
    }
    // intrinsics and min/max
    {
        volatile float va = 1.0f + 1.0f / 4096, vc = -(1.0f + 1.0f / 2048);
        const float in[2] = {va, vc};
        float o[3];
        SZ_LAUNCH(rn_kernel, 1, 1, nullptr)(in, o);
        check(o[0] == 0.0f && o[1] == std::ldexp(1.0f, -24) && o[2] == 0.0f && __float_as_int(1.0f) == 0x3f800000 &&
                  __int_as_float(0x40000000) == 2.0f,
              "rn_intrinsics");
        check(minmax_ok(), "min_max_beside_std");
    }
    // 8
    {
        using namespace pingpong;
        const int N = 2000000;
        alignas(16) static char stack[SZ_EMU_STACK_SIZE];
        sz_emu::detail::ctx_make(fiber_ctx, stack, &fiber);
        auto t0 = clk::now();
        for (int i = 0; i < N; ++i) sz_emu::detail::ctx_switch(main_ctx, fiber_ctx);
        const double ns_emu = seconds_since(t0) * 1e9 / (2.0 * N);

        static char ustack[64 * 1024];
        getcontext(&fiber_uc);
        fiber_uc.uc_stack.ss_sp = ustack;
        fiber_uc.uc_stack.ss_size = sizeof ustack;
        fiber_uc.uc_link = nullptr;
        makecontext(&fiber_uc, &fiber_uc_fn, 0);
        const int NU = 200000;
        t0 = clk::now();
        for (int i = 0; i < NU; ++i) swapcontext(&main_uc, &fiber_uc);
        const double ns_uc = seconds_since(t0) * 1e9 / (2.0 * NU);
        std::printf("timing: context switch %.1f ns (%s), glibc swapcontext %.1f ns\n", ns_emu,
                    SZ_EMU_UCONTEXT ? "ucontext build" : "asm", ns_uc);

        const int iters = 10000;
        std::vector<float> out(256);
        SZ_LAUNCH(shuffle_heavy_kernel, 1, 256, nullptr)(1, out.data());  // warm up stacks
        t0 = clk::now();
        SZ_LAUNCH(shuffle_heavy_kernel, 1, 256, nullptr)(iters, out.data());
        const double s = seconds_since(t0);
        std::printf("timing: 1 block x 256 threads x %d __shfl_xor_sync: %.1f ms (%.1f ns per thread-shuffle)\n", iters,
                    s * 1e3, s * 1e9 / (256.0 * iters));
        bool ok = true;  // every value converges to the fixed point 2 of v -> v/2 + 1
        for (float v : out) ok &= std::fabs(v - 2.0f) < 1e-3f;
        check(ok, "shuffle_heavy_result");
    }
    std::printf(failures ? "%d FAILED\n" : "all passed\n", failures);
    return failures ? 1 : 0;
}
