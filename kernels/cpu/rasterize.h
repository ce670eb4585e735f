// Entry points of the C++/OpenMP backend (raw pointers + sizes, no torch; kernels/bindings.cpp adapts
// tensors). Templated on the scalar S (float, double); explicit instantiations live in the .cpp files.
#pragma once

#include <algorithm>
#include <chrono>
#include <cstdint>
#include <vector>

#include "ctgs/bounds.h"
#include "ctgs/scene_args.h"
#include "ctgs/surfel.h"

namespace ctgs {
namespace cpu {

// The scene as the kernels see it (camera space; docs/reference/renderer.md "Per primitive"), shared with the
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

// The order in which `nt` threads pull tiles one at a time: longest lists first, so that the tiles left when
// a thread runs dry are the cheapest ones (less waiting at the end of the loop). One thread keeps raster
// order, so that its per-primitive sums are added in the same order as they always were.
inline std::vector<int> tile_order(const int64_t* offsets, int num_tiles, int nt) {
  std::vector<int> order(num_tiles);
  for (int k = 0; k < num_tiles; ++k) order[k] = k;
  if (nt > 1)
    std::stable_sort(order.begin(), order.end(), [offsets](int x, int y) {
      return offsets[x + 1] - offsets[x] > offsets[y + 1] - offsets[y];
    });
  return order;
}

// Per-row pixel spans of every primitive (spans.h): row y of primitive i covers pixels
// xs[2 k], xs[2 k + 1] (inclusive; empty if the first is larger), k = offset[i] + y - row0[i], for
// y in rects[i].y0..rects[i].y1. Every pair that can pass surfel_alpha lies inside its span.
struct PrimSpans {
  std::vector<int64_t> offset;  // [N]
  std::vector<int32_t> row0;    // [N]
  std::vector<int32_t> xs;      // [rows, 2]
  const int32_t* row(int i, int y) const { return xs.data() + 2 * (offset[i] + (y - row0[i])); }
};

// Camera-space primitives, their pixel bounds and row spans for every index, and (if bins) the tile
// lists. Culls mu_c.z < near, opacity < MIN_ALPHA (alpha <= opacity can never reach MIN_ALPHA) and
// primitives none of whose rows has pixels (their rect is empty). rects[i] is the bounding box of the
// spans; a primitive is listed in the tiles its 3-sigma rect (ctgs/bounds.h) touches, as on CUDA.
template <typename S>
void bin_primitives(const SceneArgs<S>& a, std::vector<SurfelPrim<S>>& prims, std::vector<PixelRect>& rects,
                    PrimSpans& spans, TileBins* bins);

template <typename S>
struct BlendPairs;

// Forward outputs; stats pointers may be null when no error image is given.
template <typename S>
struct ForwardOut {
  S* rgb;          // [H, W, 3]
  S* alpha;        // [H, W] 1 - final T
  S* depth;        // [H, W] sum of w z
  S* median;       // [H, W] z of the last surfel blended while T > 0.5 (2DGS's median depth; 0 where none)
  S* depth2;       // [H, W] sum of w z^2 (with alpha and depth: the depth distortion, sum_ij w_i w_j (z_i - z_j)^2)
  S* final_T;      // [H, W] saved for backward
  int32_t* n_contrib;  // [H, W] entries of the tile list processed (last blended position + 1)
  const S* error_image;  // [H, W] or null
  int32_t* count;  // [N] pixels blended
  S* contrib;      // [N] sum of w
  S* err;          // [N] sum of e w
  struct BlendPairs<S>* pairs = nullptr;  // if set: every blended (pixel, primitive, w), see BlendPairs
};

// Every blended (pixel, primitive, w) of one render, tile by tile in tile order (within a tile:
// primitive by primitive in blending order, then pixel by pixel): the error statistics of any error
// image computed afterwards are sums over these (one render instead of two, ctgs/render/api.py).
template <typename S>
struct BlendPairs {
  std::vector<int32_t> pix;   // y * W + x
  std::vector<int32_t> prim;
  std::vector<S> w;
};

// What the forward computed per primitive, kept for the backward of the same render (the autograd
// Function saves it as two opaque tensors): every primitive in lane form (LanePrim<S>, lane_math.h, as
// bytes) and the row spans they point into. Saves the backward its own binning pass.
struct FrameSetup {
  std::vector<unsigned char> prims;  // [N * sizeof(LanePrim<S>)]
  std::vector<int32_t> span_xs;      // PrimSpans::xs
};

template <typename S>
void forward(const SceneArgs<S>& a, const ForwardOut<S>& out, TileBins* bins, FrameSetup* keep = nullptr);

// Gradients (kernels/include/ctgs/scene_args.h), shared with the other backend.
template <typename S>
using BackwardOut = ctgs::BackwardOut<S>;

// v_rgb [H,W,3], v_alpha [H,W], v_depth [H,W], v_depth2 [H,W] (or null: zero): dL/d outputs. final_T, n_contrib,
// bins from forward.
// setup_prims / setup_spans: the forward's FrameSetup of this render (prims is updated in place: its span
// pointers are re-aimed at setup_spans), or null to recompute it.
// error_image [H, W] (or null): also the error statistics of the pixels blended, per primitive, as the forward's with
// that error image: stats_contrib [N] = sum of w, stats_err [N] = sum of e w (w from T recovered by division: the
// forward's up to rounding).
template <typename S>
void backward(const SceneArgs<S>& a, const TileBinsView& bins, const S* final_T, const int32_t* n_contrib,
              const S* v_rgb, const S* v_alpha, const S* v_depth, const BackwardOut<S>& out,
              unsigned char* setup_prims = nullptr, const int32_t* setup_spans = nullptr,
              const S* error_image = nullptr, S* stats_contrib = nullptr, S* stats_err = nullptr,
              const S* v_depth2 = nullptr);

// Wall-clock seconds per phase, summed over calls since the last read (benchmarks/profile_train.py reads
// them through the binding `profile_counters`). Only the calling thread touches them, outside parallel
// regions: a few clock reads per render, nothing per pixel.
enum ProfPhase : int {
  PROF_FWD_BIN = 0,     // per-primitive setup, bounds, depth sort, tile lists
  PROF_FWD_RASTER,      // blending
  PROF_FWD_REDUCE,      // per-thread error statistics -> outputs
  PROF_BWD_SETUP,       // per-primitive setup and zeroing of the gradient buffers
  PROF_BWD_RASTER,      // back-to-front blending gradients
  PROF_BWD_REDUCE,      // per-thread per-primitive gradients -> outputs
  PROF_BWD_TEX_REDUCE,  // per-thread texel gradients -> output
  PROF_COUNT
};
extern const char* const PROF_NAMES[PROF_COUNT];
void prof_add(int phase, double seconds);
// Returns the counters and, if reset, zeroes them.
std::vector<double> prof_read(bool reset);

// Adds the time from construction (or the last lap) to a phase.
struct ProfTimer {
  std::chrono::steady_clock::time_point t0 = std::chrono::steady_clock::now();
  void lap(int phase) {
    const auto t1 = std::chrono::steady_clock::now();
    prof_add(phase, std::chrono::duration<double>(t1 - t0).count());
    t0 = t1;
  }
};

}  // namespace cpu
}  // namespace ctgs
