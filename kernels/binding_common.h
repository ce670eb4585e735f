// Torch-side checks and argument packing shared by the CPU (bindings.cpp) and CUDA (bindings_cuda.cpp)
// bindings: every tensor is checked for shape, dtype, device and contiguity, with an error that names the
// argument and the expected shape, before a raw pointer reaches a core.
#pragma once

#include <torch/extension.h>

#include <vector>

#include "ctgs/scene_args.h"

namespace ctgs_binding {

using torch::Tensor;

inline void check_tensor(const Tensor& t, const char* name, const char* shape, std::vector<int64_t> sizes,
                         at::ScalarType dtype, const at::Device& device) {
  TORCH_CHECK(t.device() == device, name, " must be on ", device, " (the device of mu_c), got ", t.device());
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

// `backend` names the backend in errors; mu_c's device must be of `device_type`, and every other tensor on it.
inline Scene check_scene(Tensor mu_c, Tensor Rc, Tensor scales, Tensor opacities, Tensor colors,
                         Tensor texel_size, Tensor textures, Tensor tex_res, Tensor tex_offset, Tensor background,
                         double fx, double fy, double cx, double cy, int64_t width, int64_t height,
                         double near_plane, int64_t num_threads, at::DeviceType device_type, const char* backend) {
  TORCH_CHECK(mu_c.device().type() == device_type, "mu_c must be a ", c10::DeviceTypeName(device_type),
              " tensor for the ", backend, " backend, got ", mu_c.device());
  const at::Device dev = mu_c.device();
  const int64_t N = mu_c.size(0);
  const auto dt = mu_c.scalar_type();
  TORCH_CHECK(dt == at::kFloat || dt == at::kDouble, "mu_c must be float32 or float64, got ", dt);
  check_tensor(mu_c, "mu_c", "[N, 3]", {N, 3}, dt, dev);
  check_tensor(Rc, "Rc", "[N, 3, 3]", {N, 3, 3}, dt, dev);
  check_tensor(scales, "scales", "[N, 2]", {N, 2}, dt, dev);
  check_tensor(opacities, "opacities", "[N]", {N}, dt, dev);
  check_tensor(colors, "colors", "[N, 3]", {N, 3}, dt, dev);
  check_tensor(texel_size, "texel_size", "[N, 2]", {N, 2}, dt, dev);
  check_tensor(textures, "textures", "[T, 3]", {-1, 3}, dt, dev);
  check_tensor(tex_res, "tex_res", "[N, 2] int32", {N, 2}, at::kInt, dev);
  check_tensor(tex_offset, "tex_offset", "[N] int64", {N}, at::kLong, dev);
  check_tensor(background, "background", "[3]", {3}, dt, dev);
  TORCH_CHECK(N <= INT32_MAX, "at most 2^31-1 primitives, got ", N);
  TORCH_CHECK(width >= 1 && height >= 1, "image size must be >= 1x1, got ", width, "x", height);
  TORCH_CHECK(fx != 0.0 && fy != 0.0, "focal lengths must be non-zero");
  // Out-of-range texel rows would read (and, in backward, write) outside `textures`. Tensor ops, so the same
  // check runs where the data lives (one synchronisation on a GPU).
  if (N > 0) {
    const Tensor res = tex_res.to(at::kLong);
    TORCH_CHECK(!(res < 0).any().item<bool>(), "tex_res must be >= 0");
    const Tensor size = res.select(1, 0) * res.select(1, 1);
    const Tensor bad = (size > 0) & ((tex_offset < 0) | (tex_offset + size > textures.size(0)));
    TORCH_CHECK(!bad.any().item<bool>(), "tex_offset + res_u*res_v exceeds the texel count T = ", textures.size(0),
                " (or tex_offset < 0) for some primitive");
  }
  return Scene{mu_c, Rc, scales, opacities, colors, texel_size, textures, tex_res, tex_offset, background,
               fx, fy, cx, cy, near_plane, width, height, num_threads};
}

template <typename S>
ctgs::SceneArgs<S> scene_args(const Scene& s) {
  ctgs::SceneArgs<S> a;
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

}  // namespace ctgs_binding
