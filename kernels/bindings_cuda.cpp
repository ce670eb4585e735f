// Torch binding of the CUDA backend (module ctgs_cuda): checks every tensor (shape, dtype, device,
// contiguity), allocates outputs and scratch from torch's caching allocator, and dispatches float/double to
// the raw-pointer cores in kernels/cuda on the current CUDA stream. Its kernels are registered for the CUDA
// dispatch key of the ops the CPU binding (kernels/bindings.cpp) implements too: one schema each
// (ctgs/ops/schemas.py), and torch.ops.ctgs.<op> runs the kernel of its tensors' device.
#ifndef CTGS_WITH_CUDA
#error "bindings_cuda.cpp is the CUDA backend's binding: build it with -DCTGS_WITH_CUDA (ctgs/ops/ext_cuda.py)"
#endif

#include <c10/cuda/CUDAStream.h>
#include <c10/cuda/CUDAGuard.h>
#include <torch/extension.h>

#include <algorithm>
#include <limits>
#include <vector>

#include "binding_common.h"
#include "cuda/rasterize.cuh"

namespace {

using torch::Tensor;

using ctgs_binding::check_scene;
using ctgs_binding::check_tensor;
using ctgs_binding::Scene;
using ctgs_binding::scene_args;

// Scratch tensors live until the binding returns; the kernels that use them are queued on the same stream,
// which is what the caching allocator needs to recycle them safely.
struct TorchAllocators {
  std::vector<Tensor> keep;
  Tensor tile_list;
  ctgs::gpu::Allocators make(const at::Device& dev) {
    ctgs::gpu::Allocators a;
    a.scratch = [this, dev](size_t bytes) -> void* {
      // Never a null pointer (an empty tensor's): cub reads a null temp buffer as a size query.
      keep.push_back(torch::empty({int64_t(std::max<size_t>(bytes, 16))}, torch::dtype(at::kByte).device(dev)));
      return keep.back().data_ptr();
    };
    a.tile_list = [this, dev](int64_t pairs) -> int32_t* {
      tile_list = torch::empty({pairs}, torch::dtype(at::kInt).device(dev));
      return tile_list.data_ptr<int32_t>();
    };
    return a;
  }
};

// Returns rgb [H,W,3], alpha [H,W], depth [H,W], final_T [H,W], n_contrib [H,W] int32, tile_offsets
// [tiles+1] int64, tile_list [pairs] int32, count [N] int32, contrib [N], err [N] (the last three empty
// unless error_image [H,W] is given), then two empty tensors where the CPU kernel returns its opaque setup (one
// schema for both: ctgs/ops/schemas.py), then median [H,W] (the median depth, no gradient) and depth2 [H,W] (sum of
// w z^2). num_threads is part of that schema and ignored here.
// With poison=true outputs start as NaN, so unwritten pixels show up.
std::vector<Tensor> forward_cuda(Tensor mu_c, Tensor Rc, Tensor scales, Tensor opacities, Tensor colors,
                                 Tensor texel_size, Tensor textures, Tensor tex_res, Tensor tex_offset,
                                 Tensor background, double fx, double fy, double cx, double cy, int64_t width,
                                 int64_t height, double near_plane, c10::optional<Tensor> error_image,
                                 int64_t num_threads, bool poison) {
  const Scene s = check_scene(mu_c, Rc, scales, opacities, colors, texel_size, textures, tex_res, tex_offset,
                              background, fx, fy, cx, cy, width, height, near_plane, 0, at::kCUDA, "cuda");
  const c10::cuda::CUDAGuard guard(mu_c.device());
  const int64_t N = mu_c.size(0), H = height, W = width;
  const bool stats = error_image.has_value();
  if (stats) check_tensor(*error_image, "error_image", "[H, W]", {H, W}, mu_c.scalar_type(), mu_c.device());
  auto fopt = mu_c.options();
  auto make = [&](std::vector<int64_t> sz) {
    return poison ? torch::full(sz, std::numeric_limits<double>::quiet_NaN(), fopt) : torch::empty(sz, fopt);
  };
  Tensor rgb = make({H, W, 3}), alpha = make({H, W}), depth = make({H, W}), final_T = make({H, W});
  Tensor median = make({H, W}), depth2 = make({H, W});
  const auto iopt = fopt.dtype(at::kInt);
  Tensor n_contrib = poison ? torch::full({H, W}, -1, iopt) : torch::empty({H, W}, iopt);
  const int64_t num_tiles = int64_t(ctgs::tiles_x(int(W))) * ctgs::tiles_y(int(H));
  Tensor tile_offsets = torch::empty({num_tiles + 1}, fopt.dtype(at::kLong));
  Tensor count = torch::zeros({stats ? N : 0}, fopt.dtype(at::kInt));
  Tensor contrib = torch::zeros({stats ? N : 0}, fopt), err = torch::zeros({stats ? N : 0}, fopt);
  TorchAllocators alloc;
  const cudaStream_t stream = c10::cuda::getCurrentCUDAStream().stream();
  AT_DISPATCH_FLOATING_TYPES(mu_c.scalar_type(), "ctgs_forward_cuda", [&] {
    ctgs::gpu::ForwardOut<scalar_t> o;
    o.rgb = rgb.data_ptr<scalar_t>();
    o.alpha = alpha.data_ptr<scalar_t>();
    o.depth = depth.data_ptr<scalar_t>();
    o.median = median.data_ptr<scalar_t>();
    o.depth2 = depth2.data_ptr<scalar_t>();
    o.final_T = final_T.data_ptr<scalar_t>();
    o.n_contrib = n_contrib.data_ptr<int32_t>();
    o.tile_offsets = tile_offsets.data_ptr<int64_t>();
    o.error_image = stats ? error_image->data_ptr<scalar_t>() : nullptr;
    o.count = stats ? count.data_ptr<int32_t>() : nullptr;
    o.contrib = stats ? contrib.data_ptr<scalar_t>() : nullptr;
    o.err = stats ? err.data_ptr<scalar_t>() : nullptr;
    ctgs::gpu::forward<scalar_t>(scene_args<scalar_t>(s), o, alloc.make(mu_c.device()), stream);
  });
  const Tensor no_setup = torch::empty({0}, fopt.dtype(at::kByte));
  return {rgb, alpha, depth, final_T, n_contrib, tile_offsets, alloc.tile_list, count, contrib, err,
          no_setup, no_setup.to(at::kInt), median, depth2};
}

// Returns v_mu_c [N,3], v_Rc [N,3,3], v_scales [N,2], v_opacities [N], v_colors [N,3], v_texel_size [N,2],
// v_textures [T,3], v_background [3]. The setup tensors (the CPU kernel's) are ignored: the kernels here
// recompute what they need per tile. v_depth2 [H, W]: the gradient of the forward's depth2 (None: zero).
std::vector<Tensor> backward_cuda(Tensor mu_c, Tensor Rc, Tensor scales, Tensor opacities, Tensor colors,
                                  Tensor texel_size, Tensor textures, Tensor tex_res, Tensor tex_offset,
                                  Tensor background, double fx, double fy, double cx, double cy, int64_t width,
                                  int64_t height, double near_plane, Tensor tile_offsets, Tensor tile_list,
                                  Tensor final_T, Tensor n_contrib, Tensor v_rgb, Tensor v_alpha, Tensor v_depth,
                                  int64_t num_threads, c10::optional<Tensor> /*setup_prims*/,
                                  c10::optional<Tensor> /*setup_spans*/, c10::optional<Tensor> v_depth2) {
  const Scene s = check_scene(mu_c, Rc, scales, opacities, colors, texel_size, textures, tex_res, tex_offset,
                              background, fx, fy, cx, cy, width, height, near_plane, 0, at::kCUDA, "cuda");
  const c10::cuda::CUDAGuard guard(mu_c.device());
  const at::Device dev = mu_c.device();
  const int64_t H = height, W = width;
  const auto dt = mu_c.scalar_type();
  const int64_t num_tiles = int64_t(ctgs::tiles_x(int(W))) * ctgs::tiles_y(int(H));
  check_tensor(tile_offsets, "tile_offsets", "[tiles + 1] int64", {num_tiles + 1}, at::kLong, dev);
  check_tensor(tile_list, "tile_list", "[pairs] int32", {-1}, at::kInt, dev);
  TORCH_CHECK(tile_offsets[num_tiles].item<int64_t>() == tile_list.size(0), "tile_offsets/tile_list mismatch");
  check_tensor(final_T, "final_T", "[H, W]", {H, W}, dt, dev);
  check_tensor(n_contrib, "n_contrib", "[H, W] int32", {H, W}, at::kInt, dev);
  check_tensor(v_rgb, "v_rgb", "[H, W, 3]", {H, W, 3}, dt, dev);
  check_tensor(v_alpha, "v_alpha", "[H, W]", {H, W}, dt, dev);
  check_tensor(v_depth, "v_depth", "[H, W]", {H, W}, dt, dev);
  if (v_depth2.has_value()) check_tensor(*v_depth2, "v_depth2", "[H, W]", {H, W}, dt, dev);
  Tensor v_mu_c = torch::empty_like(mu_c), v_Rc = torch::empty_like(Rc), v_scales = torch::empty_like(scales);
  Tensor v_opacities = torch::empty_like(opacities), v_colors = torch::empty_like(colors);
  Tensor v_texel_size = torch::empty_like(texel_size), v_textures = torch::empty_like(textures);
  Tensor v_background = torch::empty_like(background);
  TorchAllocators alloc;
  const cudaStream_t stream = c10::cuda::getCurrentCUDAStream().stream();
  AT_DISPATCH_FLOATING_TYPES(dt, "ctgs_backward_cuda", [&] {
    ctgs::gpu::BackwardOut<scalar_t> o;
    o.v_mu_c = v_mu_c.data_ptr<scalar_t>();
    o.v_Rc = v_Rc.data_ptr<scalar_t>();
    o.v_scales = v_scales.data_ptr<scalar_t>();
    o.v_opacities = v_opacities.data_ptr<scalar_t>();
    o.v_colors = v_colors.data_ptr<scalar_t>();
    o.v_texel_size = v_texel_size.data_ptr<scalar_t>();
    o.v_textures = v_textures.data_ptr<scalar_t>();
    o.v_background = v_background.data_ptr<scalar_t>();
    const ctgs::gpu::TileBinsView bins{tile_offsets.data_ptr<int64_t>(), tile_list.data_ptr<int32_t>()};
    ctgs::gpu::backward<scalar_t>(scene_args<scalar_t>(s), bins, final_T.data_ptr<scalar_t>(),
                                  n_contrib.data_ptr<int32_t>(), v_rgb.data_ptr<scalar_t>(),
                                  v_alpha.data_ptr<scalar_t>(), v_depth.data_ptr<scalar_t>(),
                                  v_depth2.has_value() ? v_depth2->data_ptr<scalar_t>() : nullptr, o,
                                  alloc.make(dev), stream);
  });
  return {v_mu_c, v_Rc, v_scales, v_opacities, v_colors, v_texel_size, v_textures, v_background};
}

// ---- per-primitive preprocessing (kernels/cuda/dense.cu): the CPU binding's camera_space / sh_color ----
// num_threads is accepted for symmetry with the CPU binding and ignored.

void check_float_cuda(const Tensor& t, const char* fn, const char* name, const char* shape) {
  TORCH_CHECK(t.is_cuda() && t.is_contiguous() && (t.scalar_type() == at::kFloat || t.scalar_type() == at::kDouble),
              fn, ": ", name, " must be a contiguous float CUDA tensor ", shape, ", got ", t.sizes(), " ",
              t.scalar_type(), " on ", t.device());
}

// {mu_c [N, 3], Rc [N, 3, 3]}: the primitives in the camera space of view [4, 4].
std::vector<Tensor> camera_space_cuda(Tensor means, Tensor quats, Tensor view, int64_t num_threads) {
  check_float_cuda(quats, "camera_space", "quats", "[N, 4]");
  const int64_t n = quats.size(0);
  check_tensor(quats, "quats", "[N, 4]", {n, 4}, quats.scalar_type(), quats.device());
  check_tensor(means, "means", "[N, 3]", {n, 3}, quats.scalar_type(), quats.device());
  check_tensor(view, "view", "[4, 4]", {4, 4}, quats.scalar_type(), quats.device());
  const c10::cuda::CUDAGuard guard(quats.device());
  Tensor mu_c = torch::empty({n, 3}, quats.options()), Rc = torch::empty({n, 3, 3}, quats.options());
  const cudaStream_t stream = c10::cuda::getCurrentCUDAStream().stream();
  AT_DISPATCH_FLOATING_TYPES(quats.scalar_type(), "ctgs_camera_space_cuda", [&] {
    ctgs::gpu::camera_space<scalar_t>(means.data_ptr<scalar_t>(), quats.data_ptr<scalar_t>(),
                                      view.data_ptr<scalar_t>(), n, mu_c.data_ptr<scalar_t>(),
                                      Rc.data_ptr<scalar_t>(), stream);
  });
  return {mu_c, Rc};
}

// {grad_means [N, 3], grad_quats [N, 4]} of camera_space_cuda for the upstream gradients.
std::vector<Tensor> camera_space_backward_cuda(Tensor quats, Tensor view, Tensor grad_mu_c, Tensor grad_Rc,
                                               int64_t num_threads) {
  check_float_cuda(quats, "camera_space_backward", "quats", "[N, 4]");
  const int64_t n = quats.size(0);
  const auto dt = quats.scalar_type();
  const at::Device dev = quats.device();
  check_tensor(quats, "quats", "[N, 4]", {n, 4}, dt, dev);
  check_tensor(view, "view", "[4, 4]", {4, 4}, dt, dev);
  check_tensor(grad_mu_c, "grad_mu_c", "[N, 3]", {n, 3}, dt, dev);
  check_tensor(grad_Rc, "grad_Rc", "[N, 3, 3]", {n, 3, 3}, dt, dev);
  const c10::cuda::CUDAGuard guard(dev);
  Tensor gm = torch::empty({n, 3}, quats.options()), gq = torch::empty_like(quats);
  const cudaStream_t stream = c10::cuda::getCurrentCUDAStream().stream();
  AT_DISPATCH_FLOATING_TYPES(dt, "ctgs_camera_space_backward_cuda", [&] {
    ctgs::gpu::camera_space_backward<scalar_t>(quats.data_ptr<scalar_t>(), view.data_ptr<scalar_t>(), n,
                                               grad_mu_c.data_ptr<scalar_t>(), grad_Rc.data_ptr<scalar_t>(),
                                               gm.data_ptr<scalar_t>(), gq.data_ptr<scalar_t>(), stream);
  });
  return {gm, gq};
}

void check_sh_args_cuda(const Tensor& means, const Tensor& center, const Tensor& sh, int64_t degree) {
  check_float_cuda(means, "sh_color", "means", "[N, 3]");
  check_tensor(means, "means", "[N, 3]", {means.size(0), 3}, means.scalar_type(), means.device());
  check_tensor(center, "center", "[3]", {3}, means.scalar_type(), means.device());
  check_tensor(sh, "sh", "[N, K, 3]", {means.size(0), -1, 3}, means.scalar_type(), means.device());
  TORCH_CHECK(degree >= 0 && degree <= 3 && sh.size(1) >= (degree + 1) * (degree + 1),
              "sh_color: degree ", degree, " needs (degree + 1)^2 <= K = ", sh.size(1), " and degree in 0..3");
}

// colors [N, 3] = SH_degree(normalize(means - center)) + 0.5.
Tensor sh_color_cuda(Tensor means, Tensor center, Tensor sh, int64_t degree, int64_t num_threads) {
  check_sh_args_cuda(means, center, sh, degree);
  const c10::cuda::CUDAGuard guard(means.device());
  Tensor colors = torch::empty_like(means);
  const cudaStream_t stream = c10::cuda::getCurrentCUDAStream().stream();
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "ctgs_sh_color_cuda", [&] {
    ctgs::gpu::sh_color<scalar_t>(means.data_ptr<scalar_t>(), center.data_ptr<scalar_t>(), sh.data_ptr<scalar_t>(),
                                  means.size(0), int(sh.size(1)), int(degree), colors.data_ptr<scalar_t>(), stream);
  });
  return colors;
}

