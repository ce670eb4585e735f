// Entry points of the C++/OpenMP backend (raw pointers + sizes, no torch; kernels/bindings.cpp adapts
// tensors). Templated on the scalar S (float, double); explicit instantiations live in the .cpp files.
#pragma once

#include <cstdint>
#include <vector>

#include "ctgs/bounds.h"
#include "ctgs/scene_args.h"
#include "ctgs/surfel.h"

namespace ctgs {
namespace cpu {

// The scene as the kernels see it (camera space; docs/renderer.md "Per primitive"), shared with the
// other backend: kernels/include/ctgs/scene_args.h.
template <typename S>
using SceneArgs = ctgs::SceneArgs<S>;

// Per-tile lists: tile k blends list[offsets[k] .. offsets[k+1]) in order (centre depth, then index).
struct TileBins {
  std::vector<int64_t> offsets;  // [num_tiles + 1]
  std::vector<int32_t> list;     // [pairs] primitive indices
};

// Read-only view of TileBins (what backward gets back from Python).
struct TileBinsView {
  const int64_t* offsets;  // [num_tiles + 1]
  const int32_t* list;     // [pairs]
};

// Camera-space primitives and their pixel bounds for every index, and (if bins) the tile lists. Culls
// mu_c.z < near, opacity < MIN_ALPHA (alpha <= opacity can never reach MIN_ALPHA) and primitives whose
// bounds miss the image (their rect is empty).
template <typename S>
void bin_primitives(const SceneArgs<S>& a, std::vector<SurfelPrim<S>>& prims, std::vector<PixelRect>& rects,
                    TileBins* bins);

// Forward outputs; stats pointers may be null when no error image is given.
template <typename S>
struct ForwardOut {
  S* rgb;          // [H, W, 3]
  S* alpha;        // [H, W] 1 - final T
  S* depth;        // [H, W] sum of w z
  S* final_T;      // [H, W] saved for backward
  int32_t* n_contrib;  // [H, W] entries of the tile list processed (last blended position + 1)
  const S* error_image;  // [H, W] or null
  int32_t* count;  // [N] pixels blended
  S* contrib;      // [N] sum of w
  S* err;          // [N] sum of e w
};

template <typename S>
void forward(const SceneArgs<S>& a, const ForwardOut<S>& out, TileBins* bins);

// Gradients (kernels/include/ctgs/scene_args.h), shared with the other backend.
template <typename S>
using BackwardOut = ctgs::BackwardOut<S>;

// v_rgb [H,W,3], v_alpha [H,W], v_depth [H,W]: dL/d outputs. final_T, n_contrib, bins from forward.
template <typename S>
void backward(const SceneArgs<S>& a, const TileBinsView& bins, const S* final_T, const int32_t* n_contrib,
              const S* v_rgb, const S* v_alpha, const S* v_depth, const BackwardOut<S>& out);

}  // namespace cpu
}  // namespace ctgs
