// Internals shared by the CUDA backend's translation units: error checks, launch geometry, the
// preprocessing/binning steps forward and backward both run, warp reductions. Device code: nvcc only.
#pragma once

#include <cuda_runtime.h>

#include <stdexcept>
#include <string>

#include "rasterize.cuh"

namespace ctgs {
namespace gpu {

// Throws on a failed CUDA call, naming the call and the file:line (the binding turns it into a Python error).
inline void check_cuda(cudaError_t e, const char* what, const char* file, int line) {
  if (e != cudaSuccess)
    throw std::runtime_error(std::string("ctgs cuda: ") + what + " failed at " + file + ":" +
                             std::to_string(line) + ": " + cudaGetErrorString(e));
}
#define CTGS_CUDA_CHECK(call) ::ctgs::gpu::check_cuda((call), #call, __FILE__, __LINE__)
// After a kernel launch: catches bad launch configurations now (execution errors surface at the next sync).
#define CTGS_CUDA_LAUNCH_CHECK(name) ::ctgs::gpu::check_cuda(cudaGetLastError(), name, __FILE__, __LINE__)

// One 16x16 block per screen tile, one thread per pixel (the tile size is shared with the CPU backend).
constexpr int BLOCK_X = TILE_W, BLOCK_Y = TILE_H, BLOCK_SIZE = BLOCK_X * BLOCK_Y;
static_assert(BLOCK_SIZE % 32 == 0, "the warp reductions assume whole warps");
// Primitives staged in shared memory per batch. The double SurfelPrim is ~2x larger, so half a block's
// worth keeps the batch under the 48 KiB of static shared memory.
template <typename S>
struct Batch {
  static constexpr int SIZE = sizeof(S) == 4 ? BLOCK_SIZE : BLOCK_SIZE / 2;
};
// Threads for the one-thread-per-primitive / per-tile kernels.
constexpr int LINEAR_BLOCK = 256;
inline unsigned grid_1d(long long n) { return unsigned((n + LINEAR_BLOCK - 1) / LINEAR_BLOCK); }

constexpr unsigned FULL_MASK = 0xffffffffu;

template <typename T>
__device__ inline T warp_sum(T v) {
#pragma unroll
  for (int o = 16; o > 0; o >>= 1) v += __shfl_xor_sync(FULL_MASK, v, o);
  return v;
}

// Per-primitive constants in camera space, their pixel bounds (empty when culled: centre before the near
// plane, or opacity < MIN_ALPHA so no alpha can reach MIN_ALPHA -- the CPU backend's rule) and their tile
// counts. Writes prims [N], rects [N] and, if non-null, tiles_touched [N]. Asynchronous on `stream`.
template <typename S>
void preprocess(const SceneArgs<S>& a, SurfelPrim<S>* prims, PixelRect* rects, int64_t* tiles_touched,
                cudaStream_t stream);

// The tile list bin_tiles allocated (through Allocators::tile_list) and filled.
struct TileList {
  int64_t pairs;  // (tile, primitive) pairs
  int32_t* list;  // [pairs] primitive indices, tile by tile
};

// Per-tile lists in blending order (centre depth, ties by index), as the CPU backend's bin_primitives.
// Writes offsets [num_tiles + 1]; allocates and fills the list through alloc.tile_list. Synchronises the
// stream once (the host must learn the pair count to allocate).
template <typename S>
TileList bin_tiles(const SceneArgs<S>& a, const SurfelPrim<S>* prims, const PixelRect* rects,
                  const int64_t* tiles_touched, int64_t* offsets, const Allocators& alloc, cudaStream_t stream);

// Bytes of `count` objects of T from the scratch allocator, typed.
template <typename T>
inline T* scratch(const Allocators& alloc, long long count) {
  return static_cast<T*>(alloc.scratch(sizeof(T) * size_t(count > 0 ? count : 1)));
}

}  // namespace gpu
}  // namespace ctgs
