// The CUDA kernels of rasterize_cuda.cu compiled for the host against cuda_emulation.h, into namespace sz::emu: the
// test-only "cuda-emulated" backend runs them on CPU tensors, so CI exercises the real kernel source without a GPU.
// Built without floating-point contraction, so that, as on the GPU (see rmul/radd in surfel_math.h), the forward and
// backward kernels round every pair's alpha identically.
#pragma GCC optimize("fp-contract=off")
#define SZ_CUDA_EMULATION 1
#include "rasterize_cuda.cu"
