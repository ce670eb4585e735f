// The only file that knows torch: checks every tensor (shape, dtype, device, contiguity), allocates
// outputs and dispatches float/double to the raw-pointer cores in kernels/cpu (and, later, kernels/cuda).
#include <torch/extension.h>

#include <vector>

#include "cpu/rasterize.h"

namespace {

using torch::Tensor;

void check_tensor(const Tensor& t, const char* name, const char* shape, std::vector<int64_t> sizes,
                  at::ScalarType dtype) {
  TORCH_CHECK(t.device().is_cpu(), name, " must be a CPU tensor for the cpu backend, got ", t.device());
  TORCH_CHECK(t.scalar_type() == dtype, name, " must have dtype ", dtype, ", got ", t.scalar_type());
  TORCH_CHECK(t.dim() == int64_t(sizes.size()), name, " must have shape ", shape, ", got ", t.sizes());
  for (size_t k = 0; k < sizes.size(); ++k)
    TORCH_CHECK(sizes[k] < 0 || t.size(k) == sizes[k], name, " must have shape ", shape, ", got ", t.sizes());
  TORCH_CHECK(t.is_contiguous(), name, " must be contiguous");
}

struct Scene {
  Tensor mu_c, Rc, scales, opacities, colors, texel_size, textures, tex_res, tex_offset, background;
  double fx, fy, cx, cy, near_plane;
  int64_t width, height, num_threads;
};

Scene check_scene(Tensor mu_c, Tensor Rc, Tensor scales, Tensor opacities, Tensor colors, Tensor texel_size,
                  Tensor textures, Tensor tex_res, Tensor tex_offset, Tensor background, double fx, double fy,
                  double cx, double cy, int64_t width, int64_t height, double near_plane, int64_t num_threads) {
  const int64_t N = mu_c.size(0);
  const auto dt = mu_c.scalar_type();
  TORCH_CHECK(dt == at::kFloat || dt == at::kDouble, "mu_c must be float32 or float64, got ", dt);
  check_tensor(mu_c, "mu_c", "[N, 3]", {N, 3}, dt);
  check_tensor(Rc, "Rc", "[N, 3, 3]", {N, 3, 3}, dt);
  check_tensor(scales, "scales", "[N, 2]", {N, 2}, dt);
  check_tensor(opacities, "opacities", "[N]", {N}, dt);
  check_tensor(colors, "colors", "[N, 3]", {N, 3}, dt);
  check_tensor(texel_size, "texel_size", "[N, 2]", {N, 2}, dt);
  check_tensor(textures, "textures", "[T, 3]", {-1, 3}, dt);
  check_tensor(tex_res, "tex_res", "[N, 2] int32", {N, 2}, at::kInt);
  check_tensor(tex_offset, "tex_offset", "[N] int64", {N}, at::kLong);
  check_tensor(background, "background", "[3]", {3}, dt);
  TORCH_CHECK(N <= INT32_MAX, "at most 2^31-1 primitives, got ", N);
  TORCH_CHECK(width >= 1 && height >= 1, "image size must be >= 1x1, got ", width, "x", height);
  TORCH_CHECK(fx != 0.0 && fy != 0.0, "focal lengths must be non-zero");
  // Out-of-range texel rows would read (and, in backward, write) outside `textures`.
  const int32_t* res = tex_res.data_ptr<int32_t>();
  const int64_t* off = tex_offset.data_ptr<int64_t>();
  const int64_t T = textures.size(0);
  for (int64_t i = 0; i < N; ++i) {
    const int64_t ru = res[2 * i], rv = res[2 * i + 1];
    TORCH_CHECK(ru >= 0 && rv >= 0, "tex_res must be >= 0, got ", ru, "x", rv, " at primitive ", i);
    if (ru == 0 || rv == 0) continue;
    TORCH_CHECK(off[i] >= 0 && off[i] + ru * rv <= T, "tex_offset[", i, "] + res_u*res_v = ", off[i] + ru * rv,
                " exceeds the texel count T = ", T);
  }
  return Scene{mu_c, Rc, scales, opacities, colors, texel_size, textures, tex_res, tex_offset, background,
               fx, fy, cx, cy, near_plane, width, height, num_threads};
}

template <typename S>
ctgs::cpu::SceneArgs<S> scene_args(const Scene& s) {
  ctgs::cpu::SceneArgs<S> a;
  a.N = int(s.mu_c.size(0));
  a.mu_c = s.mu_c.data_ptr<S>();
  a.Rc = s.Rc.data_ptr<S>();
  a.scales = s.scales.data_ptr<S>();
  a.opacities = s.opacities.data_ptr<S>();
  a.colors = s.colors.data_ptr<S>();
  a.texel_size = s.texel_size.data_ptr<S>();
  a.textures = s.textures.data_ptr<S>();
  a.T = s.textures.size(0);
  a.tex_res = s.tex_res.data_ptr<int32_t>();
  a.tex_offset = reinterpret_cast<const long long*>(s.tex_offset.data_ptr<int64_t>());
  a.background = s.background.data_ptr<S>();
  a.K = ctgs::Intrinsics<S>{S(s.fx), S(s.fy), S(s.cx), S(s.cy), S(s.near_plane), int(s.width), int(s.height)};
  a.num_threads = int(s.num_threads > 0 ? s.num_threads : at::get_num_threads());
  return a;
}

// Returns rgb [H,W,3], alpha [H,W], depth [H,W], final_T [H,W], n_contrib [H,W] int32, tile_offsets
// [tiles+1] int64, tile_list [pairs] int32, count [N] int32, contrib [N], err [N] (the last three empty
// unless error_image [H,W] is given). With poison=true outputs start as NaN, so unwritten pixels show up.
std::vector<Tensor> forward_cpu(Tensor mu_c, Tensor Rc, Tensor scales, Tensor opacities, Tensor colors,
                                Tensor texel_size, Tensor textures, Tensor tex_res, Tensor tex_offset,
                                Tensor background, double fx, double fy, double cx, double cy, int64_t width,
                                int64_t height, double near_plane, c10::optional<Tensor> error_image,
                                int64_t num_threads, bool poison) {
  const Scene s = check_scene(mu_c, Rc, scales, opacities, colors, texel_size, textures, tex_res, tex_offset,
                              background, fx, fy, cx, cy, width, height, near_plane, num_threads);
  const int64_t N = mu_c.size(0), H = height, W = width;
  const bool stats = error_image.has_value();
  if (stats) check_tensor(*error_image, "error_image", "[H, W]", {H, W}, mu_c.scalar_type());
  auto fopt = mu_c.options();
  auto make = [&](std::vector<int64_t> sz) {
    return poison ? torch::full(sz, std::numeric_limits<double>::quiet_NaN(), fopt) : torch::empty(sz, fopt);
  };
  Tensor rgb = make({H, W, 3}), alpha = make({H, W}), depth = make({H, W}), final_T = make({H, W});
  Tensor n_contrib = poison ? torch::full({H, W}, -1, fopt.dtype(at::kInt)) : torch::empty({H, W}, fopt.dtype(at::kInt));
  Tensor count = torch::zeros({stats ? N : 0}, fopt.dtype(at::kInt));
  Tensor contrib = torch::zeros({stats ? N : 0}, fopt), err = torch::zeros({stats ? N : 0}, fopt);
  ctgs::cpu::TileBins bins;
  AT_DISPATCH_FLOATING_TYPES(mu_c.scalar_type(), "ctgs_forward_cpu", [&] {
    ctgs::cpu::ForwardOut<scalar_t> o;
    o.rgb = rgb.data_ptr<scalar_t>();
    o.alpha = alpha.data_ptr<scalar_t>();
    o.depth = depth.data_ptr<scalar_t>();
    o.final_T = final_T.data_ptr<scalar_t>();
    o.n_contrib = n_contrib.data_ptr<int32_t>();
    o.error_image = stats ? error_image->data_ptr<scalar_t>() : nullptr;
    o.count = stats ? count.data_ptr<int32_t>() : nullptr;
    o.contrib = stats ? contrib.data_ptr<scalar_t>() : nullptr;
    o.err = stats ? err.data_ptr<scalar_t>() : nullptr;
    ctgs::cpu::forward<scalar_t>(scene_args<scalar_t>(s), o, &bins);
  });
  Tensor tile_offsets = torch::from_blob(bins.offsets.data(), {int64_t(bins.offsets.size())}, at::kLong).clone();
  Tensor tile_list = torch::from_blob(bins.list.data(), {int64_t(bins.list.size())}, at::kInt).clone();
  return {rgb, alpha, depth, final_T, n_contrib, tile_offsets, tile_list, count, contrib, err};
}

// Returns v_mu_c [N,3], v_Rc [N,3,3], v_scales [N,2], v_opacities [N], v_colors [N,3], v_texel_size [N,2],
// v_textures [T,3], v_background [3].
std::vector<Tensor> backward_cpu(Tensor mu_c, Tensor Rc, Tensor scales, Tensor opacities, Tensor colors,
                                 Tensor texel_size, Tensor textures, Tensor tex_res, Tensor tex_offset,
                                 Tensor background, double fx, double fy, double cx, double cy, int64_t width,
                                 int64_t height, double near_plane, Tensor tile_offsets, Tensor tile_list,
                                 Tensor final_T, Tensor n_contrib, Tensor v_rgb, Tensor v_alpha, Tensor v_depth,
                                 int64_t num_threads) {
  const Scene s = check_scene(mu_c, Rc, scales, opacities, colors, texel_size, textures, tex_res, tex_offset,
                              background, fx, fy, cx, cy, width, height, near_plane, num_threads);
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
  Tensor v_mu_c = torch::empty_like(mu_c), v_Rc = torch::empty_like(Rc), v_scales = torch::empty_like(scales);
  Tensor v_opacities = torch::empty_like(opacities), v_colors = torch::empty_like(colors);
  Tensor v_texel_size = torch::empty_like(texel_size), v_textures = torch::empty_like(textures);
  Tensor v_background = torch::empty_like(background);
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
                                  v_alpha.data_ptr<scalar_t>(), v_depth.data_ptr<scalar_t>(), o);
  });
  return {v_mu_c, v_Rc, v_scales, v_opacities, v_colors, v_texel_size, v_textures, v_background};
}

}  // namespace

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.doc() = "ctgs textured 2D Gaussian surfel rasterizer, C++/OpenMP CPU backend (see docs/renderer.md)";
  m.def("forward_cpu", &forward_cpu, "forward (returns rgb, alpha, depth, final_T, n_contrib, tile_offsets, "
        "tile_list, count, contrib, err)");
  m.def("backward_cpu", &backward_cpu, "backward (returns v_mu_c, v_Rc, v_scales, v_opacities, v_colors, "
        "v_texel_size, v_textures, v_background)");
  m.def("tile_size", [] { return ctgs::TILE_SIZE; });
}
