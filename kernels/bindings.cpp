// The CPU backend's only file that knows torch: checks every tensor (shape, dtype, device, contiguity), allocates
// outputs, dispatches float/double to the raw-pointer cores in kernels/cpu, and registers each as the CPU kernel of
// an op declared in ctgs/ops/schemas.py (kernels/bindings_cuda.cpp does the same for CUDA).
#include <torch/extension.h>

#include <cmath>
#include <map>
#include <string>
#include <vector>

#include "binding_common.h"
#include "cpu/dense.h"
#include "cpu/lane_math.h"
#include "cpu/rasterize.h"

namespace {

using torch::Tensor;

using ctgs_binding::check_scene;
using ctgs_binding::Scene;
using ctgs_binding::scene_args;

const at::Device kCPU(at::kCPU);

void check_tensor(const Tensor& t, const char* name, const char* shape, std::vector<int64_t> sizes,
                  at::ScalarType dtype) {
  ctgs_binding::check_tensor(t, name, shape, std::move(sizes), dtype, kCPU);
}

// A 1-D tensor that takes over v's buffer (no copy; the tensor's deleter frees it).
template <typename T>
Tensor adopt_vector(std::vector<T>&& v, at::ScalarType dtype) {
  const int64_t n = int64_t(v.size());
  if (n == 0) return torch::empty({0}, torch::dtype(dtype));
  auto* held = new std::vector<T>(std::move(v));
  return torch::from_blob(held->data(), {n}, [held](void*) { delete held; }, torch::dtype(dtype));
}

// Returns rgb [H,W,3], alpha [H,W], depth [H,W], final_T [H,W], n_contrib [H,W] int32, tile_offsets
// [tiles+1] int64, tile_list [pairs] int32, count [N] int32, contrib [N], err [N] (these three empty
// unless error_image [H,W] is given), then setup_prims [bytes] uint8 and setup_spans int32 (ctgs::cpu::FrameSetup,
// opaque: backward_cpu takes them back), then median [H,W] (the median depth, no gradient) and depth2 [H,W] (sum of
// w z^2). With poison=true outputs start as NaN, so unwritten pixels show up.
std::vector<Tensor> forward_impl(Tensor mu_c, Tensor Rc, Tensor scales, Tensor opacities, Tensor colors,
                                 Tensor texel_size, Tensor textures, Tensor tex_res, Tensor tex_offset,
                                 Tensor background, double fx, double fy, double cx, double cy, int64_t width,
                                 int64_t height, double near_plane, c10::optional<Tensor> error_image,
                                 int64_t num_threads, bool poison, bool record_pairs) {
  const Scene s = check_scene(mu_c, Rc, scales, opacities, colors, texel_size, textures, tex_res, tex_offset,
                              background, fx, fy, cx, cy, width, height, near_plane, num_threads,
                              at::kCPU, "cpu");
  const int64_t N = mu_c.size(0), H = height, W = width;
  const bool stats = error_image.has_value();
  if (stats) check_tensor(*error_image, "error_image", "[H, W]", {H, W}, mu_c.scalar_type());
  auto fopt = mu_c.options();
  auto make = [&](std::vector<int64_t> sz) {
    return poison ? torch::full(sz, std::numeric_limits<double>::quiet_NaN(), fopt) : torch::empty(sz, fopt);
  };
  Tensor rgb = make({H, W, 3}), alpha = make({H, W}), depth = make({H, W}), final_T = make({H, W});
  Tensor median = make({H, W}), depth2 = make({H, W});
  Tensor n_contrib = poison ? torch::full({H, W}, -1, fopt.dtype(at::kInt)) : torch::empty({H, W}, fopt.dtype(at::kInt));
  Tensor count = torch::zeros({stats ? N : 0}, fopt.dtype(at::kInt));
  Tensor contrib = torch::zeros({stats ? N : 0}, fopt), err = torch::zeros({stats ? N : 0}, fopt);
  ctgs::cpu::TileBins bins;
  ctgs::cpu::FrameSetup setup;
  Tensor pix, prim, w;
  AT_DISPATCH_FLOATING_TYPES(mu_c.scalar_type(), "ctgs_forward_cpu", [&] {
    ctgs::cpu::BlendPairs<scalar_t> pairs;
    ctgs::cpu::ForwardOut<scalar_t> o;
    o.rgb = rgb.data_ptr<scalar_t>();
    o.alpha = alpha.data_ptr<scalar_t>();
    o.depth = depth.data_ptr<scalar_t>();
    o.median = median.data_ptr<scalar_t>();
    o.depth2 = depth2.data_ptr<scalar_t>();
    o.final_T = final_T.data_ptr<scalar_t>();
    o.n_contrib = n_contrib.data_ptr<int32_t>();
    o.error_image = stats ? error_image->data_ptr<scalar_t>() : nullptr;
    o.count = stats ? count.data_ptr<int32_t>() : nullptr;
    o.contrib = stats ? contrib.data_ptr<scalar_t>() : nullptr;
    o.err = stats ? err.data_ptr<scalar_t>() : nullptr;
    o.pairs = record_pairs ? &pairs : nullptr;
    ctgs::cpu::forward<scalar_t>(scene_args<scalar_t>(s), o, &bins, record_pairs ? nullptr : &setup);
    if (record_pairs) {
      // ~1M pairs per view for E: hand the buffers over instead of copying them.
      pix = adopt_vector(std::move(pairs.pix), at::kInt);
      prim = adopt_vector(std::move(pairs.prim), at::kInt);
      w = adopt_vector(std::move(pairs.w), mu_c.scalar_type());
    }
  });
  if (record_pairs) return {rgb, alpha, depth, pix, prim, w};
  Tensor tile_offsets = adopt_vector(std::move(bins.offsets), at::kLong);
  Tensor tile_list = adopt_vector(std::move(bins.list), at::kInt);
  // Opaque: what backward_cpu needs of this render besides the tile lists (ctgs::cpu::FrameSetup).
  Tensor setup_prims = adopt_vector(std::move(setup.prims), at::kByte);
  Tensor setup_spans = adopt_vector(std::move(setup.span_xs), at::kInt);
  return {rgb, alpha, depth, final_T, n_contrib, tile_offsets, tile_list, count, contrib, err, setup_prims,
          setup_spans, median, depth2};
}

std::vector<Tensor> forward_cpu(Tensor mu_c, Tensor Rc, Tensor scales, Tensor opacities, Tensor colors,
                                Tensor texel_size, Tensor textures, Tensor tex_res, Tensor tex_offset,
                                Tensor background, double fx, double fy, double cx, double cy, int64_t width,
                                int64_t height, double near_plane, c10::optional<Tensor> error_image,
                                int64_t num_threads, bool poison) {
  return forward_impl(mu_c, Rc, scales, opacities, colors, texel_size, textures, tex_res, tex_offset, background,
                      fx, fy, cx, cy, width, height, near_plane, error_image, num_threads, poison, false);
}

// Forward without gradient bookkeeping that also returns every blended pair: rgb [H,W,3], alpha [H,W],
// depth [H,W], pix [P] int32 (y * W + x), prim [P] int32, w [P] (tile by tile, ctgs::cpu::BlendPairs).
std::vector<Tensor> forward_pairs_cpu(Tensor mu_c, Tensor Rc, Tensor scales, Tensor opacities, Tensor colors,
                                      Tensor texel_size, Tensor textures, Tensor tex_res, Tensor tex_offset,
                                      Tensor background, double fx, double fy, double cx, double cy,
                                      int64_t width, int64_t height, double near_plane, int64_t num_threads,
                                      bool poison) {
  return forward_impl(mu_c, Rc, scales, opacities, colors, texel_size, textures, tex_res, tex_offset, background,
                      fx, fy, cx, cy, width, height, near_plane, c10::nullopt, num_threads, poison, true);
}

// Returns v_mu_c [N,3], v_Rc [N,3,3], v_scales [N,2], v_opacities [N], v_colors [N,3], v_texel_size [N,2],
// v_textures [T,3], v_background [3]; with an error image [H, W] also contrib [N] and err [N], the error statistics
// of the pixels blended (the forward's with that error image, up to rounding). v_depth2 [H, W]: the gradient of the
// forward's depth2 (None: zero).
std::vector<Tensor> backward_impl(Tensor mu_c, Tensor Rc, Tensor scales, Tensor opacities, Tensor colors,
                                  Tensor texel_size, Tensor textures, Tensor tex_res, Tensor tex_offset,
                                  Tensor background, double fx, double fy, double cx, double cy, int64_t width,
                                  int64_t height, double near_plane, Tensor tile_offsets, Tensor tile_list,
                                  Tensor final_T, Tensor n_contrib, Tensor v_rgb, Tensor v_alpha, Tensor v_depth,
                                  int64_t num_threads, c10::optional<Tensor> setup_prims,
                                  c10::optional<Tensor> setup_spans, c10::optional<Tensor> error_image,
                                  c10::optional<Tensor> v_depth2) {
  const Scene s = check_scene(mu_c, Rc, scales, opacities, colors, texel_size, textures, tex_res, tex_offset,
                              background, fx, fy, cx, cy, width, height, near_plane, num_threads,
                              at::kCPU, "cpu");
  const int64_t H = height, W = width;
  const auto dt = mu_c.scalar_type();
  const int64_t num_tiles = int64_t(ctgs::tiles_x(int(W))) * ctgs::tiles_y(int(H));
  check_tensor(tile_offsets, "tile_offsets", "[tiles + 1] int64", {num_tiles + 1}, at::kLong);
  check_tensor(tile_list, "tile_list", "[pairs] int32", {-1}, at::kInt);
  TORCH_CHECK(tile_offsets[num_tiles].item<int64_t>() == tile_list.size(0), "tile_offsets/tile_list mismatch");
  check_tensor(final_T, "final_T", "[H, W]", {H, W}, dt);
  check_tensor(n_contrib, "n_contrib", "[H, W] int32", {H, W}, at::kInt);
  check_tensor(v_rgb, "v_rgb", "[H, W, 3]", {H, W, 3}, dt);
  check_tensor(v_alpha, "v_alpha", "[H, W]", {H, W}, dt);
  check_tensor(v_depth, "v_depth", "[H, W]", {H, W}, dt);
  if (v_depth2.has_value()) check_tensor(*v_depth2, "v_depth2", "[H, W]", {H, W}, dt);
  // The forward's setup (forward_cpu's last two outputs), or None to recompute it.
  const bool reuse = setup_prims.has_value() && setup_spans.has_value();
  if (reuse) {
    const int64_t need = mu_c.size(0) * int64_t(dt == at::kFloat ? sizeof(ctgs::cpu::LanePrim<float>)
                                                                  : sizeof(ctgs::cpu::LanePrim<double>));
    TORCH_CHECK(setup_prims->scalar_type() == at::kByte && setup_prims->dim() == 1 && setup_prims->numel() == need &&
                    setup_prims->is_contiguous() && setup_prims->device().is_cpu(),
                "backward_cpu: setup_prims must be forward_cpu's output of the same render (", need,
                " bytes), got ", setup_prims->sizes(), " ", setup_prims->scalar_type());
    TORCH_CHECK(setup_spans->scalar_type() == at::kInt && setup_spans->dim() == 1 && setup_spans->is_contiguous() &&
                    setup_spans->device().is_cpu(),
                "backward_cpu: setup_spans must be forward_cpu's int32 output of the same render");
  }
  Tensor v_mu_c = torch::empty_like(mu_c), v_Rc = torch::empty_like(Rc), v_scales = torch::empty_like(scales);
  Tensor v_opacities = torch::empty_like(opacities), v_colors = torch::empty_like(colors);
  Tensor v_texel_size = torch::empty_like(texel_size), v_textures = torch::empty_like(textures);
  Tensor v_background = torch::empty_like(background);
  const bool stats = error_image.has_value();
  if (stats) check_tensor(*error_image, "error_image", "[H, W]", {H, W}, dt);
  Tensor contrib = torch::empty({stats ? mu_c.size(0) : 0}, mu_c.options());
  Tensor err = torch::empty({stats ? mu_c.size(0) : 0}, mu_c.options());
  AT_DISPATCH_FLOATING_TYPES(dt, "ctgs_backward_cpu", [&] {
    ctgs::cpu::BackwardOut<scalar_t> o;
    o.v_mu_c = v_mu_c.data_ptr<scalar_t>();
    o.v_Rc = v_Rc.data_ptr<scalar_t>();
    o.v_scales = v_scales.data_ptr<scalar_t>();
    o.v_opacities = v_opacities.data_ptr<scalar_t>();
    o.v_colors = v_colors.data_ptr<scalar_t>();
    o.v_texel_size = v_texel_size.data_ptr<scalar_t>();
    o.v_textures = v_textures.data_ptr<scalar_t>();
    o.v_background = v_background.data_ptr<scalar_t>();
    ctgs::cpu::TileBinsView bins{tile_offsets.data_ptr<int64_t>(), tile_list.data_ptr<int32_t>()};
    ctgs::cpu::backward<scalar_t>(scene_args<scalar_t>(s), bins, final_T.data_ptr<scalar_t>(),
                                  n_contrib.data_ptr<int32_t>(), v_rgb.data_ptr<scalar_t>(),
                                  v_alpha.data_ptr<scalar_t>(), v_depth.data_ptr<scalar_t>(), o,
                                  reuse && setup_prims->numel() ? setup_prims->data_ptr<uint8_t>() : nullptr,
                                  reuse && setup_spans->numel() ? setup_spans->data_ptr<int32_t>() : nullptr,
                                  stats ? error_image->data_ptr<scalar_t>() : nullptr,
                                  stats ? contrib.data_ptr<scalar_t>() : nullptr,
                                  stats ? err.data_ptr<scalar_t>() : nullptr,
                                  v_depth2.has_value() ? v_depth2->data_ptr<scalar_t>() : nullptr);
  });
  if (stats) return {v_mu_c, v_Rc, v_scales, v_opacities, v_colors, v_texel_size, v_textures, v_background, contrib, err};
  return {v_mu_c, v_Rc, v_scales, v_opacities, v_colors, v_texel_size, v_textures, v_background};
}

std::vector<Tensor> backward_cpu(Tensor mu_c, Tensor Rc, Tensor scales, Tensor opacities, Tensor colors,
                                 Tensor texel_size, Tensor textures, Tensor tex_res, Tensor tex_offset,
                                 Tensor background, double fx, double fy, double cx, double cy, int64_t width,
                                 int64_t height, double near_plane, Tensor tile_offsets, Tensor tile_list,
                                 Tensor final_T, Tensor n_contrib, Tensor v_rgb, Tensor v_alpha, Tensor v_depth,
                                 int64_t num_threads, c10::optional<Tensor> setup_prims,
                                 c10::optional<Tensor> setup_spans, c10::optional<Tensor> v_depth2) {
  return backward_impl(mu_c, Rc, scales, opacities, colors, texel_size, textures, tex_res, tex_offset, background, fx,
                       fy, cx, cy, width, height, near_plane, tile_offsets, tile_list, final_T, n_contrib, v_rgb,
                       v_alpha, v_depth, num_threads, setup_prims, setup_spans, c10::nullopt, v_depth2);
}

// backward_cpu, and the error statistics of error_image [H, W] (contiguous, the scene's dtype) over the pixels blended.
std::vector<Tensor> backward_stats_cpu(Tensor mu_c, Tensor Rc, Tensor scales, Tensor opacities, Tensor colors,
                                       Tensor texel_size, Tensor textures, Tensor tex_res, Tensor tex_offset,
                                       Tensor background, double fx, double fy, double cx, double cy, int64_t width,
                                       int64_t height, double near_plane, Tensor tile_offsets, Tensor tile_list,
                                       Tensor final_T, Tensor n_contrib, Tensor v_rgb, Tensor v_alpha, Tensor v_depth,
                                       int64_t num_threads, c10::optional<Tensor> setup_prims,
                                       c10::optional<Tensor> setup_spans, Tensor error_image,
                                       c10::optional<Tensor> v_depth2) {
  return backward_impl(mu_c, Rc, scales, opacities, colors, texel_size, textures, tex_res, tex_offset, background, fx,
                       fy, cx, cy, width, height, near_plane, tile_offsets, tile_list, final_T, n_contrib, v_rgb,
                       v_alpha, v_depth, num_threads, setup_prims, setup_spans, error_image, v_depth2);
}

// Adam in place on p, m, v (all contiguous, same shape and dtype as g); lr: a float, or lr_tensor of p's
// shape. Returns how many updated elements of p are NaN or infinite.
int64_t adam_step_cpu(Tensor p, Tensor g, Tensor m, Tensor v, c10::optional<Tensor> lr_tensor, double lr,
                      double beta1, double beta2, int64_t step, double eps, int64_t num_threads) {
  TORCH_CHECK(p.device().is_cpu(), "adam_step_cpu: p must be a CPU tensor, got ", p.device());
  const auto dt = p.scalar_type();
  TORCH_CHECK(dt == at::kFloat || dt == at::kDouble, "adam_step_cpu: p must be float32 or float64, got ", dt);
  TORCH_CHECK(step >= 1, "adam_step_cpu: step must be >= 1, got ", step);
  for (const Tensor* t : {&p, &g, &m, &v}) {
    TORCH_CHECK(t->device().is_cpu() && t->scalar_type() == dt && t->sizes() == p.sizes() && t->is_contiguous(),
                "adam_step_cpu: p, grad, exp_avg, exp_avg_sq must be contiguous CPU tensors of one shape and "
                "dtype, got ", t->sizes(), " ", t->scalar_type(), " vs p ", p.sizes(), " ", dt);
  }
  if (lr_tensor)
    TORCH_CHECK(lr_tensor->scalar_type() == dt && lr_tensor->sizes() == p.sizes() && lr_tensor->is_contiguous(),
                "adam_step_cpu: lr_tensor must be contiguous with p's shape ", p.sizes(), " and dtype, got ",
                lr_tensor->sizes());
  const double bc1 = 1.0 - std::pow(beta1, double(step)), bc2 = 1.0 - std::pow(beta2, double(step));
  const int threads = int(num_threads > 0 ? num_threads : at::get_num_threads());
  int64_t bad = 0;
  AT_DISPATCH_FLOATING_TYPES(dt, "ctgs_adam_step_cpu", [&] {
    bad = ctgs::cpu::adam_step<scalar_t>(p.data_ptr<scalar_t>(), g.data_ptr<scalar_t>(), m.data_ptr<scalar_t>(),
                                         v.data_ptr<scalar_t>(), p.numel(),
                                         lr_tensor ? lr_tensor->data_ptr<scalar_t>() : nullptr, lr, beta1, beta2,
                                         bc1, bc2, eps, threads);
  });
  return bad;
}

void check_texel_l1(const Tensor& raw, const Tensor& weight, const Tensor& tex_offset, const Tensor& tex_res) {
  TORCH_CHECK(raw.device().is_cpu() && raw.dim() == 2 && raw.size(1) == 3 && raw.is_contiguous() &&
              (raw.scalar_type() == at::kFloat || raw.scalar_type() == at::kDouble),
              "texel_l1: raw must be a contiguous float CPU tensor [T, 3], got ", raw.sizes(), " ", raw.scalar_type());
  const int64_t N = weight.numel();
  check_tensor(weight, "weight", "[N] of raw's dtype", {N}, raw.scalar_type());
  check_tensor(tex_offset, "tex_offset", "[N] int64", {N}, at::kLong);
  check_tensor(tex_res, "tex_res", "[N, 2] int32", {N, 2}, at::kInt);
  // Packed layout (ctgs.model.surfels.jagged_offsets): every texel belongs to exactly one primitive, so
  // the gradient kernel writes every row.
  const int64_t* off = tex_offset.data_ptr<int64_t>();
  const int32_t* res = tex_res.data_ptr<int32_t>();
  int64_t next = 0;
  for (int64_t i = 0; i < N; ++i) {
    TORCH_CHECK(res[2 * i] >= 0 && res[2 * i + 1] >= 0, "texel_l1: tex_res must be >= 0");
    const int64_t size = int64_t(res[2 * i]) * res[2 * i + 1];
    TORCH_CHECK(size == 0 || off[i] == next, "texel_l1: textures must be packed (tex_offset = exclusive cumsum "
                "of res_u*res_v), primitive ", i, " starts at ", off[i], ", expected ", next);
    next += size;
  }
  TORCH_CHECK(next == raw.size(0), "texel_l1: the primitives hold ", next, " texels, raw has ", raw.size(0));
}

// sum_i weight[i] x sum over primitive i's texels of |2 sigmoid(raw) - 1| (a 0-dim tensor of raw's dtype);
// activated: raw holds y = 2 sigmoid(x) - 1 already (the sum of |y|).
Tensor texel_l1_forward_impl(Tensor raw, Tensor weight, Tensor tex_offset, Tensor tex_res, int64_t num_threads,
                             bool activated) {
  check_texel_l1(raw, weight, tex_offset, tex_res);
  const int threads = int(num_threads > 0 ? num_threads : at::get_num_threads());
  double total = 0.0;
  AT_DISPATCH_FLOATING_TYPES(raw.scalar_type(), "ctgs_texel_l1_forward_cpu", [&] {
    total = ctgs::cpu::texel_l1<scalar_t>(raw.data_ptr<scalar_t>(), weight.data_ptr<scalar_t>(),
                                          reinterpret_cast<const long long*>(tex_offset.data_ptr<int64_t>()),
                                          tex_res.data_ptr<int32_t>(), int(weight.numel()), nullptr, scalar_t(0), threads,
                                          activated);
  });
  return torch::scalar_tensor(total, raw.options());
}

// scale * d/draw of texel_l1_forward_impl, [T, 3].
Tensor texel_l1_backward_impl(Tensor raw, Tensor weight, Tensor tex_offset, Tensor tex_res, double scale,
                              int64_t num_threads, bool activated) {
  check_texel_l1(raw, weight, tex_offset, tex_res);
  const int threads = int(num_threads > 0 ? num_threads : at::get_num_threads());
  Tensor grad = torch::empty_like(raw);
  AT_DISPATCH_FLOATING_TYPES(raw.scalar_type(), "ctgs_texel_l1_backward_cpu", [&] {
    ctgs::cpu::texel_l1<scalar_t>(raw.data_ptr<scalar_t>(), weight.data_ptr<scalar_t>(),
                                  reinterpret_cast<const long long*>(tex_offset.data_ptr<int64_t>()),
                                  tex_res.data_ptr<int32_t>(), int(weight.numel()), grad.data_ptr<scalar_t>(),
                                  scalar_t(scale), threads, activated);
  });
  return grad;
}

Tensor texel_l1_forward_cpu(Tensor raw, Tensor weight, Tensor tex_offset, Tensor tex_res, int64_t num_threads) {
  return texel_l1_forward_impl(raw, weight, tex_offset, tex_res, num_threads, false);
}
Tensor texel_l1_backward_cpu(Tensor raw, Tensor weight, Tensor tex_offset, Tensor tex_res, double scale,
                             int64_t num_threads) {
  return texel_l1_backward_impl(raw, weight, tex_offset, tex_res, scale, num_threads, false);
}
Tensor texel_abs_forward_cpu(Tensor y, Tensor weight, Tensor tex_offset, Tensor tex_res, int64_t num_threads) {
  return texel_l1_forward_impl(y, weight, tex_offset, tex_res, num_threads, true);
}
Tensor texel_abs_backward_cpu(Tensor y, Tensor weight, Tensor tex_offset, Tensor tex_res, double scale,
                              int64_t num_threads) {
  return texel_l1_backward_impl(y, weight, tex_offset, tex_res, scale, num_threads, true);
}

// y = 2 sigmoid(x) - 1 of a contiguous float CPU tensor (any shape).
Tensor texel_activation_cpu(Tensor x, int64_t num_threads) {
  TORCH_CHECK(x.device().is_cpu() && x.is_contiguous() && (x.scalar_type() == at::kFloat || x.scalar_type() == at::kDouble),
              "texel_activation: x must be a contiguous float CPU tensor, got ", x.sizes(), " ", x.scalar_type());
  Tensor y = torch::empty_like(x);
  const int threads = int(num_threads > 0 ? num_threads : at::get_num_threads());
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "ctgs_texel_activation_cpu", [&] {
    ctgs::cpu::texel_activation<scalar_t>(x.data_ptr<scalar_t>(), y.data_ptr<scalar_t>(), x.numel(), threads);
  });
  return y;
}

