"""Every compiled op of ctgs, declared once: its name and schema (torch.library). The kernels are registered by the
extension of each device (TORCH_LIBRARY_IMPL: kernels/bindings.cpp for the CPU, kernels/bindings_cuda.cpp for
CUDA), and `torch.ops.ctgs.<op>(...)` runs the kernel of its tensors' device once that device's extension is loaded
(ctgs.ops.ext.load_cpu, ctgs.ops.ext_cuda.load_cuda: both declare these first).

`knob` / `num_threads`: the OpenMP thread count on the CPU (0: torch's); the CUDA kernels run on the current stream
and ignore it. Shapes and meanings of the arguments are documented beside each kernel in the bindings."""

from __future__ import annotations

import threading

import torch

_CAMERA = "float fx, float fy, float cx, float cy, int width, int height, float near_plane"
_SCENE = ("Tensor mu_c, Tensor Rc, Tensor scales, Tensor opacities, Tensor colors, Tensor texel_size, Tensor textures, "
          f"Tensor tex_res, Tensor tex_offset, Tensor background, {_CAMERA}")

# Ops with a CPU and a CUDA kernel.
BOTH = (
    # rgb, alpha, depth, final_T, n_contrib, tile_offsets, tile_list, count, contrib, err (the last three empty
    # without error_image), then the forward's setup for the backward: two opaque tensors on the CPU, empty on CUDA,
    # then the median depth [H, W] (no gradient) and depth2 [H, W] (sum of w z^2)
    f"rasterize_forward({_SCENE}, Tensor? error_image, int knob, bool poison) -> Tensor[]",
    # v_mu_c, v_Rc, v_scales, v_opacities, v_colors, v_texel_size, v_textures, v_background (v_depth2: depth2's
    # gradient, None: zero)
    f"rasterize_backward({_SCENE}, Tensor tile_offsets, Tensor tile_list, Tensor final_T, Tensor n_contrib, "
    "Tensor v_rgb, Tensor v_alpha, Tensor v_depth, int knob, Tensor? setup_prims, Tensor? setup_spans, "
    "Tensor? v_depth2=None) -> Tensor[]",
    # {mu_c [N, 3], Rc [N, 3, 3]}: world -> camera space of the means and quaternions for view [4, 4]
    "camera_space(Tensor means, Tensor quats, Tensor view, int num_threads) -> Tensor[]",
    # {grad_means [N, 3], grad_quats [N, 4]} of camera_space for its upstream gradients
    "camera_space_backward(Tensor quats, Tensor view, Tensor grad_mu_c, Tensor grad_Rc, int num_threads) -> Tensor[]",
    # colors [N, 3] = SH_degree(normalize(means - center)) + 0.5
    "sh_color(Tensor means, Tensor center, Tensor sh, int degree, int num_threads) -> Tensor",
    # {grad_means [N, 3], grad_sh [N, K, 3]} of sh_color for the upstream gradient grad_colors [N, 3]
    "sh_color_backward(Tensor means, Tensor center, Tensor sh, int degree, Tensor grad_colors, int num_threads)"
    " -> Tensor[]",
    # int32 0-dim on the inputs' device: 0 if the surfel tensors pass render()'s value checks (surfel_values_ok's
    # checks), else not; no synchronisation, so the caller reads it together with its other checks
    "surfel_value_flags(Tensor means, Tensor quats, Tensor scales, Tensor opacities, Tensor sh, Tensor texel_size, "
    "Tensor textures, Tensor tex_res, Tensor tex_offset, int num_threads) -> Tensor",
    # jagged texture buffers re-laid out (ctgs.model.jagged.remap); new_rows: the new layout's texel count
    "jagged_remap(Tensor[] buffers, Tensor old_res, Tensor old_off, Tensor src, Tensor shift, Tensor new_res, "
    "Tensor new_off, int new_rows, int num_threads) -> Tensor[]",
)

