// Entry points of the CUDA backend (raw device pointers + sizes + a stream, no torch: nvcc compiles this
// on a machine without torch headers or a GPU; kernels/bindings_cuda.cpp adapts tensors). Same semantics
// and buffers as the CPU backend (kernels/cpu/rasterize.h, docs/reference/renderer.md); templated on the scalar S
// (float, double), explicit instantiations in the .cu files. Errors throw std::runtime_error.
#pragma once

#include <cuda_runtime_api.h>

#include <cstddef>
#include <cstdint>
#include <functional>

#include "ctgs/bounds.h"
#include "ctgs/scene_args.h"
#include "ctgs/surfel.h"

namespace ctgs {
namespace gpu {

// The scene as the kernels see it (camera space; docs/reference/renderer.md "Per primitive"), shared with the
// other backend: kernels/include/ctgs/scene_args.h.
template <typename S>
using SceneArgs = ctgs::SceneArgs<S>;

// Device memory the core cannot allocate itself (it knows no torch): the binding hands out tensors from
// torch's caching allocator and keeps them alive until the call returns (scratch) or beyond (tile_list).
struct Allocators {
  std::function<void*(size_t bytes)> scratch;         // temporary device bytes, 256-byte aligned, never null
  std::function<int32_t*(int64_t pairs)> tile_list;   // [pairs] output kept for backward
};

// Per-tile lists produced by forward: tile k blends list[offsets[k] .. offsets[k+1]) in order (centre
// depth, then index) -- the same lists as the CPU backend's TileBins.
struct TileBinsView {
  const int64_t* offsets;  // [num_tiles + 1]
  const int32_t* list;     // [pairs] primitive indices
};

// Forward outputs (device). stats pointers may be null when no error image is given.
template <typename S>
struct ForwardOut {
  S* rgb;                // [H, W, 3]
  S* alpha;              // [H, W] 1 - final T
  S* depth;              // [H, W] sum of w z
  S* median;             // [H, W] z of the last surfel blended while T > 0.5 (2DGS's median depth; 0 where none)
  S* depth2;             // [H, W] sum of w z^2
  S* final_T;            // [H, W] saved for backward
  int32_t* n_contrib;    // [H, W] entries of the tile list processed (last blended position + 1)
  int64_t* tile_offsets; // [num_tiles + 1] (the list itself comes from Allocators::tile_list)
  const S* error_image;  // [H, W] or null
  int32_t* count;        // [N] pixels blended
  S* contrib;            // [N] sum of w
  S* err;                // [N] sum of e w
};

// Bins the primitives, renders, and (if error_image) accumulates the per-primitive error statistics.
// Returns the number of (tile, primitive) pairs (the length of the tile list). Synchronises the stream once
// (to learn that number); everything else is asynchronous on `stream`.
template <typename S>
int64_t forward(const SceneArgs<S>& a, const ForwardOut<S>& out, const Allocators& alloc, cudaStream_t stream);

// Gradients (kernels/include/ctgs/scene_args.h), shared with the other backend.
template <typename S>
using BackwardOut = ctgs::BackwardOut<S>;

// v_rgb [H,W,3], v_alpha [H,W], v_depth [H,W], v_depth2 [H,W] (or null: zero): dL/d outputs. final_T, n_contrib,
// bins from forward.
template <typename S>
void backward(const SceneArgs<S>& a, const TileBinsView& bins, const S* final_T, const int32_t* n_contrib,
              const S* v_rgb, const S* v_alpha, const S* v_depth, const S* v_depth2, const BackwardOut<S>& out,
              const Allocators& alloc, cudaStream_t stream);

// Per-primitive preprocessing (kernels/cuda/dense.cu; the math: kernels/include/ctgs/preprocess.h), one
// thread per primitive, asynchronous on `stream`; the same functions as the CPU backend's camera_space /
// sh_color (kernels/cpu/dense.h). view: [4, 4] row-major world-to-camera, center: [3] camera centre, sh:
// [N, K, 3] with K >= (deg + 1)^2; all device pointers.
template <typename S>
void camera_space(const S* means, const S* quats, const S* view, int64_t n, S* mu_c, S* Rc, cudaStream_t stream);
template <typename S>
void camera_space_backward(const S* quats, const S* view, int64_t n, const S* grad_mu_c, const S* grad_Rc,
                           S* grad_means, S* grad_quats, cudaStream_t stream);
template <typename S>
void sh_color(const S* means, const S* center, const S* sh, int64_t n, int K, int deg, S* colors, cudaStream_t stream);
template <typename S>
void sh_color_backward(const S* means, const S* center, const S* sh, int64_t n, int K, int deg, const S* grad_colors,
                       S* grad_means, S* grad_sh, cudaStream_t stream);

// The value checks of ctgs.render.api.validate_inputs (surfel_values_ok) in one pass, one thread per primitive and
// texel row: *flag (an int on the device, zeroed by the caller) becomes non-zero where a check fails. ts_row: 1 or 2
// texel sizes per primitive; sh_row: K * 3 values per primitive; T: texel rows of textures [T, 3].
template <typename S>
void surfel_value_flags(const S* means, const S* quats, const S* scales, const S* opacities, const S* sh,
                        int64_t sh_row, const S* texel_size, int ts_row, const S* textures, int64_t T,
                        const int* tex_res, const int64_t* tex_offset, int64_t n, int* flag, cudaStream_t stream);

// Jagged texture re-layout (ctgs/model/jagged.py remap): up to 4 buffers [rows, C] laid out alike (texel
// values and their Adam moments) copied into the packed layout new_res/new_off [n_new] (T' = new_rows rows,
// every one written), new primitive j taking src[j]'s texels re-centred and moved by shift[j]; 0 outside.
template <typename S>
struct RemapBuffers {
  const S* in[4];
  S* out[4];
  int64_t old_rows[4];
  int count;
};
template <typename S>
void jagged_remap(const RemapBuffers<S>& bufs, int C, const int* old_res, const int64_t* old_off, const int64_t* src,
                  const int64_t* shift, const int* new_res, const int64_t* new_off, int64_t n_new, int64_t new_rows,
                  cudaStream_t stream);

}  // namespace gpu
}  // namespace ctgs
