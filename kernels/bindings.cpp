// The only file that knows torch: checks every tensor (shape, dtype, device, contiguity), allocates
// outputs and dispatches float/double to the raw-pointer cores in kernels/cpu (and, later, kernels/cuda).
#include <torch/extension.h>

#include <map>
#include <string>
#include <vector>

#include "binding_common.h"
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

// Returns rgb [H,W,3], alpha [H,W], depth [H,W], final_T [H,W], n_contrib [H,W] int32, tile_offsets
// [tiles+1] int64, tile_list [pairs] int32, count [N] int32, contrib [N], err [N] (the last three empty
// unless error_image [H,W] is given). With poison=true outputs start as NaN, so unwritten pixels show up.
std::vector<Tensor> forward_cpu(Tensor mu_c, Tensor Rc, Tensor scales, Tensor opacities, Tensor colors,
                                Tensor texel_size, Tensor textures, Tensor tex_res, Tensor tex_offset,
                                Tensor background, double fx, double fy, double cx, double cy, int64_t width,
                                int64_t height, double near_plane, c10::optional<Tensor> error_image,
                                int64_t num_threads, bool poison) {
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
  m.def("profile_counters", [](bool reset) {
    const std::vector<double> v = ctgs::cpu::prof_read(reset);
    std::map<std::string, double> out;
    for (int k = 0; k < ctgs::cpu::PROF_COUNT; ++k) out[ctgs::cpu::PROF_NAMES[k]] = v[k];
    return out;
  }, "wall-clock seconds per kernel phase since the last reset (benchmarks/profile_train.py)",
  py::arg("reset") = true);
}
