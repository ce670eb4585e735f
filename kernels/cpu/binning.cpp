// Per-primitive preprocessing and per-tile depth-sorted lists for the CPU backend.
#include <algorithm>

#include "rasterize.h"

namespace ctgs {
namespace cpu {

const char* const PROF_NAMES[PROF_COUNT] = {"fwd_bin", "fwd_raster", "fwd_reduce", "bwd_setup",
                                            "bwd_raster", "bwd_reduce", "bwd_tex_reduce"};
namespace {
double prof_seconds[PROF_COUNT] = {};
}  // namespace

void prof_add(int phase, double seconds) { prof_seconds[phase] += seconds; }

std::vector<double> prof_read(bool reset) {
  std::vector<double> out(prof_seconds, prof_seconds + PROF_COUNT);
  if (reset)
    for (double& v : prof_seconds) v = 0.0;
  return out;
}

template <typename S>
void bin_primitives(const SceneArgs<S>& a, std::vector<SurfelPrim<S>>& prims, std::vector<PixelRect>& rects,
                    TileBins* bins) {
  const int N = a.N;
  const int ntx = tiles_x(a.K.width), nty = tiles_y(a.K.height);
  const int num_tiles = ntx * nty;
  prims.resize(N);
  rects.resize(N);
#pragma omp parallel for schedule(static) num_threads(a.num_threads)
  for (int i = 0; i < N; ++i) {
    prims[i] = load_prim(i, a.mu_c, a.Rc, a.scales, a.opacities, a.colors, a.texel_size, a.tex_res, a.tex_offset,
                         a.K);
    const bool culled = !(prims[i].mu.z >= a.K.near_plane) || prims[i].opacity < S(MIN_ALPHA);
    rects[i] = culled ? PixelRect{0, 0, -1, -1} : surfel_pixel_rect(prims[i], a.K);
  }
  if (bins == nullptr) return;
  // Sorting once globally by (centre depth, index) and then bucketing stably by tile leaves every tile
  // list in blending order without a per-tile sort.
  std::vector<int32_t> order;
  order.reserve(N);
  for (int i = 0; i < N; ++i)
    if (rects[i].x0 <= rects[i].x1 && rects[i].y0 <= rects[i].y1) order.push_back(i);
  std::sort(order.begin(), order.end(), [&](int32_t p, int32_t q) {
    const S zp = prims[p].mu.z, zq = prims[q].mu.z;
    return zp < zq || (zp == zq && p < q);
  });
  std::vector<int64_t>& off = bins->offsets;
  off.assign(num_tiles + 1, 0);
  for (int32_t i : order) {
    const TileRect r = tiles_of(rects[i]);
    for (int ty = r.y0; ty < r.y1; ++ty)
      for (int tx = r.x0; tx < r.x1; ++tx) ++off[ty * ntx + tx + 1];
  }
  for (int k = 0; k < num_tiles; ++k) off[k + 1] += off[k];
  bins->list.resize(off[num_tiles]);
  std::vector<int64_t> cursor(off.begin(), off.end() - 1);
  for (int32_t i : order) {
    const TileRect r = tiles_of(rects[i]);
    for (int ty = r.y0; ty < r.y1; ++ty)
      for (int tx = r.x0; tx < r.x1; ++tx) bins->list[cursor[ty * ntx + tx]++] = i;
  }
}

template void bin_primitives<float>(const SceneArgs<float>&, std::vector<SurfelPrim<float>>&,
                                    std::vector<PixelRect>&, TileBins*);
template void bin_primitives<double>(const SceneArgs<double>&, std::vector<SurfelPrim<double>>&,
                                     std::vector<PixelRect>&, TileBins*);

}  // namespace cpu
}  // namespace ctgs