// {grad_means [N, 3], grad_sh [N, K, 3]} of sh_color_cuda for the upstream gradient grad_colors [N, 3].
std::vector<Tensor> sh_color_backward_cuda(Tensor means, Tensor center, Tensor sh, int64_t degree, Tensor grad_colors,
                                           int64_t num_threads) {
  check_sh_args_cuda(means, center, sh, degree);
  check_tensor(grad_colors, "grad_colors", "[N, 3]", {means.size(0), 3}, means.scalar_type(), means.device());
  const c10::cuda::CUDAGuard guard(means.device());
  Tensor gm = torch::empty_like(means), gs = torch::empty_like(sh);
  const cudaStream_t stream = c10::cuda::getCurrentCUDAStream().stream();
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "ctgs_sh_color_backward_cuda", [&] {
    ctgs::gpu::sh_color_backward<scalar_t>(means.data_ptr<scalar_t>(), center.data_ptr<scalar_t>(),
                                           sh.data_ptr<scalar_t>(), means.size(0), int(sh.size(1)), int(degree),
                                           grad_colors.data_ptr<scalar_t>(), gm.data_ptr<scalar_t>(),
                                           gs.data_ptr<scalar_t>(), stream);
  });
  return {gm, gs};
}

// New jagged buffers [new_rows, C] (ctgs/model/jagged.py remap, which builds the arguments): buffers [T, C] (1-4,
// one dtype and C), old_res [N, 2] int32, old_off [N] int64, src [N'] int64, shift [N', 2] int64, new_res [N', 2]
// int32, new_off [N'] int64 packed (jagged_offsets of new_res) and new_rows = the sum of new_res' products (the
// caller has it; finding it here would cost a synchronisation). Unlike the CPU binding, the values of the
// layouts are not checked (that needs the host): reads past a buffer's end give 0.
std::vector<Tensor> jagged_remap_cuda(std::vector<Tensor> buffers, Tensor old_res, Tensor old_off, Tensor src,
                                      Tensor shift, Tensor new_res, Tensor new_off, int64_t new_rows,
                                      int64_t /*num_threads*/) {
  TORCH_CHECK(!buffers.empty() && buffers.size() <= 4, "jagged_remap: 1 to 4 buffers, got ", buffers.size());
  const at::Device dev = buffers[0].device();
  const auto dt = buffers[0].scalar_type();
  TORCH_CHECK(buffers[0].is_cuda() && (dt == at::kFloat || dt == at::kDouble) && buffers[0].dim() == 2,
              "jagged_remap: buffers must be float CUDA tensors [T, C]");
  const int64_t C = buffers[0].size(1), N = old_res.size(0), M = src.size(0);
  for (const Tensor& b : buffers)
    TORCH_CHECK(b.device() == dev && b.scalar_type() == dt && b.dim() == 2 && b.size(1) == C && b.is_contiguous(),
                "jagged_remap: buffers must be contiguous [T, ", C, "] ", dt, " tensors on ", dev, ", got ", b.sizes());
  check_tensor(old_res, "old_res", "[N, 2] int32", {N, 2}, at::kInt, dev);
  check_tensor(old_off, "old_off", "[N] int64", {N}, at::kLong, dev);
  check_tensor(src, "src", "[N'] int64", {M}, at::kLong, dev);
  check_tensor(shift, "shift", "[N', 2] int64", {M, 2}, at::kLong, dev);
  check_tensor(new_res, "new_res", "[N', 2] int32", {M, 2}, at::kInt, dev);
  check_tensor(new_off, "new_off", "[N'] int64", {M}, at::kLong, dev);
  TORCH_CHECK(new_rows >= 0, "jagged_remap: new_rows must be >= 0");
  const c10::cuda::CUDAGuard guard(dev);
  std::vector<Tensor> out;
  for (const Tensor& b : buffers) out.push_back(torch::empty({new_rows, C}, b.options()));
  const cudaStream_t stream = c10::cuda::getCurrentCUDAStream().stream();
  AT_DISPATCH_FLOATING_TYPES(dt, "ctgs_jagged_remap_cuda", [&] {
    ctgs::gpu::RemapBuffers<scalar_t> rb{};
    rb.count = int(buffers.size());
    for (int b = 0; b < rb.count; ++b) {
      rb.in[b] = buffers[b].data_ptr<scalar_t>();
      rb.out[b] = out[b].data_ptr<scalar_t>();
      rb.old_rows[b] = buffers[b].size(0);
    }
    ctgs::gpu::jagged_remap<scalar_t>(rb, int(C), old_res.data_ptr<int32_t>(), old_off.data_ptr<int64_t>(),
                                      src.data_ptr<int64_t>(), shift.data_ptr<int64_t>(), new_res.data_ptr<int32_t>(),
                                      new_off.data_ptr<int64_t>(), M, new_rows, stream);
  });
  return out;
}

