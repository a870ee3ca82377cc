// cuda_emulation.h: runs CUDA kernel source unchanged on the CPU, compiled as C++ against this header (included
// instead of <cuda_runtime.h>, with SZ_CUDA_EMULATION defined), so that kernels can be tested without a GPU. It aims
// at exact semantics, not speed.
//
// Every CUDA thread of a block is a fiber (a user-level context with its own stack) on the OS thread that launched
// the kernel. A scheduler runs the ready fibers in thread order, each until it waits at a barrier or returns, and
// releases a barrier once every participant has arrived. Blocks run one after another and launches are serialised
// by a process-wide mutex, so a launch is deterministic and atomics are plain read-modify-writes.
//
// Supported: 1- to 3-D grids and blocks (up to 1024 threads; warps are formed from the linear thread index, as on a
// GPU), static __shared__ memory, __syncthreads{,_count,_or,_and}, __syncwarp, warp shuffles and votes, the common
// atomics and math intrinsics, and launches written SZ_LAUNCH(kernel, grid, block, stream)(args...).
//
// Limitations:
//  - __shared__ variables are function-local statics: shared by the threads of a block, but holding whatever the
//    previous block or launch left there. Kernels must not rely on their contents before writing them (as on a
//    GPU). No dynamic (extern __shared__) shared memory.
//  - A warp collective needs a mask naming every existing lane of the warp, and all of them must take part. Lanes
//    missing from a partial last warp are absent: their ballot bits are 0, a shuffle from one returns the caller's
//    own value. There is no divergence model: __activemask() returns every lane that has not finished.
//  - Threads that finished do not take part in later __syncthreads (as on current GPUs). Threads waiting at
//    different barriers (part of a block at __syncthreads while others wait in a warp collective, or a collective
//    that some lane of the warp never reaches) can never be released: the launch then throws std::runtime_error
//    naming the kernel, the block and which threads wait where; so does a collective with an unsupported mask. The
//    stuck fibers are abandoned, not unwound: destructors of their locals do not run.
//  - Kernels must not throw (that calls std::terminate). No dynamic parallelism; streams are ignored and a launch
//    has completed when SZ_LAUNCH returns.
//  - The context switch is a few lines of x86-64 assembly (ELF); elsewhere, or with SZ_EMU_USE_UCONTEXT defined,
//    <ucontext.h>, much slower (glibc's swapcontext makes a system call). Not for AddressSanitizer or -flto builds.
//    Fiber stacks (SZ_EMU_STACK_SIZE, 256 KiB, plus a guard page) are reserved once and reused; pages are only
//    committed when touched.
//  - The header's own symbols have hidden visibility, so several shared libraries built with it (or with different
//    versions of it) can live in one process without sharing state or clashing.
//  - GCC warns about CUDA's `#pragma unroll` under -Wall (-Wunknown-pragmas) and cannot be told otherwise from here.
#ifndef SZ_CUDA_EMULATION_H
#define SZ_CUDA_EMULATION_H

#ifdef __CUDACC__
#error "cuda_emulation.h emulates CUDA for host compilers; CUDA builds include <cuda_runtime.h>"
#endif
#ifndef SZ_CUDA_EMULATION
#define SZ_CUDA_EMULATION 1
#endif

#include <math.h>
#include <sys/mman.h>
#include <unistd.h>

#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <memory>  // before __noinline__ is defined below: libstdc++ spells __attribute__((__noinline__)) in it
#include <mutex>
#include <new>
#include <stdexcept>
#include <string>
#include <tuple>
#include <type_traits>
#include <utility>
#include <vector>

#if defined(__x86_64__) && defined(__ELF__) && !defined(SZ_EMU_USE_UCONTEXT)
#define SZ_EMU_UCONTEXT 0
#else
#define SZ_EMU_UCONTEXT 1
#include <ucontext.h>
#endif

#ifndef SZ_EMU_STACK_SIZE
#define SZ_EMU_STACK_SIZE (256 * 1024)
#endif

