// Per-tile depth-sorted lists of the CUDA backend (3DGS/gsplat style): every (tile, primitive) pair gets a
// 64-bit key tile << RANK_BITS | depth_rank and one stable radix sort leaves each tile's pairs contiguous
// and in blending order. The depth rank (position of the primitive when all are sorted by centre depth,
// ties by index) replaces the usual 32 raw depth bits: it reproduces the CPU backend's order exactly, for
// float and double depths alike (raw float bits would tie doubles that differ past float precision), and
// needs only ceil(log2 N) bits, so the pair sort makes fewer radix passes.
#include <algorithm>

#include <cub/cub.cuh>

#include "common.cuh"

namespace ctgs {
namespace gpu {

namespace {

// IEEE bits made monotone as unsigned integers (flip all bits of negatives, the sign bit of positives),
// in the low 32 (float) or all 64 (double) bits: both depth sorts and the pair sort then share one cub
// instantiation (u64 keys, i32 values), which halves the compile time of this file.
__device__ inline unsigned long long depth_key(float z) {
  const uint32_t b = __float_as_uint(z);
  return (b & 0x80000000u) ? ~b : (b | 0x80000000u);
}
__device__ inline unsigned long long depth_key(double z) {
  const unsigned long long b = static_cast<unsigned long long>(__double_as_longlong(z));
  return (b & 0x8000000000000000ull) ? ~b : (b | 0x8000000000000000ull);
}

// Bits needed to write x (0 for 0).
inline int bit_width(unsigned long long x) {
  int b = 0;
  while (x != 0) {
    ++b;
    x >>= 1;
  }
  return b;
}

template <typename S>
__global__ void depth_keys_kernel(int N, const SurfelPrim<S>* prims, unsigned long long* keys, int32_t* index) {
  const int i = blockIdx.x * blockDim.x + threadIdx.x;
  if (i >= N) return;
  S z = prims[i].mu.z;
  if (z == S(0)) z = S(0);  // -0 and +0 compare equal on the CPU (then the index decides): one key for both
  keys[i] = depth_key(z);
  index[i] = i;
}

__global__ void rank_kernel(int N, const int32_t* order, int32_t* rank) {
  const int k = blockIdx.x * blockDim.x + threadIdx.x;
  if (k < N) rank[order[k]] = k;
}

// One thread per primitive writes its pairs at [start, start + tiles_touched) (start = exclusive prefix).
__global__ void duplicate_kernel(int N, int ntx, int rank_bits, const PixelRect* rects, const int64_t* cum_tiles,
                                 const int32_t* rank, unsigned long long* keys, int32_t* values) {
  const int i = blockIdx.x * blockDim.x + threadIdx.x;
  if (i >= N) return;
  const TileRect t = tiles_of(rects[i]);
  int64_t out = i == 0 ? 0 : cum_tiles[i - 1];
  const unsigned long long r = static_cast<unsigned long long>(rank[i]);
  for (int ty = t.y0; ty < t.y1; ++ty)
    for (int tx = t.x0; tx < t.x1; ++tx) {
      const unsigned long long tile = static_cast<unsigned long long>(ty) * ntx + tx;
      keys[out] = (tile << rank_bits) | r;
      values[out] = i;
      ++out;
    }
}

// offsets[t] = first sorted pair of tile t (lower bound of t << rank_bits); offsets[num_tiles] = pairs.
__global__ void tile_offsets_kernel(int num_tiles, int rank_bits, const unsigned long long* keys, int64_t pairs,
                                    int64_t* offsets) {
  const int t = blockIdx.x * blockDim.x + threadIdx.x;
  if (t > num_tiles) return;
  if (t == num_tiles) {
    offsets[t] = pairs;
    return;
  }
  const unsigned long long target = static_cast<unsigned long long>(t) << rank_bits;
  int64_t lo = 0, hi = pairs;
  while (lo < hi) {
    const int64_t mid = lo + (hi - lo) / 2;
    if (keys[mid] < target)
      lo = mid + 1;
    else
      hi = mid;
  }
  offsets[t] = lo;
}

}  // namespace

template <typename S>
TileList bin_tiles(const SceneArgs<S>& a, const SurfelPrim<S>* prims, const PixelRect* rects,
                  const int64_t* tiles_touched, int64_t* offsets, const Allocators& alloc, cudaStream_t stream) {
  using Key = unsigned long long;
  const int N = a.N;
  const int ntx = tiles_x(a.K.width), num_tiles = ntx * tiles_y(a.K.height);
  if (N == 0) {
    CTGS_CUDA_CHECK(cudaMemsetAsync(offsets, 0, sizeof(int64_t) * (num_tiles + 1), stream));
    return TileList{0, alloc.tile_list(0)};
  }
  // 1. Depth rank of every primitive: stable sort by depth key, so equal depths keep index order.
  Key* keys = scratch<Key>(alloc, N);
  Key* keys_sorted = scratch<Key>(alloc, N);
  int32_t* index = scratch<int32_t>(alloc, N);
  int32_t* order = scratch<int32_t>(alloc, N);
  int32_t* rank = scratch<int32_t>(alloc, N);
  depth_keys_kernel<S><<<grid_1d(N), LINEAR_BLOCK, 0, stream>>>(N, prims, keys, index);
  CTGS_CUDA_LAUNCH_CHECK("depth_keys_kernel");
  size_t bytes = 0;
  // int64 item counts here too: one cub instantiation for both sorts (it dominates the compile time).
  CTGS_CUDA_CHECK(cub::DeviceRadixSort::SortPairs(nullptr, bytes, keys, keys_sorted, index, order, int64_t(N), 0,
                                                  int(8 * sizeof(S)), stream));
  void* temp = alloc.scratch(bytes);
  CTGS_CUDA_CHECK(cub::DeviceRadixSort::SortPairs(temp, bytes, keys, keys_sorted, index, order, int64_t(N), 0,
                                                  int(8 * sizeof(S)), stream));
  rank_kernel<<<grid_1d(N), LINEAR_BLOCK, 0, stream>>>(N, order, rank);
  CTGS_CUDA_LAUNCH_CHECK("rank_kernel");

  // 2. Pair count: inclusive prefix sum of the tiles each primitive touches; the host needs the total.
  int64_t* cum = scratch<int64_t>(alloc, N);
  bytes = 0;
  CTGS_CUDA_CHECK(cub::DeviceScan::InclusiveSum(nullptr, bytes, tiles_touched, cum, N, stream));
  temp = alloc.scratch(bytes);
  CTGS_CUDA_CHECK(cub::DeviceScan::InclusiveSum(temp, bytes, tiles_touched, cum, N, stream));
  int64_t pairs = 0;
  CTGS_CUDA_CHECK(cudaMemcpyAsync(&pairs, cum + (N - 1), sizeof(int64_t), cudaMemcpyDeviceToHost, stream));
  CTGS_CUDA_CHECK(cudaStreamSynchronize(stream));

  // 3. Keys tile << rank_bits | rank, sorted on exactly the bits in use.
  const int rank_bits = std::max(1, bit_width(static_cast<unsigned long long>(N - 1)));
  const int tile_bits = std::max(1, bit_width(static_cast<unsigned long long>(num_tiles - 1)));
  if (rank_bits + tile_bits > 64) throw std::runtime_error("ctgs cuda: too many primitives x tiles for 64-bit keys");
  int32_t* list = alloc.tile_list(pairs);
  unsigned long long* pair_keys_sorted = scratch<unsigned long long>(alloc, pairs);
  if (pairs > 0) {
    unsigned long long* pair_keys = scratch<unsigned long long>(alloc, pairs);
    int32_t* pair_values = scratch<int32_t>(alloc, pairs);
    duplicate_kernel<<<grid_1d(N), LINEAR_BLOCK, 0, stream>>>(N, ntx, rank_bits, rects, cum, rank, pair_keys,
                                                               pair_values);
    CTGS_CUDA_LAUNCH_CHECK("duplicate_kernel");
    bytes = 0;
    CTGS_CUDA_CHECK(cub::DeviceRadixSort::SortPairs(nullptr, bytes, pair_keys, pair_keys_sorted, pair_values, list,
                                                    pairs, 0, rank_bits + tile_bits, stream));
    temp = alloc.scratch(bytes);
    CTGS_CUDA_CHECK(cub::DeviceRadixSort::SortPairs(temp, bytes, pair_keys, pair_keys_sorted, pair_values, list,
                                                    pairs, 0, rank_bits + tile_bits, stream));
  }
  // 4. Per-tile ranges (empty tiles get empty ranges).
  tile_offsets_kernel<<<grid_1d(num_tiles + 1), LINEAR_BLOCK, 0, stream>>>(num_tiles, rank_bits, pair_keys_sorted,
                                                                           pairs, offsets);
  CTGS_CUDA_LAUNCH_CHECK("tile_offsets_kernel");
  return TileList{pairs, list};
}

template TileList bin_tiles<float>(const SceneArgs<float>&, const SurfelPrim<float>*, const PixelRect*,
                                   const int64_t*, int64_t*, const Allocators&, cudaStream_t);
template TileList bin_tiles<double>(const SceneArgs<double>&, const SurfelPrim<double>*, const PixelRect*,
                                    const int64_t*, int64_t*, const Allocators&, cudaStream_t);

}  // namespace gpu
}  // namespace ctgs