// grad_y: a contiguous CPU tensor of y's dtype and shape.
void check_grad_like(const Tensor& y, const Tensor& grad_y, const char* what) {
  TORCH_CHECK(grad_y.device().is_cpu() && grad_y.is_contiguous() && grad_y.scalar_type() == y.scalar_type() &&
              grad_y.sizes() == y.sizes(), what, ": grad must match y ", y.sizes(), ", got ", grad_y.sizes());
}

// grad_x = grad_y (1 - y^2) / 2 for y = texel_activation_cpu(x).
Tensor texel_activation_backward_cpu(Tensor y, Tensor grad_y, int64_t num_threads) {
  TORCH_CHECK(y.device().is_cpu() && y.is_contiguous() && (y.scalar_type() == at::kFloat || y.scalar_type() == at::kDouble),
              "texel_activation_backward: y must be a contiguous float CPU tensor");
  check_grad_like(y, grad_y, "texel_activation_backward");
  Tensor g = torch::empty_like(y);
  const int threads = int(num_threads > 0 ? num_threads : at::get_num_threads());
  AT_DISPATCH_FLOATING_TYPES(y.scalar_type(), "ctgs_texel_activation_backward_cpu", [&] {
    ctgs::cpu::texel_activation_backward<scalar_t>(y.data_ptr<scalar_t>(), grad_y.data_ptr<scalar_t>(),
                                                   g.data_ptr<scalar_t>(), y.numel(), threads);
  });
  return g;
}

