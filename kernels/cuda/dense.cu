// Per-primitive preprocessing of the CUDA backend, one thread per primitive: world -> camera space and the
// view-dependent SH colour, forward and backward (the math: kernels/include/ctgs/preprocess.h, shared with
// the CPU backend's kernels/cpu/camera.cpp and sh.cpp). In PyTorch these were ~150 small kernels per
// training step, whose launches took most of a large forward+backward (benchmarks/bench_cuda.py measures it).
#include <cstdlib>

#include "common.cuh"
#include "ctgs/exact.h"
#include "ctgs/preprocess.h"

namespace ctgs {
namespace gpu {

namespace {

template <typename S>
__global__ void __launch_bounds__(LINEAR_BLOCK)
    camera_space_kernel(const S* means, const S* quats, const S* view, int64_t n, S* mu_c, S* Rc) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n) return;
  S r[9], t[3];
  pre::view_rt(view, r, t);
  pre::camera_space(r, t, means + 3 * i, quats + 4 * i, mu_c + 3 * i, Rc + 9 * i);
}

template <typename S>
__global__ void __launch_bounds__(LINEAR_BLOCK)
    camera_space_backward_kernel(const S* quats, const S* view, int64_t n, const S* grad_mu_c, const S* grad_Rc,
                                 S* grad_means, S* grad_quats) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n) return;
  S r[9], t[3];
  pre::view_rt(view, r, t);
  pre::camera_space_backward(r, quats + 4 * i, grad_mu_c + 3 * i, grad_Rc + 9 * i, grad_means + 3 * i,
                             grad_quats + 4 * i);
}

template <typename S>
__global__ void __launch_bounds__(LINEAR_BLOCK)
    sh_color_kernel(const S* means, const S* center, const S* sh, int64_t n, int K, int deg, S* colors) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n) return;
  pre::sh_color(means + 3 * i, center, sh + i * K * 3, deg, colors + 3 * i);
}

template <typename S>
__global__ void __launch_bounds__(LINEAR_BLOCK)
    sh_color_backward_kernel(const S* means, const S* center, const S* sh, int64_t n, int K, int deg,
                             const S* grad_colors, S* grad_means, S* grad_sh) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n) return;
  pre::sh_color_backward(means + 3 * i, center, sh + i * K * 3, K, deg, grad_colors + 3 * i, grad_means + 3 * i,
                         grad_sh + i * K * 3);
}

