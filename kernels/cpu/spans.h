// Conservative per-row pixel spans of one surfel (CPU backend): on each image row, the pixels whose
// (pixel, primitive) pair can pass surfel_alpha. The 3-sigma bounding rect (ctgs/bounds.h) holds about
// four times as many pixels as pass on trained scenes (thin tilted surfels, the alpha threshold of
// low-opacity ones, the rect's margins); skipping the rest before any per-pixel math is the largest
// saving of the rasterizer.
//
// A pair passes only if min(rho3d, rho2d) <= R with R = min(CUTOFF_RHO, 2 ln(opacity / MIN_ALPHA))
// (alpha = opacity exp(-rho/2) >= MIN_ALPHA). With d = (dx, dy, 1) the pixel ray and the surfel frame u, v, n:
//   lx (n.d) = (n.mu)(u.d) - (u.mu)(n.d) = a1 dx + b1(dy),  ly (n.d) = a2 dx + b2(dy),
// so rho3d <= R  <=>  (a1 dx + b1)^2 / sx^2 + (a2 dx + b2)^2 / sy^2 - R (nx dx + bn(dy))^2 <= 0, a quadratic
// in dx on every row (the projected ellipse), and rho2d <= R is a disk around the projected centre. The
// span is the hull of both, solved in double with margins (SPAN_*) far above the rounding of either
// side, and clipped to the bounding rect; a degenerate quadratic (the surfel seen edge-on or crossing the
// horizon) keeps the rect's whole row.
#pragma once

#include <math.h>

#include <algorithm>
#include <cstdint>

#include "ctgs/bounds.h"
#include "ctgs/surfel.h"