// int32 0-dim on the device: 0 if every value check of render()'s validate_inputs passes (the CPU's
// surfel_values_ok), else not; one kernel over the primitives and texel rows, no synchronisation.
Tensor surfel_value_flags_cuda(Tensor means, Tensor quats, Tensor scales, Tensor opacities, Tensor sh,
                               Tensor texel_size, Tensor textures, Tensor tex_res, Tensor tex_offset,
                               int64_t num_threads) {
  const auto dt = means.scalar_type();
  TORCH_CHECK(means.is_cuda() && (dt == at::kFloat || dt == at::kDouble),
              "surfel_value_flags: means must be a float32 or float64 CUDA tensor");
  const int64_t n = means.size(0);
  for (const Tensor* t : {&means, &quats, &scales, &opacities, &sh, &texel_size, &textures})
    TORCH_CHECK(t->device() == means.device() && t->is_contiguous() && t->scalar_type() == dt &&
                    (t == &textures || t->size(0) == n),
                "surfel_value_flags: float tensors must be contiguous, on means' device and dtype, with N rows");
  TORCH_CHECK(means.numel() == 3 * n && quats.numel() == 4 * n && scales.numel() == 2 * n && opacities.numel() == n &&
                  (texel_size.numel() == n || texel_size.numel() == 2 * n) && textures.dim() == 2 &&
                  textures.size(1) == 3,
              "surfel_value_flags: means [N, 3], quats [N, 4], scales [N, 2], opacities [N], texel_size [N] or [N, 2], "
              "textures [T, 3]");
  check_tensor(tex_res, "tex_res", "[N, 2] int32", {n, 2}, at::kInt, means.device());
  check_tensor(tex_offset, "tex_offset", "[N] int64", {n}, at::kLong, means.device());
  const c10::cuda::CUDAGuard guard(means.device());
  Tensor flag = torch::zeros({}, means.options().dtype(at::kInt));
  const cudaStream_t stream = c10::cuda::getCurrentCUDAStream().stream();
  const int ts_row = n > 0 && texel_size.numel() == 2 * n ? 2 : 1;
  const int64_t sh_row = n > 0 ? sh.numel() / n : 0;
  AT_DISPATCH_FLOATING_TYPES(dt, "ctgs_surfel_value_flags_cuda", [&] {
    ctgs::gpu::surfel_value_flags<scalar_t>(
        means.data_ptr<scalar_t>(), quats.data_ptr<scalar_t>(), scales.data_ptr<scalar_t>(),
        opacities.data_ptr<scalar_t>(), sh.data_ptr<scalar_t>(), sh_row, texel_size.data_ptr<scalar_t>(), ts_row,
        textures.data_ptr<scalar_t>(), textures.size(0), tex_res.data_ptr<int32_t>(), tex_offset.data_ptr<int64_t>(),
        n, flag.data_ptr<int32_t>(), stream);
  });
  return flag;
}

}  // namespace

// The CUDA kernels of ctgs's ops that both backends have (torch.ops.ctgs.<op>; their schemas: ctgs/ops/schemas.py).
TORCH_LIBRARY_IMPL(ctgs, CUDA, m) {
  m.impl("rasterize_forward", &forward_cuda);
  m.impl("rasterize_backward", &backward_cuda);
  m.impl("camera_space", &camera_space_cuda);
  m.impl("camera_space_backward", &camera_space_backward_cuda);
  m.impl("sh_color", &sh_color_cuda);
  m.impl("sh_color_backward", &sh_color_backward_cuda);
  m.impl("jagged_remap", &jagged_remap_cuda);
  m.impl("surfel_value_flags", &surfel_value_flags_cuda);
}

// The module torch's loader imports; the ops above are reached through torch.ops.ctgs, not through it.
PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.doc() = "ctgs textured 2D Gaussian surfel rasterizer, CUDA backend (see docs/reference/renderer.md)";
  m.def("tile_size", [] { return ctgs::TILE_SIZE; });
}
