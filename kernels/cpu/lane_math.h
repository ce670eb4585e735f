// docs/reference/renderer.md steps 1-6 for W consecutive pixels of one row at once (lanes.h), as the CPU forward
// and backward both evaluate them: everything that depends only on the primitive is computed once per
// render (LanePrim), everything that depends only on the row once per row (LaneRow), and per pixel
// only what varies along the row. With d = (dx, dy, 1), the plane hit uses
//   t = (n.mu) / (n.d),  lx = u.(t d - mu) = t (u.d) - u.mu,  ly = t (v.d) - v.mu,
// where n.d = (nx dx + ny dy) + nz (likewise u.d, v.d) has its row term ny dy precomputed: the
// reference's formula (ctgs/render/reference.py), and the shared header's (ctgs/surfel.h) regrouped. Forward and
// backward call these same inline functions, so their alphas (and blending decisions) are identical.
#pragma once

#include <algorithm>
#include <cstdint>

#include "ctgs/bounds.h"
#include "ctgs/constants.h"
#include "ctgs/surfel.h"
#include "lanes.h"
#include "tex_gather.h"

namespace ctgs {
namespace cpu {

// One primitive in the form the lane kernels use (camera space, precomputed reciprocals).
template <typename S>
struct LanePrim {
  S nx, ny, nz, ux, uy, uz, vx, vy, vz;  // frame columns u, v, n
  S mux, muy, muz;                        // centre
  S n_mu, u_mu, v_mu;                     // n.mu, u.mu, v.mu
  S sx, sy, isx, isy, isx2, isy2;         // sx, sy, 1/sx, 1/sy, 1/sx^2, 1/sy^2
  S opacity;
  S mx, my;                               // projected centre, pixels
  S color[3];
  S ku, kv, iku, ikv, iku2, ikv2;         // ku, kv, 1/ku, 1/kv, 1/ku^2, 1/kv^2
  S half_u, half_v;                       // (res - 1) / 2: texel centres at integer coordinates
  S res_uf, res_vf;
  int res_u, res_v;
  long long tex_off;
  bool textured;                          // res_u > 0 and res_v > 0
  // Where its pixels are (binning.cpp), kept here so a tile touches one struct per primitive:
  PixelRect rect;                         // bounding box of the spans
  const int32_t* spans;                   // row rect.y0's span (PrimSpans), then one pair per row
  int64_t span_off;                       // spans - PrimSpans::xs.data(), -1 without spans
};

template <typename S>
inline LanePrim<S> lane_prim(const SurfelPrim<S>& P, const PixelRect& rect, const int32_t* spans,
                             const int32_t* spans_base) {
  LanePrim<S> L;
  L.rect = rect;
  L.spans = spans;
  L.span_off = spans ? spans - spans_base : -1;
  L.nx = P.n.x, L.ny = P.n.y, L.nz = P.n.z;
  L.ux = P.u.x, L.uy = P.u.y, L.uz = P.u.z;
  L.vx = P.v.x, L.vy = P.v.y, L.vz = P.v.z;
  L.mux = P.mu.x, L.muy = P.mu.y, L.muz = P.mu.z;
  L.n_mu = P.n_mu;
  L.u_mu = dot(P.u, P.mu);
  L.v_mu = dot(P.v, P.mu);
  L.sx = P.sx;
  L.sy = P.sy;
  L.isx = S(1) / P.sx;
  L.isy = S(1) / P.sy;
  L.isx2 = S(1) / (P.sx * P.sx);
  L.isy2 = S(1) / (P.sy * P.sy);
  L.opacity = P.opacity;
  L.mx = P.mx;
  L.my = P.my;
  for (int c = 0; c < 3; ++c) L.color[c] = P.color[c];
  L.ku = P.ku;
  L.kv = P.kv;
  L.iku = S(1) / P.ku;
  L.ikv = S(1) / P.kv;
  L.iku2 = S(1) / (P.ku * P.ku);
  L.ikv2 = S(1) / (P.kv * P.kv);
  L.half_u = S(0.5) * S(P.res_u - 1);
  L.half_v = S(0.5) * S(P.res_v - 1);
  L.res_uf = S(P.res_u);
  L.res_vf = S(P.res_v);
  L.res_u = P.res_u;
  L.res_v = P.res_v;
  L.tex_off = P.tex_off;
  L.textured = P.res_u > 0 && P.res_v > 0;
  return L;
}

// Row constants of one primitive.
template <typename S>
struct LaneRow {
  S dy;          // ray direction y
  S bn, bu, bv;  // ny dy, uy dy, vy dy: n.d = (nx dx + ny dy) + nz (the reference's order), ...
  S ey;          // pixel-centre y - projected centre y
  S ey2;
};

template <typename S>
CTGS_INLINE LaneRow<S> lane_row(const LanePrim<S>& P, S py, S dy) {
  LaneRow<S> r;
  r.dy = dy;
  r.bn = P.ny * dy;
  r.bu = P.uy * dy;
  r.bv = P.vy * dy;
  r.ey = py - P.my;
  r.ey2 = r.ey * r.ey;
  return r;
}

// Steps 1-4 for W pixels; lanes outside `in` (or failing) come out with ok = 0 and may hold any value.
template <typename S>
struct LaneHit {
  typename Lanes<S>::V nd, ud, vd, t, lx, ly, G, alpha, z;
  typename Lanes<S>::I ok, valid, use3d;
};

template <typename S>
CTGS_INLINE void lane_alpha(const LanePrim<S>& P, const LaneRow<S>& R, typename Lanes<S>::V dx,
                            typename Lanes<S>::V px, typename Lanes<S>::V dn, S near_plane,
                            typename Lanes<S>::I in, LaneHit<S>& h) {
  using V = typename Lanes<S>::V;
  h.nd = (P.nx * dx + R.bn) + P.nz;
  h.ud = (P.ux * dx + R.bu) + P.uz;
  h.vd = (P.vx * dx + R.bv) + P.vz;
  h.valid = vabs<S>(h.nd) > S(PARALLEL_EPS) * dn;
  h.t = P.n_mu / h.nd;
  h.lx = h.t * h.ud - P.u_mu;
  h.ly = h.t * h.vd - P.v_mu;
  const V ax = h.lx / P.sx, ay = h.ly / P.sy;
  const V rho3d = sel(h.valid, ax * ax + ay * ay, splat(S(INFINITY)));
  const typename Lanes<S>::I behind = h.valid & (h.t < near_plane);
  const V ex = px - P.mx;
  const V rho2d = S(FILTER_INV_SQUARE) * (ex * ex + R.ey2);
  h.use3d = rho3d <= rho2d;
  const V rho = sel(h.use3d, rho3d, rho2d);
  // rho is NaN or above the cutoff only in lanes that fail below; the clamp keeps exp's input in range.
  const V rc = sel(rho < S(CUTOFF_RHO), rho, splat(S(CUTOFF_RHO)));
  h.G = vexp(S(-0.5) * rc);
  const V a = P.opacity * h.G;
  h.alpha = sel(a < S(MAX_ALPHA), a, splat(S(MAX_ALPHA)));
  h.ok = in & ~behind & (rho <= S(CUTOFF_RHO)) & (h.alpha >= S(MIN_ALPHA));
  h.z = sel(h.valid, h.t, splat(P.muz));
}

// One texel's three channels in a short vector (a fourth lane, 0, pads it to a power of two): a texel is read and its
// gradient added with a few vector instructions instead of three scalar ones each. Reads and writes exactly three
// values, so a texel at the end of a buffer is safe and a neighbour's channel is never touched.
template <typename S>
struct Quad {
  typedef S Q __attribute__((vector_size(4 * sizeof(S))));
};

template <typename S>
CTGS_INLINE typename Quad<S>::Q load_rgb(const S* p) {
  return typename Quad<S>::Q{p[0], p[1], p[2], S(0)};
}

template <typename S>
CTGS_INLINE void store_rgb(S* p, typename Quad<S>::Q q) {
  p[0] = q[0];
  p[1] = q[1];
  p[2] = q[2];
}

// Step 5 (bilinear taps) for the lanes in `use`: active lanes, fractions, tap weights, and per lane the
// fetched colour tex (the taps summed in order, 0 in inactive lanes). With keep, also each tap's texel
// values and row (-1 outside the grid) for the backward. The fetch itself is a gather: twelve AVX2 gathers
// (tex_gather.h) where the CPU has them, else lane by lane with a texel's channels as one short vector; both
// write plain arrays that are read back as whole vectors only once per channel.
template <typename S>
struct LaneTex {
  typename Lanes<S>::I active;
  typename Lanes<S>::V fu, fv, w[4];
  alignas(32) S tex[3][Lanes<S>::W];       // [channel][lane]
  alignas(32) S texel[4][3][Lanes<S>::W];  // [tap][channel][lane] (keep only)
  alignas(32) long long row[4][Lanes<S>::W];  // [tap][lane] (keep only)
};

template <typename S>
CTGS_INLINE void lane_texture(const LanePrim<S>& P, const S* textures, const LaneHit<S>& h,
                              typename Lanes<S>::I use, LaneTex<S>& tx, bool keep) {
  using V = typename Lanes<S>::V;
  constexpr int W = Lanes<S>::W;
  // Divisions, not reciprocals: at texel centres (uu integral) the bilinear derivative jumps, so uu must
  // round exactly as the reference computes it.
  const V uu = h.lx / P.ku + P.half_u, vv = h.ly / P.kv + P.half_v;
  // Written as a positive test so NaN lands in the inactive branch (ctgs/texture.h).
  tx.active = use & h.valid & h.use3d & (uu > S(-1)) & (uu < P.res_uf) & (vv > S(-1)) & (vv < P.res_vf);
  const V uc = sel(tx.active, uu, splat(S(0))), vc = sel(tx.active, vv, splat(S(0)));
  const V fl_u = vfloor<S>(uc), fl_v = vfloor<S>(vc);
  tx.fu = uc - fl_u;
  tx.fv = vc - fl_v;
  const V one = splat(S(1));
  tx.w[0] = (one - tx.fu) * (one - tx.fv);
  tx.w[1] = tx.fu * (one - tx.fv);
  tx.w[2] = (one - tx.fu) * tx.fv;
  tx.w[3] = tx.fu * tx.fv;
  alignas(32) S flu[W], flv[W], wt[4][W];
  alignas(32) typename Lanes<S>::Int act[W];
  vstore(flu, fl_u);
  vstore(flv, fl_v);
  vstore(act, tx.active);
  for (int t = 0; t < 4; ++t) vstore(wt[t], tx.w[t]);
#ifdef CTGS_AVX2_GATHER
  if constexpr (W == 8 && sizeof(S) == 4) {
    // (the gathers index texels with 32-bit offsets: a block of 2^28 texels or more, 3 GB, takes the loop below)
    if (have_avx2_gather() && static_cast<long long>(P.res_u) * P.res_v < (1LL << 28)) {
      fetch_taps_avx2(flu, flv, act, &wt[0][0], P.res_u, P.res_v, P.tex_off, textures, &tx.tex[0][0],
                      keep ? &tx.texel[0][0][0] : nullptr, keep ? &tx.row[0][0] : nullptr);
      return;
    }
  }
#endif
  using Q = typename Quad<S>::Q;
  const Q zero{};
  for (int k = 0; k < W; ++k) {
    Q sum = zero;
    if (act[k]) {
      const int u0 = int(flu[k]), v0 = int(flv[k]);  // in [-1, res - 1]
      const bool in_u0 = u0 >= 0, in_u1 = u0 + 1 < P.res_u, in_v0 = v0 >= 0, in_v1 = v0 + 1 < P.res_v;
      const bool inside[4] = {in_u0 && in_v0, in_u1 && in_v0, in_u0 && in_v1, in_u1 && in_v1};
      const long long row0 = P.tex_off + static_cast<long long>(v0) * P.res_u + u0;
      const long long rows[4] = {row0, row0 + 1, row0 + P.res_u, row0 + P.res_u + 1};
      // A texel's three channels as one short vector (the fourth lane 0): the same products and sums, in the same
      // order, as channel by channel: w[0] t[0] + w[1] t[1] + w[2] t[2] + w[3] t[3].
      for (int t = 0; t < 4; ++t) {
        const Q val = inside[t] ? load_rgb(textures + 3 * rows[t]) : zero;
        sum = t == 0 ? wt[0][k] * val : sum + wt[t][k] * val;
        if (keep) {
          for (int c = 0; c < 3; ++c) tx.texel[t][c][k] = val[c];
          tx.row[t][k] = inside[t] ? rows[t] : -1;
        }
      }
    } else if (keep) {
      for (int t = 0; t < 4; ++t) tx.row[t][k] = -1;
    }
    for (int c = 0; c < 3; ++c) tx.tex[c][k] = sum[c];
  }
}

// Step 6: c_raw = colour + texture, c = max(c_raw, 0).
template <typename S>
CTGS_INLINE void lane_color(const LanePrim<S>& P, const LaneTex<S>& tx, typename Lanes<S>::V c_raw[3],
                            typename Lanes<S>::V c[3]) {
  using V = typename Lanes<S>::V;
  for (int ch = 0; ch < 3; ++ch) {
    c_raw[ch] = P.color[ch] + vload<V>(tx.tex[ch]);
    c[ch] = sel(c_raw[ch] > S(0), c_raw[ch], splat(S(0)));
  }
}

// Asks for a primitive's struct (the tile lists visit primitives in depth order, i.e. at random).
template <typename S>
CTGS_INLINE void prefetch_prim(const LanePrim<S>* P) {
  const char* a = reinterpret_cast<const char*>(P);
  for (size_t off = 0; off < sizeof(LanePrim<S>); off += 64) __builtin_prefetch(a + off, 0, 3);
}

// Its spans for rows [y0, y1] (the tile's rows; the struct itself must be at hand).
template <typename S>
CTGS_INLINE void prefetch_spans(const LanePrim<S>& P, int y0, int y1) {
  const int ya = std::max(P.rect.y0, y0), yb = std::min(P.rect.y1, y1);
  if (ya > yb) return;
  const char* a = reinterpret_cast<const char*>(P.spans + 2 * (ya - P.rect.y0));
  const char* b = reinterpret_cast<const char*>(P.spans + 2 * (yb - P.rect.y0));
  for (; a <= b; a += 64) __builtin_prefetch(a, 0, 3);
  __builtin_prefetch(b, 0, 3);
}

// Asks the memory system for the start of a primitive's texel block (and of its gradient rows) ahead of
// use: the gathers and scatters of trained scenes (1-2M texels, tens of MB) miss the caches, and the
// next primitive of a tile list is known while the current one is processed.
constexpr long long PREFETCH_TEXELS = 32;  // 384 B of float texels: the first rows (the hardware prefetcher streams on)
template <typename S>
CTGS_INLINE void prefetch_texels(const LanePrim<S>& P, const S* textures, const S* grad) {
  if (!P.textured) return;
  const long long n = std::min<long long>(PREFETCH_TEXELS, static_cast<long long>(P.res_u) * P.res_v);
  const char* a = reinterpret_cast<const char*>(textures + 3 * P.tex_off);
  const char* b = grad ? reinterpret_cast<const char*>(grad + 3 * P.tex_off) : nullptr;
  for (long long off = 0; off < n * 3 * static_cast<long long>(sizeof(S)); off += 64) {
    __builtin_prefetch(a + off, 0, 3);
    if (b) __builtin_prefetch(b + off, 1, 3);
  }
}

// Step 6 for an untextured primitive (c_raw = colour).
template <typename S>
CTGS_INLINE void lane_color_plain(const LanePrim<S>& P, typename Lanes<S>::V c_raw[3], typename Lanes<S>::V c[3]) {
  for (int ch = 0; ch < 3; ++ch) {
    c_raw[ch] = splat(P.color[ch]);
    c[ch] = sel(c_raw[ch] > S(0), c_raw[ch], splat(S(0)));
  }
}


template <typename I>
CTGS_INLINE int count_lanes(I m) {
  int n = 0;
  for (int k = 0; k < int(sizeof(I) / sizeof(m[0])); ++k) n += m[k] != 0;
  return n;
}

}  // namespace cpu
}  // namespace ctgs
