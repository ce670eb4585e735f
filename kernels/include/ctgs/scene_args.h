// The raw-pointer view of one render's inputs (and of its gradients), shared by the CPU (kernels/cpu) and CUDA (kernels/cuda)
// cores. No torch here: the bindings fill it (kernels/binding_common.h).
#pragma once

#include "ctgs/surfel.h"

namespace ctgs {

template <typename S>
struct SceneArgs {
  int N;                        // primitives
  const S* mu_c;                // [N, 3] centres, camera space
  const S* Rc;                  // [N, 3, 3] row-major, columns u, v, n
  const S* scales;              // [N, 2] world units
  const S* opacities;           // [N]
  const S* colors;              // [N, 3] SH + 0.5
  const S* texel_size;          // [N, 2] world units per texel
  const S* textures;            // [T, 3]
  long long T;                  // texels
  const int* tex_res;           // [N, 2]
  const long long* tex_offset;  // [N]
  const S* background;          // [3] (on the device of the other inputs)
  Intrinsics<S> K;
  int num_threads = 0;          // CPU only: OpenMP threads (<= 0: OpenMP's default); CUDA ignores it
};

// Gradients, same shapes as the inputs they belong to. All outputs are overwritten.
template <typename S>
struct BackwardOut {
  S* v_mu_c;        // [N, 3]
  S* v_Rc;          // [N, 3, 3]
  S* v_scales;      // [N, 2]
  S* v_opacities;   // [N]
  S* v_colors;      // [N, 3]
  S* v_texel_size;  // [N, 2]
  S* v_textures;    // [T, 3]
  S* v_background;  // [3]
};

}  // namespace ctgs