// ---- qualifiers ----
#define __global__
#define __device__
#define __host__
#define __constant__
#define __forceinline__ inline
#define __noinline__ __attribute__((noinline))
#define __launch_bounds__(...)
#define __shared__ static

#pragma GCC visibility push(hidden)

// ---- vector types and runtime API ----
struct uint3 { unsigned x, y, z; };
struct dim3 {
    unsigned x, y, z;
    constexpr dim3(unsigned x_ = 1, unsigned y_ = 1, unsigned z_ = 1) : x(x_), y(y_), z(z_) {}
    constexpr dim3(uint3 v) : x(v.x), y(v.y), z(v.z) {}
    constexpr operator uint3() const { return {x, y, z}; }
};
// Same sizes and alignments as CUDA's, so structs holding them have the same layout on both sides.
struct alignas(8) int2 { int x, y; };
struct alignas(16) int4 { int x, y, z, w; };
struct alignas(8) float2 { float x, y; };
inline int2 make_int2(int x, int y) { return {x, y}; }
inline int4 make_int4(int x, int y, int z, int w) { return {x, y, z, w}; }
inline float2 make_float2(float x, float y) { return {x, y}; }

struct CUstream_st;
typedef CUstream_st* cudaStream_t;
enum cudaError { cudaSuccess = 0, cudaErrorInvalidValue = 1, cudaErrorInvalidConfiguration = 9 };
typedef cudaError cudaError_t;

namespace sz_emu::detail {
inline thread_local cudaError_t last_error = cudaSuccess;  // per host thread, like CUDA's
inline thread_local bool in_launch = false;
}  // namespace sz_emu::detail

inline cudaError_t cudaGetLastError() {
    const cudaError_t e = sz_emu::detail::last_error;
    sz_emu::detail::last_error = cudaSuccess;
    return e;
}
inline cudaError_t cudaPeekAtLastError() { return sz_emu::detail::last_error; }
inline const char* cudaGetErrorString(cudaError_t e) {
    switch (e) {
        case cudaSuccess: return "no error";
        case cudaErrorInvalidValue: return "invalid argument";
        case cudaErrorInvalidConfiguration: return "invalid configuration argument";
    }
    return "unrecognized error code";
}
// Launches are synchronous, so there is never anything to wait for.
inline cudaError_t cudaDeviceSynchronize() { return cudaSuccess; }
inline cudaError_t cudaStreamSynchronize(cudaStream_t) { return cudaSuccess; }

// Built-in indices: set by the scheduler before it resumes a thread (threadIdx) or starts a block (blockIdx).
inline uint3 threadIdx, blockIdx;
inline dim3 blockDim, gridDim;
inline constexpr int warpSize = 32;

// ---- device maths ----
// Plain overloads at global scope, like CUDA's: an exact match beats the std::min/std::max templates when both are
// visible, and std::min(...) written out is untouched.
#define SZ_EMU_MINMAX(T)                                 \
    inline T min(T a, T b) { return b < a ? b : a; } \
    inline T max(T a, T b) { return a < b ? b : a; }
SZ_EMU_MINMAX(int)
SZ_EMU_MINMAX(unsigned)
SZ_EMU_MINMAX(long)
SZ_EMU_MINMAX(unsigned long)
SZ_EMU_MINMAX(long long)
SZ_EMU_MINMAX(unsigned long long)
#undef SZ_EMU_MINMAX
inline float min(float a, float b) { return fminf(a, b); }  // CUDA's float min/max ignore a NaN operand
inline float max(float a, float b) { return fmaxf(a, b); }
inline double min(double a, double b) { return fmin(a, b); }
inline double max(double a, double b) { return fmax(a, b); }

#if !defined(__GLIBC__) || !defined(_GNU_SOURCE)  // glibc declares sincosf itself
inline void sincosf(float x, float* s, float* c) { *s = sinf(x), *c = cosf(x); }
inline void sincos(double x, double* s, double* c) { *s = sin(x), *c = cos(x); }
#endif
inline float rsqrtf(float x) { return 1.0f / sqrtf(x); }
inline double rsqrt(double x) { return 1.0 / sqrt(x); }

