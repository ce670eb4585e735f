// The photometric training loss (1 - l) L1 + l (1 - SSIM) of two [H, W, C] images, its gradient w.r.t. the
// render and the per-pixel error image of paper 3.3, in one fused pass on the CPU (as a chain of
// PyTorch ops - five moment images, two grouped convolutions forward, their autograd backward - the loss
// cost ~6 ms forward plus ~8 ms backward per 192x144 iteration and did not scale with threads).
//
// SSIM as ctgs/metrics/ssim.py: 11x11 separable Gaussian window, sigma 1.5, zero padding ("same" map),
// C1 = 0.01^2, C2 = 0.03^2. With m = G*x, e = G*(x x), e_xy = G*(x y) (G the blur):
//   A1 = 2 m_x m_y + C1, A2 = 2 (e_xy - m_x m_y) + C2, B1 = m_x^2 + m_y^2 + C1,
//   B2 = (e_xx - m_x^2) + (e_yy - m_y^2) + C2, ssim = A1 A2 / (B1 B2);
//   d ssim / d m_x  = (2 m_y (A2 - A1) - ssim 2 m_x (B2 - B1)) / (B1 B2),
//   d ssim / d e_xx = -ssim / B2,   d ssim / d e_xy = 2 A1 / (B1 B2).
// The blur is zero-padded correlation with a symmetric kernel, so its adjoint is the same blur:
//   dL/dx = G*(dL/dm_x) + 2 x G*(dL/de_xx) + y G*(dL/de_xy) + (1 - l) sign(x - y) / (H W C).
// Same float formulas as the PyTorch version up to summation order (sums in double; the tests compare
// both). Rows run in parallel; the row loops vectorise (channels interleaved: a tap is a shift by C).
#include <omp.h>

#include <algorithm>
#include <cmath>
#include <vector>

#include "dense.h"
#include "lanes.h"