// texel_activation_backward_cpu(y, grad_y + texel_abs_backward_cpu(y, weight, tex_offset, tex_res, scale)) in
// one pass, bit for bit (ctgs/ops/fused.py: the texture regulariser's gradient folded into the activation's).
Tensor texel_activation_backward_l1_cpu(Tensor y, Tensor grad_y, Tensor weight, Tensor tex_offset, Tensor tex_res,
                                        double scale, int64_t num_threads) {
  check_texel_l1(y, weight, tex_offset, tex_res);
  check_grad_like(y, grad_y, "texel_activation_backward_l1");
  Tensor g = torch::empty_like(y);
  const int threads = int(num_threads > 0 ? num_threads : at::get_num_threads());
  AT_DISPATCH_FLOATING_TYPES(y.scalar_type(), "ctgs_texel_activation_backward_l1_cpu", [&] {
    ctgs::cpu::texel_activation_backward_l1<scalar_t>(
        y.data_ptr<scalar_t>(), grad_y.data_ptr<scalar_t>(), g.data_ptr<scalar_t>(), weight.data_ptr<scalar_t>(),
        reinterpret_cast<const long long*>(tex_offset.data_ptr<int64_t>()), tex_res.data_ptr<int32_t>(),
        int(weight.numel()), scalar_t(scale), threads);
  });
  return g;
}

