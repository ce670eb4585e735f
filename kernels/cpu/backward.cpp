// Hand-written backward of the CPU backend: back-to-front per pixel over the entries the forward
// processed (3DGS), recovering T by division (alpha <= MAX_ALPHA keeps it safe). Tiles in parallel;
// per-primitive gradients go to per-thread buffers reduced at the end. Texel gradients go to per-thread
// copies of the texel buffer too while those stay small (MAX_PRIVATE_TEXEL_BYTES), else to the output
// with atomics (a float atomic add is a CAS loop: 12 per pair would dominate the backward).
#include <omp.h>

#include <algorithm>
#include <memory>

#include "rasterize.h"

namespace ctgs {
namespace cpu {

namespace {
// Layout of one primitive's gradient row in the per-thread buffers.
enum : int { G_MU = 0, G_RC = 3, G_SCALE = 12, G_OPACITY = 14, G_COLOR = 15, G_TEXEL = 18, G_STRIDE = 20 };
// Above this many bytes of extra per-thread texel-gradient copies, atomics are used instead.
constexpr size_t MAX_PRIVATE_TEXEL_BYTES = size_t(256) << 20;
}  // namespace

template <typename S>
inline void add_grad(SurfelGrad<S>& sum, const SurfelGrad<S>& g) {
  sum.mu += g.mu;
  sum.u += g.u;
  sum.v += g.v;
  sum.n += g.n;
  sum.sx += g.sx;
  sum.sy += g.sy;
  sum.opacity += g.opacity;
  sum.ku += g.ku;
  sum.kv += g.kv;
  for (int c = 0; c < 3; ++c) sum.color[c] += g.color[c];
}

template <typename S>
void backward(const SceneArgs<S>& a, const TileBinsView& bins, const S* final_T, const int32_t* n_contrib,
              const S* v_rgb, const S* v_alpha, const S* v_depth, const BackwardOut<S>& out) {
  ProfTimer timer;
  std::vector<SurfelPrim<S>> prims;
  std::vector<PixelRect> rects;
  PrimSpans spans;
  bin_primitives<S>(a, prims, rects, spans, nullptr);  // camera-space constants only; the lists come from forward
  const int W = a.K.width, H = a.K.height, N = a.N;
  const int ntx = tiles_x(W), num_tiles = ntx * tiles_y(H);
  const int nt = std::max(1, a.num_threads);
  std::vector<S> gbuf(size_t(nt) * N * G_STRIDE, S(0));
  std::vector<S> bgbuf(size_t(nt) * 3, S(0));
  // Thread 0 writes texel gradients straight into the output, threads 1.. into private copies.
  const size_t tex_n = size_t(3) * size_t(a.T);
  const bool private_tex = nt > 1 && tex_n * (nt - 1) * sizeof(S) <= MAX_PRIVATE_TEXEL_BYTES;
  std::unique_ptr<S[]> tbuf(private_tex ? new S[tex_n * (nt - 1)] : nullptr);
  const size_t tex_zero_n = private_tex ? tex_n * nt : tex_n;
  // Zeroed in parallel: for large jagged textures (hundreds of MB) this first touch is a visible cost.
#pragma omp parallel for schedule(static) num_threads(nt)
  for (long long k = 0; k < (long long)tex_zero_n; ++k) {
    if (size_t(k) < tex_n) out.v_textures[k] = S(0);
    else tbuf[k - tex_n] = S(0);
  }
  const bool use_atomics = nt > 1 && !private_tex;
  const S bg[3] = {a.background[0], a.background[1], a.background[2]};
  constexpr int TP = TILE_W * TILE_H;
  timer.lap(PROF_BWD_SETUP);

#pragma omp parallel for schedule(dynamic, 1) num_threads(nt)
  for (int tile = 0; tile < num_tiles; ++tile) {
    const int tid = omp_get_thread_num();
    S* g_thread = gbuf.data() + size_t(tid) * N * G_STRIDE;
    S* v_tex_thread = (tid == 0 || !private_tex) ? out.v_textures : tbuf.get() + size_t(tid - 1) * tex_n;
    const int64_t begin = bins.offsets[tile];
    const int x0 = (tile % ntx) * TILE_W, y0 = (tile / ntx) * TILE_H;
    const int x1 = std::min(x0 + TILE_W, W), y1 = std::min(y0 + TILE_H, H);  // exclusive
    PixelRay<S> rays[TP];
    S T[TP], acc[TP], gC[TP][3], gD[TP];
    int32_t ncon[TP];
    int32_t jmax = 0;
    for (int y = y0; y < y1; ++y)
      for (int x = x0; x < x1; ++x) {
        const int p = (y - y0) * TILE_W + (x - x0);
        const int64_t pix = int64_t(y) * W + x;
        rays[p] = pixel_ray<S>(x, y, a.K);
        for (int c = 0; c < 3; ++c) gC[p][c] = v_rgb[3 * pix + c];
        gD[p] = v_depth[pix];
        T[p] = final_T[pix];
        for (int c = 0; c < 3; ++c) bgbuf[3 * tid + c] += T[p] * gC[p][c];
        // acc = sum_{j>i} w_j f_j + T_final (bg . gC - gA), f_j = c_j . gC + z_j gD: everything behind i
        // that alpha_i attenuates (alpha = 1 - T_final, hence -gA).
        acc[p] = T[p] * (bg[0] * gC[p][0] + bg[1] * gC[p][1] + bg[2] * gC[p][2] - v_alpha[pix]);
        ncon[p] = n_contrib[pix];
        jmax = std::max(jmax, ncon[p]);
      }
    for (int32_t jj = jmax - 1; jj >= 0; --jj) {
      const int32_t i = bins.list[begin + jj];
      const SurfelPrim<S>& P = prims[i];
      const PixelRect& r = rects[i];
      const int ry0 = std::max(r.y0, y0), ry1 = std::min(r.y1, y1 - 1);
      const int32_t* sp = ry0 <= ry1 ? spans.row(i, ry0) : nullptr;
      SurfelGrad<S> sum;
      const Vec3<S> zero = make_vec3(S(0), S(0), S(0));
      sum.mu = sum.u = sum.v = sum.n = zero;
      sum.sx = sum.sy = sum.opacity = sum.ku = sum.kv = S(0);
      sum.color[0] = sum.color[1] = sum.color[2] = S(0);
      bool any = false;
      for (int y = ry0; y <= ry1; ++y, sp += 2) {
        const int rx0 = std::max(int(sp[0]), x0), rx1 = std::min(int(sp[1]), x1 - 1);
        for (int x = rx0; x <= rx1; ++x) {
          const int p = (y - y0) * TILE_W + (x - x0);
          if (jj >= ncon[p]) continue;  // behind where this pixel stopped
          SurfelHit<S> h;
          if (!surfel_alpha(P, rays[p], a.K.near_plane, h)) continue;
          surfel_color(P, a.textures, h);
          const S one_minus = std::max(S(T_RECOVER_EPS), S(1) - h.alpha);
          const S T_i = T[p] / one_minus;
          const S w = h.alpha * T_i;
          const S f = h.c[0] * gC[p][0] + h.c[1] * gC[p][1] + h.c[2] * gC[p][2] + h.z * gD[p];
          const S v_a = T_i * f - acc[p] / one_minus;
          const S v_c[3] = {w * gC[p][0], w * gC[p][1], w * gC[p][2]};
          SurfelGrad<S> g;
          surfel_backward(P, rays[p], a.K, h, a.textures, v_a, v_c, w * gD[p], g);
          add_grad(sum, g);
          any = true;
          if (h.taps.active) {
            for (int k = 0; k < 4; ++k) {
              if (h.taps.row[k] < 0) continue;
              S* dst = v_tex_thread + 3 * h.taps.row[k];
              if (use_atomics) {
                for (int c = 0; c < 3; ++c) {
                  const S val = h.taps.w[k] * g.tex[c];
#pragma omp atomic
                  dst[c] += val;
                }
              } else {
                for (int c = 0; c < 3; ++c) dst[c] += h.taps.w[k] * g.tex[c];
              }
            }
          }
          acc[p] += w * f;
          T[p] = T_i;
        }
      }
      if (!any) continue;
      S* row = g_thread + size_t(i) * G_STRIDE;
      row[G_MU] += sum.mu.x;
      row[G_MU + 1] += sum.mu.y;
      row[G_MU + 2] += sum.mu.z;
      // Rc row-major with columns u, v, n: element (row k, col c) at 3k + c.
      row[G_RC + 0] += sum.u.x;
      row[G_RC + 3] += sum.u.y;
      row[G_RC + 6] += sum.u.z;
      row[G_RC + 1] += sum.v.x;
      row[G_RC + 4] += sum.v.y;
      row[G_RC + 7] += sum.v.z;
      row[G_RC + 2] += sum.n.x;
      row[G_RC + 5] += sum.n.y;
      row[G_RC + 8] += sum.n.z;
      row[G_SCALE] += sum.sx;
      row[G_SCALE + 1] += sum.sy;
      row[G_OPACITY] += sum.opacity;
      row[G_COLOR] += sum.color[0];
      row[G_COLOR + 1] += sum.color[1];
      row[G_COLOR + 2] += sum.color[2];
      row[G_TEXEL] += sum.ku;
      row[G_TEXEL + 1] += sum.kv;
    }
  }
  timer.lap(PROF_BWD_RASTER);

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
  timer.lap(PROF_BWD_REDUCE);
  if (private_tex) {
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
                              const float*, const float*, const float*, const BackwardOut<float>&);
template void backward<double>(const SceneArgs<double>&, const TileBinsView&, const double*, const int32_t*,
                               const double*, const double*, const double*, const BackwardOut<double>&);

}  // namespace cpu
}  // namespace ctgs