namespace ctgs {
namespace cpu {

namespace {

constexpr int SSIM_RADIUS = 5;  // 11-tap window
constexpr int SSIM_TAPS = 2 * SSIM_RADIUS + 1;
constexpr double SSIM_SIGMA = 1.5;
constexpr double SSIM_C1 = 0.01 * 0.01;
constexpr double SSIM_C2 = 0.03 * 0.03;

// Normalised 1D Gaussian computed in double, then rounded to S (as ctgs/metrics/ssim.py _window).
template <typename S>
void gaussian_taps(S* g) {
  double w[SSIM_TAPS], sum = 0.0;
  for (int t = 0; t < SSIM_TAPS; ++t) {
    const double x = t - SSIM_RADIUS;
    w[t] = std::exp(-(x * x) / (2 * SSIM_SIGMA * SSIM_SIGMA));
    sum += w[t];
  }
  for (int t = 0; t < SSIM_TAPS; ++t) g[t] = S(w[t] / sum);
}

// out[i] = sum_t g[t] in[i + (t - R) C] over the taps inside the row (i = j C + c, n = W C): the horizontal
// pass of the blur on one row of interleaved channels, zero padded.
template <typename S>
CTGS_INLINE void hblur_row_impl(const S* __restrict in, S* __restrict out, int n, int C, const S* g) {
  for (int i = 0; i < n; ++i) out[i] = S(0);
  for (int t = 0; t < SSIM_TAPS; ++t) {
    const int off = (t - SSIM_RADIUS) * C;
    const int lo = std::max(0, -off), hi = std::min(n, n - off);
    const S gt = g[t];
#pragma omp simd
    for (int i = lo; i < hi; ++i) out[i] += gt * in[i + off];
  }
}

// out = sum_t g[t] plane[(r + t - R) n ...] over the rows inside the image: the vertical pass at row r.
template <typename S>
CTGS_INLINE void vblur_row_impl(const S* __restrict plane, S* __restrict out, int r, int H, int n, const S* g) {
  for (int i = 0; i < n; ++i) out[i] = S(0);
  for (int t = 0; t < SSIM_TAPS; ++t) {
    const int rr = r + t - SSIM_RADIUS;
    if (rr < 0 || rr >= H) continue;
    const S* __restrict src = plane + int64_t(rr) * n;
    const S gt = g[t];
#pragma omp simd
    for (int i = 0; i < n; ++i) out[i] += gt * src[i];
  }
}

// Baseline and AVX2 clones (lanes.h): the clone attribute needs plain functions, not templates.
CTGS_LANE_CLONES void hblur_row(const float* in, float* out, int n, int C, const float* g) {
  hblur_row_impl(in, out, n, C, g);
}
CTGS_LANE_CLONES void hblur_row(const double* in, double* out, int n, int C, const double* g) {
  hblur_row_impl(in, out, n, C, g);
}
CTGS_LANE_CLONES void vblur_row(const float* plane, float* out, int r, int H, int n, const float* g) {
  vblur_row_impl(plane, out, r, H, n, g);
}
CTGS_LANE_CLONES void vblur_row(const double* plane, double* out, int r, int H, int n, const double* g) {
  vblur_row_impl(plane, out, r, H, n, g);
}

}  // namespace

template <typename S>
void photometric_loss(const S* x, const S* y, int H, int W, int C, double lambda_ssim, S* grad, S* error,
                      double* l1_sum, double* ssim_sum, int threads) {
  const int n = W * C;
  const int64_t plane = int64_t(H) * n;
  S g[SSIM_TAPS];
  gaussian_taps(g);
  // Horizontally blurred moments x, y, xx, yy, xy ([5][H][n]); later the three gradient maps' blur.
  std::vector<S> hbuf(5 * plane);
  // Per-pixel coefficient maps dL/dm_x, dL/de_xx, dL/de_xy ([3][H][n]), only for the gradient.
  std::vector<S> coef(grad ? 3 * plane : 0);
  const S c1 = S(SSIM_C1), c2 = S(SSIM_C2), two = S(2);
  const double inv_n = 1.0 / (double(plane) > 0 ? double(plane) : 1.0);
  const S ssim_scale = S(-lambda_ssim * inv_n);  // dL / d ssim(pixel, channel)
  const S l1_scale = S((1.0 - lambda_ssim) * inv_n);
  const S err_l1 = S((1.0 - lambda_ssim) / C), err_ssim = S(lambda_ssim / C);
  double l1_acc = 0.0, ssim_acc = 0.0;
  const int nt = std::max(1, threads);
#pragma omp parallel num_threads(nt)
  {
    std::vector<S> row(5 * size_t(n));  // per-thread scratch: 5 rows
    S* q = row.data();
    // 1. Moment products of each row, blurred horizontally.
#pragma omp for schedule(static)
    for (int r = 0; r < H; ++r) {
      const S* xr = x + int64_t(r) * n;
      const S* yr = y + int64_t(r) * n;
      S *qx = q, *qy = q + n, *qxx = q + 2 * n, *qyy = q + 3 * n, *qxy = q + 4 * n;
#pragma omp simd
      for (int i = 0; i < n; ++i) {
        qxx[i] = xr[i] * xr[i];
        qyy[i] = yr[i] * yr[i];
        qxy[i] = xr[i] * yr[i];
      }
      hblur_row(xr, hbuf.data() + int64_t(r) * n, n, C, g);
      hblur_row(yr, hbuf.data() + plane + int64_t(r) * n, n, C, g);
      hblur_row(qxx, hbuf.data() + 2 * plane + int64_t(r) * n, n, C, g);
      hblur_row(qyy, hbuf.data() + 3 * plane + int64_t(r) * n, n, C, g);
      hblur_row(qxy, hbuf.data() + 4 * plane + int64_t(r) * n, n, C, g);
      (void)qx;
      (void)qy;
    }
    // 2. Vertical pass, SSIM per pixel and channel, the sums, the error image and the coefficient maps.
#pragma omp for schedule(static) reduction(+ : l1_acc, ssim_acc)
    for (int r = 0; r < H; ++r) {
      for (int k = 0; k < 5; ++k) vblur_row(hbuf.data() + k * plane, q + k * n, r, H, n, g);
      const S* xr = x + int64_t(r) * n;
      const S* yr = y + int64_t(r) * n;
      double l1_row = 0.0, ssim_row = 0.0;
      for (int j = 0; j < W; ++j) {
        S l1_pix = S(0), dssim_pix = S(0);
        for (int c = 0; c < C; ++c) {
          const int i = j * C + c;
          const S mx = q[i], my = q[n + i];
          const S mxx = mx * mx, myy = my * my, mxy = mx * my;
          const S sx = q[2 * n + i] - mxx, sy = q[3 * n + i] - myy, sxy = q[4 * n + i] - mxy;
          const S a1 = two * mxy + c1, a2 = two * sxy + c2;
          const S b1 = mxx + myy + c1, b2 = sx + sy + c2;
          const S den = b1 * b2;
          const S s = (a1 * a2) / den;
          const S d = xr[i] - yr[i];
          l1_pix += std::abs(d);
          dssim_pix += S(1) - s;
          ssim_row += double(s);
          if (grad) {
            const int64_t o = int64_t(r) * n + i;
            coef[o] = ssim_scale * (two * my * (a2 - a1) - s * two * mx * (b2 - b1)) / den;
            coef[plane + o] = ssim_scale * (-s / b2);
            coef[2 * plane + o] = ssim_scale * (two * a1 / den);
          }
        }
        l1_row += double(l1_pix);
        if (error) error[int64_t(r) * W + j] = err_l1 * l1_pix + err_ssim * dssim_pix;
      }
      l1_acc += l1_row;
      ssim_acc += ssim_row;
    }
    if (grad) {
      // 3. Adjoint blur of the coefficient maps (horizontal into hbuf), then vertical and the chain rule.
#pragma omp for schedule(static)
      for (int r = 0; r < H; ++r)
        for (int k = 0; k < 3; ++k)
          hblur_row(coef.data() + k * plane + int64_t(r) * n, hbuf.data() + k * plane + int64_t(r) * n, n, C, g);
#pragma omp for schedule(static)
      for (int r = 0; r < H; ++r) {
        for (int k = 0; k < 3; ++k) vblur_row(hbuf.data() + k * plane, q + k * n, r, H, n, g);
        const S* xr = x + int64_t(r) * n;
        const S* yr = y + int64_t(r) * n;
        S* gr = grad + int64_t(r) * n;
        const S* bm = q;
        const S* bxx = q + n;
        const S* bxy = q + 2 * n;
#pragma omp simd
        for (int i = 0; i < n; ++i) {
          const S d = xr[i] - yr[i];
          const S sgn = S((d > S(0)) - (d < S(0)));
          gr[i] = bm[i] + two * xr[i] * bxx[i] + yr[i] * bxy[i] + l1_scale * sgn;
        }
      }
    }
  }
  *l1_sum = l1_acc;
  *ssim_sum = ssim_acc;
}

template void photometric_loss<float>(const float*, const float*, int, int, int, double, float*, float*, double*,
                                      double*, int);
template void photometric_loss<double>(const double*, const double*, int, int, int, double, double*, double*,
                                       double*, double*, int);

}  // namespace cpu
}  // namespace ctgs