// Per-primitive (count int32, contrib, err) [n] from a forward's blended pairs (forward_pairs_cpu: pix, prim
// int32 [P], w [P]) and the error image e [H, W] (kernels/cpu/dense.h accumulate_pairs).
std::vector<Tensor> accumulate_pairs_cpu(Tensor pix, Tensor prim, Tensor w, Tensor e, int64_t n, int64_t num_threads) {
  const int64_t P = w.size(0);
  check_tensor(pix, "pix", "[P] int32", {P}, at::kInt);
  check_tensor(prim, "prim", "[P] int32", {P}, at::kInt);
  TORCH_CHECK(w.device().is_cpu() && w.dim() == 1 && w.is_contiguous() &&
                  (w.scalar_type() == at::kFloat || w.scalar_type() == at::kDouble),
              "accumulate_pairs: w must be a contiguous float CPU tensor [P]");
  TORCH_CHECK(e.device().is_cpu() && e.is_contiguous() && e.scalar_type() == w.scalar_type(),
              "accumulate_pairs: the error image must be a contiguous CPU tensor of w's dtype");
  TORCH_CHECK(n >= 0, "accumulate_pairs: n must be >= 0");
  const int64_t npix = e.numel();
  const int32_t* pp = pix.data_ptr<int32_t>();
  const int32_t* qq = prim.data_ptr<int32_t>();
  const int threads = int(num_threads > 0 ? num_threads : at::get_num_threads());
  int bad = 0;
#pragma omp parallel for schedule(static) reduction(| : bad) num_threads(std::max(1, threads))
  for (int64_t k = 0; k < P; ++k) bad |= int(!(pp[k] >= 0 && pp[k] < npix && qq[k] >= 0 && qq[k] < n));
  for (int64_t k = 0; bad && k < P; ++k)  // name the first bad pair
    TORCH_CHECK(pp[k] >= 0 && pp[k] < npix && qq[k] >= 0 && qq[k] < n, "accumulate_pairs: pair ", k,
                " out of range (pixel ", pp[k], " of ", npix, ", primitive ", qq[k], " of ", n, ")");
  Tensor count = torch::empty({n}, torch::dtype(at::kInt));
  Tensor contrib = torch::empty({n}, w.options());
  Tensor err = torch::empty({n}, w.options());
  AT_DISPATCH_FLOATING_TYPES(w.scalar_type(), "ctgs_accumulate_pairs_cpu", [&] {
    ctgs::cpu::accumulate_pairs<scalar_t>(pp, qq, w.data_ptr<scalar_t>(), P, e.data_ptr<scalar_t>(),
                                          count.data_ptr<int32_t>(), contrib.data_ptr<scalar_t>(),
                                          err.data_ptr<scalar_t>(), n, threads);
  });
  return {count, contrib, err};
}