# CPU-only passes (their callers use PyTorch on other devices).
CPU_ONLY = (
    # rasterize_backward's gradients, then contrib [N] and err [N]: the error statistics of error_image [H, W] over the
    # pixels blended (the forward's with that error image, w from T recovered by division)
    f"rasterize_backward_stats({_SCENE}, Tensor tile_offsets, Tensor tile_list, Tensor final_T, Tensor n_contrib, "
    "Tensor v_rgb, Tensor v_alpha, Tensor v_depth, int knob, Tensor? setup_prims, Tensor? setup_spans, "
    "Tensor error_image, Tensor? v_depth2=None) -> Tensor[]",
    # rgb, alpha, depth, and every blended pair: pix (y * W + x) int32, prim int32, w
    f"rasterize_pairs({_SCENE}, int num_threads, bool poison) -> Tensor[]",
    # per-primitive count int32, contrib, err over a forward's blended pairs and an error image e [H, W]
    "accumulate_pairs(Tensor pix, Tensor prim, Tensor w, Tensor e, int n, int num_threads) -> Tensor[]",
    # Adam in place on p, m, v; returns how many updated values of p are not finite
    "adam_step(Tensor(a!) p, Tensor g, Tensor(b!) m, Tensor(c!) v, Tensor? lr_tensor, float lr, float beta1, "
    "float beta2, int step, float eps, int num_threads) -> int",
    # sum_i weight[i] sum over primitive i's texels of |2 sigmoid(raw) - 1| (0-dim), and scale x its gradient
    "texel_l1_forward(Tensor raw, Tensor weight, Tensor tex_offset, Tensor tex_res, int num_threads) -> Tensor",
    "texel_l1_backward(Tensor raw, Tensor weight, Tensor tex_offset, Tensor tex_res, float scale, int num_threads)"
    " -> Tensor",
    # the same on activated offsets y (sum of |y|)
    "texel_abs_forward(Tensor y, Tensor weight, Tensor tex_offset, Tensor tex_res, int num_threads) -> Tensor",
    "texel_abs_backward(Tensor y, Tensor weight, Tensor tex_offset, Tensor tex_res, float scale, int num_threads)"
    " -> Tensor",
    # y = 2 sigmoid(x) - 1, its gradient, and its gradient with texel_abs_backward's added to grad_y first
    "texel_activation(Tensor x, int num_threads) -> Tensor",
    "texel_activation_backward(Tensor y, Tensor grad_y, int num_threads) -> Tensor",
    "texel_activation_backward_l1(Tensor y, Tensor grad_y, Tensor weight, Tensor tex_offset, Tensor tex_res, "
    "float scale, int num_threads) -> Tensor",
    # whether the surfel tensors pass render()'s value checks (False: the PyTorch checks name the problem)
    "surfel_values_ok(Tensor means, Tensor quats, Tensor scales, Tensor opacities, Tensor sh, Tensor texel_size, "
    "Tensor textures, Tensor tex_res, Tensor tex_offset, int num_threads) -> bool",
    # {(1 - l) L1 + l (1 - SSIM) (0-dim), L1, SSIM, its gradient (or empty), the error image [H, W] (or empty)}
    "photometric_loss(Tensor x, Tensor y, float lambda_ssim, bool want_grad, bool want_error, int num_threads)"
    " -> Tensor[]",
)

_lock = threading.Lock()
_library: torch.library.Library | None = None


def declare() -> None:
    """Declare the ctgs op namespace and every schema (once per process); an extension's kernels register against
    these when it loads."""
    global _library
    with _lock:
        if _library is not None:
            return
        library = torch.library.Library("ctgs", "DEF")
        for schema in BOTH + CPU_ONLY:
            library.define(schema)
        _library = library


def op_names() -> list[str]:
    """The op names, in declaration order."""
    return [schema.split("(", 1)[0] for schema in BOTH + CPU_ONLY]