// The same gradients with LANES lanes per primitive (LANES a power of two >= K, at most 32): lane k reads and
// writes row k of the primitive's [K, 3] SH block, so a warp's loads and stores of sh and grad_sh are contiguous
// (one thread per primitive reads rows K * 12 bytes apart), and the direction gradient is summed across the lanes
// with shuffles. grad_sh is the per-primitive kernel's to the bit; grad_means differs in the order of that sum.
// Every thread of the block reaches the shuffles (no early return), so the full mask holds.
template <typename S, int LANES>
__global__ void __launch_bounds__(LINEAR_BLOCK)
    sh_color_backward_lanes_kernel(const S* means, const S* center, const S* sh, int64_t n, int K, int deg,
                                   const S* grad_colors, S* grad_means, S* grad_sh) {
  static_assert(LANES >= 1 && LANES <= 32 && (LANES & (LANES - 1)) == 0, "LANES: a power of two up to 32");
  const int64_t t = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  const int64_t i = t / LANES;
  const int k = int(t % LANES);
  const int nb = (deg + 1) * (deg + 1);
  S gd[3] = {S(0), S(0), S(0)};
  S dir[3] = {S(0), S(0), S(0)}, r = S(0);
  if (i < n) {
    S b[16], g[16][3];
    r = pre::unit_dir(means + 3 * i, center, dir);
    pre::sh_basis<S>(dir[0], dir[1], dir[2], deg, b, g);
    if (k < K) {
      const S* gc = grad_colors + 3 * i;
      S* gs = grad_sh + (i * K + k) * 3;
      if (k < nb) {
        S bk = S(0), gk[3] = {S(0), S(0), S(0)};
#pragma unroll
        for (int j = 0; j < 16; ++j) {  // constant indices keep b and g in registers
          if (j == k) bk = b[j], gk[0] = g[j][0], gk[1] = g[j][1], gk[2] = g[j][2];
        }
        const S* s = sh + (i * K + k) * 3;
        gs[0] = bk * gc[0];
        gs[1] = bk * gc[1];
        gs[2] = bk * gc[2];
        const S dot = s[0] * gc[0] + s[1] * gc[1] + s[2] * gc[2];
        gd[0] = dot * gk[0];
        gd[1] = dot * gk[1];
        gd[2] = dot * gk[2];
      } else {
        gs[0] = gs[1] = gs[2] = S(0);
      }
    }
  }
#pragma unroll
  for (int off = LANES / 2; off > 0; off >>= 1) {
    gd[0] += __shfl_xor_sync(0xffffffffu, gd[0], off);
    gd[1] += __shfl_xor_sync(0xffffffffu, gd[1], off);
    gd[2] += __shfl_xor_sync(0xffffffffu, gd[2], off);
  }
  if (i < n && k == 0) {
    S* gm = grad_means + 3 * i;
    if (r > S(0)) {  // d dir / d mean = (I - dir dir^T) / |d|, as pre::sh_color_backward
      const S proj = dir[0] * gd[0] + dir[1] * gd[1] + dir[2] * gd[2];
      const S inv = S(1) / r;
      for (int a = 0; a < 3; ++a) gm[a] = (gd[a] - dir[a] * proj) * inv;
    } else {
      gm[0] = gm[1] = gm[2] = S(0);
    }
  }
}

// Which SH backward runs: lanes per coefficient (CTGS_CUDA_SH_LANES=1) or one thread per primitive (the default
// until the lanes kernel is measured on a GPU). Read at every launch so that one process can compare them.
inline bool sh_backward_lanes() {
  const char* v = std::getenv("CTGS_CUDA_SH_LANES");
  return v && v[0] == '1';
}


template <typename S>
__device__ inline bool positive(S v) { return v > S(0) && isfinite(v); }

template <typename S>
__global__ void __launch_bounds__(LINEAR_BLOCK)
    surfel_value_flags_kernel(const S* means, const S* quats, const S* scales, const S* opacities, const S* sh,
                              int64_t sh_row, const S* texel_size, int ts_row, const S* textures, int64_t T,
                              const int* tex_res, const int64_t* tex_offset, int64_t n, int* flag) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  bool bad = false;
  if (i < n) {
    for (int c = 0; c < 3; ++c) bad |= !isfinite(means[3 * i + c]);
    S qq = S(0);  // summed in the CPU check's order: zero exactly where it is zero there
    for (int c = 0; c < 4; ++c) {
      const S q = quats[4 * i + c];
      bad |= !isfinite(q);
      qq = xadd(qq, xmul(q, q));
    }
    bad |= qq == S(0);
    bad |= !positive(scales[2 * i]) || !positive(scales[2 * i + 1]);
    const S o = opacities[i];
    bad |= !(o >= S(0) && o <= S(1));
    for (int c = 0; c < ts_row; ++c) bad |= !positive(texel_size[ts_row * i + c]);
    for (int64_t k = 0; k < sh_row; ++k) bad |= !isfinite(sh[i * sh_row + k]);
    const int ru = tex_res[2 * i], rv = tex_res[2 * i + 1];
    bad |= ru < 0 || rv < 0;
    const int64_t size = int64_t(ru) * rv;
    if (size > 0) bad |= tex_offset[i] < 0 || tex_offset[i] > T - size;
  }
  if (i < T) {
    for (int c = 0; c < 3; ++c) bad |= !isfinite(textures[3 * i + c]);
  }
  if (bad) *flag = 1;  // every writer writes the same value
}

