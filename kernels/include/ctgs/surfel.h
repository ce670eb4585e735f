// Per-(pixel, primitive) math of the textured 2D Gaussian surfel renderer, forward and hand-written
// backward (docs/reference/renderer.md steps 1-7). HOST_DEVICE inline, templated on the scalar (float, double),
// no torch: the CPU (kernels/cpu) and CUDA (kernels/cuda) backends both call these.
#pragma once

#include <math.h>

#include "ctgs/constants.h"
#include "ctgs/exact.h"
#include "ctgs/texture.h"
#include "ctgs/vec3.h"

namespace ctgs {

// Pinhole intrinsics, pixels; near in world units (camera-space depth).
template <typename S>
struct Intrinsics {
  S fx, fy, cx, cy, near_plane;
  int width, height;
};

// One primitive in camera space, precomputed once per render.
template <typename S>
struct SurfelPrim {
  Vec3<S> mu;         // centre, camera space, world units
  Vec3<S> u, v, n;    // columns of Rc: tangent u, tangent v, normal (unit)
  S sx, sy;           // standard deviations along u, v, world units
  S opacity;          // [0, 1]
  S color[3];         // view-dependent base colour (SH + 0.5), unclamped
  S ku, kv;           // texel size along u, v, world units per texel
  int res_u, res_v;   // texels along u, v; 0 = no texture
  long long tex_off;  // first row of this primitive in the flat [T, 3] texel buffer
  S mx, my;           // projected centre, pixels
  S n_mu;             // n . mu (numerator of the ray parameter)
};

// Fills everything but the projected centre from raw arrays; index i of mu_c [N,3], Rc [N,3,3]
// (row-major, columns u, v, n), scales [N,2], opacities [N], colors [N,3], texel_size [N,2],
// tex_res [N,2], tex_offset [N].
template <typename S>
HOST_DEVICE inline SurfelPrim<S> load_prim(int i, const S* mu_c, const S* Rc, const S* scales, const S* opacities,
                                           const S* colors, const S* texel_size, const int* tex_res,
                                           const long long* tex_offset, const Intrinsics<S>& K) {
  SurfelPrim<S> P;
  const S* r = Rc + 9 * i;
  P.mu = make_vec3(mu_c[3 * i], mu_c[3 * i + 1], mu_c[3 * i + 2]);
  P.u = make_vec3(r[0], r[3], r[6]);
  P.v = make_vec3(r[1], r[4], r[7]);
  P.n = make_vec3(r[2], r[5], r[8]);
  P.sx = scales[2 * i];
  P.sy = scales[2 * i + 1];
  P.opacity = opacities[i];
  for (int c = 0; c < 3; ++c) P.color[c] = colors[3 * i + c];
  P.ku = texel_size[2 * i];
  P.kv = texel_size[2 * i + 1];
  P.res_u = tex_res[2 * i];
  P.res_v = tex_res[2 * i + 1];
  P.tex_off = tex_offset[i];
  P.mx = K.fx * P.mu.x / P.mu.z + K.cx;
  P.my = K.fy * P.mu.y / P.mu.z + K.cy;
  P.n_mu = dot(P.n, P.mu);
  return P;
}

// Camera ray through the centre of pixel (x, y): d = ((x+0.5-cx)/fx, (y+0.5-cy)/fy, 1), so t = depth.
template <typename S>
struct PixelRay {
  S px, py;    // pixel centre, continuous image coordinates
  Vec3<S> d;   // direction, z = 1
  S d_norm;    // |d|
};

template <typename S>
HOST_DEVICE inline PixelRay<S> pixel_ray(int x, int y, const Intrinsics<S>& K) {
  PixelRay<S> R;
  R.px = S(x) + S(0.5);
  R.py = S(y) + S(0.5);
  R.d = make_vec3(xsub(R.px, K.cx) / K.fx, xsub(R.py, K.cy) / K.fy, S(1));
  R.d_norm = sqrt(xdot(R.d, R.d));  // exact arithmetic (ctgs/exact.h): both kernels recompute the ray
  return R;
}

// Everything the forward computes for one (pixel, primitive) pair and the backward reuses.
template <typename S>
struct SurfelHit {
  bool valid;     // ray/plane hit is numerically well defined
  bool use_tex;   // valid, rho3d won over rho2d and the primitive has a texture
  S denom;        // n . d
  S t;            // ray parameter = camera-space depth of the hit
  Vec3<S> p;      // hit point, camera space
  S lx, ly;       // hit in the surfel plane, world units along u, v
  S rho3d, rho2d; // squared Mahalanobis distances (object space, screen-space fallback)
  S G;            // exp(-rho/2)
  S alpha;        // min(MAX_ALPHA, opacity * G)
  S z;            // depth of this hit (t if valid, else the centre depth)
  S c[3];         // colour after the texture and the clamp
  S c_raw[3];     // colour before the clamp (gradient mask)
  TexTaps<S> taps;
};

// Steps 1-4 (geometry and alpha). Returns false if the primitive does not contribute to this pixel
// (behind near, outside 3 sigma, alpha < MIN_ALPHA); then h is only partly filled. Every sum of products here is
// exact arithmetic (ctgs/exact.h): the forward and the backward kernel get the same alpha, and so agree on which
// pairs blend, whether or not the build contracts the rest into FMAs.
template <typename S>
HOST_DEVICE inline bool surfel_alpha(const SurfelPrim<S>& P, const PixelRay<S>& R, S near_plane, SurfelHit<S>& h) {
  h.denom = xdot(P.n, R.d);
  h.valid = fabs(h.denom) > S(PARALLEL_EPS) * R.d_norm;
  if (h.valid) {
    h.t = P.n_mu / h.denom;
    if (h.t < near_plane) return false;
    h.p = make_vec3(xmul(h.t, R.d.x), xmul(h.t, R.d.y), xmul(h.t, R.d.z));
    const Vec3<S> q = make_vec3(xsub(h.p.x, P.mu.x), xsub(h.p.y, P.mu.y), xsub(h.p.z, P.mu.z));
    h.lx = xdot(P.u, q);
    h.ly = xdot(P.v, q);
    const S ax = h.lx / P.sx, ay = h.ly / P.sy;
    h.rho3d = xadd(xmul(ax, ax), xmul(ay, ay));
    h.z = h.t;
  } else {
    h.rho3d = S(INFINITY);
    h.z = P.mu.z;
  }
  const S ex = xsub(R.px, P.mx), ey = xsub(R.py, P.my);
  h.rho2d = xmul(S(FILTER_INV_SQUARE), xadd(xmul(ex, ex), xmul(ey, ey)));
  const bool use3d = h.rho3d <= h.rho2d;
  const S rho = use3d ? h.rho3d : h.rho2d;
  if (!(rho <= S(CUTOFF_RHO))) return false;
  h.G = exp(xmul(S(-0.5), rho));
  const S a = xmul(P.opacity, h.G);
  h.alpha = a < S(MAX_ALPHA) ? a : S(MAX_ALPHA);
  if (h.alpha < S(MIN_ALPHA)) return false;
  h.use_tex = h.valid && use3d && P.res_u > 0 && P.res_v > 0;
  return true;
}

// Steps 5-6 (texture and colour), only for pairs that passed surfel_alpha. textures: [T, 3].
template <typename S>
HOST_DEVICE inline void surfel_color(const SurfelPrim<S>& P, const S* textures, SurfelHit<S>& h) {
  S tex[3] = {S(0), S(0), S(0)};
  if (h.use_tex) {
    const S uu = h.lx / P.ku + S(0.5) * S(P.res_u - 1);
    const S vv = h.ly / P.kv + S(0.5) * S(P.res_v - 1);
    h.taps = texture_taps(uu, vv, P.res_u, P.res_v, P.tex_off);
    texture_fetch(h.taps, textures, tex);
  } else {
    h.taps.active = false;
  }
  for (int c = 0; c < 3; ++c) {
    h.c_raw[c] = P.color[c] + tex[c];
    h.c[c] = h.c_raw[c] > S(0) ? h.c_raw[c] : S(0);
  }
}

// Gradients of one pair w.r.t. the primitive's camera-space parameters (what the kernels return).
template <typename S>
struct SurfelGrad {
  Vec3<S> mu, u, v, n;  // v_mu_c and the three columns of v_Rc
  S sx, sy, opacity;
  S color[3];
  S ku, kv;
  S tex[3];  // dL/d(fetched texture value); texel k receives taps.w(k) * tex (backend scatters)
};

// Backward of one pair. v_alpha, v_c[3], v_z: dL/d of this pair's alpha, colour c and depth z (the
// blending backward computes them). Overwrites g.
template <typename S>
HOST_DEVICE inline void surfel_backward(const SurfelPrim<S>& P, const PixelRay<S>& R, const Intrinsics<S>& K,
                                        const SurfelHit<S>& h, const S* textures, S v_alpha, const S v_c[3], S v_z, SurfelGrad<S>& g) {
  const Vec3<S> zero = make_vec3(S(0), S(0), S(0));
  g.mu = g.u = g.v = g.n = zero;
  g.sx = g.sy = g.ku = g.kv = S(0);
  // Colour: c = max(c_raw, 0), c_raw = color + tex (no gradient where clamped, c_raw <= 0, as relu).
  for (int c = 0; c < 3; ++c) {
    const S vc = h.c_raw[c] > S(0) ? v_c[c] : S(0);
    g.color[c] = vc;
    g.tex[c] = h.taps.active ? vc : S(0);
  }
  // alpha = min(MAX_ALPHA, o G): no gradient through the clamped branch.
  S v_G = S(0);
  g.opacity = S(0);
  if (P.opacity * h.G < S(MAX_ALPHA)) {
    g.opacity = v_alpha * h.G;
    v_G = v_alpha * P.opacity;
  }
  const S v_rho = v_G * S(-0.5) * h.G;
  S v_lx = S(0), v_ly = S(0), v_t = S(0);
  if (h.valid && h.rho3d <= h.rho2d) {
    // rho3d = (lx/sx)^2 + (ly/sy)^2
    const S isx2 = S(1) / (P.sx * P.sx), isy2 = S(1) / (P.sy * P.sy);
    v_lx += v_rho * S(2) * h.lx * isx2;
    v_ly += v_rho * S(2) * h.ly * isy2;
    g.sx = -v_rho * S(2) * h.lx * h.lx * isx2 / P.sx;
    g.sy = -v_rho * S(2) * h.ly * h.ly * isy2 / P.sy;
  } else {
    // rho2d = F |pix - m|^2, m = (fx mu.x/mu.z + cx, fy mu.y/mu.z + cy)
    const S v_mx = -v_rho * S(2) * S(FILTER_INV_SQUARE) * (R.px - P.mx);
    const S v_my = -v_rho * S(2) * S(FILTER_INV_SQUARE) * (R.py - P.my);
    const S iz = S(1) / P.mu.z;
    g.mu.x += v_mx * K.fx * iz;
    g.mu.y += v_my * K.fy * iz;
    g.mu.z -= (v_mx * (P.mx - K.cx) + v_my * (P.my - K.cy)) * iz;
  }
  // Texture: uu = lx/ku + (res_u-1)/2 -> dL/dlx += v_uu/ku, dL/dku = -v_uu lx/ku^2 (never the scales).
  if (h.taps.active) {
    S v_uu, v_vv;
    texture_fetch_backward(h.taps, textures, g.tex, &v_uu, &v_vv);
    v_lx += v_uu / P.ku;
    v_ly += v_vv / P.kv;
    g.ku = -v_uu * h.lx / (P.ku * P.ku);
    g.kv = -v_vv * h.ly / (P.kv * P.kv);
  }
  if (h.valid) {
    v_t += v_z;  // z = t
    // lx = u . (p - mu), ly = v . (p - mu)
    const Vec3<S> q = h.p - P.mu;
    g.u = v_lx * q;
    g.v = v_ly * q;
    const Vec3<S> v_p = v_lx * P.u + v_ly * P.v;
    g.mu.x -= v_p.x;
    g.mu.y -= v_p.y;
    g.mu.z -= v_p.z;
    // p = t d; t = (n . mu) / (n . d): dt/dmu = n/denom, dt/dn = (mu - p)/denom
    v_t += dot(v_p, R.d);
    const S s = v_t / h.denom;
    g.mu += s * P.n;
    g.n = s * (P.mu - h.p);
  } else {
    g.mu.z += v_z;  // z = mu.z
  }
}

}  // namespace ctgs
