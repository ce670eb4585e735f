// View-dependent colour of every primitive, SH(normalize(mean - camera centre)) + 0.5 (ctgs/render/sh.py:
// 3DGS's real SH basis and constants, degrees 0..3), and its backward w.r.t. the means and the SH
// coefficients, one pass over the primitives each (issue 11: in PyTorch this was ~50 [N, 3] ops forward and
// ~100 in autograd's backward per step, a few ms of small-op overhead at 2k-20k primitives).
#include <omp.h>

#include <algorithm>
#include <cmath>

#include "dense.h"

namespace ctgs {
namespace cpu {

namespace {

constexpr double C0 = 0.28209479177387814;
constexpr double C1 = 0.4886025119029199;
constexpr double C2[5] = {1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
                          0.5462742152960396};
constexpr double C3[7] = {-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
                          -0.4570457994644658, 1.445305721320277, -0.5900435899266435};

// The basis b[0..(deg+1)^2) at unit direction (x, y, z), and (if grad) its gradient g[k] = d b[k] / d(x, y, z).
template <typename S>
inline void sh_basis(S x, S y, S z, int deg, S* b, S (*g)[3]) {
  b[0] = S(C0);
  if (g) g[0][0] = g[0][1] = g[0][2] = S(0);
  if (deg < 1) return;
  const S c1 = S(C1);
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
  b[4] = S(C2[0]) * xy;
  b[5] = S(C2[1]) * yz;
  b[6] = S(C2[2]) * (S(2) * zz - xx - yy);
  b[7] = S(C2[3]) * xz;
  b[8] = S(C2[4]) * (xx - yy);
  if (g) {
    g[4][0] = S(C2[0]) * y, g[4][1] = S(C2[0]) * x, g[4][2] = S(0);
    g[5][0] = S(0), g[5][1] = S(C2[1]) * z, g[5][2] = S(C2[1]) * y;
    g[6][0] = S(C2[2]) * (S(-2) * x), g[6][1] = S(C2[2]) * (S(-2) * y), g[6][2] = S(C2[2]) * (S(4) * z);
    g[7][0] = S(C2[3]) * z, g[7][1] = S(0), g[7][2] = S(C2[3]) * x;
    g[8][0] = S(C2[4]) * (S(2) * x), g[8][1] = S(C2[4]) * (S(-2) * y), g[8][2] = S(0);
  }
  if (deg < 3) return;
  b[9] = S(C3[0]) * y * (S(3) * xx - yy);
  b[10] = S(C3[1]) * xy * z;
  b[11] = S(C3[2]) * y * (S(4) * zz - xx - yy);
  b[12] = S(C3[3]) * z * (S(2) * zz - S(3) * xx - S(3) * yy);
  b[13] = S(C3[4]) * x * (S(4) * zz - xx - yy);
  b[14] = S(C3[5]) * z * (xx - yy);
  b[15] = S(C3[6]) * x * (xx - S(3) * yy);
  if (g) {
    g[9][0] = S(C3[0]) * (S(6) * xy), g[9][1] = S(C3[0]) * (S(3) * xx - S(3) * yy), g[9][2] = S(0);
    g[10][0] = S(C3[1]) * yz, g[10][1] = S(C3[1]) * xz, g[10][2] = S(C3[1]) * xy;
    g[11][0] = S(C3[2]) * (S(-2) * xy), g[11][1] = S(C3[2]) * (S(4) * zz - xx - S(3) * yy),
    g[11][2] = S(C3[2]) * (S(8) * yz);
    g[12][0] = S(C3[3]) * (S(-6) * xz), g[12][1] = S(C3[3]) * (S(-6) * yz),
    g[12][2] = S(C3[3]) * (S(6) * zz - S(3) * xx - S(3) * yy);
    g[13][0] = S(C3[4]) * (S(4) * zz - S(3) * xx - yy), g[13][1] = S(C3[4]) * (S(-2) * xy),
    g[13][2] = S(C3[4]) * (S(8) * xz);
    g[14][0] = S(C3[5]) * (S(2) * xz), g[14][1] = S(C3[5]) * (S(-2) * yz), g[14][2] = S(C3[5]) * (xx - yy);
    g[15][0] = S(C3[6]) * (S(3) * xx - S(3) * yy), g[15][1] = S(C3[6]) * (S(-6) * xy), g[15][2] = S(0);
  }
}

// d = mean - centre; dir = d / |d| (0 where d = 0). Returns |d| (0 where d = 0).
template <typename S>
inline S unit_dir(const S* m, const S* c, S* dir) {
  const S d0 = m[0] - c[0], d1 = m[1] - c[1], d2 = m[2] - c[2];
  const S sq = d0 * d0 + d1 * d1 + d2 * d2;
  if (!(sq > S(0))) {
    dir[0] = dir[1] = dir[2] = S(0);
    return S(0);
  }
  const S r = std::sqrt(sq), inv = S(1) / r;
  dir[0] = d0 * inv, dir[1] = d1 * inv, dir[2] = d2 * inv;
  return r;
}

}  // namespace

template <typename S>
void sh_color(const S* means, const S* center, const S* sh, int64_t n, int K, int deg, S* colors, int threads) {
  const int nb = (deg + 1) * (deg + 1);
#pragma omp parallel for schedule(static) num_threads(std::max(1, threads))
  for (int64_t i = 0; i < n; ++i) {
    S dir[3], b[16];
    unit_dir(means + 3 * i, center, dir);
    sh_basis<S>(dir[0], dir[1], dir[2], deg, b, nullptr);
    const S* s = sh + i * K * 3;
    for (int ch = 0; ch < 3; ++ch) {
      S acc = S(0);
      for (int k = 0; k < nb; ++k) acc += b[k] * s[3 * k + ch];
      colors[3 * i + ch] = acc + S(0.5);
    }
  }
}

template <typename S>
void sh_color_backward(const S* means, const S* center, const S* sh, int64_t n, int K, int deg, const S* grad_colors,
                       S* grad_means, S* grad_sh, int threads) {
  const int nb = (deg + 1) * (deg + 1);
#pragma omp parallel for schedule(static) num_threads(std::max(1, threads))
  for (int64_t i = 0; i < n; ++i) {
    S dir[3], b[16], g[16][3];
    const S r = unit_dir(means + 3 * i, center, dir);
    sh_basis<S>(dir[0], dir[1], dir[2], deg, b, g);
    const S* s = sh + i * K * 3;
    const S* gc = grad_colors + 3 * i;
    S* gs = grad_sh + i * K * 3;
    S gdir[3] = {S(0), S(0), S(0)};
    for (int k = 0; k < K; ++k) {
      if (k >= nb) {
        gs[3 * k] = gs[3 * k + 1] = gs[3 * k + 2] = S(0);
        continue;
      }
      gs[3 * k] = b[k] * gc[0];
      gs[3 * k + 1] = b[k] * gc[1];
      gs[3 * k + 2] = b[k] * gc[2];
      const S dot = s[3 * k] * gc[0] + s[3 * k + 1] * gc[1] + s[3 * k + 2] * gc[2];
      gdir[0] += dot * g[k][0];
      gdir[1] += dot * g[k][1];
      gdir[2] += dot * g[k][2];
    }
    S* gm = grad_means + 3 * i;
    if (r > S(0)) {  // d dir / d mean = (I - dir dir^T) / |d|
      const S proj = dir[0] * gdir[0] + dir[1] * gdir[1] + dir[2] * gdir[2];
      const S inv = S(1) / r;
      for (int a = 0; a < 3; ++a) gm[a] = (gdir[a] - dir[a] * proj) * inv;
    } else {
      gm[0] = gm[1] = gm[2] = S(0);
    }
  }
}

template void sh_color<float>(const float*, const float*, const float*, int64_t, int, int, float*, int);
template void sh_color<double>(const double*, const double*, const double*, int64_t, int, int, double*, int);
template void sh_color_backward<float>(const float*, const float*, const float*, int64_t, int, int, const float*,
                                       float*, float*, int);
template void sh_color_backward<double>(const double*, const double*, const double*, int64_t, int, int,
                                        const double*, double*, double*, int);

}  // namespace cpu
}  // namespace ctgs