// Jagged texture re-layout (ctgs/model/jagged.py remap; the CPU version is kernels/cpu/dense.cpp jagged_remap):
// one thread per texel of the new packed layout finds its primitive j by binary search over new_off (packed:
// increasing, a primitive of 0 texels shares its successor's offset, and upper_bound skips it), then copies
// texel (iu + du, iv + dv) of primitive src[j], or writes 0 outside the old grid. The index arithmetic in
// PyTorch made ~15 temporaries of [T'] int64 (a few GB at the paper's 29M texels).
template <typename S>
__global__ void __launch_bounds__(LINEAR_BLOCK)
    jagged_remap_kernel(RemapBuffers<S> bufs, int C, const int* old_res, const int64_t* old_off,
                        const int64_t* src, const int64_t* shift, const int* new_res, const int64_t* new_off,
                        int64_t n_new, int64_t new_rows) {
  const int64_t t = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (t >= new_rows) return;
  int64_t lo = 0, hi = n_new;  // first primitive whose offset is > t
  while (lo < hi) {
    const int64_t mid = (lo + hi) >> 1;
    if (new_off[mid] <= t) lo = mid + 1; else hi = mid;
  }
  const int64_t j = lo - 1;
  const int64_t s = src[j];
  const int64_t ru = old_res[2 * s], rv = old_res[2 * s + 1];
  const int64_t nu = new_res[2 * j], nv = new_res[2 * j + 1];
  const int64_t local = t - new_off[j];
  const int64_t iu = local % nu, iv = local / nu;
  auto floor_half = [](int64_t d) { return d >= 0 ? d / 2 : -((-d + 1) / 2); };
  const int64_t ou = iu + floor_half(ru - nu) + shift[2 * j];
  const int64_t ov = iv + floor_half(rv - nv) + shift[2 * j + 1];
  const bool inside = ou >= 0 && ou < ru && ov >= 0 && ov < rv && iv < nv;
  const int64_t from = old_off[s] + ov * ru + ou;
  for (int b = 0; b < bufs.count; ++b) {
    const bool ok = inside && from < bufs.old_rows[b];
    for (int c = 0; c < C; ++c) bufs.out[b][C * t + c] = ok ? bufs.in[b][C * from + c] : S(0);
  }
}

}  // namespace

template <typename S>
void camera_space(const S* means, const S* quats, const S* view, int64_t n, S* mu_c, S* Rc, cudaStream_t stream) {
  if (n == 0) return;  // a grid of 0 blocks is a launch error
  camera_space_kernel<S><<<grid_1d(n), LINEAR_BLOCK, 0, stream>>>(means, quats, view, n, mu_c, Rc);
  CTGS_CUDA_LAUNCH_CHECK("camera_space_kernel");
}

template <typename S>
void camera_space_backward(const S* quats, const S* view, int64_t n, const S* grad_mu_c, const S* grad_Rc,
                           S* grad_means, S* grad_quats, cudaStream_t stream) {
  if (n == 0) return;
  camera_space_backward_kernel<S><<<grid_1d(n), LINEAR_BLOCK, 0, stream>>>(quats, view, n, grad_mu_c, grad_Rc,
                                                                          grad_means, grad_quats);
  CTGS_CUDA_LAUNCH_CHECK("camera_space_backward_kernel");
}

template <typename S>
void sh_color(const S* means, const S* center, const S* sh, int64_t n, int K, int deg, S* colors,
              cudaStream_t stream) {
  if (n == 0) return;
  sh_color_kernel<S><<<grid_1d(n), LINEAR_BLOCK, 0, stream>>>(means, center, sh, n, K, deg, colors);
  CTGS_CUDA_LAUNCH_CHECK("sh_color_kernel");
}

