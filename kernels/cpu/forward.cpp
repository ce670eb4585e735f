// Forward pass of the CPU backend (docs/renderer.md step 8) plus the per-primitive error statistics.
// Per tile, primitives are the outer loop (in blending order) and only the pixels inside each one's
// pixel bounds are visited, with per-pixel blending state kept in small arrays: the same per-pixel
// front-to-back result as a pixel-outer loop, but the work scales with the area primitives cover, not
// with (pixels x primitives in the tile).
#include <omp.h>

#include <algorithm>

#include "rasterize.h"

namespace ctgs {
namespace cpu {

template <typename S>
void forward(const SceneArgs<S>& a, const ForwardOut<S>& out, TileBins* bins) {
  ProfTimer timer;
  std::vector<SurfelPrim<S>> prims;
  std::vector<PixelRect> rects;
  PrimSpans spans;
  bin_primitives(a, prims, rects, spans, bins);
  timer.lap(PROF_FWD_BIN);
  const int W = a.K.width, H = a.K.height, N = a.N;
  const int ntx = tiles_x(W), num_tiles = ntx * tiles_y(H);
  const bool stats = out.error_image != nullptr;
  const int nt = std::max(1, a.num_threads);
  // Per-thread statistics, reduced at the end: race-free and deterministic for a fixed thread count.
  std::vector<int32_t> count_buf(stats ? size_t(nt) * N : 0, 0);
  std::vector<S> contrib_buf(stats ? size_t(nt) * N : 0, S(0)), err_buf(stats ? size_t(nt) * N : 0, S(0));
  const S bg[3] = {a.background[0], a.background[1], a.background[2]};
  constexpr int TP = TILE_W * TILE_H;

#pragma omp parallel for schedule(dynamic, 1) num_threads(nt)
  for (int tile = 0; tile < num_tiles; ++tile) {
    const int tid = omp_get_thread_num();
    const int64_t begin = bins->offsets[tile], end = bins->offsets[tile + 1];
    const int32_t* list = bins->list.data();
    const int x0 = (tile % ntx) * TILE_W, y0 = (tile / ntx) * TILE_H;
    const int x1 = std::min(x0 + TILE_W, W), y1 = std::min(y0 + TILE_H, H);  // exclusive
    PixelRay<S> rays[TP];
    S T[TP], D[TP], C[TP][3], E[TP];
    int32_t last[TP];
    bool done[TP];
    int alive = 0;
    for (int y = y0; y < y1; ++y)
      for (int x = x0; x < x1; ++x) {
        const int p = (y - y0) * TILE_W + (x - x0);
        rays[p] = pixel_ray<S>(x, y, a.K);
        T[p] = S(1);
        D[p] = C[p][0] = C[p][1] = C[p][2] = S(0);
        E[p] = stats ? out.error_image[int64_t(y) * W + x] : S(0);
        last[p] = 0;
        done[p] = false;
        ++alive;
      }
    for (int64_t j = begin; j < end && alive > 0; ++j) {
      const int32_t i = list[j];
      const SurfelPrim<S>& P = prims[i];
      const PixelRect& r = rects[i];
      const int ry0 = std::max(r.y0, y0), ry1 = std::min(r.y1, y1 - 1);
      const int32_t* sp = ry0 <= ry1 ? spans.row(i, ry0) : nullptr;
      int32_t n_blend = 0;
      S sum_w = S(0), sum_ew = S(0);
      for (int y = ry0; y <= ry1; ++y, sp += 2) {
        const int rx0 = std::max(int(sp[0]), x0), rx1 = std::min(int(sp[1]), x1 - 1);
        for (int x = rx0; x <= rx1; ++x) {
          const int p = (y - y0) * TILE_W + (x - x0);
          if (done[p]) continue;
          SurfelHit<S> h;
          if (!surfel_alpha(P, rays[p], a.K.near_plane, h)) continue;
          const S T_next = T[p] * (S(1) - h.alpha);
          if (T_next < S(T_EPS)) {  // 3DGS rule: stop without blending this one
            done[p] = true;
            --alive;
            continue;
          }
          surfel_color(P, a.textures, h);
          const S w = h.alpha * T[p];
          C[p][0] += w * h.c[0];
          C[p][1] += w * h.c[1];
          C[p][2] += w * h.c[2];
          D[p] += w * h.z;
          T[p] = T_next;
          last[p] = int32_t(j - begin + 1);
          ++n_blend;
          sum_w += w;
          sum_ew += E[p] * w;
        }
      }
      if (stats && n_blend > 0) {
        const size_t k = size_t(tid) * N + i;
        count_buf[k] += n_blend;
        contrib_buf[k] += sum_w;
        err_buf[k] += sum_ew;
      }
    }
    for (int y = y0; y < y1; ++y)
      for (int x = x0; x < x1; ++x) {
        const int p = (y - y0) * TILE_W + (x - x0);
        const int64_t pix = int64_t(y) * W + x;
        out.rgb[3 * pix] = C[p][0] + T[p] * bg[0];
        out.rgb[3 * pix + 1] = C[p][1] + T[p] * bg[1];
        out.rgb[3 * pix + 2] = C[p][2] + T[p] * bg[2];
        out.alpha[pix] = S(1) - T[p];
        out.depth[pix] = D[p];
        out.final_T[pix] = T[p];
        out.n_contrib[pix] = last[p];
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
  timer.lap(PROF_FWD_REDUCE);
}

template void forward<float>(const SceneArgs<float>&, const ForwardOut<float>&, TileBins*);
template void forward<double>(const SceneArgs<double>&, const ForwardOut<double>&, TileBins*);

}  // namespace cpu
}  // namespace ctgs