namespace sz_emu::detail {
// The compiler may not fuse a*b+c into an FMA across a value passed through here. CUDA's _rn intrinsics promise
// separately rounded operations, while GCC contracts by default (-ffp-contract=fast) once FMA is available.
template <class T>
inline T rounded(T v) {
#if defined(__GNUC__) && defined(__SSE2__)
    __asm__("" : "+x"(v));
#elif defined(__GNUC__) && defined(__aarch64__)
    __asm__("" : "+w"(v));
#else
    volatile T t = v;
    v = t;
#endif
    return v;
}
template <class To, class From>
inline To bit_cast(From v) {
    static_assert(sizeof(To) == sizeof(From), "bit cast between types of different sizes");
    To r;
    std::memcpy(&r, &v, sizeof r);
    return r;
}
}  // namespace sz_emu::detail

#define SZ_EMU_RN(name, T, op) \
    inline T name(T a, T b) { return sz_emu::detail::rounded(sz_emu::detail::rounded(a) op sz_emu::detail::rounded(b)); }
SZ_EMU_RN(__fmul_rn, float, *)
SZ_EMU_RN(__fadd_rn, float, +)
SZ_EMU_RN(__fsub_rn, float, -)
SZ_EMU_RN(__fdiv_rn, float, /)
SZ_EMU_RN(__dmul_rn, double, *)
SZ_EMU_RN(__dadd_rn, double, +)
SZ_EMU_RN(__dsub_rn, double, -)
SZ_EMU_RN(__ddiv_rn, double, /)
#undef SZ_EMU_RN
inline float __fmaf_rn(float a, float b, float c) { return std::fma(a, b, c); }
inline double __fma_rn(double a, double b, double c) { return std::fma(a, b, c); }
inline float __fsqrt_rn(float x) { return sqrtf(x); }

inline int __float_as_int(float x) { return sz_emu::detail::bit_cast<int>(x); }
inline float __int_as_float(int x) { return sz_emu::detail::bit_cast<float>(x); }
inline unsigned __float_as_uint(float x) { return sz_emu::detail::bit_cast<unsigned>(x); }
inline float __uint_as_float(unsigned x) { return sz_emu::detail::bit_cast<float>(x); }
inline long long __double_as_longlong(double x) { return sz_emu::detail::bit_cast<long long>(x); }
inline double __longlong_as_double(long long x) { return sz_emu::detail::bit_cast<double>(x); }
inline int __popc(unsigned x) { return __builtin_popcount(x); }
inline int __popcll(unsigned long long x) { return __builtin_popcountll(x); }
inline int __ffs(int x) { return __builtin_ffs(x); }
inline int __clz(int x) { return x == 0 ? 32 : __builtin_clz(unsigned(x)); }
template <class T>
inline T __ldg(const T* p) { return *p; }
inline void __threadfence() {}
inline void __threadfence_block() {}

// ---- atomics: threads never run concurrently, so a plain read-modify-write is atomic ----
#define SZ_EMU_ATOMIC(name, T, update) \
    inline T name(T* p, T v) {         \
        const T old = *p;              \
        *p = (update);                 \
        return old;                    \
    }
#define SZ_EMU_ATOMIC_INT(name, update) SZ_EMU_ATOMIC(name, int, update) SZ_EMU_ATOMIC(name, unsigned, update)
SZ_EMU_ATOMIC_INT(atomicAdd, old + v)
SZ_EMU_ATOMIC(atomicAdd, unsigned long long, old + v)
SZ_EMU_ATOMIC(atomicAdd, float, old + v)
SZ_EMU_ATOMIC(atomicAdd, double, old + v)
SZ_EMU_ATOMIC_INT(atomicSub, old - v)
SZ_EMU_ATOMIC_INT(atomicMax, max(old, v))
SZ_EMU_ATOMIC_INT(atomicMin, min(old, v))
SZ_EMU_ATOMIC_INT(atomicExch, v)
SZ_EMU_ATOMIC(atomicExch, float, v)
SZ_EMU_ATOMIC_INT(atomicOr, old | v)
SZ_EMU_ATOMIC_INT(atomicAnd, old & v)
SZ_EMU_ATOMIC_INT(atomicXor, old ^ v)
#undef SZ_EMU_ATOMIC_INT
#undef SZ_EMU_ATOMIC
#define SZ_EMU_CAS(T)                                \
    inline T atomicCAS(T* p, T compare, T value) {   \
        const T old = *p;                            \
        if (old == compare) *p = value;              \
        return old;                                  \
    }
