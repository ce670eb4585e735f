// Per-primitive preprocessing of the CUDA backend: camera-space constants (ctgs::load_prim), conservative
// pixel bounds (ctgs::surfel_pixel_rect, docs/reference/renderer.md "Screen bounds") and tile counts, one thread per
// primitive. The culling rule is the CPU backend's (kernels/cpu/binning.cpp), so both bin the same pairs.
#include "common.cuh"

namespace ctgs {
namespace gpu {

template <typename S>
__global__ void __launch_bounds__(LINEAR_BLOCK)
    preprocess_kernel(SceneArgs<S> a, SurfelPrim<S>* prims, PixelRect* rects, int64_t* tiles_touched) {
  const int i = blockIdx.x * blockDim.x + threadIdx.x;
  if (i >= a.N) return;
  const SurfelPrim<S> P = load_prim(i, a.mu_c, a.Rc, a.scales, a.opacities, a.colors, a.texel_size, a.tex_res,
                                    a.tex_offset, a.K);
  // Written as a positive test so a NaN depth is culled too.
  const bool culled = !(P.mu.z >= a.K.near_plane) || P.opacity < S(MIN_ALPHA);
  const PixelRect r = culled ? PixelRect{0, 0, -1, -1} : surfel_pixel_rect(P, a.K);
  prims[i] = P;
  rects[i] = r;
  if (tiles_touched != nullptr) {
    const TileRect t = tiles_of(r);
    tiles_touched[i] = int64_t(t.x1 - t.x0) * int64_t(t.y1 - t.y0);
  }
}

template <typename S>
void preprocess(const SceneArgs<S>& a, SurfelPrim<S>* prims, PixelRect* rects, int64_t* tiles_touched,
                cudaStream_t stream) {
  if (a.N == 0) return;  // a grid of 0 blocks is a launch error
  preprocess_kernel<S><<<grid_1d(a.N), LINEAR_BLOCK, 0, stream>>>(a, prims, rects, tiles_touched);
  CTGS_CUDA_LAUNCH_CHECK("preprocess_kernel");
}

template void preprocess<float>(const SceneArgs<float>&, SurfelPrim<float>*, PixelRect*, int64_t*, cudaStream_t);
template void preprocess<double>(const SceneArgs<double>&, SurfelPrim<double>*, PixelRect*, int64_t*,
                                 cudaStream_t);

}  // namespace gpu
}  // namespace ctgs
