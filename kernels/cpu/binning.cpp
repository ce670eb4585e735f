// Per-primitive preprocessing and per-tile depth-sorted lists for the CPU backend.
#include <algorithm>
#include <cstdint>
#include <cstring>

#include "rasterize.h"
#include "lanes.h"
#include "spans.h"

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


namespace {
// The order of std::sort over (depth, index) pairs, whose depths are finite (culling keeps z >= near):
// float32 keys by an LSD radix sort (three stable 11-bit passes over an order-preserving uint32 form of
// the depth; the input is in index order, so equal depths stay in index order), ~0.1 ms instead of
// ~0.85 ms for 18k primitives; float64 (the test path) by std::sort.
inline uint32_t depth_key(float z) {
  z = z + 0.0f;  // -0 -> +0: equal depths must get equal keys
  uint32_t b;
  std::memcpy(&b, &z, sizeof b);
  return (b & 0x80000000u) ? ~b : (b | 0x80000000u);
}

inline void sort_by_depth(std::vector<std::pair<double, int32_t>>& order) { std::sort(order.begin(), order.end()); }

inline void sort_by_depth(std::vector<std::pair<float, int32_t>>& order) {
  const size_t n = order.size();
  if (n < 64) {
    std::sort(order.begin(), order.end());
    return;
  }
  constexpr int BITS = 11, NB = 1 << BITS, PASSES = 3;
  std::vector<uint32_t> key(n), key2(n);
  std::vector<int32_t> idx(n), idx2(n);
  for (size_t k = 0; k < n; ++k) {
    key[k] = depth_key(order[k].first);
    idx[k] = int32_t(k);
  }
  std::vector<uint32_t> count(size_t(NB) * PASSES, 0);
  for (size_t k = 0; k < n; ++k)
    for (int p = 0; p < PASSES; ++p) ++count[size_t(p) * NB + ((key[k] >> (BITS * p)) & (NB - 1))];
  for (int p = 0; p < PASSES; ++p) {
    uint32_t* c = count.data() + size_t(p) * NB;
    uint32_t sum = 0;
    for (int b = 0; b < NB; ++b) {
      const uint32_t cb = c[b];
      c[b] = sum;
      sum += cb;
    }
    for (size_t k = 0; k < n; ++k) {
      const uint32_t pos = c[(key[k] >> (BITS * p)) & (NB - 1)]++;
      key2[pos] = key[k];
      idx2[pos] = idx[k];
    }
    key.swap(key2);
    idx.swap(idx2);
  }
  std::vector<std::pair<float, int32_t>> sorted(n);
  for (size_t k = 0; k < n; ++k) sorted[k] = order[idx[k]];
  order.swap(sorted);
}

// One primitive's row spans; the rect shrinks to their bounding box. Multiversioned (lanes.h): the AVX2
// clone rounds with roundsd where baseline x86-64 calls ceil() and floor() in the C library.
template <typename S>
CTGS_INLINE PixelRect prim_spans_impl(const SurfelPrim<S>& P, const Intrinsics<S>& K, const PixelRect r,
                                      int32_t* xs) {
  const SpanConic c = span_conic(P);
  PixelRect t = {r.x1 + 1, r.y1 + 1, r.x0 - 1, r.y0 - 1};
  for (int y = r.y0; y <= r.y1; ++y, xs += 2) {
    int lo, hi;
    if (span_of_row(c, K, y, r.x0, r.x1, &lo, &hi)) {
      t = PixelRect{std::min(t.x0, lo), std::min(t.y0, y), std::max(t.x1, hi), std::max(t.y1, y)};
    } else {
      lo = 0;
      hi = -1;
    }
    xs[0] = lo;
    xs[1] = hi;
  }
  return t.x0 <= t.x1 ? t : PixelRect{0, 0, -1, -1};
}
CTGS_LANE_CLONES PixelRect prim_spans(const SurfelPrim<float>& P, const Intrinsics<float>& K, const PixelRect r,
                                      int32_t* xs) {
  return prim_spans_impl(P, K, r, xs);
}
CTGS_LANE_CLONES PixelRect prim_spans(const SurfelPrim<double>& P, const Intrinsics<double>& K, const PixelRect r,
                                      int32_t* xs) {
  return prim_spans_impl(P, K, r, xs);
}
}  // namespace