SZ_EMU_CAS(int)
SZ_EMU_CAS(unsigned)
SZ_EMU_CAS(unsigned long long)
#undef SZ_EMU_CAS

// ---- fibers ----
namespace sz_emu::detail {

#if SZ_EMU_UCONTEXT
struct Context { ucontext_t uc; };
inline void ctx_switch(Context& from, Context& to) { swapcontext(&from.uc, &to.uc); }
inline void ctx_make(Context& c, char* stack, void (*entry)()) {
    getcontext(&c.uc);
    c.uc.uc_stack.ss_sp = stack;
    c.uc.uc_stack.ss_size = SZ_EMU_STACK_SIZE;
    c.uc.uc_link = nullptr;
    makecontext(&c.uc, entry, 0);
}
#else
struct Context { void* sp = nullptr; };
extern "C" void sz_emu_switch_v1(void** save_sp, void* load_sp);
extern "C" void sz_emu_start_v1();
// sz_emu_switch_v1 pushes the callee-saved registers and the MXCSR and x87 control words (callee-saved too in the
// SysV ABI), stores the stack pointer in *save_sp, loads load_sp and pops the same from there. A new context's stack
// is laid out by ctx_make so that its first resume returns into sz_emu_start_v1, which calls the entry function held
// in r13 on a 16-byte aligned stack; the entry never returns. The symbols are local to the object file (no .globl),
// so every translation unit and library that includes this header has its own copy and nothing can clash; the
// code uses no absolute addresses, so it is position independent.
__asm__(
    ".pushsection .text\n"
    ".p2align 4\n"
    ".type sz_emu_switch_v1, @function\n"
    "sz_emu_switch_v1:\n"
    "  pushq %rbp; pushq %rbx; pushq %r12; pushq %r13; pushq %r14; pushq %r15\n"
    "  subq $16, %rsp; stmxcsr 8(%rsp); fnstcw (%rsp)\n"
    "  movq %rsp, (%rdi)\n"
    "  movq %rsi, %rsp\n"
    "  fldcw (%rsp); ldmxcsr 8(%rsp); addq $16, %rsp\n"
    "  popq %r15; popq %r14; popq %r13; popq %r12; popq %rbx; popq %rbp\n"
    "  ret\n"
    ".size sz_emu_switch_v1, .-sz_emu_switch_v1\n"
    ".p2align 4\n"
    ".type sz_emu_start_v1, @function\n"
    "sz_emu_start_v1:\n"
    "  callq *%r13; ud2\n"
    ".size sz_emu_start_v1, .-sz_emu_start_v1\n"
    ".popsection\n");
inline void ctx_switch(Context& from, Context& to) { sz_emu_switch_v1(&from.sp, to.sp); }
inline void ctx_make(Context& c, char* stack, void (*entry)()) {
    // The frame sz_emu_switch_v1 pops, lowest address first: x87 control word, MXCSR, r15, r14, r13, r12, rbx,
    // rbp, return address; then two zero words. After the return, rsp = top - 16: aligned for the call.
    const uintptr_t top = (reinterpret_cast<uintptr_t>(stack) + SZ_EMU_STACK_SIZE) & ~uintptr_t(15);
    uint64_t* sp = reinterpret_cast<uint64_t*>(top) - 11;
    unsigned mxcsr;
    unsigned short fpucw;
    __asm__ volatile("stmxcsr %0\n\tfnstcw %1" : "=m"(mxcsr), "=m"(fpucw));
    std::memset(sp, 0, 11 * sizeof *sp);
    sp[0] = fpucw;
    sp[1] = mxcsr;
    sp[4] = reinterpret_cast<uint64_t>(entry);
    sp[8] = reinterpret_cast<uint64_t>(&sz_emu_start_v1);
    c.sp = sp;
}
#endif

inline char* new_stack() {
    const size_t page = size_t(sysconf(_SC_PAGESIZE));
    int flags = MAP_PRIVATE | MAP_ANONYMOUS;
#ifdef MAP_NORESERVE
    flags |= MAP_NORESERVE;
#endif
    void* p = mmap(nullptr, SZ_EMU_STACK_SIZE + page, PROT_READ | PROT_WRITE, flags, -1, 0);
    if (p == MAP_FAILED) throw std::bad_alloc();
    mprotect(p, page, PROT_NONE);  // guard page: an overflow faults instead of corrupting the neighbouring stack
    return static_cast<char*>(p) + page;
}

// ---- scheduler ----
enum class State : unsigned char { Ready, BlockBarrier, WarpBarrier, Done };

struct Warp {
    // Collective n of a lane writes buf[n % 2]. A lane can write the same buffer again only at collective n + 2,
    // after collective n + 1 was released, i.e. after every lane has finished reading collective n.
    uint64_t buf[2][32];
    unsigned round[32];
    unsigned lanes;  // bit l: lane l exists (a block's last warp may be partial)
    int size, waiting;
};

struct Engine {
    std::mutex mutex;  // one launch at a time: shared memory is static
    std::vector<char*> stacks;
    std::vector<Context> ctx;
    std::vector<State> state;
    std::vector<Warp> warps;
    Context sched;
    bool active = false;
    int n = 0, cur = 0, live = 0, at_block = 0;
    int bar_acc = 0, bar_total = 0, bar_size = 0;  // __syncthreads_*: sum of predicates, released total, participants
    void (*body)(const void*) = nullptr;  // runs the kernel for the current threadIdx
    const void* body_arg = nullptr;
    const char *kernel = "", *file = "";  // the launch, for messages
    int line = 0;
    std::string error;  // set by a thread that hit an error; the scheduler throws it
};

inline Engine& eng() {
    static Engine* e = new Engine;  // never destroyed: another thread may still be launching at exit
    return *e;
}

inline std::string where(const Engine& e) {
    char b[512];
    std::snprintf(b, sizeof b, "kernel %s (launched at %s:%d), block (%u,%u,%u) of grid (%u,%u,%u), block size (%u,%u,%u)",
                  e.kernel, e.file, e.line, blockIdx.x, blockIdx.y, blockIdx.z, gridDim.x, gridDim.y, gridDim.z,
                  blockDim.x, blockDim.y, blockDim.z);
    return b;
}

// Linear thread indices in state s as ranges ("0-15,32-47"), the first 12 ranges only.
inline std::string thread_list(const Engine& e, State s) {
    std::string r;
    int count = 0, ranges = 0;
    for (int t = 0; t < e.n; ++t) {
        if (e.state[t] != s) continue;
        int u = t;
        while (u + 1 < e.n && e.state[u + 1] == s) ++u;
        if (++ranges <= 12) r += (r.empty() ? "" : ",") + std::to_string(t) + (u > t ? "-" + std::to_string(u) : "");
        count += u - t + 1;
        t = u;
    }
    if (ranges > 12) r += ",...";
    return count ? r + " (" + std::to_string(count) + " threads)" : "none";
}

[[noreturn]] inline void fail_in_fiber(const std::string& what) {
    Engine& e = eng();
    e.error = "sz_emu: " + what + " in " + where(e) + ", thread " + std::to_string(e.cur);
    ctx_switch(e.ctx[e.cur], e.sched);
    std::abort();  // never resumed
}

inline Engine& fiber_engine(const char* what) {
    Engine& e = eng();
    if (!e.active) {
        std::fprintf(stderr, "sz_emu: %s called outside a kernel launch\n", what);
        std::abort();
    }
    return e;
}

inline void fiber_main() noexcept {
    Engine& e = eng();
    e.body(e.body_arg);
    const int t = e.cur;
    e.state[t] = State::Done;
    --e.live;
    ctx_switch(e.ctx[t], e.sched);
    std::abort();  // a finished thread is never resumed
}

inline void run_block(Engine& e) {
    for (int t = 0; t < e.n; ++t) {
        ctx_make(e.ctx[t], e.stacks[t], &fiber_main);
        e.state[t] = State::Ready;
    }
    for (size_t w = 0; w < e.warps.size(); ++w) {
        Warp& wp = e.warps[w];
        wp.size = ::min(32, e.n - int(32 * w));
        wp.lanes = wp.size == 32 ? ~0u : (1u << wp.size) - 1;
        wp.waiting = 0;
        std::memset(wp.round, 0, sizeof wp.round);
    }
    e.live = e.n;
    e.at_block = e.bar_acc = 0;
    const unsigned bx = blockDim.x, by = blockDim.y;
    const bool linear = blockDim.y == 1 && blockDim.z == 1;
    for (;;) {
        for (int t = 0; t < e.n; ++t) {
            if (e.state[t] != State::Ready) continue;
            e.cur = t;
            const unsigned u = unsigned(t);
            threadIdx = linear ? uint3{u, 0, 0} : uint3{u % bx, u / bx % by, u / (bx * by)};
            ctx_switch(e.sched, e.ctx[t]);
            if (!e.error.empty()) {
                std::string msg;
                msg.swap(e.error);
                throw std::runtime_error(msg);
            }
        }
        if (e.live == 0) return;
        bool released = false;
        for (Warp& w : e.warps) {
            if (w.waiting == 0 || w.waiting != w.size) continue;  // a finished lane keeps its warp from releasing
            const int t0 = int(&w - e.warps.data()) * 32;
            for (int t = t0; t < t0 + w.size; ++t) e.state[t] = State::Ready;
            w.waiting = 0;
            released = true;
        }
        if (released) continue;
        if (e.at_block != e.live)
            throw std::runtime_error("sz_emu: deadlock in " + where(e) + ": threads waiting at __syncthreads: " +
                                     thread_list(e, State::BlockBarrier) + "; at a warp collective: " +
                                     thread_list(e, State::WarpBarrier) + "; finished: " +
                                     thread_list(e, State::Done) +
                                     " (a __syncthreads not reached by every thread of the block, or a warp "
                                     "collective not reached by every lane of the warp)");
        // Threads that finished do not take part, as on current GPUs.
        e.bar_total = e.bar_acc;
        e.bar_size = e.live;
        e.bar_acc = e.at_block = 0;
        for (int t = 0; t < e.n; ++t)
            if (e.state[t] == State::BlockBarrier) e.state[t] = State::Ready;
    }
}

inline void launch(dim3 grid, dim3 block, void (*body)(const void*), const void* arg, const char* kernel,
                   const char* file, int line) {
    const unsigned long long n = 1ull * block.x * block.y * block.z;
    if (n == 0 || n > 1024 || block.z > 64 || grid.x == 0 || grid.y == 0 || grid.z == 0 || grid.y > 65535 ||
        grid.z > 65535) {
        last_error = cudaErrorInvalidConfiguration;  // reported by cudaGetLastError(), as with CUDA
        return;
    }
    if (in_launch) {  // the mutex would deadlock
        std::fprintf(stderr, "sz_emu: kernel %s launched from inside a kernel (%s:%d)\n", kernel, file, line);
        std::abort();
    }
    Engine& e = eng();
    std::lock_guard<std::mutex> lock(e.mutex);
    struct Reset {
        Engine& e;
        ~Reset() { e.active = in_launch = false; }
    } reset{e};
    while (e.stacks.size() < n) e.stacks.push_back(new_stack());
    if (e.ctx.size() < n) e.ctx.resize(n);
    e.state.assign(n, State::Done);
    e.warps.resize((n + 31) / 32);
    e.n = int(n), e.body = body, e.body_arg = arg, e.kernel = kernel, e.file = file, e.line = line;
    e.error.clear();
    gridDim = grid, blockDim = block;
    e.active = in_launch = true;
    for (unsigned z = 0; z < grid.z; ++z)
        for (unsigned y = 0; y < grid.y; ++y)
            for (unsigned x = 0; x < grid.x; ++x) {
                blockIdx = {x, y, z};
                run_block(e);
            }
}

// A thread waits here for the rest of its block; returns the number of threads whose predicate was non-zero.
inline int block_barrier(int pred) {
    Engine& e = fiber_engine("__syncthreads");
    const int t = e.cur;
    e.bar_acc += pred != 0;
    e.state[t] = State::BlockBarrier;
    ++e.at_block;
    ctx_switch(e.ctx[t], e.sched);
    return e.bar_total;  // stays valid until the next release, which needs this thread again
}

struct Exchange {
    const uint64_t* v;  // every lane's value, indexed by lane
    unsigned lanes;     // lanes that exist
    int lane;           // the caller's
};

inline Exchange warp_exchange(uint64_t value, unsigned mask, const char* what) {
    Engine& e = fiber_engine(what);
    const int t = e.cur, lane = t & 31;
    Warp& w = e.warps[t >> 5];
    if ((mask & w.lanes) != w.lanes) {
        char m[200];
        std::snprintf(m, sizeof m, "%s with mask 0x%08x (only masks naming every lane of the warp, 0x%08x, are emulated)",
                      what, mask, w.lanes);
        fail_in_fiber(m);
    }
    uint64_t* buf = w.buf[w.round[lane]++ & 1];
    buf[lane] = value;
    e.state[t] = State::WarpBarrier;
    ++w.waiting;
    ctx_switch(e.ctx[t], e.sched);
    return {buf, w.lanes, lane};
}

enum class Shfl { Idx, Up, Down, Xor };

template <class T>
inline T shuffle(unsigned mask, T var, int b, int width, Shfl mode, const char* what) {
    static_assert(std::is_trivially_copyable<T>::value && sizeof(T) <= 8,
                  "warp shuffles move trivially copyable values of at most 8 bytes");
    uint64_t bits = 0;
    std::memcpy(&bits, &var, sizeof(T));
    const Exchange x = warp_exchange(bits, mask, what);
    // The source lane as PTX shfl.sync computes it: segments of `width` lanes, b taken modulo 32. A source outside
    // the segment, or a lane the block does not have, leaves the caller's own value.
    const int seg = (32 - width) & 31, lo = x.lane & seg, hi = lo | (31 & ~seg), bv = b & 31;
    int j = 0;
    bool ok = true;
    switch (mode) {
        case Shfl::Idx: j = lo | (bv & ~seg); break;
        case Shfl::Up: j = x.lane - bv, ok = j >= lo; break;
        case Shfl::Down: j = x.lane + bv, ok = j <= hi; break;
        case Shfl::Xor: j = x.lane ^ bv, ok = j <= hi; break;
    }
    if (ok && (x.lanes >> j & 1u)) std::memcpy(&var, &x.v[j], sizeof(T));
    return var;
}

struct Vote {
    unsigned ballot, lanes;
};
inline Vote vote(unsigned mask, int pred, const char* what) {
    const Exchange x = warp_exchange(pred != 0, mask, what);
    Vote r{0, x.lanes};
    for (int l = 0; l < 32; ++l)
        if ((x.lanes >> l & 1u) && x.v[l]) r.ballot |= 1u << l;
    return r;
}

template <class F>
struct Launch {
    const char *kernel, *file;
    int line;
    dim3 grid, block;
    F f;
    template <class... A>
    void operator()(A&&... args) const {
        // The arguments are copied once per launch; each thread copies them again into the kernel's by-value
        // parameters, so a thread that modifies a parameter modifies its own copy, as in CUDA.
        struct Call {
            const F* f;
            std::tuple<std::decay_t<A>...> args;
        };
        const Call call{&f, std::tuple<std::decay_t<A>...>(std::forward<A>(args)...)};
        auto run = [](const void* p) {
            const Call& c = *static_cast<const Call*>(p);
            std::apply(*c.f, c.args);
        };
        launch(grid, block, run, &call, kernel, file, line);
    }
};

template <class F, class Stream>
inline Launch<F> make_launch(const char* kernel, const char* file, int line, dim3 grid, dim3 block, const Stream&, F f) {
    return {kernel, file, line, grid, block, f};
}

}  // namespace sz_emu::detail

