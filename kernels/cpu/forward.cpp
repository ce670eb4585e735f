// Forward pass of the CPU backend: front-to-back blending per pixel over its tile's depth-sorted list,
// tiles in parallel (docs/renderer.md step 8), plus the per-primitive error statistics.
#include <omp.h>

#include <algorithm>

#include "rasterize.h"

namespace ctgs {
namespace cpu {

template <typename S>
void forward(const SceneArgs<S>& a, const ForwardOut<S>& out, TileBins* bins) {
  std::vector<SurfelPrim<S>> prims;
  bin_primitives(a, prims, bins);
  const int W = a.K.width, H = a.K.height, N = a.N;
  const int ntx = tiles_x(W), num_tiles = ntx * tiles_y(H);
  const bool stats = out.error_image != nullptr;
  const int nt = std::max(1, a.num_threads);
  // Per-thread statistics, reduced at the end: race-free and deterministic for a fixed thread count.
  std::vector<int32_t> count_buf(stats ? size_t(nt) * N : 0, 0);
  std::vector<S> contrib_buf(stats ? size_t(nt) * N : 0, S(0)), err_buf(stats ? size_t(nt) * N : 0, S(0));
  const S bg[3] = {a.background[0], a.background[1], a.background[2]};

#pragma omp parallel for schedule(dynamic, 1) num_threads(nt)
  for (int tile = 0; tile < num_tiles; ++tile) {
    const int tid = omp_get_thread_num();
    const int64_t begin = bins->offsets[tile], end = bins->offsets[tile + 1];
    const int32_t* list = bins->list.data();
    const int x0 = (tile % ntx) * TILE_W, y0 = (tile / ntx) * TILE_H;
    const int x1 = std::min(x0 + TILE_W, W), y1 = std::min(y0 + TILE_H, H);
    for (int y = y0; y < y1; ++y) {
      for (int x = x0; x < x1; ++x) {
        const PixelRay<S> ray = pixel_ray<S>(x, y, a.K);
        const int64_t pix = int64_t(y) * W + x;
        const S e = stats ? out.error_image[pix] : S(0);
        S T = S(1), D = S(0), C[3] = {S(0), S(0), S(0)};
        int32_t last = 0;
        for (int64_t j = begin; j < end; ++j) {
          const int32_t i = list[j];
          const SurfelPrim<S>& P = prims[i];
          SurfelHit<S> h;
          if (!surfel_alpha(P, ray, a.K.near_plane, h)) continue;
          const S T_next = T * (S(1) - h.alpha);
          if (T_next < S(T_EPS)) break;  // 3DGS rule: stop without blending this one
          surfel_color(P, a.textures, h);
          const S w = h.alpha * T;
          C[0] += w * h.c[0];
          C[1] += w * h.c[1];
          C[2] += w * h.c[2];
          D += w * h.z;
          T = T_next;
          last = int32_t(j - begin + 1);
          if (stats) {
            const size_t k = size_t(tid) * N + i;
            count_buf[k] += 1;
            contrib_buf[k] += w;
            err_buf[k] += e * w;
          }
        }
        out.rgb[3 * pix] = C[0] + T * bg[0];
        out.rgb[3 * pix + 1] = C[1] + T * bg[1];
        out.rgb[3 * pix + 2] = C[2] + T * bg[2];
        out.alpha[pix] = S(1) - T;
        out.depth[pix] = D;
        out.final_T[pix] = T;
        out.n_contrib[pix] = last;
      }
    }
  }
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
}

template void forward<float>(const SceneArgs<float>&, const ForwardOut<float>&, TileBins*);
template void forward<double>(const SceneArgs<double>&, const ForwardOut<double>&, TileBins*);

}  // namespace cpu
}  // namespace ctgs
