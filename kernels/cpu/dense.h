// Dense per-element training work (dense.cpp): fused Adam, the texel L1 regulariser, jagged re-layout;
// and the fused photometric loss (ssim.cpp).
#pragma once

#include <cstdint>
#include <vector>

namespace ctgs {
namespace cpu {

// One Adam step in place on n contiguous elements: m = b1 m + (1-b1) g, v = b2 v + (1-b2) g^2,
// p -= lr (m / bc1) / (sqrt(v / bc2) + eps), with lr per element (lr_vec, if not null) or lr. bc1, bc2:
// the bias corrections 1 - beta^t. Returns how many updated p are NaN or infinite.
template <typename S>
int64_t adam_step(S* p, const S* g, S* m, S* v, int64_t n, const S* lr_vec, double lr, double beta1,
                  double beta2, double bc1, double bc2, double eps, int threads);

// Weighted texel L1 (texels of i: rows tex_offset[i] .. + res_u*res_v of raw [T, 3], packed):
// grad == null -> returns sum_i weight[i] sum over i's texels of |2 sigmoid(raw) - 1|; else writes
// grad = scale * d/draw of that sum (0 for the texels of primitives with weight 0) and returns 0.
// The weights (the loss's visibility mask, times 1 - transmittance on option) are constants here.
// activated: raw holds the activated offsets y = 2 sigmoid(x) - 1 already: the sum of |y| and grad = scale *
// sign(y) (the same term, differentiated w.r.t. y; no exp).
template <typename S>
double texel_l1(const S* raw, const S* weight, const long long* tex_offset, const int* tex_res, int n_prims,
                S* grad, S scale, int threads, bool activated = false);

// Whether none of x[0..n) is NaN or infinite (exponent bits, one pass, no temporaries).
template <typename S>
bool all_finite(const S* x, int64_t n, int threads);

// Texel activation y = 2 sigmoid(x) - 1 = tanh(x / 2) on n elements, and its backward
// grad_x = grad_y (1 - y) (1 + y) / 2.
template <typename S>
void texel_activation(const S* x, S* y, int64_t n, int threads);
template <typename S>
void texel_activation_backward(const S* y, const S* grad_y, S* grad_x, int64_t n, int threads);
// The same backward with the texture regulariser's gradient folded in (packed layout, as texel_l1):
// grad_x = (grad_y + g_l1) (1 - y) (1 + y) / 2, g_l1 = (scale weight[i]) sign(y) on primitive i's texels
// (0 where weight[i] = 0): what autograd computes from texel_l1(activated)'s backward plus the sum of the
// two gradients of y, bit for bit, without the [T, 3] gradient tensor and the extra pass of that sum.
template <typename S>
void texel_activation_backward_l1(const S* y, const S* grad_y, S* grad_x, const S* weight,
                                  const long long* tex_offset, const int* tex_res, int n_prims, S scale, int threads);

// Jagged texture re-layout (ctgs/model/jagged.py remap): new primitive j copies primitive src[j]'s
// texels re-centred, new texel (iu, iv) <- old (iu + floor((ru_old - ru_new) / 2) + shift[j, 0], iv + ...),
// 0 where that falls outside the old grid. Buffers [rows, C] (one old, one new per buffer); offsets of
// both layouts given. Row by row copies, primitives in parallel.
template <typename S>
void jagged_remap(const S* old_buf, int64_t old_rows, S* new_buf, int C, const int* old_res,
                  const long long* old_off, const long long* src, const long long* shift, const int* new_res,
                  const long long* new_off, int64_t n_new, int threads);

// Per-primitive error statistics from a forward's blended pairs (pix[k], prim[k], w[k]), k < n_pairs, and the
// error image e [H*W]: count[i] = #pairs of i, contrib[i] = sum of their w, err[i] = sum of e[pix] w, summed
// in pair order (the order of PyTorch's index_add_) by one thread; with more (from 65536 pairs on), each sums a
// contiguous chunk in pair order and the chunks are added in order (deterministic for a thread count).
// Outputs [n_prims], overwritten.
template <typename S>
void accumulate_pairs(const int32_t* pix, const int32_t* prim, const S* w, int64_t n_pairs, const S* e,
                      int32_t* count, S* contrib, S* err, int64_t n_prims, int threads);

// View-dependent colour (kernels/cpu/sh.cpp, ctgs/render/sh.py): colors [n, 3] = SH_deg(normalize(mean -
// center)) + 0.5 from sh [n, K, 3] (K >= (deg + 1)^2, coefficients past the degree unused); and its backward:
// grad_means [n, 3] through the view direction (0 where mean == center), grad_sh [n, K, 3] (0 past the degree).
template <typename S>
void sh_color(const S* means, const S* center, const S* sh, int64_t n, int K, int deg, S* colors, int threads);
template <typename S>
void sh_color_backward(const S* means, const S* center, const S* sh, int64_t n, int K, int deg, const S* grad_colors,
                       S* grad_means, S* grad_sh, int threads);

// World -> camera space (kernels/cpu/camera.cpp, ctgs/render/preprocess.py): mu_c [n, 3] = R mean + t and
// Rc [n, 3, 3] = R quat_to_rotmat(quat) for view [4, 4] = [R t] (row-major), quats [n, 4] (w, x, y, z) of any
// norm; and its backward: grad_means [n, 3], grad_quats [n, 4] from grad_mu_c [n, 3], grad_Rc [n, 3, 3].
template <typename S>
void camera_space(const S* means, const S* quats, const S* view, int64_t n, S* mu_c, S* Rc, int threads);
template <typename S>
void camera_space_backward(const S* quats, const S* view, int64_t n, const S* grad_mu_c, const S* grad_Rc,
                           S* grad_means, S* grad_quats, int threads);

// The photometric loss of two [H, W, C] images x (render) and y (ground truth), kernels/cpu/ssim.cpp:
// l1_sum = sum |x - y|, ssim_sum = sum of the SSIM map (11x11 Gaussian window, sigma 1.5, zero padded), so
// the loss is (1 - l) l1_sum / (H W C) + l (1 - ssim_sum / (H W C)). grad (if not null) [H, W, C] gets its
// gradient w.r.t. x; error (if not null) [H, W] gets (1 - l) mean_c |x - y| + l mean_c (1 - SSIM).
template <typename S>
void photometric_loss(const S* x, const S* y, int H, int W, int C, double lambda_ssim, S* grad, S* error,
                      double* l1_sum, double* ssim_sum, int threads);

}  // namespace cpu
}  // namespace ctgs