void check_sh_args(const Tensor& means, const Tensor& center, const Tensor& sh, int64_t degree) {
  TORCH_CHECK(means.device().is_cpu() && means.dim() == 2 && means.size(1) == 3 && means.is_contiguous() &&
                  (means.scalar_type() == at::kFloat || means.scalar_type() == at::kDouble),
              "sh_color: means must be a contiguous float CPU tensor [N, 3], got ", means.sizes());
  check_tensor(center, "center", "[3]", {3}, means.scalar_type());
  check_tensor(sh, "sh", "[N, K, 3]", {means.size(0), -1, 3}, means.scalar_type());
  TORCH_CHECK(degree >= 0 && degree <= 3 && sh.size(1) >= (degree + 1) * (degree + 1),
              "sh_color: degree ", degree, " needs (degree + 1)^2 <= K = ", sh.size(1), " and degree in 0..3");
}

// colors [N, 3] = SH_degree(normalize(means - center)) + 0.5 (kernels/cpu/sh.cpp).
Tensor sh_color_cpu(Tensor means, Tensor center, Tensor sh, int64_t degree, int64_t num_threads) {
  check_sh_args(means, center, sh, degree);
  const int threads = int(num_threads > 0 ? num_threads : at::get_num_threads());
  Tensor colors = torch::empty_like(means);
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "ctgs_sh_color_cpu", [&] {
    ctgs::cpu::sh_color<scalar_t>(means.data_ptr<scalar_t>(), center.data_ptr<scalar_t>(), sh.data_ptr<scalar_t>(),
                                  means.size(0), int(sh.size(1)), int(degree), colors.data_ptr<scalar_t>(), threads);
  });
  return colors;
}