template <typename S>
void sh_color_backward(const S* means, const S* center, const S* sh, int64_t n, int K, int deg, const S* grad_colors,
                       S* grad_means, S* grad_sh, cudaStream_t stream) {
  if (n == 0) return;
  if (sh_backward_lanes() && K > 1 && K <= 16) {
    if (K > 4) {
      sh_color_backward_lanes_kernel<S, 16><<<grid_1d(16 * n), LINEAR_BLOCK, 0, stream>>>(
          means, center, sh, n, K, deg, grad_colors, grad_means, grad_sh);
    } else {
      sh_color_backward_lanes_kernel<S, 4><<<grid_1d(4 * n), LINEAR_BLOCK, 0, stream>>>(
          means, center, sh, n, K, deg, grad_colors, grad_means, grad_sh);
    }
    CTGS_CUDA_LAUNCH_CHECK("sh_color_backward_lanes_kernel");
    return;
  }
  sh_color_backward_kernel<S><<<grid_1d(n), LINEAR_BLOCK, 0, stream>>>(means, center, sh, n, K, deg, grad_colors,
                                                                      grad_means, grad_sh);
  CTGS_CUDA_LAUNCH_CHECK("sh_color_backward_kernel");
}

template <typename S>
void surfel_value_flags(const S* means, const S* quats, const S* scales, const S* opacities, const S* sh,
                        int64_t sh_row, const S* texel_size, int ts_row, const S* textures, int64_t T,
                        const int* tex_res, const int64_t* tex_offset, int64_t n, int* flag, cudaStream_t stream) {
  const int64_t rows = n > T ? n : T;
  if (rows == 0) return;
  surfel_value_flags_kernel<S><<<grid_1d(rows), LINEAR_BLOCK, 0, stream>>>(
      means, quats, scales, opacities, sh, sh_row, texel_size, ts_row, textures, T, tex_res, tex_offset, n, flag);
  CTGS_CUDA_LAUNCH_CHECK("surfel_value_flags_kernel");
}

template <typename S>
void jagged_remap(const RemapBuffers<S>& bufs, int C, const int* old_res, const int64_t* old_off, const int64_t* src,
                  const int64_t* shift, const int* new_res, const int64_t* new_off, int64_t n_new, int64_t new_rows,
                  cudaStream_t stream) {
  if (new_rows == 0 || n_new == 0) return;
  jagged_remap_kernel<S><<<grid_1d(new_rows), LINEAR_BLOCK, 0, stream>>>(bufs, C, old_res, old_off, src, shift,
                                                                         new_res, new_off, n_new, new_rows);
  CTGS_CUDA_LAUNCH_CHECK("jagged_remap_kernel");
}

#define CTGS_INSTANTIATE_DENSE(S)                                                                                 \
  template void camera_space<S>(const S*, const S*, const S*, int64_t, S*, S*, cudaStream_t);                   \
  template void camera_space_backward<S>(const S*, const S*, int64_t, const S*, const S*, S*, S*, cudaStream_t); \
  template void sh_color<S>(const S*, const S*, const S*, int64_t, int, int, S*, cudaStream_t);                  \
  template void sh_color_backward<S>(const S*, const S*, const S*, int64_t, int, int, const S*, S*, S*,          \
                                     cudaStream_t);                                                             \
  template void jagged_remap<S>(const RemapBuffers<S>&, int, const int*, const int64_t*, const int64_t*,          \
                                const int64_t*, const int*, const int64_t*, int64_t, int64_t, cudaStream_t);   \
  template void surfel_value_flags<S>(const S*, const S*, const S*, const S*, const S*, int64_t, const S*, int,      \
                                      const S*, int64_t, const int*, const int64_t*, int64_t, int*, cudaStream_t);
CTGS_INSTANTIATE_DENSE(float)
CTGS_INSTANTIATE_DENSE(double)
#undef CTGS_INSTANTIATE_DENSE

}  // namespace gpu
}  // namespace ctgs