namespace ctgs {
namespace cpu {

// rho threshold margins: R' = R (1 + SPAN_RHO_REL) + SPAN_RHO_ABS. The kernels' float32 rho carries a
// relative error of ~1e-6 (more for surfels ~1e4 times smaller than their depth, where the hit point
// loses digits to cancellation): 1e-3 relative plus 1e-2 absolute covers that with room to spare.
constexpr double SPAN_RHO_REL = 1e-3;
constexpr double SPAN_RHO_ABS = 1e-2;
// Pixels whose centre lies within SPAN_PX of the solved span are kept (root rounding is ~1e-4 px).
constexpr double SPAN_PX = 0.05;
// |A| below this fraction of its terms' magnitude is treated as 0 (degenerate: keep the whole row), so
// that rounding can never turn an unbounded row set into a bounded one.
constexpr double SPAN_DEGENERATE = 1e-9;

// Per-primitive coefficients (double whatever the kernel's scalar).
struct SpanConic {
  double A, a1, a2, nx;  // row-independent: A = a1^2 wx + a2^2 wy - R nx^2
  double p1, q1, p2, q2, ny, nz;  // b1 = p1 dy + q1, b2 = p2 dy + q2, bn = ny dy + nz
  double wx, wy, R;      // 1/sx^2, 1/sy^2, the threshold with margins
  bool degenerate;       // |A| too small to trust: whole rows
  double mx, my, r2d2;   // disk (X - mx)^2 + (Y - my)^2 <= r2d2 (pixels)
};

template <typename S>
inline SpanConic span_conic(const SurfelPrim<S>& P) {
  SpanConic c;
  const double o = double(P.opacity);
  const double R = std::min(CUTOFF_RHO, 2.0 * log(o / MIN_ALPHA));
  c.R = R * (1.0 + SPAN_RHO_REL) + SPAN_RHO_ABS;
  const double mu[3] = {double(P.mu.x), double(P.mu.y), double(P.mu.z)};
  const double u[3] = {double(P.u.x), double(P.u.y), double(P.u.z)};
  const double v[3] = {double(P.v.x), double(P.v.y), double(P.v.z)};
  const double n[3] = {double(P.n.x), double(P.n.y), double(P.n.z)};
  const double n_mu = n[0] * mu[0] + n[1] * mu[1] + n[2] * mu[2];
  const double u_mu = u[0] * mu[0] + u[1] * mu[1] + u[2] * mu[2];
  const double v_mu = v[0] * mu[0] + v[1] * mu[1] + v[2] * mu[2];
  c.a1 = n_mu * u[0] - u_mu * n[0];
  c.p1 = n_mu * u[1] - u_mu * n[1];
  c.q1 = n_mu * u[2] - u_mu * n[2];
  c.a2 = n_mu * v[0] - v_mu * n[0];
  c.p2 = n_mu * v[1] - v_mu * n[1];
  c.q2 = n_mu * v[2] - v_mu * n[2];
  c.nx = n[0];
  c.ny = n[1];
  c.nz = n[2];
  const double sx = double(P.sx), sy = double(P.sy);
  c.wx = 1.0 / (sx * sx);
  c.wy = 1.0 / (sy * sy);
  const double t1 = c.a1 * c.a1 * c.wx + c.a2 * c.a2 * c.wy, t2 = c.R * c.nx * c.nx;
  c.A = t1 - t2;
  // Written so that NaN or infinite coefficients land in the degenerate (whole row) branch.
  c.degenerate = !(c.A > SPAN_DEGENERATE * (t1 + t2)) || !(fabs(c.A) < INFINITY);
  c.mx = double(P.mx);
  c.my = double(P.my);
  c.r2d2 = c.R / FILTER_INV_SQUARE;
  return c;
}

// Pixels [*lo, *hi] of row y (clipped to [x_min, x_max]) that can pass; returns false if none.
template <typename S>
inline bool span_of_row(const SpanConic& c, const Intrinsics<S>& K, int y, int x_min, int x_max, int* lo,
                        int* hi) {
  if (c.degenerate) {
    *lo = x_min;
    *hi = x_max;
    return x_min <= x_max;
  }
  const double Y = double(y) + 0.5;
  const double fx = double(K.fx), cx = double(K.cx);
  const double dy = (Y - double(K.cy)) / double(K.fy);
  double xlo = INFINITY, xhi = -INFINITY;  // pixel-centre coordinates
  bool whole = false;
  // Projected ellipse.
  const double b1 = c.p1 * dy + c.q1, b2 = c.p2 * dy + c.q2, bn = c.ny * dy + c.nz;
  const double B = 2.0 * (c.a1 * b1 * c.wx + c.a2 * b2 * c.wy - c.R * c.nx * bn);
  const double C = b1 * b1 * c.wx + b2 * b2 * c.wy - c.R * bn * bn;
  const double disc = B * B - 4.0 * c.A * C;
  if (disc >= 0.0) {
    const double q = -0.5 * (B + copysign(sqrt(disc), B));  // stable roots q/A and C/q
    const double r1 = q / c.A, r2 = q != 0.0 ? C / q : r1;
    const double X1 = cx + fx * r1, X2 = cx + fx * r2;
    if (X1 == X1 && X2 == X2) {
      xlo = std::min(X1, X2);
      xhi = std::max(X1, X2);
    } else {
      whole = true;
    }
  } else if (!(disc < 0.0)) {
    whole = true;  // NaN
  }
  // Screen-space disk.
  const double ey = Y - c.my;
  const double h = c.r2d2 - ey * ey;
  if (h >= 0.0) {
    const double r = sqrt(h);
    xlo = std::min(xlo, c.mx - r);
    xhi = std::max(xhi, c.mx + r);
  } else if (!(h < 0.0)) {
    whole = true;
  }
  if (whole) {
    *lo = x_min;
    *hi = x_max;
    return x_min <= x_max;
  }
  if (!(xlo <= xhi)) return false;
  // Pixel x has its centre at x + 0.5; clamp in double before converting (values may be huge).
  const double a = ceil(xlo - 0.5 - SPAN_PX), b = floor(xhi - 0.5 + SPAN_PX);
  *lo = a > double(x_min) ? int(std::min(a, double(x_max) + 1.0)) : x_min;
  *hi = b < double(x_max) ? int(std::max(b, double(x_min) - 1.0)) : x_max;
  return *lo <= *hi;
}

}  // namespace cpu
}  // namespace ctgs
