// World -> camera space of every primitive (ctgs/render/preprocess.py): mu_c = R_view mean + t_view and
// Rc = R_view quat_to_rotmat(quat) (ctgs/render/geometry.py: the quaternion normalised with its norm
// clamped at 1e-12; columns tangent u, tangent v, normal), and the backward w.r.t. the means and the raw
// quaternions; one pass over the primitives each (in PyTorch ~40 small [N, ...] ops forward and
// as many in autograd's backward per training step). The per-primitive math is shared with the CUDA
// backend (kernels/include/ctgs/preprocess.h).
#include <omp.h>

#include <algorithm>

#include "ctgs/preprocess.h"
#include "dense.h"

namespace ctgs {
namespace cpu {

template <typename S>
void camera_space(const S* means, const S* quats, const S* view, int64_t n, S* mu_c, S* Rc, int threads) {
  S r[9], t[3];  // view: [4, 4] row-major world-to-camera
  pre::view_rt(view, r, t);
#pragma omp parallel for schedule(static) num_threads(std::max(1, threads))
  for (int64_t i = 0; i < n; ++i) pre::camera_space(r, t, means + 3 * i, quats + 4 * i, mu_c + 3 * i, Rc + 9 * i);
}

template <typename S>
void camera_space_backward(const S* quats, const S* view, int64_t n, const S* grad_mu_c, const S* grad_Rc,
                           S* grad_means, S* grad_quats, int threads) {
  S r[9], t[3];
  pre::view_rt(view, r, t);
#pragma omp parallel for schedule(static) num_threads(std::max(1, threads))
  for (int64_t i = 0; i < n; ++i)
    pre::camera_space_backward(r, quats + 4 * i, grad_mu_c + 3 * i, grad_Rc + 9 * i, grad_means + 3 * i,
                               grad_quats + 4 * i);
}

template void camera_space<float>(const float*, const float*, const float*, int64_t, float*, float*, int);
template void camera_space<double>(const double*, const double*, const double*, int64_t, double*, double*, int);
template void camera_space_backward<float>(const float*, const float*, int64_t, const float*, const float*, float*,
                                           float*, int);
template void camera_space_backward<double>(const double*, const double*, int64_t, const double*, const double*,
                                            double*, double*, int);

}  // namespace cpu
}  // namespace ctgs