// ---- barriers and warp collectives ----
inline void __syncthreads() { sz_emu::detail::block_barrier(0); }
inline int __syncthreads_count(int pred) { return sz_emu::detail::block_barrier(pred); }
inline int __syncthreads_or(int pred) { return sz_emu::detail::block_barrier(pred) != 0; }
inline int __syncthreads_and(int pred) {
    return sz_emu::detail::block_barrier(pred) == sz_emu::detail::eng().bar_size;
}
inline void __syncwarp(unsigned mask = 0xffffffffu) { sz_emu::detail::warp_exchange(0, mask, "__syncwarp"); }

template <class T>
inline T __shfl_sync(unsigned mask, T var, int srcLane, int width = warpSize) {
    return sz_emu::detail::shuffle(mask, var, srcLane, width, sz_emu::detail::Shfl::Idx, "__shfl_sync");
}
template <class T>
inline T __shfl_up_sync(unsigned mask, T var, unsigned delta, int width = warpSize) {
    return sz_emu::detail::shuffle(mask, var, int(delta), width, sz_emu::detail::Shfl::Up, "__shfl_up_sync");
}
template <class T>
inline T __shfl_down_sync(unsigned mask, T var, unsigned delta, int width = warpSize) {
    return sz_emu::detail::shuffle(mask, var, int(delta), width, sz_emu::detail::Shfl::Down, "__shfl_down_sync");
}
template <class T>
inline T __shfl_xor_sync(unsigned mask, T var, int laneMask, int width = warpSize) {
    return sz_emu::detail::shuffle(mask, var, laneMask, width, sz_emu::detail::Shfl::Xor, "__shfl_xor_sync");
}

