// View-dependent colour of every primitive, SH(normalize(mean - camera centre)) + 0.5 (ctgs/render/sh.py:
// 3DGS's real SH basis and constants, degrees 0..3), and its backward w.r.t. the means and the SH
// coefficients, one pass over the primitives each (in PyTorch this was ~50 [N, 3] ops forward and
// ~100 in autograd's backward per step, a few ms of small-op overhead at 2k-20k primitives). The
// per-primitive math is shared with the CUDA backend (kernels/include/ctgs/preprocess.h).
#include <omp.h>

#include <algorithm>

#include "ctgs/preprocess.h"
#include "dense.h"

namespace ctgs {
namespace cpu {

template <typename S>
void sh_color(const S* means, const S* center, const S* sh, int64_t n, int K, int deg, S* colors, int threads) {
#pragma omp parallel for schedule(static) num_threads(std::max(1, threads))
  for (int64_t i = 0; i < n; ++i) pre::sh_color(means + 3 * i, center, sh + i * K * 3, deg, colors + 3 * i);
}

template <typename S>
void sh_color_backward(const S* means, const S* center, const S* sh, int64_t n, int K, int deg, const S* grad_colors,
                       S* grad_means, S* grad_sh, int threads) {
#pragma omp parallel for schedule(static) num_threads(std::max(1, threads))
  for (int64_t i = 0; i < n; ++i)
    pre::sh_color_backward(means + 3 * i, center, sh + i * K * 3, K, deg, grad_colors + 3 * i, grad_means + 3 * i,
                           grad_sh + i * K * 3);
}

template void sh_color<float>(const float*, const float*, const float*, int64_t, int, int, float*, int);
template void sh_color<double>(const double*, const double*, const double*, int64_t, int, int, double*, int);
template void sh_color_backward<float>(const float*, const float*, const float*, int64_t, int, int, const float*,
                                       float*, float*, int);
template void sh_color_backward<double>(const double*, const double*, const double*, int64_t, int, int,
                                        const double*, double*, double*, int);

}  // namespace cpu
}  // namespace ctgs
