// Forward pass of the CPU backend (docs/reference/renderer.md step 8) plus the per-primitive error statistics.
// Per tile, primitives are the outer loop (in blending order) and only the pixels of each one's row
// spans (spans.h) are visited, W at a time (lanes.h, lane_math.h), with the per-pixel blending state in
// small per-tile arrays: the same per-pixel front-to-back result as a pixel-outer loop, but the work
// scales with the area primitives cover, not with (pixels x primitives in the tile).
#include <omp.h>

#include <algorithm>

#include "lane_math.h"
#include "rasterize.h"

namespace ctgs {
namespace cpu {

namespace {

// One tile's blended pairs while it is rasterised: arrays grown W entries ahead, written without a
// per-entry capacity check (each lane writes its slot and the count advances by the lanes that blended).
template <typename S>
struct TilePairs {
  std::vector<int32_t> pix, prim;
  std::vector<S> w;
  size_t n = 0;
  CTGS_INLINE void room(size_t extra) {
    if (n + extra <= pix.size()) return;
    const size_t cap = std::max<size_t>(std::max<size_t>(2 * pix.size(), n + extra), 1024);
    pix.resize(cap);
    prim.resize(cap);
    w.resize(cap);
  }
};

template <typename S>
struct ForwardTileArgs {
  const SceneArgs<S>* a;
  const ForwardOut<S>* out;
  const LanePrim<S>* prims;
  const int32_t* list;
  int ntx;
  int32_t* count;  // this thread's statistics [N] (null without an error image)
  S* contrib;
  S* err;
  struct TilePairs<S>* pairs;  // this tile's blended pairs (null unless recorded)
};

// One tile: list entries [begin, end).
template <typename S>
CTGS_INLINE void forward_tile_impl(const ForwardTileArgs<S>& f, int tile, int64_t begin, int64_t end) {
  using L = Lanes<S>;
  using V = typename L::V;
  using I = typename L::I;
  using Int = typename L::Int;
  constexpr int W = L::W;
  // Rows of RS entries: a lane group starting inside a row may run past its end into the padding.
  constexpr int RS = TILE_W + W;
  constexpr int NP = TILE_H * RS;
  const SceneArgs<S>& a = *f.a;
  const ForwardOut<S>& out = *f.out;
  const int Wimg = a.K.width, Himg = a.K.height;
  const bool stats = out.error_image != nullptr;
  const int x0 = (tile % f.ntx) * TILE_W, y0 = (tile / f.ntx) * TILE_H;
  const int x1 = std::min(x0 + TILE_W, Wimg), y1 = std::min(y0 + TILE_H, Himg);  // exclusive
  alignas(32) S T[NP], C0[NP], C1[NP], C2[NP], D[NP], D2[NP], M[NP], E[NP], dn[NP];
  alignas(32) Int last[NP], done[NP];
  alignas(32) S pxa[RS], dxa[RS], pya[TILE_H], dya[TILE_H];
  for (int k = 0; k < RS; ++k) {
    pxa[k] = S(x0 + k) + S(0.5);
    dxa[k] = (pxa[k] - a.K.cx) / a.K.fx;
  }
  int alive = 0;
  for (int r = 0; r < TILE_H; ++r) {
    pya[r] = S(y0 + r) + S(0.5);
    dya[r] = (pya[r] - a.K.cy) / a.K.fy;
    for (int k = 0; k < RS; ++k) {
      const int p = r * RS + k;
      const bool inside = y0 + r < y1 && x0 + k < x1 && k < TILE_W;
      dn[p] = sqrt(dxa[k] * dxa[k] + dya[r] * dya[r] + S(1) * S(1));
      T[p] = S(1);
      C0[p] = C1[p] = C2[p] = D[p] = D2[p] = M[p] = S(0);
      E[p] = stats && inside ? out.error_image[int64_t(y0 + r) * Wimg + x0 + k] : S(0);
      last[p] = 0;
      done[p] = inside ? 0 : -1;  // padding never blends
      alive += inside;
    }
  }
  I iota;
  for (int k = 0; k < W; ++k) iota[k] = k;
  for (int64_t j = begin; j < end && alive > 0; ++j) {
    const int32_t i = f.list[j];
    const LanePrim<S>& P = f.prims[i];
    // Two entries ahead: the struct; one ahead: its spans and texels (the struct is in cache by now).
    if (j + 2 < end) prefetch_prim(&f.prims[f.list[j + 2]]);
    if (j + 1 < end) {
      const LanePrim<S>& Q = f.prims[f.list[j + 1]];
      prefetch_spans(Q, y0, y1 - 1);
      prefetch_texels(Q, a.textures, static_cast<const S*>(nullptr));
    }
    const PixelRect& r = P.rect;
    const int ry0 = std::max(r.y0, y0), ry1 = std::min(r.y1, y1 - 1);
    if (ry0 > ry1) continue;
    const int32_t* sp = P.spans + 2 * (ry0 - r.y0);
    const Int jpos = Int(j - begin + 1);
    V sum_w{}, sum_ew{};
    I n_blend{};
    for (int y = ry0; y <= ry1; ++y, sp += 2) {
      const int lo = std::max(int(sp[0]), x0), hi = std::min(int(sp[1]), x1 - 1);
      if (lo > hi) continue;
      const int ty = y - y0;
      const LaneRow<S> R = lane_row(P, pya[ty], dya[ty]);
      for (int x = lo; x <= hi; x += W) {
        const int k0 = x - x0, p0 = ty * RS + k0;
        const I in = (iota <= Int(hi - x)) & ~vload<I>(done + p0);
        if (!any(in)) continue;
        LaneHit<S> h;
        lane_alpha(P, R, vload<V>(dxa + k0), vload<V>(pxa + k0), vload<V>(dn + p0), a.K.near_plane, in, h);
        if (!any(h.ok)) continue;
        const V Tv = vload<V>(T + p0);
        const V T_next = Tv * (S(1) - h.alpha);
        const I stop = h.ok & (T_next < S(T_EPS));  // 3DGS rule: stop without blending this one
        const I blend = h.ok & ~stop;
        if (any(stop)) {
          vstore(done + p0, vload<I>(done + p0) | stop);
          alive -= count_lanes(stop);
        }
        if (!any(blend)) continue;
        V c_raw[3], c[3];
        if (P.textured) {
          LaneTex<S> tx;
          lane_texture(P, a.textures, h, blend, tx, false);
          lane_color(P, tx, c_raw, c);
        } else {
          lane_color_plain(P, c_raw, c);
        }
        const V w = h.alpha * Tv;
        vstore(C0 + p0, sel(blend, vload<V>(C0 + p0) + w * c[0], vload<V>(C0 + p0)));
        vstore(C1 + p0, sel(blend, vload<V>(C1 + p0) + w * c[1], vload<V>(C1 + p0)));
        vstore(C2 + p0, sel(blend, vload<V>(C2 + p0) + w * c[2], vload<V>(C2 + p0)));
        vstore(D + p0, sel(blend, vload<V>(D + p0) + w * h.z, vload<V>(D + p0)));
        vstore(D2 + p0, sel(blend, vload<V>(D2 + p0) + w * h.z * h.z, vload<V>(D2 + p0)));
        // the median depth: the hit that takes T from above 0.5 to at most 0.5 (or the last one while it stays above)
        vstore(M + p0, sel(blend & (Tv > S(0.5)), h.z, vload<V>(M + p0)));
        vstore(T + p0, sel(blend, T_next, Tv));
        vstore(last + p0, seli(blend, I{} + jpos, vload<I>(last + p0)));
        if (f.pairs) {
          TilePairs<S>& tp = *f.pairs;
          tp.room(W);
          const int32_t row = int32_t(int64_t(y) * Wimg + x);
          for (int k = 0; k < W; ++k) {  // in lane order, as before: the same list
            tp.pix[tp.n] = row + k;
            tp.prim[tp.n] = i;
            tp.w[tp.n] = w[k];
            tp.n += blend[k] != 0;
          }
        }
        if (stats) {
          n_blend -= blend;
          sum_w += sel(blend, w, splat(S(0)));
          sum_ew += sel(blend, vload<V>(E + p0) * w, splat(S(0)));
        }
      }
    }
    if (stats && any(n_blend)) {
      int n = 0;
      for (int k = 0; k < W; ++k) n += int(n_blend[k]);
      f.count[i] += n;
      f.contrib[i] += hsum<S>(sum_w);
      f.err[i] += hsum<S>(sum_ew);
    }
  }
  const S bg[3] = {a.background[0], a.background[1], a.background[2]};
  for (int y = y0; y < y1; ++y)
    for (int x = x0; x < x1; ++x) {
      const int p = (y - y0) * RS + (x - x0);
      const int64_t pix = int64_t(y) * Wimg + x;
      out.rgb[3 * pix] = C0[p] + T[p] * bg[0];
      out.rgb[3 * pix + 1] = C1[p] + T[p] * bg[1];
      out.rgb[3 * pix + 2] = C2[p] + T[p] * bg[2];
      out.alpha[pix] = S(1) - T[p];
      out.depth[pix] = D[p];
      out.median[pix] = M[p];
      out.depth2[pix] = D2[p];
      out.final_T[pix] = T[p];
      out.n_contrib[pix] = int32_t(last[p]);
    }
}

// Non-template entry points so that each can be multiversioned (lanes.h).
CTGS_LANE_CLONES void forward_tile(const ForwardTileArgs<float>& f, int tile, int64_t begin, int64_t end) {
  forward_tile_impl(f, tile, begin, end);
}
CTGS_LANE_CLONES void forward_tile(const ForwardTileArgs<double>& f, int tile, int64_t begin, int64_t end) {
  forward_tile_impl(f, tile, begin, end);
}

}  // namespace

template <typename S>
void forward(const SceneArgs<S>& a, const ForwardOut<S>& out, TileBins* bins, FrameSetup* keep) {
  ProfTimer timer;
  std::vector<SurfelPrim<S>> prims;
  std::vector<PixelRect> rects;
  PrimSpans spans;
  bin_primitives(a, prims, rects, spans, bins);
  const int N = a.N;
  const int nt = std::max(1, a.num_threads);
  // LanePrim is trivially copyable; held as bytes so that the backward can be handed the same buffer.
  std::vector<unsigned char> lp_bytes(size_t(N) * sizeof(LanePrim<S>));
  LanePrim<S>* lp = reinterpret_cast<LanePrim<S>*>(lp_bytes.data());
#pragma omp parallel for schedule(static) num_threads(nt)
  for (int i = 0; i < N; ++i) {
    const PixelRect& r = rects[i];
    lp[i] = lane_prim(prims[i], r, r.x0 <= r.x1 && r.y0 <= r.y1 ? spans.row(i, r.y0) : nullptr, spans.xs.data());
  }
  timer.lap(PROF_FWD_BIN);
  const int ntx = tiles_x(a.K.width), num_tiles = ntx * tiles_y(a.K.height);
  const bool stats = out.error_image != nullptr;
  // Per-thread statistics, reduced at the end: race-free and deterministic for a fixed thread count.
  std::vector<int32_t> count_buf(stats ? size_t(nt) * N : 0, 0);
  std::vector<S> contrib_buf(stats ? size_t(nt) * N : 0, S(0)), err_buf(stats ? size_t(nt) * N : 0, S(0));
  std::vector<TilePairs<S>> tile_pairs(out.pairs ? num_tiles : 0);

  const std::vector<int> order = tile_order(bins->offsets.data(), num_tiles, nt);
#pragma omp parallel for schedule(dynamic, 1) num_threads(nt)
  for (int k = 0; k < num_tiles; ++k) {
    const int tile = order[k];
    const int tid = omp_get_thread_num();
    ForwardTileArgs<S> f{&a, &out, lp, bins->list.data(), ntx,
                         stats ? count_buf.data() + size_t(tid) * N : nullptr,
                         stats ? contrib_buf.data() + size_t(tid) * N : nullptr,
                         stats ? err_buf.data() + size_t(tid) * N : nullptr,
                         out.pairs ? &tile_pairs[tile] : nullptr};
    forward_tile(f, tile, bins->offsets[tile], bins->offsets[tile + 1]);
  }
  if (out.pairs) {
    size_t total = 0;
    for (const auto& t : tile_pairs) total += t.n;
    out.pairs->pix.reserve(total);
    out.pairs->prim.reserve(total);
    out.pairs->w.reserve(total);
    for (const auto& t : tile_pairs) {
      out.pairs->pix.insert(out.pairs->pix.end(), t.pix.begin(), t.pix.begin() + t.n);
      out.pairs->prim.insert(out.pairs->prim.end(), t.prim.begin(), t.prim.begin() + t.n);
      out.pairs->w.insert(out.pairs->w.end(), t.w.begin(), t.w.begin() + t.n);
    }
  }
  timer.lap(PROF_FWD_RASTER);
  if (stats) {
#pragma omp parallel for schedule(static) num_threads(nt)
    for (int i = 0; i < N; ++i) {
      int32_t c = 0;
      S s = S(0), r = S(0);
      for (int t = 0; t < nt; ++t) {
        c += count_buf[size_t(t) * N + i];
        s += contrib_buf[size_t(t) * N + i];
        r += err_buf[size_t(t) * N + i];
      }
      out.count[i] = c;
      out.contrib[i] = s;
      out.err[i] = r;
    }
  }
  if (keep) {
    keep->prims = std::move(lp_bytes);  // the buffers move, the pointers into them stay valid
    keep->span_xs = std::move(spans.xs);
  }
  timer.lap(PROF_FWD_REDUCE);
}

template void forward<float>(const SceneArgs<float>&, const ForwardOut<float>&, TileBins*, FrameSetup*);
template void forward<double>(const SceneArgs<double>&, const ForwardOut<double>&, TileBins*, FrameSetup*);

}  // namespace cpu
}  // namespace ctgs
