// Hand-written backward of the CPU backend: back-to-front per pixel over the entries the forward
// processed (3DGS), recovering T by division (alpha <= MAX_ALPHA keeps it safe). Tiles in parallel;
// per-primitive gradients go to per-thread buffers reduced at the end. Texel gradients go to per-thread
// copies of the texel buffer too while those stay small (MAX_PRIVATE_TEXEL_BYTES), else to the output
// with atomics (a float atomic add is a CAS loop: 12 per pair would dominate the backward).
//
// Pixels are processed W at a time along the primitive's row spans (lanes.h, lane_math.h): the same
// alpha as the forward (same functions), then the gradient of docs/reference/renderer.md steps 1-8 per lane (the
// derivative of ctgs/surfel.h's surfel_backward, regrouped: terms that are a per-primitive vector times a
// per-pixel scalar are summed as scalars and multiplied once per primitive and tile).
#include <omp.h>

#include <algorithm>
#include <memory>

#include "lane_math.h"
#include "rasterize.h"

namespace ctgs {
namespace cpu {

namespace {
// Layout of one primitive's gradient row in the per-thread buffers.
// G_CONTRIB, G_ERR: the error statistics of a backward given an error image (the forward's with error_image:
// sum of w, sum of e w over the pixels blended).
enum : int { G_MU = 0, G_RC = 3, G_SCALE = 12, G_OPACITY = 14, G_COLOR = 15, G_TEXEL = 18, G_CONTRIB = 20, G_ERR = 21,
             G_STRIDE = 22 };
// Above this many bytes of extra per-thread texel-gradient copies, atomics are used instead.
constexpr size_t MAX_PRIVATE_TEXEL_BYTES = size_t(256) << 20;

template <typename S>
struct BackwardTileArgs {
  const SceneArgs<S>* a;
  const TileBinsView* bins;
  const LanePrim<S>* prims;
  const S* final_T;
  const int32_t* n_contrib;
  const S* v_rgb;
  const S* v_alpha;
  const S* v_depth;
  const S* v_depth2;  // [H, W] or null (zero)
  const S* error_image;  // [H, W] or null: no error statistics
  int ntx;
  S* g_thread;    // [N, G_STRIDE] this thread's per-primitive gradients
  S* v_tex;       // [T, 3] this thread's texel gradients
  bool atomics;   // v_tex is shared: add atomically
  S* bg_thread;   // [3] this thread's background gradient
  // With several threads: this thread's first-touch flags per primitive (SEEN_*), else nullptr. g_thread rows
  // are then zeroed on first write, and with lazy_tex a primitive's block of v_tex on first visit, so that
  // neither buffer is cleared nor reduced whole.
  unsigned char* seen;
  bool lazy_tex;
};

enum : unsigned char { SEEN_ROW = 1, SEEN_TEX = 2 };

// Per-lane sums of one primitive over one tile.
template <typename S>
struct GradSums {
  typename Lanes<S>::V color[3], opacity, sx, sy, mx, my, ku, kv, lx, ly, s, u[3], v[3], n[3], z_invalid, cw, ew;
};

template <typename S>
CTGS_INLINE void backward_tile_impl(const BackwardTileArgs<S>& b, int tile) {
  using L = Lanes<S>;
  using V = typename L::V;
  using I = typename L::I;
  using Int = typename L::Int;
  constexpr int W = L::W;
  constexpr int RS = TILE_W + W;  // row stride: lane groups may run past a row end into the padding
  constexpr int NP = TILE_H * RS;
  const SceneArgs<S>& a = *b.a;
  const int Wimg = a.K.width, Himg = a.K.height;
  const int64_t begin = b.bins->offsets[tile];
  const int x0 = (tile % b.ntx) * TILE_W, y0 = (tile / b.ntx) * TILE_H;
  const int x1 = std::min(x0 + TILE_W, Wimg), y1 = std::min(y0 + TILE_H, Himg);  // exclusive
  alignas(32) S T[NP], acc[NP], g0[NP], g1[NP], g2[NP], gD[NP], gD2[NP], dn[NP], ev[NP];
  const bool stats = b.error_image != nullptr;
  alignas(32) Int ncon[NP];
  alignas(32) S pxa[RS], dxa[RS], pya[TILE_H], dya[TILE_H];
  const S bg[3] = {a.background[0], a.background[1], a.background[2]};
  for (int k = 0; k < RS; ++k) {
    pxa[k] = S(x0 + k) + S(0.5);
    dxa[k] = (pxa[k] - a.K.cx) / a.K.fx;
  }
  int32_t jmax = 0;
  for (int r = 0; r < TILE_H; ++r) {
    pya[r] = S(y0 + r) + S(0.5);
    dya[r] = (pya[r] - a.K.cy) / a.K.fy;
    for (int k = 0; k < RS; ++k) {
      const int p = r * RS + k;
      dn[p] = sqrt(dxa[k] * dxa[k] + dya[r] * dya[r] + S(1) * S(1));
      if (!(y0 + r < y1 && x0 + k < x1 && k < TILE_W)) {
        T[p] = acc[p] = g0[p] = g1[p] = g2[p] = gD[p] = gD2[p] = ev[p] = S(0);
        ncon[p] = 0;  // padding: no entry is ever in front of where it stopped
        continue;
      }
      const int64_t pix = int64_t(y0 + r) * Wimg + x0 + k;
      g0[p] = b.v_rgb[3 * pix];
      g1[p] = b.v_rgb[3 * pix + 1];
      g2[p] = b.v_rgb[3 * pix + 2];
      ev[p] = stats ? b.error_image[pix] : S(0);
      gD[p] = b.v_depth[pix];
      gD2[p] = b.v_depth2 != nullptr ? b.v_depth2[pix] : S(0);
      T[p] = b.final_T[pix];
      b.bg_thread[0] += T[p] * g0[p];
      b.bg_thread[1] += T[p] * g1[p];
      b.bg_thread[2] += T[p] * g2[p];
      // acc = sum_{j>i} w_j f_j + T_final (bg . gC - gA), f_j = c_j . gC + z_j gD + z_j^2 gD2: everything behind i
      // that alpha_i attenuates (alpha = 1 - T_final, hence -gA).
      acc[p] = T[p] * (bg[0] * g0[p] + bg[1] * g1[p] + bg[2] * g2[p] - b.v_alpha[pix]);
      ncon[p] = b.n_contrib[pix];
      jmax = std::max(jmax, b.n_contrib[pix]);
    }
  }
  I iota;
  for (int k = 0; k < W; ++k) iota[k] = k;
  const V zero = splat(S(0));
  for (int32_t jj = jmax - 1; jj >= 0; --jj) {
    const int32_t i = b.bins->list[begin + jj];
    const LanePrim<S>& P = b.prims[i];
    // Two entries ahead: the struct; one ahead: its spans, texels and texel gradients.
    if (jj > 1) prefetch_prim(&b.prims[b.bins->list[begin + jj - 2]]);
    if (jj > 0) {
      const int32_t next = b.bins->list[begin + jj - 1];
      const LanePrim<S>& Q = b.prims[next];
      prefetch_spans(Q, y0, y1 - 1);
      prefetch_texels(Q, a.textures, b.v_tex);
      // and its gradient row, which the end of its tile reads and writes (a miss: primitives come in depth order)
      const char* g = reinterpret_cast<const char*>(b.g_thread + size_t(next) * G_STRIDE);
      __builtin_prefetch(g, 1, 3);
      __builtin_prefetch(g + G_STRIDE * sizeof(S) - 1, 1, 3);
    }
    const PixelRect& r = P.rect;
    const int ry0 = std::max(r.y0, y0), ry1 = std::min(r.y1, y1 - 1);
    if (ry0 > ry1) continue;
    if (b.lazy_tex && !(b.seen[i] & SEEN_TEX)) {
      const long long n = 3LL * a.tex_res[2 * i] * a.tex_res[2 * i + 1];
      std::fill(b.v_tex + 3 * a.tex_offset[i], b.v_tex + 3 * a.tex_offset[i] + n, S(0));
      b.seen[i] |= SEEN_TEX;
    }
    const int32_t* sp = P.spans + 2 * (ry0 - r.y0);
    GradSums<S> g;
    g.opacity = g.sx = g.sy = g.mx = g.my = g.ku = g.kv = g.lx = g.ly = g.s = g.z_invalid = g.cw = g.ew = zero;
    for (int c = 0; c < 3; ++c) g.color[c] = g.u[c] = g.v[c] = g.n[c] = zero;
    bool any_pass = false;
    for (int y = ry0; y <= ry1; ++y, sp += 2) {
      const int lo = std::max(int(sp[0]), x0), hi = std::min(int(sp[1]), x1 - 1);
      if (lo > hi) continue;
      const int ty = y - y0;
      const LaneRow<S> R = lane_row(P, pya[ty], dya[ty]);
      for (int x = lo; x <= hi; x += W) {
        const int k0 = x - x0, p0 = ty * RS + k0;
        const I in = (iota <= Int(hi - x)) & (Int(jj) < vload<I>(ncon + p0));  // not behind where it stopped
        if (!any(in)) continue;
        const V dx = vload<V>(dxa + k0), px = vload<V>(pxa + k0);
        LaneHit<S> h;
        lane_alpha(P, R, dx, px, vload<V>(dn + p0), a.K.near_plane, in, h);
        const I pass = h.ok;
        if (!any(pass)) continue;
        any_pass = true;
        V c_raw[3], c[3];
        LaneTex<S> tx;
        if (P.textured) {
          lane_texture(P, a.textures, h, pass, tx, true);
          lane_color(P, tx, c_raw, c);
        } else {
          tx.active = I{};
          lane_color_plain(P, c_raw, c);
        }
        const V Tv = vload<V>(T + p0), accv = vload<V>(acc + p0);
        const V gc[3] = {vload<V>(g0 + p0), vload<V>(g1 + p0), vload<V>(g2 + p0)};
        const V gd = vload<V>(gD + p0), gd2 = vload<V>(gD2 + p0);
        const V om = S(1) - h.alpha;
        const V one_minus = sel(om > S(T_RECOVER_EPS), om, splat(S(T_RECOVER_EPS)));
        const V T_i = Tv / one_minus;
        const V w = h.alpha * T_i;
        if (stats) {
          g.cw += sel(pass, w, zero);
          g.ew += sel(pass, w * vload<V>(ev + p0), zero);
        }
        const V f = c[0] * gc[0] + c[1] * gc[1] + c[2] * gc[2] + h.z * (gd + h.z * gd2);
        const V v_a = T_i * f - accv / one_minus;
        // Colour: no gradient where clamped (c_raw <= 0); the texture gets what the colour gets.
        V vc[3], gtex[3];
        for (int ch = 0; ch < 3; ++ch) {
          vc[ch] = sel(c_raw[ch] > S(0), w * gc[ch], zero);
          gtex[ch] = sel(tx.active, vc[ch], zero);
          g.color[ch] += sel(pass, vc[ch], zero);
        }
        // alpha = min(MAX_ALPHA, o G): no gradient through the clamped branch.
        const I unclamped = (P.opacity * h.G) < S(MAX_ALPHA);
        g.opacity += sel(pass & unclamped, v_a * h.G, zero);
        const V v_G = sel(unclamped, v_a * P.opacity, zero);
        const V v_rho = v_G * S(-0.5) * h.G;
        const I is3d = pass & h.valid & h.use3d;
        // rho3d = (lx/sx)^2 + (ly/sy)^2
        V v_lx = sel(is3d, v_rho * S(2) * h.lx * P.isx2, zero);
        V v_ly = sel(is3d, v_rho * S(2) * h.ly * P.isy2, zero);
        g.sx += sel(is3d, -v_rho * S(2) * h.lx * h.lx * P.isx2 * P.isx, zero);
        g.sy += sel(is3d, -v_rho * S(2) * h.ly * h.ly * P.isy2 * P.isy, zero);
        // rho2d = F |pix - m|^2: summed here, times d m / d mu once per primitive below.
        const I is2d = pass & ~(h.valid & h.use3d);
        g.mx += sel(is2d, -v_rho * S(2) * S(FILTER_INV_SQUARE) * (px - P.mx), zero);
        g.my += sel(is2d, -v_rho * S(2) * S(FILTER_INV_SQUARE) * R.ey, zero);
        // Texture: uu = lx/ku + (res_u-1)/2 -> dL/dlx += v_uu/ku, dL/dku = -v_uu lx/ku^2; the texel
        // gradients (tap weight x dL/d(fetched value)) are scattered lane by lane.
        if (any(tx.active)) {
          V tv[4];  // dL/d(fetched value) . texel, per tap (0 outside the grid)
          for (int t = 0; t < 4; ++t)
            tv[t] = gtex[0] * vload<V>(tx.texel[t][0]) + gtex[1] * vload<V>(tx.texel[t][1]) +
                    gtex[2] * vload<V>(tx.texel[t][2]);
          const V one = splat(S(1));
          const V v_uu = sel(tx.active, (one - tx.fv) * (tv[1] - tv[0]) + tx.fv * (tv[3] - tv[2]), zero);
          const V v_vv = sel(tx.active, (one - tx.fu) * (tv[2] - tv[0]) + tx.fu * (tv[3] - tv[1]), zero);
          v_lx = v_lx + v_uu * P.iku;
          v_ly = v_ly + v_vv * P.ikv;
          g.ku += sel(tx.active, -v_uu * h.lx * P.iku2, zero);
          g.kv += sel(tx.active, -v_vv * h.ly * P.ikv2, zero);
          using Q = typename Quad<S>::Q;
          for (int k = 0; k < W; ++k) {
            if (!tx.active[k]) continue;
            const Q gk{gtex[0][k], gtex[1][k], gtex[2][k], S(0)};
            for (int t = 0; t < 4; ++t) {
              if (tx.row[t][k] < 0) continue;
              S* dst = b.v_tex + 3 * tx.row[t][k];
              const Q val = tx.w[t][k] * gk;
              if (b.atomics) {
                for (int ch = 0; ch < 3; ++ch) {
#pragma omp atomic
                  dst[ch] += val[ch];
                }
              } else {
                store_rgb(dst, load_rgb(dst) + val);
              }
            }
          }
        }
        const V v_z = w * (gd + S(2) * h.z * gd2);  // D and D2 = sum w z^2
        const I pv = pass & h.valid;
        // lx = u.(p - mu), ly = v.(p - mu), p = t d; t = (n.mu) / (n.d): dt/dmu = n/(n.d),
        // dt/dn = (mu - p)/(n.d). v_p . d = v_lx (u.d) + v_ly (v.d).
        const V v_t = v_z + (v_lx * h.ud + v_ly * h.vd);
        const V s = sel(pv, v_t / h.nd, zero);
        const V q[3] = {h.t * dx - P.mux, h.t * R.dy - P.muy, h.t - P.muz};  // p - mu
        const V vlx = sel(pv, v_lx, zero), vly = sel(pv, v_ly, zero);
        g.lx += vlx;
        g.ly += vly;
        g.s += s;
        for (int k = 0; k < 3; ++k) {
          g.u[k] += sel(pv, vlx * q[k], zero);
          g.v[k] += sel(pv, vly * q[k], zero);
          g.n[k] += sel(pv, -s * q[k], zero);
        }
        g.z_invalid += sel(pass & ~h.valid, v_z, zero);  // z = mu.z
        vstore(acc + p0, sel(pass, accv + w * f, accv));
        vstore(T + p0, sel(pass, T_i, Tv));
      }
    }
    if (!any_pass) continue;
    // The 22 lane sums of this primitive and tile at once (lanes.h hsums: the same sums as hsum, bit for bit).
    enum { H_LX, H_LY, H_S, H_MX, H_MY, H_ZI, H_U, H_V = H_U + 3, H_N = H_V + 3, H_SX = H_N + 3, H_SY, H_OP,
           H_COL, H_KU = H_COL + 3, H_KV, H_CW, H_EW, H_COUNT };
    V hv[H_COUNT];
    hv[H_LX] = g.lx, hv[H_LY] = g.ly, hv[H_S] = g.s, hv[H_MX] = g.mx, hv[H_MY] = g.my, hv[H_ZI] = g.z_invalid;
    for (int k = 0; k < 3; ++k) hv[H_U + k] = g.u[k], hv[H_V + k] = g.v[k], hv[H_N + k] = g.n[k];
    hv[H_SX] = g.sx, hv[H_SY] = g.sy, hv[H_OP] = g.opacity;
    for (int ch = 0; ch < 3; ++ch) hv[H_COL + ch] = g.color[ch];
    hv[H_KU] = g.ku, hv[H_KV] = g.kv, hv[H_CW] = g.cw, hv[H_EW] = g.ew;
    alignas(32) S hs[H_COUNT + 8];
    hsums(hv, stats ? int(H_COUNT) : int(H_CW), hs);
    const S slx = hs[H_LX], sly = hs[H_LY], ss = hs[H_S];
    const S smx = hs[H_MX], smy = hs[H_MY];
    const S iz = S(1) / P.muz;
    S* row = b.g_thread + size_t(i) * G_STRIDE;
    if (b.seen != nullptr && !(b.seen[i] & SEEN_ROW)) {
      std::fill(row, row + G_STRIDE, S(0));
      b.seen[i] |= SEEN_ROW;
    }
    // mu: -v_p (through lx, ly) + s n (through t) + the screen-space centre + z = mu.z where invalid.
    row[G_MU] += -(P.ux * slx + P.vx * sly) + P.nx * ss + smx * a.K.fx * iz;
    row[G_MU + 1] += -(P.uy * slx + P.vy * sly) + P.ny * ss + smy * a.K.fy * iz;
    row[G_MU + 2] += -(P.uz * slx + P.vz * sly) + P.nz * ss -
                     (smx * (P.mx - a.K.cx) + smy * (P.my - a.K.cy)) * iz + hs[H_ZI];
    // Rc row-major with columns u, v, n: element (row k, col c) at 3k + c.
    for (int k = 0; k < 3; ++k) {
      row[G_RC + 3 * k] += hs[H_U + k];
      row[G_RC + 3 * k + 1] += hs[H_V + k];
      row[G_RC + 3 * k + 2] += hs[H_N + k];
    }
    row[G_SCALE] += hs[H_SX];
    row[G_SCALE + 1] += hs[H_SY];
    row[G_OPACITY] += hs[H_OP];
    for (int ch = 0; ch < 3; ++ch) row[G_COLOR + ch] += hs[H_COL + ch];
    row[G_TEXEL] += hs[H_KU];
    row[G_TEXEL + 1] += hs[H_KV];
    if (stats) {
      row[G_CONTRIB] += hs[H_CW];
      row[G_ERR] += hs[H_EW];
    }
  }
}

// Non-template entry points so that each can be multiversioned (lanes.h).
CTGS_LANE_CLONES void backward_tile(const BackwardTileArgs<float>& b, int tile) { backward_tile_impl(b, tile); }
CTGS_LANE_CLONES void backward_tile(const BackwardTileArgs<double>& b, int tile) { backward_tile_impl(b, tile); }

}  // namespace

template <typename S>
void backward(const SceneArgs<S>& a, const TileBinsView& bins, const S* final_T, const int32_t* n_contrib,
              const S* v_rgb, const S* v_alpha, const S* v_depth, const BackwardOut<S>& out,
              unsigned char* setup_prims, const int32_t* setup_spans, const S* error_image, S* stats_contrib,
              S* stats_err, const S* v_depth2) {
  ProfTimer timer;
  const int W = a.K.width, H = a.K.height, N = a.N;
  const int ntx = tiles_x(W), num_tiles = ntx * tiles_y(H);
  const int nt = std::max(1, a.num_threads);
  std::vector<LanePrim<S>> lp_own;
  PrimSpans spans;  // (recomputed case) the lane primitives point into it
  LanePrim<S>* lp;
  if (setup_prims != nullptr) {
    // The forward's primitives; their span pointers are re-aimed at the spans buffer as handed back.
    lp = reinterpret_cast<LanePrim<S>*>(setup_prims);
#pragma omp parallel for schedule(static) num_threads(nt)
    for (int i = 0; i < N; ++i) lp[i].spans = lp[i].span_off >= 0 ? setup_spans + lp[i].span_off : nullptr;
  } else {
    std::vector<SurfelPrim<S>> prims;
    std::vector<PixelRect> rects;
    bin_primitives<S>(a, prims, rects, spans, nullptr);  // camera-space constants only; the lists come from forward
    lp_own.resize(N);
    lp = lp_own.data();
#pragma omp parallel for schedule(static) num_threads(nt)
    for (int i = 0; i < N; ++i) {
      const PixelRect& r = rects[i];
      lp[i] = lane_prim(prims[i], r, r.x0 <= r.x1 && r.y0 <= r.y1 ? spans.row(i, r.y0) : nullptr, spans.xs.data());
    }
  }
  // One thread: gradients straight into zeroed buffers, reduced in one pass. Several: per-thread rows and
  // texel blocks zeroed on first touch and summed per primitive over the threads that touched them (in
  // thread order, so the same sums as adding every thread's full buffer: untouched parts are zeros).
  const bool multi = nt > 1;
  std::unique_ptr<S[]> gbuf(new S[size_t(nt) * N * G_STRIDE]);
  if (!multi) std::fill(gbuf.get(), gbuf.get() + size_t(N) * G_STRIDE, S(0));
  std::vector<unsigned char> seen(multi ? size_t(nt) * N : 0, 0);
  std::vector<S> bgbuf(size_t(nt) * 3, S(0));
  // Thread 0 writes texel gradients straight into the output, threads 1.. into private copies.
  const size_t tex_n = size_t(3) * size_t(a.T);
  const bool private_tex = multi && tex_n * (nt - 1) * sizeof(S) <= MAX_PRIVATE_TEXEL_BYTES;
  // Per-primitive lazy zeroing needs disjoint blocks; the model keeps them packed in primitive order, which is
  // what is checked (other layouts, e.g. blocks shared between primitives, zero and reduce whole copies).
  bool packed = private_tex;
  for (int i = 0, last = -1; packed && i < N; ++i) {
    if (a.tex_res[2 * i] * a.tex_res[2 * i + 1] <= 0) continue;
    if (last >= 0 && a.tex_offset[i] < a.tex_offset[last] + (long long)a.tex_res[2 * last] * a.tex_res[2 * last + 1])
      packed = false;
    last = i;
  }
  std::unique_ptr<S[]> tbuf(private_tex ? new S[tex_n * (nt - 1)] : nullptr);
  const size_t tex_zero_n = private_tex && !packed ? tex_n * nt : tex_n;
  // Zeroed in parallel: for large jagged textures (hundreds of MB) this first touch is a visible cost.
#pragma omp parallel for schedule(static) num_threads(nt)
  for (long long k = 0; k < (long long)tex_zero_n; ++k) {
    if (size_t(k) < tex_n) out.v_textures[k] = S(0);
    else tbuf[k - tex_n] = S(0);
  }
  const bool use_atomics = multi && !private_tex;
  timer.lap(PROF_BWD_SETUP);

  const std::vector<int> order = tile_order(bins.offsets, num_tiles, nt);
  // Tiles dealt round-robin, heaviest first (static, not dynamic): which thread sums which tile's gradients, and so
  // the order of every float sum, does not depend on the machine's load, and a run is the same idle or loaded
  // (textures past MAX_PRIVATE_TEXEL_BYTES are summed with atomics, in the order the threads reach them).
#pragma omp parallel for schedule(static, 1) num_threads(nt)
  for (int k = 0; k < num_tiles; ++k) {
    const int tile = order[k];
    const int tid = omp_get_thread_num();
    BackwardTileArgs<S> b{&a, &bins, lp, final_T, n_contrib, v_rgb, v_alpha, v_depth, v_depth2, error_image,
                          ntx, gbuf.get() + size_t(tid) * N * G_STRIDE,
                          (tid == 0 || !private_tex) ? out.v_textures : tbuf.get() + size_t(tid - 1) * tex_n,
                          use_atomics, bgbuf.data() + 3 * tid,
                          multi ? seen.data() + size_t(tid) * N : nullptr, packed && tid > 0};
    backward_tile(b, tile);
  }
  timer.lap(PROF_BWD_RASTER);

#pragma omp parallel for schedule(static) num_threads(nt)
  for (int i = 0; i < N; ++i) {
    S row[G_STRIDE] = {};
    for (int t = 0; t < nt; ++t) {
      if (multi && !(seen[size_t(t) * N + i] & SEEN_ROW)) continue;
      const S* src = gbuf.get() + (size_t(t) * N + i) * G_STRIDE;
      for (int k = 0; k < G_STRIDE; ++k) row[k] += src[k];
    }
    for (int k = 0; k < 3; ++k) out.v_mu_c[3 * i + k] = row[G_MU + k];
    for (int k = 0; k < 9; ++k) out.v_Rc[9 * i + k] = row[G_RC + k];
    for (int k = 0; k < 2; ++k) out.v_scales[2 * i + k] = row[G_SCALE + k];
    out.v_opacities[i] = row[G_OPACITY];
    for (int k = 0; k < 3; ++k) out.v_colors[3 * i + k] = row[G_COLOR + k];
    for (int k = 0; k < 2; ++k) out.v_texel_size[2 * i + k] = row[G_TEXEL + k];
    if (error_image != nullptr) {
      stats_contrib[i] = row[G_CONTRIB];
      stats_err[i] = row[G_ERR];
    }
  }
  timer.lap(PROF_BWD_REDUCE);
  if (packed) {
#pragma omp parallel for schedule(dynamic, 64) num_threads(nt)
    for (int i = 0; i < N; ++i) {
      const long long n = 3LL * a.tex_res[2 * i] * a.tex_res[2 * i + 1];
      S* dst = out.v_textures + 3 * a.tex_offset[i];
      for (int t = 0; t + 1 < nt; ++t) {
        if (!(seen[size_t(t + 1) * N + i] & SEEN_TEX)) continue;
        const S* src = tbuf.get() + size_t(t) * tex_n + 3 * a.tex_offset[i];
        for (long long k = 0; k < n; ++k) dst[k] += src[k];
      }
    }
  } else if (private_tex) {
#pragma omp parallel for schedule(static) num_threads(nt)
    for (long long k = 0; k < (long long)tex_n; ++k) {
      S s = out.v_textures[k];
      for (int t = 0; t + 1 < nt; ++t) s += tbuf[size_t(t) * tex_n + k];
      out.v_textures[k] = s;
    }
  }
  for (int c = 0; c < 3; ++c) {
    S s = S(0);
    for (int t = 0; t < nt; ++t) s += bgbuf[3 * t + c];
    out.v_background[c] = s;
  }
  timer.lap(PROF_BWD_TEX_REDUCE);
}

template void backward<float>(const SceneArgs<float>&, const TileBinsView&, const float*, const int32_t*,
                              const float*, const float*, const float*, const BackwardOut<float>&,
                              unsigned char*, const int32_t*, const float*, float*, float*, const float*);
template void backward<double>(const SceneArgs<double>&, const TileBinsView&, const double*, const int32_t*,
                               const double*, const double*, const double*, const BackwardOut<double>&,
                               unsigned char*, const int32_t*, const double*, double*, double*, const double*);

}  // namespace cpu
}  // namespace ctgs
