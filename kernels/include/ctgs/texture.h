// Bilinear texel fetch on one primitive's jagged texture, forward and hand-written backward.
// docs/reference/renderer.md step 5: texel centres at integer (uu, vv); taps outside [0, res) read 0; a lookup with
// uu or vv non-finite or outside (-1, res) reads 0 (this also keeps floor() away from int overflow).
#pragma once

#include <math.h>

#include "ctgs/constants.h"

namespace ctgs {

// The four taps of one lookup, order (u0,v0), (u0+1,v0), (u0,v0+1), (u0+1,v0+1), kept compact (the first tap's
// row, the row stride, a mask of the taps inside the grid and the two fractions) because the CUDA backward holds
// one per lane across its gradient scatter: rows and weights are recomputed by row(k) and w(k), the same
// expressions as when they were stored.
template <typename S>
struct TexTaps {
  long long base;  // row of tap 0 in the flat [T, 3] buffer (meaningful for the taps in `inside` only)
  int stride;      // res_u: rows between (u, v) and (u, v+1)
  unsigned inside; // bit k: tap k lies inside the grid
  S fu, fv;        // fractional parts of uu, vv
  bool active;     // false: the lookup reads 0 and sends no gradient
  // Texel row of tap k, or -1 where it is outside the grid (or the lookup inactive).
  HOST_DEVICE long long row(int k) const { return (inside >> k) & 1u ? base + (k & 1) + (k >> 1) * stride : -1; }
  // Bilinear weight of tap k (the four sum to 1; 0 when inactive).
  HOST_DEVICE S w(int k) const {
    if (!active) return S(0);
    const S wu = (k & 1) ? fu : S(1) - fu, wv = (k >> 1) ? fv : S(1) - fv;
    return wu * wv;
  }
};

// uu, vv: continuous texel coordinates; res_u, res_v >= 1; offset: first row of this primitive.
template <typename S>
HOST_DEVICE inline TexTaps<S> texture_taps(S uu, S vv, int res_u, int res_v, long long offset) {
  TexTaps<S> tp;
  tp.stride = res_u;
  tp.inside = 0u;
  tp.base = -1;
  // Written as a positive test so NaN (all comparisons false) lands in the inactive branch.
  tp.active = (uu > S(-1)) && (uu < S(res_u)) && (vv > S(-1)) && (vv < S(res_v));
  if (!tp.active) {
    tp.fu = tp.fv = S(0);
    return tp;
  }
  const S fu0 = floor(uu), fv0 = floor(vv);
  const int u0 = static_cast<int>(fu0), v0 = static_cast<int>(fv0);  // in [-1, res-1]
  tp.fu = uu - fu0;
  tp.fv = vv - fv0;
  tp.base = offset + static_cast<long long>(v0) * res_u + u0;
  for (int k = 0; k < 4; ++k) {
    const int iu = u0 + (k & 1), iv = v0 + (k >> 1);
    if (iu >= 0 && iu < res_u && iv >= 0 && iv < res_v) tp.inside |= 1u << k;
  }
  return tp;
}

// out[3] = sum_k w_k * texel_k. textures: [T, 3].
template <typename S>
HOST_DEVICE inline void texture_fetch(const TexTaps<S>& tp, const S* textures, S out[3]) {
  out[0] = out[1] = out[2] = S(0);
  if (!tp.active) return;
  for (int k = 0; k < 4; ++k) {
    const long long r = tp.row(k);
    if (r < 0) continue;
    const S* t = textures + 3 * r;
    const S wk = tp.w(k);
    out[0] += wk * t[0];
    out[1] += wk * t[1];
    out[2] += wk * t[2];
  }
}

// Given v_tex[3] = dL/d(fetched value): dL/duu and dL/dvv (the texel gradients are w_k * v_tex, scattered
// by the backend, which owns the atomics).
template <typename S>
HOST_DEVICE inline void texture_fetch_backward(const TexTaps<S>& tp, const S* textures, const S v_tex[3],
                                               S* v_uu, S* v_vv) {
  *v_uu = S(0);
  *v_vv = S(0);
  if (!tp.active) return;
  S tv[4];  // v_tex . texel_k (0 outside the grid)
  for (int k = 0; k < 4; ++k) {
    const long long r = tp.row(k);
    if (r < 0) {
      tv[k] = S(0);
      continue;
    }
    const S* t = textures + 3 * r;
    tv[k] = v_tex[0] * t[0] + v_tex[1] * t[1] + v_tex[2] * t[2];
  }
  *v_uu = (S(1) - tp.fv) * (tv[1] - tv[0]) + tp.fv * (tv[3] - tv[2]);
  *v_vv = (S(1) - tp.fu) * (tv[2] - tv[0]) + tp.fu * (tv[3] - tv[1]);
}

}  // namespace ctgs