// {grad_means [N, 3], grad_sh [N, K, 3]} of sh_color_cpu for the upstream gradient grad_colors [N, 3].
std::vector<Tensor> sh_color_backward_cpu(Tensor means, Tensor center, Tensor sh, int64_t degree, Tensor grad_colors,
                                          int64_t num_threads) {
  check_sh_args(means, center, sh, degree);
  check_tensor(grad_colors, "grad_colors", "[N, 3]", {means.size(0), 3}, means.scalar_type());
  const int threads = int(num_threads > 0 ? num_threads : at::get_num_threads());
  Tensor gm = torch::empty_like(means), gs = torch::empty_like(sh);
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "ctgs_sh_color_backward_cpu", [&] {
    ctgs::cpu::sh_color_backward<scalar_t>(means.data_ptr<scalar_t>(), center.data_ptr<scalar_t>(),
                                           sh.data_ptr<scalar_t>(), means.size(0), int(sh.size(1)), int(degree),
                                           grad_colors.data_ptr<scalar_t>(), gm.data_ptr<scalar_t>(),
                                           gs.data_ptr<scalar_t>(), threads);
  });
  return {gm, gs};
}

// True if the surfel tensors pass every value check of ctgs.render.api.validate_inputs (all finite,
// scales > 0, texel_size > 0, opacities in [0, 1], no all-zero quaternion, tex_res >= 0, texel blocks inside
// textures): one pass each without temporaries. False means some check may fail: the caller then runs the
// PyTorch checks, which name the problem. Shapes, dtypes and devices are the caller's (checked here too).
bool surfel_values_ok_cpu(Tensor means, Tensor quats, Tensor scales, Tensor opacities, Tensor sh, Tensor texel_size,
                          Tensor textures, Tensor tex_res, Tensor tex_offset, int64_t num_threads) {
  const auto dt = means.scalar_type();
  TORCH_CHECK(dt == at::kFloat || dt == at::kDouble, "surfel_values_ok: means must be float32 or float64");
  const int64_t n = means.size(0);
  for (const Tensor* t : {&means, &quats, &scales, &opacities, &sh, &texel_size, &textures})
    TORCH_CHECK(t->device().is_cpu() && t->is_contiguous() && t->scalar_type() == dt && (t == &textures || t->size(0) == n),
                "surfel_values_ok: float tensors must be contiguous CPU tensors of means' dtype with N rows");
  TORCH_CHECK(quats.numel() == 4 * n && scales.numel() == 2 * n && opacities.numel() == n &&
                  (texel_size.numel() == n || texel_size.numel() == 2 * n),
              "surfel_values_ok: quats [N, 4], scales [N, 2], opacities [N], texel_size [N] or [N, 2]");
  check_tensor(tex_res, "tex_res", "[N, 2] int32", {n, 2}, at::kInt);
  check_tensor(tex_offset, "tex_offset", "[N] int64", {n}, at::kLong);
  const int threads = int(num_threads > 0 ? num_threads : at::get_num_threads());
  bool ok = true;
  AT_DISPATCH_FLOATING_TYPES(dt, "ctgs_surfel_values_ok_cpu", [&] {
    for (const Tensor* t : {&means, &quats, &scales, &opacities, &sh, &texel_size, &textures})
      ok = ok && ctgs::cpu::all_finite<scalar_t>(t->data_ptr<scalar_t>(), t->numel(), threads);
    if (!ok) return;
    const scalar_t* sc = scales.data_ptr<scalar_t>();
    for (int64_t k = 0; k < scales.numel() && ok; ++k) ok = sc[k] > scalar_t(0);
    const scalar_t* ts = texel_size.data_ptr<scalar_t>();
    for (int64_t k = 0; k < texel_size.numel() && ok; ++k) ok = ts[k] > scalar_t(0);
    const scalar_t* op = opacities.data_ptr<scalar_t>();
    for (int64_t k = 0; k < n && ok; ++k) ok = op[k] >= scalar_t(0) && op[k] <= scalar_t(1);
    // A sum of squares that is 0 in the tensor's dtype flags every quaternion PyTorch's norm can call zero.
    const scalar_t* q = quats.data_ptr<scalar_t>();
    for (int64_t i = 0; i < n && ok; ++i)
      ok = q[4 * i] * q[4 * i] + q[4 * i + 1] * q[4 * i + 1] + q[4 * i + 2] * q[4 * i + 2] + q[4 * i + 3] * q[4 * i + 3] !=
           scalar_t(0);
  });
  if (!ok) return false;
  const int32_t* res = tex_res.data_ptr<int32_t>();
  const int64_t* off = tex_offset.data_ptr<int64_t>();
  const int64_t T = textures.dim() >= 1 ? textures.size(0) : 0;
  for (int64_t i = 0; i < n; ++i) {
    if (res[2 * i] < 0 || res[2 * i + 1] < 0) return false;
    const int64_t size = int64_t(res[2 * i]) * res[2 * i + 1];
    if (size > 0 && (off[i] < 0 || off[i] > T - size)) return false;
  }
  return true;
}

// surfel_values_ok as the flag tensor both backends return (0: every check passed).
Tensor surfel_value_flags_cpu(Tensor means, Tensor quats, Tensor scales, Tensor opacities, Tensor sh,
                              Tensor texel_size, Tensor textures, Tensor tex_res, Tensor tex_offset,
                              int64_t num_threads) {
  const bool ok = surfel_values_ok_cpu(means, quats, scales, opacities, sh, texel_size, textures, tex_res, tex_offset,
                                       num_threads);
  return at::scalar_tensor(ok ? 0 : 1, at::TensorOptions().dtype(at::kInt));
}

