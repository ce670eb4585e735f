// Hand-written backward of the CUDA backend: one 16x16 block per tile, one thread per pixel, back to front
// over the entries its forward processed (3DGS), recovering T by division (alpha <= MAX_ALPHA keeps it
// safe; T_RECOVER_EPS guards it anyway). The per-pair gradients are ctgs::surfel_backward (shared with the
// CPU backend); the blending backward mirrors kernels/cpu/backward.cpp line for line. Per-primitive
// gradients are summed over each warp (all lanes walk the same batch entry in lockstep) before one set of
// atomics per warp; texel gradients are scattered per tap with atomics.
#include <cstdlib>

#include "common.cuh"

namespace ctgs {
namespace gpu {

namespace {

// Sum one pair's gradient over the warp; lanes whose pair did not contribute pass zeros.
template <typename S>
__device__ inline void warp_sum_grad(SurfelGrad<S>& g) {
  g.mu.x = warp_sum(g.mu.x);
  g.mu.y = warp_sum(g.mu.y);
  g.mu.z = warp_sum(g.mu.z);
  g.u.x = warp_sum(g.u.x);
  g.u.y = warp_sum(g.u.y);
  g.u.z = warp_sum(g.u.z);
  g.v.x = warp_sum(g.v.x);
  g.v.y = warp_sum(g.v.y);
  g.v.z = warp_sum(g.v.z);
  g.n.x = warp_sum(g.n.x);
  g.n.y = warp_sum(g.n.y);
  g.n.z = warp_sum(g.n.z);
  g.sx = warp_sum(g.sx);
  g.sy = warp_sum(g.sy);
  g.opacity = warp_sum(g.opacity);
  g.color[0] = warp_sum(g.color[0]);
  g.color[1] = warp_sum(g.color[1]);
  g.color[2] = warp_sum(g.color[2]);
  g.ku = warp_sum(g.ku);
  g.kv = warp_sum(g.kv);
}

template <typename S>
__device__ inline void zero_grad(SurfelGrad<S>& g) {
  const Vec3<S> z = make_vec3(S(0), S(0), S(0));
  g.mu = g.u = g.v = g.n = z;
  g.sx = g.sy = g.opacity = g.ku = g.kv = S(0);
  g.color[0] = g.color[1] = g.color[2] = S(0);
  g.tex[0] = g.tex[1] = g.tex[2] = S(0);
}

// Adds one primitive's (warp-summed) gradient to the outputs. Rc is row-major with columns u, v, n:
// element (row k, column c) at 3k + c.
template <typename S>
__device__ inline void atomic_add_grad(const BackwardOut<S>& out, int i, const SurfelGrad<S>& g) {
  S* mu = out.v_mu_c + 3 * i;
  atomicAdd(mu, g.mu.x);
  atomicAdd(mu + 1, g.mu.y);
  atomicAdd(mu + 2, g.mu.z);
  S* R = out.v_Rc + 9 * i;
  atomicAdd(R + 0, g.u.x);
  atomicAdd(R + 3, g.u.y);
  atomicAdd(R + 6, g.u.z);
  atomicAdd(R + 1, g.v.x);
  atomicAdd(R + 4, g.v.y);
  atomicAdd(R + 7, g.v.z);
  atomicAdd(R + 2, g.n.x);
  atomicAdd(R + 5, g.n.y);
  atomicAdd(R + 8, g.n.z);
  atomicAdd(out.v_scales + 2 * i, g.sx);
  atomicAdd(out.v_scales + 2 * i + 1, g.sy);
  atomicAdd(out.v_opacities + i, g.opacity);
  atomicAdd(out.v_colors + 3 * i, g.color[0]);
  atomicAdd(out.v_colors + 3 * i + 1, g.color[1]);
  atomicAdd(out.v_colors + 3 * i + 2, g.color[2]);
  atomicAdd(out.v_texel_size + 2 * i, g.ku);
  atomicAdd(out.v_texel_size + 2 * i + 1, g.kv);
}

// Adds val[0..2] to the texel row `row` (-1: nothing) of every lane, with one atomic per run of consecutive
// lanes that share a row instead of one per lane. A warp is 2 rows of 16 pixels; where texels span several
// pixels, neighbouring lanes read the same taps and their atomics on one address serialise: with one atomic per
// lane and tap the backward kernel was several times slower on textured scenes (docs/guide/gpu.md). Segmented
// suffix sum over each run (Hillis-Steele with shuffles, bounded by the run's last lane from a ballot); the run's
// first lane adds the run's total. Lanes equal but not adjacent form separate runs: more atomics, never a wrong
// sum. All 32 lanes must call it (warp-uniform control flow).
template <typename S>
__device__ inline void scatter_texel_grad(S* v_textures, long long row, const S val[3], int lane) {
  const long long next = __shfl_down_sync(FULL_MASK, row, 1);
  const long long prev = __shfl_up_sync(FULL_MASK, row, 1);
  const bool last = lane == 31 || next != row;
  const unsigned ends = __ballot_sync(FULL_MASK, last);
  const int end = __ffs(ends & (~0u << lane)) - 1;  // the last lane of this lane's run
  S sum[3] = {val[0], val[1], val[2]};
  for (int sft = 1; sft < 32; sft <<= 1) {
    for (int c = 0; c < 3; ++c) {
      const S o = __shfl_down_sync(FULL_MASK, sum[c], sft);
      if (lane + sft <= end) sum[c] += o;
    }
  }
  if (row >= 0 && (lane == 0 || prev != row)) {
    S* dst = v_textures + 3 * row;
    atomicAdd(dst, sum[0]);
    atomicAdd(dst + 1, sum[1]);
    atomicAdd(dst + 2, sum[2]);
  }
}

// Whether the texel gradients go through scatter_texel_grad (default) or one atomic per lane and tap as before
// (CTGS_CUDA_TEX_AGG=0, to compare; read at every launch).
inline bool texel_aggregation() {
  const char* v = std::getenv("CTGS_CUDA_TEX_AGG");
  return !(v && v[0] == '0');
}

// MIN_BLOCKS > 1 caps the registers so that that many blocks fit an SM (see backward_min_blocks).
template <typename S, int MIN_BLOCKS>
__global__ void __launch_bounds__(BLOCK_SIZE, MIN_BLOCKS)
    backward_kernel(SceneArgs<S> a, const SurfelPrim<S>* prims, const PixelRect* rects, TileBinsView bins,
                    const S* final_T, const int32_t* n_contrib, const S* v_rgb, const S* v_alpha,
                    const S* v_depth, const S* v_depth2, BackwardOut<S> out, bool aggregate_texels) {
  constexpr int B = Batch<S>::SIZE;
  __shared__ SurfelPrim<S> s_prim[B];
  __shared__ PixelRect s_rect[B];
  __shared__ int32_t s_id[B];
  __shared__ int32_t s_max_contrib;

  const int W = a.K.width, H = a.K.height;
  const int tile = blockIdx.y * gridDim.x + blockIdx.x;
  const int tid = threadIdx.y * BLOCK_X + threadIdx.x;
  const int lane = tid & 31;
  const int x = blockIdx.x * BLOCK_X + threadIdx.x, y = blockIdx.y * BLOCK_Y + threadIdx.y;
  const bool inside = x < W && y < H;
  const int64_t pix = int64_t(y) * W + x;
  const PixelRay<S> ray = pixel_ray<S>(x, y, a.K);
  const int64_t begin = bins.offsets[tile];
  const S bg[3] = {a.background[0], a.background[1], a.background[2]};

  S gC[3] = {S(0), S(0), S(0)}, gD = S(0), gD2 = S(0), gA = S(0), T = S(0);
  int32_t ncon = 0;  // pixels past the image edge contribute nothing
  if (inside) {
    for (int c = 0; c < 3; ++c) gC[c] = v_rgb[3 * pix + c];
    gD = v_depth[pix];
    gD2 = v_depth2 != nullptr ? v_depth2[pix] : S(0);
    gA = v_alpha[pix];
    T = final_T[pix];
    ncon = n_contrib[pix];
  }
  // rgb = C + T_final bg.
  for (int c = 0; c < 3; ++c) {
    const S s = warp_sum<S>(T * gC[c]);
    if (lane == 0 && s != S(0)) atomicAdd(out.v_background + c, s);
  }
  // acc = sum_{j>i} w_j f_j + T_final (bg . gC - gA), f_j = c_j . gC + z_j gD + z_j^2 gD2: everything behind i that
  // alpha_i attenuates (alpha = 1 - T_final, hence -gA).
  S acc = T * (bg[0] * gC[0] + bg[1] * gC[1] + bg[2] * gC[2] - gA);

  if (tid == 0) s_max_contrib = 0;
  __syncthreads();
  if (ncon > 0) atomicMax(&s_max_contrib, ncon);
  __syncthreads();
  const int32_t jmax = s_max_contrib;

  for (int32_t hi = jmax; hi > 0; hi -= B) {
    const int32_t n = hi < B ? hi : B;
    __syncthreads();  // the previous batch is consumed before it is overwritten
    if (tid < n) {
      const int32_t i = bins.list[begin + (hi - 1 - tid)];
      s_id[tid] = i;
      s_prim[tid] = prims[i];
      s_rect[tid] = rects[i];
    }
    __syncthreads();
    for (int k = 0; k < n; ++k) {
      const int32_t jj = hi - 1 - k;  // position in the tile list
      SurfelGrad<S> g;
      bool contributes = false;
      bool textured = false;  // this lane's pair reads texels (aggregated scatter below)
      TexTaps<S> taps{};
      const PixelRect& r = s_rect[k];
      // jj >= ncon: behind where this pixel stopped. Same pairs as the forward (same rect test, same math).
      if (jj < ncon && x >= r.x0 && x <= r.x1 && y >= r.y0 && y <= r.y1) {
        const SurfelPrim<S>& P = s_prim[k];
        SurfelHit<S> h;
        if (surfel_alpha(P, ray, a.K.near_plane, h)) {
          contributes = true;
          surfel_color(P, a.textures, h);
          const S one_minus = fmax(S(T_RECOVER_EPS), S(1) - h.alpha);
          const S T_i = T / one_minus;
          const S w = h.alpha * T_i;
          const S f = h.c[0] * gC[0] + h.c[1] * gC[1] + h.c[2] * gC[2] + h.z * (gD + h.z * gD2);
          const S v_a = T_i * f - acc / one_minus;
          const S v_c[3] = {w * gC[0], w * gC[1], w * gC[2]};
          surfel_backward(P, ray, a.K, h, a.textures, v_a, v_c, w * (gD + S(2) * h.z * gD2), g);
          if (h.taps.active && aggregate_texels) {
            textured = true;
            taps = h.taps;
          } else if (h.taps.active) {
            for (int t = 0; t < 4; ++t) {
              const long long r = h.taps.row(t);
              if (r < 0) continue;
              S* dst = out.v_textures + 3 * r;
              const S wt = h.taps.w(t);
              atomicAdd(dst, wt * g.tex[0]);
              atomicAdd(dst + 1, wt * g.tex[1]);
              atomicAdd(dst + 2, wt * g.tex[2]);
            }
          }
          acc += w * f;
          T = T_i;
        }
      }
      if (aggregate_texels && __any_sync(FULL_MASK, textured)) {
        for (int t = 0; t < 4; ++t) {
          const long long row = textured ? taps.row(t) : -1;
          const S wt = textured ? taps.w(t) : S(0);
          const S val[3] = {textured ? wt * g.tex[0] : S(0), textured ? wt * g.tex[1] : S(0),
                            textured ? wt * g.tex[2] : S(0)};
          scatter_texel_grad(out.v_textures, row, val, lane);
        }
      }
      if (__any_sync(FULL_MASK, contributes)) {
        if (!contributes) zero_grad(g);
        warp_sum_grad(g);
        if (lane == 0) atomic_add_grad(out, s_id[k], g);
      }
    }
  }
}

// Blocks per SM the float kernel is compiled for: 3 by default (at most 80 registers: more warps to hide the
// latency of its loads and atomics; uncapped, its registers and shared memory left room for 2 blocks per SM), or
// from CTGS_CUDA_BWD_MIN_BLOCKS: 1 (no register cap), 3, or 4 (at most 64 registers). Read at every launch so
// that one process can compare them (benchmarks/bench_cuda.py --bwd-min-blocks).
inline int backward_min_blocks() {
  const char* v = std::getenv("CTGS_CUDA_BWD_MIN_BLOCKS");
  const int b = v ? std::atoi(v) : 3;
  return b == 1 || b == 4 ? b : 3;
}

}  // namespace

template <typename S>
void backward(const SceneArgs<S>& a, const TileBinsView& bins, const S* final_T, const int32_t* n_contrib,
              const S* v_rgb, const S* v_alpha, const S* v_depth, const S* v_depth2, const BackwardOut<S>& out,
              const Allocators& alloc, cudaStream_t stream) {
  const int N = a.N;
  // Camera-space constants only: the lists come from forward.
  SurfelPrim<S>* prims = scratch<SurfelPrim<S>>(alloc, N);
  PixelRect* rects = scratch<PixelRect>(alloc, N);
  preprocess(a, prims, rects, nullptr, stream);
  if (N > 0) {
    CTGS_CUDA_CHECK(cudaMemsetAsync(out.v_mu_c, 0, sizeof(S) * 3 * N, stream));
    CTGS_CUDA_CHECK(cudaMemsetAsync(out.v_Rc, 0, sizeof(S) * 9 * N, stream));
    CTGS_CUDA_CHECK(cudaMemsetAsync(out.v_scales, 0, sizeof(S) * 2 * N, stream));
    CTGS_CUDA_CHECK(cudaMemsetAsync(out.v_opacities, 0, sizeof(S) * N, stream));
    CTGS_CUDA_CHECK(cudaMemsetAsync(out.v_colors, 0, sizeof(S) * 3 * N, stream));
    CTGS_CUDA_CHECK(cudaMemsetAsync(out.v_texel_size, 0, sizeof(S) * 2 * N, stream));
  }
  if (a.T > 0) CTGS_CUDA_CHECK(cudaMemsetAsync(out.v_textures, 0, sizeof(S) * 3 * size_t(a.T), stream));
  CTGS_CUDA_CHECK(cudaMemsetAsync(out.v_background, 0, sizeof(S) * 3, stream));
  const dim3 grid(tiles_x(a.K.width), tiles_y(a.K.height)), block(BLOCK_X, BLOCK_Y);
  const int min_blocks = sizeof(S) == 4 ? backward_min_blocks() : 1;  // (double: never capped)
  const bool aggregate = texel_aggregation();
  if constexpr (sizeof(S) == 4) {
    if (min_blocks == 3) {
      backward_kernel<S, 3><<<grid, block, 0, stream>>>(a, prims, rects, bins, final_T, n_contrib, v_rgb, v_alpha,
                                                        v_depth, v_depth2, out, aggregate);
    } else if (min_blocks == 4) {
      backward_kernel<S, 4><<<grid, block, 0, stream>>>(a, prims, rects, bins, final_T, n_contrib, v_rgb, v_alpha,
                                                        v_depth, v_depth2, out, aggregate);
    }
  }
  if (min_blocks == 1)
    backward_kernel<S, 1><<<grid, block, 0, stream>>>(a, prims, rects, bins, final_T, n_contrib, v_rgb, v_alpha,
                                                      v_depth, v_depth2, out, aggregate);
  CTGS_CUDA_LAUNCH_CHECK("backward_kernel");
}

template void backward<float>(const SceneArgs<float>&, const TileBinsView&, const float*, const int32_t*,
                              const float*, const float*, const float*, const float*, const BackwardOut<float>&,
                              const Allocators&, cudaStream_t);
template void backward<double>(const SceneArgs<double>&, const TileBinsView&, const double*, const int32_t*,
                               const double*, const double*, const double*, const double*, const BackwardOut<double>&,
                               const Allocators&, cudaStream_t);

}  // namespace gpu
}  // namespace ctgs
