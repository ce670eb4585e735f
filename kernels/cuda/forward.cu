// Forward kernel of the CUDA backend (docs/reference/renderer.md step 8) and the per-primitive error statistics:
// one 16x16 block per tile, one thread per pixel, front to back over the tile's list, primitives staged
// in shared memory a batch at a time (3DGS). All per-pixel math is ctgs::surfel_alpha / surfel_color,
// shared with the CPU backend; the blending, the stop rule and n_contrib follow kernels/cpu/forward.cpp.
#include "common.cuh"

namespace ctgs {
namespace gpu {

namespace {

// STATS: also accumulate count / contrib / err per primitive (a separate instantiation, so plain renders
// pay nothing for it). Statistics are summed over each warp before one atomic per warp and primitive.
template <typename S, bool STATS>
__global__ void __launch_bounds__(BLOCK_SIZE)
    forward_kernel(SceneArgs<S> a, const SurfelPrim<S>* prims, const PixelRect* rects, const int64_t* offsets,
                   const int32_t* list, ForwardOut<S> out) {
  constexpr int B = Batch<S>::SIZE;
  __shared__ SurfelPrim<S> s_prim[B];
  __shared__ PixelRect s_rect[B];
  __shared__ int32_t s_id[B];

  const int W = a.K.width, H = a.K.height;
  const int tile = blockIdx.y * gridDim.x + blockIdx.x;
  const int tid = threadIdx.y * BLOCK_X + threadIdx.x;
  const int lane = tid & 31;
  const int x = blockIdx.x * BLOCK_X + threadIdx.x, y = blockIdx.y * BLOCK_Y + threadIdx.y;
  const bool inside = x < W && y < H;
  const int64_t pix = int64_t(y) * W + x;
  const PixelRay<S> ray = pixel_ray<S>(x, y, a.K);
  const int64_t begin = offsets[tile], end = offsets[tile + 1];
  const S e = (STATS && inside) ? out.error_image[pix] : S(0);

  S T = S(1), D = S(0), D2 = S(0), M = S(0), C[3] = {S(0), S(0), S(0)};
  int32_t last = 0;
  bool done = !inside;  // pixels past the image edge only help load batches
  for (int64_t base = begin; base < end; base += B) {
    // Also the barrier that lets the previous batch be overwritten.
    if (__syncthreads_count(done) == BLOCK_SIZE) break;
    const int n = int(end - base < B ? end - base : B);
    if (tid < n) {
      const int32_t i = list[base + tid];
      s_id[tid] = i;
      s_prim[tid] = prims[i];
      s_rect[tid] = rects[i];
    }
    __syncthreads();
    // Every thread walks the whole batch (finished ones idle) so the warp reductions see all 32 lanes.
    for (int k = 0; k < n; ++k) {
      bool blended = false;
      S w = S(0);
      const PixelRect& r = s_rect[k];
      // The CPU backend visits only pixels inside the primitive's rect: same test, same pairs.
      if (!done && x >= r.x0 && x <= r.x1 && y >= r.y0 && y <= r.y1) {
        const SurfelPrim<S>& P = s_prim[k];
        SurfelHit<S> h;
        if (surfel_alpha(P, ray, a.K.near_plane, h)) {
          const S T_next = T * (S(1) - h.alpha);
          if (T_next < S(T_EPS)) {
            done = true;  // 3DGS rule: stop without blending this one
          } else {
            surfel_color(P, a.textures, h);
            w = h.alpha * T;
            C[0] += w * h.c[0];
            C[1] += w * h.c[1];
            C[2] += w * h.c[2];
            D += w * h.z;
            D2 += w * h.z * h.z;
            if (T > S(0.5)) M = h.z;  // the median depth (kernels/cpu/forward.cpp)
            T = T_next;
            last = int32_t(base - begin + k + 1);
            blended = true;
          }
        }
      }
      if (STATS && __any_sync(FULL_MASK, blended)) {
        const int cnt = warp_sum<int>(blended ? 1 : 0);
        const S sum_w = warp_sum<S>(w);
        const S sum_ew = warp_sum<S>(e * w);
        if (lane == 0) {
          const int32_t i = s_id[k];
          atomicAdd(out.count + i, cnt);
          atomicAdd(out.contrib + i, sum_w);
          atomicAdd(out.err + i, sum_ew);
        }
      }
    }
  }
  if (!inside) return;
  const S* bg = a.background;
  out.rgb[3 * pix] = C[0] + T * bg[0];
  out.rgb[3 * pix + 1] = C[1] + T * bg[1];
  out.rgb[3 * pix + 2] = C[2] + T * bg[2];
  out.alpha[pix] = S(1) - T;
  out.depth[pix] = D;
  out.median[pix] = M;
  out.depth2[pix] = D2;
  out.final_T[pix] = T;
  out.n_contrib[pix] = last;
}

}  // namespace

template <typename S>
int64_t forward(const SceneArgs<S>& a, const ForwardOut<S>& out, const Allocators& alloc, cudaStream_t stream) {
  SurfelPrim<S>* prims = scratch<SurfelPrim<S>>(alloc, a.N);
  PixelRect* rects = scratch<PixelRect>(alloc, a.N);
  int64_t* touched = scratch<int64_t>(alloc, a.N);
  preprocess(a, prims, rects, touched, stream);
  const TileList bins = bin_tiles(a, prims, rects, touched, out.tile_offsets, alloc, stream);
  const bool stats = out.error_image != nullptr;
  if (stats && a.N > 0) {
    CTGS_CUDA_CHECK(cudaMemsetAsync(out.count, 0, sizeof(int32_t) * a.N, stream));
    CTGS_CUDA_CHECK(cudaMemsetAsync(out.contrib, 0, sizeof(S) * a.N, stream));
    CTGS_CUDA_CHECK(cudaMemsetAsync(out.err, 0, sizeof(S) * a.N, stream));
  }
  const dim3 grid(tiles_x(a.K.width), tiles_y(a.K.height)), block(BLOCK_X, BLOCK_Y);
  if (stats)
    forward_kernel<S, true><<<grid, block, 0, stream>>>(a, prims, rects, out.tile_offsets, bins.list, out);
  else
    forward_kernel<S, false><<<grid, block, 0, stream>>>(a, prims, rects, out.tile_offsets, bins.list, out);
  CTGS_CUDA_LAUNCH_CHECK("forward_kernel");
  return bins.pairs;
}

template int64_t forward<float>(const SceneArgs<float>&, const ForwardOut<float>&, const Allocators&, cudaStream_t);
template int64_t forward<double>(const SceneArgs<double>&, const ForwardOut<double>&, const Allocators&,
                                 cudaStream_t);

}  // namespace gpu
}  // namespace ctgs
