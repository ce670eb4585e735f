// Conservative screen bounds of a surfel, in tiles (docs/reference/renderer.md "Screen bounds"): the projected
// 3-sigma corners in object space (2DGS fix: a screen-space 3-sigma box misses tiles of long tilted
// surfels) united with the screen-space fallback box m +- sqrt(CUTOFF_RHO / FILTER_INV_SQUARE) px.
#pragma once

#include <math.h>

#include "ctgs/constants.h"
#include "ctgs/surfel.h"

namespace ctgs {

// Tiles [x0, x1) x [y0, y1); empty if x0 >= x1 or y0 >= y1.
struct TileRect {
  int x0, y0, x1, y1;
};

HOST_DEVICE inline int tiles_x(int width) { return (width + TILE_W - 1) / TILE_W; }
HOST_DEVICE inline int tiles_y(int height) { return (height + TILE_H - 1) / TILE_H; }

// Pixel range [lo, hi] (inclusive) whose centres can lie in [vmin, vmax], with one pixel of margin for
// rounding, clamped to [0, size-1] before converting to int (values can be huge or infinite).
template <typename S>
HOST_DEVICE inline void pixel_span(S vmin, S vmax, int size, int* lo, int* hi) {
  S a = floor(vmin) - S(1), b = ceil(vmax) + S(1);
  if (!(a >= S(0))) a = S(0);  // also catches NaN: conservative
  if (!(b <= S(size - 1))) b = S(size - 1);
  *lo = static_cast<int>(a);
  *hi = static_cast<int>(b);
}

// Pixels [x0, x1] x [y0, y1] (inclusive) that the surfel can touch; empty if x0 > x1 or y0 > y1.
struct PixelRect {
  int x0, y0, x1, y1;
};

template <typename S>
HOST_DEVICE inline PixelRect surfel_pixel_rect(const SurfelPrim<S>& P, const Intrinsics<S>& K) {
  const PixelRect whole = {0, 0, K.width - 1, K.height - 1};
  const PixelRect empty = {0, 0, -1, -1};
  const S r2 = S(sqrt(CUTOFF_RHO / FILTER_INV_SQUARE));
  S xmin = P.mx - r2, xmax = P.mx + r2, ymin = P.my - r2, ymax = P.my + r2;
  const Vec3<S> a = S(3) * P.sx * P.u, b = S(3) * P.sy * P.v;
  for (int k = 0; k < 4; ++k) {
    const S su = (k & 1) ? S(1) : S(-1), sv = (k & 2) ? S(1) : S(-1);
    const Vec3<S> c = P.mu + su * a + sv * b;
    if (!(c.z >= K.near_plane)) return whole;  // straddles the near plane (or NaN): project nothing
    const S x = K.fx * c.x / c.z + K.cx, y = K.fy * c.y / c.z + K.cy;
    xmin = x < xmin ? x : xmin;
    xmax = x > xmax ? x : xmax;
    ymin = y < ymin ? y : ymin;
    ymax = y > ymax ? y : ymax;
  }
  // Pixel centres lie in [0.5, size - 0.5].
  if (xmax < S(0) || ymax < S(0) || xmin > S(K.width) || ymin > S(K.height)) return empty;
  PixelRect r;
  pixel_span(xmin, xmax, K.width, &r.x0, &r.x1);
  pixel_span(ymin, ymax, K.height, &r.y0, &r.y1);
  return r;
}

HOST_DEVICE inline TileRect tiles_of(const PixelRect& r) {
  if (r.x0 > r.x1 || r.y0 > r.y1) return TileRect{0, 0, 0, 0};
  return TileRect{r.x0 / TILE_W, r.y0 / TILE_H, r.x1 / TILE_W + 1, r.y1 / TILE_H + 1};
}

}  // namespace ctgs