inline unsigned __ballot_sync(unsigned mask, int pred) { return sz_emu::detail::vote(mask, pred, "__ballot_sync").ballot; }
inline int __any_sync(unsigned mask, int pred) { return sz_emu::detail::vote(mask, pred, "__any_sync").ballot != 0; }
inline int __all_sync(unsigned mask, int pred) {
    const sz_emu::detail::Vote v = sz_emu::detail::vote(mask, pred, "__all_sync");
    return v.ballot == v.lanes;
}
inline unsigned __activemask() {
    const sz_emu::detail::Engine& e = sz_emu::detail::fiber_engine("__activemask");
    const int t0 = e.cur & ~31, size = e.warps[e.cur >> 5].size;
    unsigned m = 0;
    for (int l = 0; l < size; ++l)
        if (e.state[t0 + l] != sz_emu::detail::State::Done) m |= 1u << l;
    return m;
}

#pragma GCC visibility pop

// SZ_LAUNCH(kernel, grid, block, stream)(args...) runs kernel(args...) on every thread of the grid and returns when
// all are done; the stream is ignored. A kernel name with a comma (k<A, B>) must be parenthesised: (k<A, B>).
#define SZ_LAUNCH(kernel, grid, block, stream)                                                 \
    ::sz_emu::detail::make_launch(#kernel, __FILE__, __LINE__, (grid), (block), (stream), \
                                  [](const auto&... sz_emu_args) { kernel(sz_emu_args...); })

#endif  // SZ_CUDA_EMULATION_H