void check_camera_args(const Tensor& quats, const Tensor& view) {
  TORCH_CHECK(quats.device().is_cpu() && quats.dim() == 2 && quats.size(1) == 4 && quats.is_contiguous() &&
                  (quats.scalar_type() == at::kFloat || quats.scalar_type() == at::kDouble),
              "camera_space: quats must be a contiguous float CPU tensor [N, 4], got ", quats.sizes());
  check_tensor(view, "view", "[4, 4]", {4, 4}, quats.scalar_type());
}

// {mu_c [N, 3], Rc [N, 3, 3]}: the primitives in the camera space of view [4, 4] (kernels/cpu/camera.cpp).
std::vector<Tensor> camera_space_cpu(Tensor means, Tensor quats, Tensor view, int64_t num_threads) {
  check_camera_args(quats, view);
  check_tensor(means, "means", "[N, 3]", {quats.size(0), 3}, quats.scalar_type());
  const int threads = int(num_threads > 0 ? num_threads : at::get_num_threads());
  const int64_t n = quats.size(0);
  Tensor mu_c = torch::empty({n, 3}, quats.options()), Rc = torch::empty({n, 3, 3}, quats.options());
  AT_DISPATCH_FLOATING_TYPES(quats.scalar_type(), "ctgs_camera_space_cpu", [&] {
    ctgs::cpu::camera_space<scalar_t>(means.data_ptr<scalar_t>(), quats.data_ptr<scalar_t>(),
                                      view.data_ptr<scalar_t>(), n, mu_c.data_ptr<scalar_t>(),
                                      Rc.data_ptr<scalar_t>(), threads);
  });
  return {mu_c, Rc};
}

// {grad_means [N, 3], grad_quats [N, 4]} of camera_space_cpu for the upstream gradients.
std::vector<Tensor> camera_space_backward_cpu(Tensor quats, Tensor view, Tensor grad_mu_c, Tensor grad_Rc,
                                              int64_t num_threads) {
  check_camera_args(quats, view);
  const int64_t n = quats.size(0);
  check_tensor(grad_mu_c, "grad_mu_c", "[N, 3]", {n, 3}, quats.scalar_type());
  check_tensor(grad_Rc, "grad_Rc", "[N, 3, 3]", {n, 3, 3}, quats.scalar_type());
  const int threads = int(num_threads > 0 ? num_threads : at::get_num_threads());
  Tensor gm = torch::empty({n, 3}, quats.options()), gq = torch::empty_like(quats);
  AT_DISPATCH_FLOATING_TYPES(quats.scalar_type(), "ctgs_camera_space_backward_cpu", [&] {
    ctgs::cpu::camera_space_backward<scalar_t>(quats.data_ptr<scalar_t>(), view.data_ptr<scalar_t>(), n,
                                               grad_mu_c.data_ptr<scalar_t>(), grad_Rc.data_ptr<scalar_t>(),
                                               gm.data_ptr<scalar_t>(), gq.data_ptr<scalar_t>(), threads);
  });
  return {gm, gq};
}

// The photometric loss of render x and ground truth y, [H, W, C] float CPU tensors of one dtype
// (kernels/cpu/ssim.cpp). Returns {total (0-d) = (1 - l) mean |x - y| + l (1 - mean SSIM), mean |x - y|,
// mean SSIM, grad [H, W, C] = d total / d x (empty unless want_grad), error [H, W] (empty unless
// want_error)}.
std::vector<Tensor> photometric_loss_cpu(Tensor x, Tensor y, double lambda_ssim, bool want_grad, bool want_error,
                                         int64_t num_threads) {
  TORCH_CHECK(x.device().is_cpu() && x.dim() == 3 && x.is_contiguous() &&
                  (x.scalar_type() == at::kFloat || x.scalar_type() == at::kDouble),
              "photometric_loss: render must be a contiguous float CPU tensor [H, W, C], got ", x.sizes(), " ",
              x.scalar_type());
  TORCH_CHECK(y.device().is_cpu() && y.is_contiguous() && y.scalar_type() == x.scalar_type() &&
                  y.sizes() == x.sizes(),
              "photometric_loss: ground truth must be a contiguous CPU tensor like the render ", x.sizes(), " ",
              x.scalar_type(), ", got ", y.sizes(), " ", y.scalar_type());
  TORCH_CHECK(lambda_ssim >= 0 && lambda_ssim <= 1, "photometric_loss: lambda_ssim must be in [0, 1]");
  const int64_t H = x.size(0), W = x.size(1), C = x.size(2);
  TORCH_CHECK(H * W * C < (int64_t(1) << 31), "photometric_loss: image too large");
  const int threads = int(num_threads > 0 ? num_threads : at::get_num_threads());
  Tensor grad = want_grad ? torch::empty_like(x) : torch::empty({0}, x.options());
  Tensor error = want_error ? torch::empty({H, W}, x.options()) : torch::empty({0}, x.options());
  double l1_sum = 0.0, ssim_sum = 0.0;
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "ctgs_photometric_loss_cpu", [&] {
    ctgs::cpu::photometric_loss<scalar_t>(x.data_ptr<scalar_t>(), y.data_ptr<scalar_t>(), int(H), int(W), int(C),
                                          lambda_ssim, want_grad ? grad.data_ptr<scalar_t>() : nullptr,
                                          want_error ? error.data_ptr<scalar_t>() : nullptr, &l1_sum, &ssim_sum,
                                          threads);
  });
  const double count = double(std::max<int64_t>(1, H * W * C));
  const double l1 = l1_sum / count, ssim = ssim_sum / count;
  const double total = (1 - lambda_ssim) * l1 + lambda_ssim * (1 - ssim);
  return {torch::scalar_tensor(total, x.options()), torch::scalar_tensor(l1, x.options()),
          torch::scalar_tensor(ssim, x.options()), grad, error};
}

