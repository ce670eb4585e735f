// World -> camera space of every primitive (ctgs/render/preprocess.py): mu_c = R_view mean + t_view and
// Rc = R_view quat_to_rotmat(quat) (ctgs/model/geometry.py: the quaternion normalised with its norm
// clamped at 1e-12; columns tangent u, tangent v, normal), and the backward w.r.t. the means and the raw
// quaternions; one pass over the primitives each (issue 11: in PyTorch ~40 small [N, ...] ops forward and
// as many in autograd's backward per training step).
#include <omp.h>

#include <algorithm>
#include <cmath>

#include "dense.h"

namespace ctgs {
namespace cpu {

namespace {

constexpr double QUAT_NORM_MIN = 1e-12;  // geometry.py's clamp_min

// Rotation of the unit quaternion (w, x, y, z), row-major.
template <typename S>
inline void quat_rotmat(S w, S x, S y, S z, S* R) {
  R[0] = S(1) - S(2) * (y * y + z * z);
  R[1] = S(2) * (x * y - w * z);
  R[2] = S(2) * (x * z + w * y);
  R[3] = S(2) * (x * y + w * z);
  R[4] = S(1) - S(2) * (x * x + z * z);
  R[5] = S(2) * (y * z - w * x);
  R[6] = S(2) * (x * z - w * y);
  R[7] = S(2) * (y * z + w * x);
  R[8] = S(1) - S(2) * (x * x + y * y);
}

}  // namespace

template <typename S>
void camera_space(const S* means, const S* quats, const S* view, int64_t n, S* mu_c, S* Rc, int threads) {
  // view: [4, 4] row-major world-to-camera.
  const S r[9] = {view[0], view[1], view[2], view[4], view[5], view[6], view[8], view[9], view[10]};
  const S t[3] = {view[3], view[7], view[11]};
#pragma omp parallel for schedule(static) num_threads(std::max(1, threads))
  for (int64_t i = 0; i < n; ++i) {
    const S* m = means + 3 * i;
    for (int a = 0; a < 3; ++a) mu_c[3 * i + a] = (r[3 * a] * m[0] + r[3 * a + 1] * m[1] + r[3 * a + 2] * m[2]) + t[a];
    const S* q = quats + 4 * i;
    const S nrm = std::max(std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]), S(QUAT_NORM_MIN));
    S R[9];
    quat_rotmat(q[0] / nrm, q[1] / nrm, q[2] / nrm, q[3] / nrm, R);
    S* out = Rc + 9 * i;
    for (int a = 0; a < 3; ++a)
      for (int c = 0; c < 3; ++c) out[3 * a + c] = r[3 * a] * R[c] + r[3 * a + 1] * R[3 + c] + r[3 * a + 2] * R[6 + c];
  }
}

template <typename S>
void camera_space_backward(const S* quats, const S* view, int64_t n, const S* grad_mu_c, const S* grad_Rc,
                           S* grad_means, S* grad_quats, int threads) {
  const S r[9] = {view[0], view[1], view[2], view[4], view[5], view[6], view[8], view[9], view[10]};
#pragma omp parallel for schedule(static) num_threads(std::max(1, threads))
  for (int64_t i = 0; i < n; ++i) {
    // mean: d mu_c / d mean = R_view, so grad_mean = R_view^T grad_mu_c.
    const S* gm = grad_mu_c + 3 * i;
    for (int c = 0; c < 3; ++c) grad_means[3 * i + c] = r[c] * gm[0] + r[3 + c] * gm[1] + r[6 + c] * gm[2];
    // Rc = R_view R: grad_R = R_view^T grad_Rc.
    const S* gR = grad_Rc + 9 * i;
    S G[9];
    for (int a = 0; a < 3; ++a)
      for (int c = 0; c < 3; ++c) G[3 * a + c] = r[a] * gR[c] + r[3 + a] * gR[3 + c] + r[6 + a] * gR[6 + c];
    const S* q = quats + 4 * i;
    const S len = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
    const bool clamped = !(len > S(QUAT_NORM_MIN));
    const S nrm = clamped ? S(QUAT_NORM_MIN) : len;
    const S w = q[0] / nrm, x = q[1] / nrm, y = q[2] / nrm, z = q[3] / nrm;
    // d R / d (w, x, y, z) of quat_rotmat, contracted with G.
    const S gw = S(2) * (-z * G[1] + y * G[2] + z * G[3] - x * G[5] - y * G[6] + x * G[7]);
    const S gx = S(2) * (y * G[1] + z * G[2] + y * G[3] - S(2) * x * G[4] - w * G[5] + z * G[6] + w * G[7] -
                         S(2) * x * G[8]);
    const S gy = S(2) * (-S(2) * y * G[0] + x * G[1] + w * G[2] + x * G[3] + z * G[5] - w * G[6] + z * G[7] -
                         S(2) * y * G[8]);
    const S gz = S(2) * (-S(2) * z * G[0] - w * G[1] + x * G[2] + w * G[3] - S(2) * z * G[4] + y * G[5] + x * G[6] +
                         y * G[7]);
    S* gq = grad_quats + 4 * i;
    if (clamped) {  // q / 1e-12: the clamp passes no gradient to the norm
      gq[0] = gw / nrm, gq[1] = gx / nrm, gq[2] = gy / nrm, gq[3] = gz / nrm;
    } else {  // d (q / |q|) / d q = (I - u u^T) / |q|
      const S proj = w * gw + x * gx + y * gy + z * gz;
      gq[0] = (gw - w * proj) / nrm;
      gq[1] = (gx - x * proj) / nrm;
      gq[2] = (gy - y * proj) / nrm;
      gq[3] = (gz - z * proj) / nrm;
    }
  }
}

template void camera_space<float>(const float*, const float*, const float*, int64_t, float*, float*, int);
template void camera_space<double>(const double*, const double*, const double*, int64_t, double*, double*, int);
template void camera_space_backward<float>(const float*, const float*, int64_t, const float*, const float*, float*,
                                           float*, int);
template void camera_space_backward<double>(const double*, const double*, int64_t, const double*, const double*,
                                            double*, double*, int);

}  // namespace cpu
}  // namespace ctgs