template <typename S>
void bin_primitives(const SceneArgs<S>& a, std::vector<SurfelPrim<S>>& prims, std::vector<PixelRect>& rects,
                    PrimSpans& spans, TileBins* bins) {
  const int N = a.N;
  const int ntx = tiles_x(a.K.width), nty = tiles_y(a.K.height);
  const int num_tiles = ntx * nty;
  const int nt = std::max(1, a.num_threads);
  prims.resize(N);
  rects.resize(N);
  spans.offset.resize(N);
  spans.row0.resize(N);
#pragma omp parallel for schedule(static) num_threads(nt)
  for (int i = 0; i < N; ++i) {
    prims[i] = load_prim(i, a.mu_c, a.Rc, a.scales, a.opacities, a.colors, a.texel_size, a.tex_res, a.tex_offset,
                         a.K);
    const bool culled = !(prims[i].mu.z >= a.K.near_plane) || prims[i].opacity < S(MIN_ALPHA);
    rects[i] = culled ? PixelRect{0, 0, -1, -1} : surfel_pixel_rect(prims[i], a.K);
  }
  std::vector<PixelRect> bounds;
  if (bins != nullptr) bounds = rects;  // the 3-sigma rects, for the tile lists
  int64_t rows = 0;
  for (int i = 0; i < N; ++i) {
    spans.offset[i] = rows;
    spans.row0[i] = rects[i].y0;
    if (rects[i].x0 <= rects[i].x1 && rects[i].y0 <= rects[i].y1) rows += rects[i].y1 - rects[i].y0 + 1;
  }
  spans.xs.resize(size_t(2 * rows));
  // Spans row by row; the rect shrinks to their bounding box.
#pragma omp parallel for schedule(dynamic, 64) num_threads(nt)
  for (int i = 0; i < N; ++i) {
    if (rects[i].x0 > rects[i].x1 || rects[i].y0 > rects[i].y1) continue;
    rects[i] = prim_spans(prims[i], a.K, rects[i], spans.xs.data() + 2 * spans.offset[i]);
  }
  if (bins == nullptr) return;
  // Tile lists from the 3-sigma rects (not the spans): the same lists as the CUDA backend's
  // (tests/render/test_cuda_backend.py), so n_contrib means the same on both.
  std::vector<int64_t>& off = bins->offsets;
  off.assign(num_tiles + 1, 0);
  for (int i = 0; i < N; ++i) {
    const TileRect r = tiles_of(bounds[i]);
    for (int ty = r.y0; ty < r.y1; ++ty)
      for (int tx = r.x0; tx < r.x1; ++tx) ++off[ty * ntx + tx + 1];
  }
  for (int k = 0; k < num_tiles; ++k) off[k + 1] += off[k];
  // Sorting once globally by (centre depth, index) and then bucketing stably by tile leaves every tile
  // list in blending order without a per-tile sort. The keys are copied out so the sort reads
  // contiguous memory.
  std::vector<std::pair<S, int32_t>> order;
  order.reserve(N);
  for (int i = 0; i < N; ++i)
    if (bounds[i].x0 <= bounds[i].x1 && bounds[i].y0 <= bounds[i].y1) order.emplace_back(prims[i].mu.z, i);
  sort_by_depth(order);
  bins->list.resize(off[num_tiles]);
  std::vector<int64_t> cursor(off.begin(), off.end() - 1);
  for (const auto& zi : order) {
    const TileRect r = tiles_of(bounds[zi.second]);
    for (int ty = r.y0; ty < r.y1; ++ty)
      for (int tx = r.x0; tx < r.x1; ++tx) bins->list[cursor[ty * ntx + tx]++] = zi.second;
  }
}

template void bin_primitives<float>(const SceneArgs<float>&, std::vector<SurfelPrim<float>>&,
                                    std::vector<PixelRect>&, PrimSpans&, TileBins*);
template void bin_primitives<double>(const SceneArgs<double>&, std::vector<SurfelPrim<double>>&,
                                     std::vector<PixelRect>&, PrimSpans&, TileBins*);

}  // namespace cpu
}  // namespace ctgs
