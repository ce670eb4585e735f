// Per-primitive preprocessing math (ctgs/render/preprocess.py, ctgs/render/sh.py), forward and hand-written
// backward, one primitive per call: world -> camera space (mu_c = R_view mean + t_view, Rc = R_view
// quat_to_rotmat(quat), the quaternion normalised with its norm clamped at 1e-12) and the view-dependent
// colour SH(normalize(mean - camera centre)) + 0.5 (3DGS's real SH basis, degrees 0..3). HOST_DEVICE inline,
// templated on the scalar, no torch: the CPU loops (kernels/cpu/camera.cpp, sh.cpp) and the CUDA kernels
// (kernels/cuda/dense.cu) call the same code, so both backends compute the same values.
#pragma once

#include <math.h>

#include "ctgs/constants.h"

namespace ctgs {

namespace pre {

constexpr double QUAT_NORM_MIN = 1e-12;  // geometry.py's clamp_min
// SH constants (3DGS); scalars, not arrays, so device code can use them.
constexpr double SH_C0 = 0.28209479177387814;
constexpr double SH_C1 = 0.4886025119029199;
constexpr double SH_C2_0 = 1.0925484305920792, SH_C2_1 = -1.0925484305920792, SH_C2_2 = 0.31539156525252005,
                 SH_C2_3 = -1.0925484305920792, SH_C2_4 = 0.5462742152960396;
constexpr double SH_C3_0 = -0.5900435899266435, SH_C3_1 = 2.890611442640554, SH_C3_2 = -0.4570457994644658,
                 SH_C3_3 = 0.3731763325901154, SH_C3_4 = -0.4570457994644658, SH_C3_5 = 1.445305721320277,
                 SH_C3_6 = -0.5900435899266435;

// Rotation of the unit quaternion (w, x, y, z), row-major.
template <typename S>
HOST_DEVICE inline void quat_rotmat(S w, S x, S y, S z, S* R) {
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

// The rotation r[9] (row-major) and translation t[3] of a row-major [4, 4] world-to-camera matrix.
template <typename S>
HOST_DEVICE inline void view_rt(const S* view, S* r, S* t) {
  r[0] = view[0], r[1] = view[1], r[2] = view[2];
  r[3] = view[4], r[4] = view[5], r[5] = view[6];
  r[6] = view[8], r[7] = view[9], r[8] = view[10];
  t[0] = view[3], t[1] = view[7], t[2] = view[11];
}

// mu_c[3], Rc[9] (row-major, columns u, v, n) of one primitive with centre m[3] and raw quaternion q[4].
template <typename S>
HOST_DEVICE inline void camera_space(const S* r, const S* t, const S* m, const S* q, S* mu_c, S* Rc) {
  for (int a = 0; a < 3; ++a) mu_c[a] = (r[3 * a] * m[0] + r[3 * a + 1] * m[1] + r[3 * a + 2] * m[2]) + t[a];
  S nrm = sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
  if (nrm < S(QUAT_NORM_MIN)) nrm = S(QUAT_NORM_MIN);  // std::max(norm, 1e-12): a NaN norm stays NaN
  S R[9];
  quat_rotmat(q[0] / nrm, q[1] / nrm, q[2] / nrm, q[3] / nrm, R);
  for (int a = 0; a < 3; ++a)
    for (int c = 0; c < 3; ++c) Rc[3 * a + c] = r[3 * a] * R[c] + r[3 * a + 1] * R[3 + c] + r[3 * a + 2] * R[6 + c];
}

// grad_mean[3], grad_quat[4] of camera_space for the upstream gradients gm[3] (mu_c), gR[9] (Rc).
template <typename S>
HOST_DEVICE inline void camera_space_backward(const S* r, const S* q, const S* gm, const S* gR, S* grad_mean,
                                              S* grad_quat) {
  // mean: d mu_c / d mean = R_view, so grad_mean = R_view^T grad_mu_c.
  for (int c = 0; c < 3; ++c) grad_mean[c] = r[c] * gm[0] + r[3 + c] * gm[1] + r[6 + c] * gm[2];
  // Rc = R_view R: grad_R = R_view^T grad_Rc.
  S G[9];
  for (int a = 0; a < 3; ++a)
    for (int c = 0; c < 3; ++c) G[3 * a + c] = r[a] * gR[c] + r[3 + a] * gR[3 + c] + r[6 + a] * gR[6 + c];
  const S len = sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
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
  if (clamped) {  // q / 1e-12: the clamp passes no gradient to the norm
    grad_quat[0] = gw / nrm, grad_quat[1] = gx / nrm, grad_quat[2] = gy / nrm, grad_quat[3] = gz / nrm;
  } else {  // d (q / |q|) / d q = (I - u u^T) / |q|
    const S proj = w * gw + x * gx + y * gy + z * gz;
    grad_quat[0] = (gw - w * proj) / nrm;
    grad_quat[1] = (gx - x * proj) / nrm;
    grad_quat[2] = (gy - y * proj) / nrm;
    grad_quat[3] = (gz - z * proj) / nrm;
  }
}

// The SH basis b[0..(deg+1)^2) at unit direction (x, y, z), and (if g) its gradient g[k] = d b[k] / d(x, y, z).
template <typename S>
HOST_DEVICE inline void sh_basis(S x, S y, S z, int deg, S* b, S (*g)[3]) {
  b[0] = S(SH_C0);
  if (g) g[0][0] = g[0][1] = g[0][2] = S(0);
  if (deg < 1) return;
  const S c1 = S(SH_C1);
  b[1] = -c1 * y;
  b[2] = c1 * z;
  b[3] = -c1 * x;
  if (g) {
    g[1][0] = S(0), g[1][1] = -c1, g[1][2] = S(0);
    g[2][0] = S(0), g[2][1] = S(0), g[2][2] = c1;
    g[3][0] = -c1, g[3][1] = S(0), g[3][2] = S(0);
  }
  if (deg < 2) return;
  const S xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
  b[4] = S(SH_C2_0) * xy;
  b[5] = S(SH_C2_1) * yz;
  b[6] = S(SH_C2_2) * (S(2) * zz - xx - yy);
  b[7] = S(SH_C2_3) * xz;
  b[8] = S(SH_C2_4) * (xx - yy);
  if (g) {
    g[4][0] = S(SH_C2_0) * y, g[4][1] = S(SH_C2_0) * x, g[4][2] = S(0);
    g[5][0] = S(0), g[5][1] = S(SH_C2_1) * z, g[5][2] = S(SH_C2_1) * y;
    g[6][0] = S(SH_C2_2) * (S(-2) * x), g[6][1] = S(SH_C2_2) * (S(-2) * y), g[6][2] = S(SH_C2_2) * (S(4) * z);
    g[7][0] = S(SH_C2_3) * z, g[7][1] = S(0), g[7][2] = S(SH_C2_3) * x;
    g[8][0] = S(SH_C2_4) * (S(2) * x), g[8][1] = S(SH_C2_4) * (S(-2) * y), g[8][2] = S(0);
  }
  if (deg < 3) return;
  b[9] = S(SH_C3_0) * y * (S(3) * xx - yy);
  b[10] = S(SH_C3_1) * xy * z;
  b[11] = S(SH_C3_2) * y * (S(4) * zz - xx - yy);
  b[12] = S(SH_C3_3) * z * (S(2) * zz - S(3) * xx - S(3) * yy);
  b[13] = S(SH_C3_4) * x * (S(4) * zz - xx - yy);
  b[14] = S(SH_C3_5) * z * (xx - yy);
  b[15] = S(SH_C3_6) * x * (xx - S(3) * yy);
  if (g) {
    g[9][0] = S(SH_C3_0) * (S(6) * xy), g[9][1] = S(SH_C3_0) * (S(3) * xx - S(3) * yy), g[9][2] = S(0);
    g[10][0] = S(SH_C3_1) * yz, g[10][1] = S(SH_C3_1) * xz, g[10][2] = S(SH_C3_1) * xy;
    g[11][0] = S(SH_C3_2) * (S(-2) * xy), g[11][1] = S(SH_C3_2) * (S(4) * zz - xx - S(3) * yy),
    g[11][2] = S(SH_C3_2) * (S(8) * yz);
    g[12][0] = S(SH_C3_3) * (S(-6) * xz), g[12][1] = S(SH_C3_3) * (S(-6) * yz),
    g[12][2] = S(SH_C3_3) * (S(6) * zz - S(3) * xx - S(3) * yy);
    g[13][0] = S(SH_C3_4) * (S(4) * zz - S(3) * xx - yy), g[13][1] = S(SH_C3_4) * (S(-2) * xy),
    g[13][2] = S(SH_C3_4) * (S(8) * xz);
    g[14][0] = S(SH_C3_5) * (S(2) * xz), g[14][1] = S(SH_C3_5) * (S(-2) * yz), g[14][2] = S(SH_C3_5) * (xx - yy);
    g[15][0] = S(SH_C3_6) * (S(3) * xx - S(3) * yy), g[15][1] = S(SH_C3_6) * (S(-6) * xy), g[15][2] = S(0);
  }
}

// d = mean - centre; dir = d / |d| (0 where d = 0). Returns |d| (0 where d = 0).
template <typename S>
HOST_DEVICE inline S unit_dir(const S* m, const S* c, S* dir) {
  const S d0 = m[0] - c[0], d1 = m[1] - c[1], d2 = m[2] - c[2];
  const S sq = d0 * d0 + d1 * d1 + d2 * d2;
  if (!(sq > S(0))) {
    dir[0] = dir[1] = dir[2] = S(0);
    return S(0);
  }
  const S r = sqrt(sq), inv = S(1) / r;
  dir[0] = d0 * inv, dir[1] = d1 * inv, dir[2] = d2 * inv;
  return r;
}

// color[3] = SH_deg(normalize(m - c)) + 0.5 for one primitive's coefficients s [K, 3] (K >= (deg+1)^2).
template <typename S>
HOST_DEVICE inline void sh_color(const S* m, const S* c, const S* s, int deg, S* color) {
  const int nb = (deg + 1) * (deg + 1);
  S dir[3], b[16];
  unit_dir(m, c, dir);
  sh_basis<S>(dir[0], dir[1], dir[2], deg, b, nullptr);
  for (int ch = 0; ch < 3; ++ch) {
    S acc = S(0);
    for (int k = 0; k < nb; ++k) acc += b[k] * s[3 * k + ch];
    color[ch] = acc + S(0.5);
  }
}

// grad_mean[3], grad_sh[K, 3] of sh_color for the upstream gradient gc[3] (rows k >= (deg+1)^2 get 0).
template <typename S>
HOST_DEVICE inline void sh_color_backward(const S* m, const S* c, const S* s, int K, int deg, const S* gc,
                                          S* grad_mean, S* grad_sh) {
  const int nb = (deg + 1) * (deg + 1);
  S dir[3], b[16], g[16][3];
  const S r = unit_dir(m, c, dir);
  sh_basis<S>(dir[0], dir[1], dir[2], deg, b, g);
  S gdir[3] = {S(0), S(0), S(0)};
  for (int k = 0; k < K; ++k) {
    if (k >= nb) {
      grad_sh[3 * k] = grad_sh[3 * k + 1] = grad_sh[3 * k + 2] = S(0);
      continue;
    }
    grad_sh[3 * k] = b[k] * gc[0];
    grad_sh[3 * k + 1] = b[k] * gc[1];
    grad_sh[3 * k + 2] = b[k] * gc[2];
    const S dot = s[3 * k] * gc[0] + s[3 * k + 1] * gc[1] + s[3 * k + 2] * gc[2];
    gdir[0] += dot * g[k][0];
    gdir[1] += dot * g[k][1];
    gdir[2] += dot * g[k][2];
  }
  if (r > S(0)) {  // d dir / d mean = (I - dir dir^T) / |d|
    const S proj = dir[0] * gdir[0] + dir[1] * gdir[1] + dir[2] * gdir[2];
    const S inv = S(1) / r;
    for (int a = 0; a < 3; ++a) grad_mean[a] = (gdir[a] - dir[a] * proj) * inv;
  } else {
    grad_mean[0] = grad_mean[1] = grad_mean[2] = S(0);
  }
}

}  // namespace pre

}  // namespace ctgs
