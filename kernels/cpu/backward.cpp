// Hand-written backward of the CPU backend: back-to-front per pixel over the entries the forward
// processed (3DGS), recovering T by division (alpha <= MAX_ALPHA keeps it safe). Tiles in parallel;
// per-primitive gradients go to per-thread buffers reduced at the end, texel gradients use atomics
// (a per-thread copy of the whole texel buffer would not fit for large scenes).
#include <omp.h>

#include <algorithm>

#include "rasterize.h"

namespace ctgs {
namespace cpu {

namespace {
// Layout of one primitive's gradient row in the per-thread buffers.
enum : int { G_MU = 0, G_RC = 3, G_SCALE = 12, G_OPACITY = 14, G_COLOR = 15, G_TEXEL = 18, G_STRIDE = 20 };
}  // namespace

template <typename S>
void backward(const SceneArgs<S>& a, const TileBinsView& bins, const S* final_T, const int32_t* n_contrib,
              const S* v_rgb, const S* v_alpha, const S* v_depth, const BackwardOut<S>& out) {
  std::vector<SurfelPrim<S>> prims;
  bin_primitives<S>(a, prims, nullptr);  // camera-space constants only; the lists come from forward
  const int W = a.K.width, H = a.K.height, N = a.N;
  const int ntx = tiles_x(W), num_tiles = ntx * tiles_y(H);
  const int nt = std::max(1, a.num_threads);
  std::vector<S> gbuf(size_t(nt) * N * G_STRIDE, S(0));
  std::vector<S> bgbuf(size_t(nt) * 3, S(0));
  std::fill(out.v_textures, out.v_textures + 3 * a.T, S(0));
  const S bg[3] = {a.background[0], a.background[1], a.background[2]};

#pragma omp parallel for schedule(dynamic, 1) num_threads(nt)
  for (int tile = 0; tile < num_tiles; ++tile) {
    const int tid = omp_get_thread_num();
    S* g_thread = gbuf.data() + size_t(tid) * N * G_STRIDE;
    const int64_t begin = bins.offsets[tile];
    if (bins.offsets[tile + 1] == begin) continue;
    const int x0 = (tile % ntx) * TILE_W, y0 = (tile / ntx) * TILE_H;
    const int x1 = std::min(x0 + TILE_W, W), y1 = std::min(y0 + TILE_H, H);
    for (int y = y0; y < y1; ++y) {
      for (int x = x0; x < x1; ++x) {
        const PixelRay<S> ray = pixel_ray<S>(x, y, a.K);
        const int64_t pix = int64_t(y) * W + x;
        const S gC[3] = {v_rgb[3 * pix], v_rgb[3 * pix + 1], v_rgb[3 * pix + 2]};
        const S gA = v_alpha[pix], gD = v_depth[pix];
        S T = final_T[pix];
        bgbuf[3 * tid] += T * gC[0];
        bgbuf[3 * tid + 1] += T * gC[1];
        bgbuf[3 * tid + 2] += T * gC[2];
        // acc = sum_{j>i} w_j f_j + T_final (bg . gC - gA), f_j = c_j . gC + z_j gD: everything behind i
        // that alpha_i attenuates (alpha = 1 - T_final, hence -gA).
        S acc = T * (bg[0] * gC[0] + bg[1] * gC[1] + bg[2] * gC[2] - gA);
        for (int64_t j = begin + n_contrib[pix] - 1; j >= begin; --j) {
          const int32_t i = bins.list[j];
          const SurfelPrim<S>& P = prims[i];
          SurfelHit<S> h;
          if (!surfel_alpha(P, ray, a.K.near_plane, h)) continue;
          surfel_color(P, a.textures, h);
          const S one_minus = std::max(S(T_RECOVER_EPS), S(1) - h.alpha);
          const S T_i = T / one_minus;
          const S w = h.alpha * T_i;
          const S f = h.c[0] * gC[0] + h.c[1] * gC[1] + h.c[2] * gC[2] + h.z * gD;
          const S v_a = T_i * f - acc / one_minus;
          const S v_c[3] = {w * gC[0], w * gC[1], w * gC[2]};
          SurfelGrad<S> g;
          surfel_backward(P, ray, a.K, h, a.textures, v_a, v_c, w * gD, g);
          S* r = g_thread + size_t(i) * G_STRIDE;
          r[G_MU] += g.mu.x;
          r[G_MU + 1] += g.mu.y;
          r[G_MU + 2] += g.mu.z;
          // Rc row-major with columns u, v, n: element (row k, col c) at 3k + c.
          r[G_RC + 0] += g.u.x;
          r[G_RC + 3] += g.u.y;
          r[G_RC + 6] += g.u.z;
          r[G_RC + 1] += g.v.x;
          r[G_RC + 4] += g.v.y;
          r[G_RC + 7] += g.v.z;
          r[G_RC + 2] += g.n.x;
          r[G_RC + 5] += g.n.y;
          r[G_RC + 8] += g.n.z;
          r[G_SCALE] += g.sx;
          r[G_SCALE + 1] += g.sy;
          r[G_OPACITY] += g.opacity;
          r[G_COLOR] += g.color[0];
          r[G_COLOR + 1] += g.color[1];
          r[G_COLOR + 2] += g.color[2];
          r[G_TEXEL] += g.ku;
          r[G_TEXEL + 1] += g.kv;
          if (h.taps.active) {
            for (int k = 0; k < 4; ++k) {
              if (h.taps.row[k] < 0) continue;
              S* dst = out.v_textures + 3 * h.taps.row[k];
              for (int c = 0; c < 3; ++c) {
                const S val = h.taps.w[k] * g.tex[c];
#pragma omp atomic
                dst[c] += val;
              }
            }
          }
          acc += w * f;
          T = T_i;
        }
      }
    }
  }

#pragma omp parallel for schedule(static) num_threads(nt)
  for (int i = 0; i < N; ++i) {
    S row[G_STRIDE] = {};
    for (int t = 0; t < nt; ++t) {
      const S* src = gbuf.data() + (size_t(t) * N + i) * G_STRIDE;
      for (int k = 0; k < G_STRIDE; ++k) row[k] += src[k];
    }
    for (int k = 0; k < 3; ++k) out.v_mu_c[3 * i + k] = row[G_MU + k];
    for (int k = 0; k < 9; ++k) out.v_Rc[9 * i + k] = row[G_RC + k];
    for (int k = 0; k < 2; ++k) out.v_scales[2 * i + k] = row[G_SCALE + k];
    out.v_opacities[i] = row[G_OPACITY];
    for (int k = 0; k < 3; ++k) out.v_colors[3 * i + k] = row[G_COLOR + k];
    for (int k = 0; k < 2; ++k) out.v_texel_size[2 * i + k] = row[G_TEXEL + k];
  }
  for (int c = 0; c < 3; ++c) {
    S s = S(0);
    for (int t = 0; t < nt; ++t) s += bgbuf[3 * t + c];
    out.v_background[c] = s;
  }
}

template void backward<float>(const SceneArgs<float>&, const TileBinsView&, const float*, const int32_t*,
                              const float*, const float*, const float*, const BackwardOut<float>&);
template void backward<double>(const SceneArgs<double>&, const TileBinsView&, const double*, const int32_t*,
                               const double*, const double*, const double*, const BackwardOut<double>&);

}  // namespace cpu
}  // namespace ctgs