// New jagged buffers [T', C] where new primitive j holds src[j]'s texels re-centred (ctgs/model/jagged.py
// remap, which checks the arguments): buffers [T, C] each, old_res [N, 2] int32, old_off [N] int64,
// src [N'] int64, shift [N', 2] int64, new_res [N', 2] int32, new_off [N'] int64; new_rows = T', the end of
// the new layout (the CUDA kernel needs it without reading the layout back; here it is checked).
std::vector<Tensor> jagged_remap_cpu(std::vector<Tensor> buffers, Tensor old_res, Tensor old_off, Tensor src,
                                     Tensor shift, Tensor new_res, Tensor new_off, int64_t new_rows_given,
                                     int64_t num_threads) {
  const int64_t N = old_res.size(0), M = src.size(0);
  check_tensor(old_res, "old_res", "[N, 2] int32", {N, 2}, at::kInt);
  check_tensor(old_off, "old_off", "[N] int64", {N}, at::kLong);
  check_tensor(src, "src", "[N'] int64", {M}, at::kLong);
  check_tensor(shift, "shift", "[N', 2] int64", {M, 2}, at::kLong);
  check_tensor(new_res, "new_res", "[N', 2] int32", {M, 2}, at::kInt);
  check_tensor(new_off, "new_off", "[N'] int64", {M}, at::kLong);
  const int32_t* ores = old_res.data_ptr<int32_t>();
  const int32_t* nres = new_res.data_ptr<int32_t>();
  const int64_t* ooff = old_off.data_ptr<int64_t>();
  const int64_t* noff = new_off.data_ptr<int64_t>();
  const int64_t* srcp = src.data_ptr<int64_t>();
  int64_t new_rows = 0;
  for (int64_t j = 0; j < M; ++j) {
    TORCH_CHECK(srcp[j] >= 0 && srcp[j] < N, "jagged_remap: src out of range");
    TORCH_CHECK(nres[2 * j] >= 0 && nres[2 * j + 1] >= 0, "jagged_remap: new_res must be >= 0");
    TORCH_CHECK(noff[j] >= 0, "jagged_remap: new_off must be >= 0");
    new_rows = std::max<int64_t>(new_rows, noff[j] + int64_t(nres[2 * j]) * nres[2 * j + 1]);
  }
  TORCH_CHECK(new_rows_given == new_rows, "jagged_remap: new_rows = ", new_rows_given, " but the new layout ends at row ",
              new_rows);
  int64_t packed_rows = 0;  // every row written iff the new layout has no gaps (jagged_offsets packs)
  for (int64_t j = 0; j < M; ++j) packed_rows += int64_t(nres[2 * j]) * nres[2 * j + 1];
  const int threads = int(num_threads > 0 ? num_threads : at::get_num_threads());
  std::vector<Tensor> out;
  for (const Tensor& b : buffers) {
    TORCH_CHECK(b.device().is_cpu() && b.dim() == 2 && b.is_contiguous() &&
                (b.scalar_type() == at::kFloat || b.scalar_type() == at::kDouble),
                "jagged_remap: buffers must be contiguous float CPU tensors [T, C], got ", b.sizes());
    for (int64_t j = 0; j < M && b.size(0) > 0; ++j) {
      const int64_t s = srcp[j];
      TORCH_CHECK(ores[2 * s] >= 0 && ores[2 * s + 1] >= 0 && ooff[s] >= 0 &&
                  ooff[s] + int64_t(ores[2 * s]) * ores[2 * s + 1] <= b.size(0),
                  "jagged_remap: old layout exceeds a buffer of ", b.size(0), " rows");
    }
    Tensor o = packed_rows == new_rows ? torch::empty({new_rows, b.size(1)}, b.options())
                                       : torch::zeros({new_rows, b.size(1)}, b.options());
    AT_DISPATCH_FLOATING_TYPES(b.scalar_type(), "ctgs_jagged_remap_cpu", [&] {
      ctgs::cpu::jagged_remap<scalar_t>(b.data_ptr<scalar_t>(), b.size(0), o.data_ptr<scalar_t>(), int(b.size(1)),
                                        ores, reinterpret_cast<const long long*>(ooff),
                                        reinterpret_cast<const long long*>(srcp),
                                        reinterpret_cast<const long long*>(shift.data_ptr<int64_t>()), nres,
                                        reinterpret_cast<const long long*>(noff), M, threads);
    });
    out.push_back(o);
  }
  return out;
}

}  // namespace

// The CPU kernels of ctgs's ops (torch.ops.ctgs.<op>; their schemas: ctgs/ops/schemas.py). The first seven have
// CUDA kernels too (kernels/bindings_cuda.cpp); the rest are CPU-only passes, whose callers use PyTorch elsewhere.
TORCH_LIBRARY_IMPL(ctgs, CPU, m) {
  m.impl("rasterize_forward", &forward_cpu);
  m.impl("rasterize_backward", &backward_cpu);
  m.impl("camera_space", &camera_space_cpu);
  m.impl("camera_space_backward", &camera_space_backward_cpu);
  m.impl("sh_color", &sh_color_cpu);
  m.impl("sh_color_backward", &sh_color_backward_cpu);
  m.impl("jagged_remap", &jagged_remap_cpu);
  m.impl("rasterize_backward_stats", &backward_stats_cpu);
  m.impl("rasterize_pairs", &forward_pairs_cpu);
  m.impl("accumulate_pairs", &accumulate_pairs_cpu);
  m.impl("adam_step", &adam_step_cpu);
  m.impl("texel_l1_forward", &texel_l1_forward_cpu);
  m.impl("texel_l1_backward", &texel_l1_backward_cpu);
  m.impl("texel_abs_forward", &texel_abs_forward_cpu);
  m.impl("texel_abs_backward", &texel_abs_backward_cpu);
  m.impl("texel_activation", &texel_activation_cpu);
  m.impl("texel_activation_backward", &texel_activation_backward_cpu);
  m.impl("texel_activation_backward_l1", &texel_activation_backward_l1_cpu);
  m.impl("surfel_values_ok", &surfel_values_ok_cpu);
  m.impl("surfel_value_flags", &surfel_value_flags_cpu);
  m.impl("photometric_loss", &photometric_loss_cpu);
}

// The module torch's loader imports; the ops above are reached through torch.ops.ctgs, not through it.
PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.doc() = "ctgs textured 2D Gaussian surfel rasterizer, C++/OpenMP CPU backend (see docs/reference/renderer.md)";
  m.def("tile_size", [] { return ctgs::TILE_SIZE; });
  m.def("profile_counters", [](bool reset) {
    const std::vector<double> v = ctgs::cpu::prof_read(reset);
    std::map<std::string, double> out;
    for (int k = 0; k < ctgs::cpu::PROF_COUNT; ++k) out[ctgs::cpu::PROF_NAMES[k]] = v[k];
    return out;
  }, "wall-clock seconds per kernel phase since the last reset (benchmarks/profile_train.py)",
  py::arg("reset") = true);
}
