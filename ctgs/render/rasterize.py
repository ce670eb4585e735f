"""The one autograd bridge between PyTorch and the compiled rasterizers (CPU and CUDA alike).

Both extensions implement the same two ops (schemas: ctgs/ops/schemas.py), and the dispatcher runs the kernel of
the tensors' device:
  torch.ops.ctgs.rasterize_forward(mu_c, Rc, scales, opacities, colors, texel_size, textures, tex_res, tex_offset,
                                   background, fx, fy, cx, cy, W, H, near, error_image, knob, poison)
      -> rgb, alpha, depth, final_T, n_contrib, tile_offsets, tile_list, count, contrib, err, setup_prims, setup_spans,
         median (the median depth, no gradient), depth2 (sum of w z^2)
  torch.ops.ctgs.rasterize_backward(..., background, fx, fy, cx, cy, W, H, near, tile_offsets, tile_list, final_T,
                                    n_contrib, v_rgb, v_alpha, v_depth, knob, setup_prims, setup_spans, v_depth2)
      -> v_mu_c, v_Rc, v_scales, v_opacities, v_colors, v_texel_size, v_textures, v_background
`knob` is the OpenMP thread count on the CPU (the CUDA kernels run on the current stream); the setup is the CPU
forward's per-primitive work handed to its backward (empty on CUDA, whose backward redoes it per tile). On the CPU,
rasterize_backward_stats is the backward that also sums an error image's statistics (BackwardStats).
"""

from __future__ import annotations

import torch

from typing import Callable

from ctgs.ops.ext import load_cpu
from ctgs.ops.ext_cuda import load_cuda
from ctgs.render.camera import Camera
from ctgs.render.preprocess import to_camera_space
from ctgs.render.types import BackwardStats, ErrorStats, RenderOutput, SurfelInputs


def _load(device: str):
    """The forward and backward ops, once the extension whose kernels serve `device` is loaded."""
    if device == "cuda":
        load_cuda()
    else:
        load_cpu()
    return torch.ops.ctgs.rasterize_forward, torch.ops.ctgs.rasterize_backward


class _Rasterize(torch.autograd.Function):
    """Camera-space primitives -> (rgb, alpha, depth, count, contrib, err, tile_list, median, depth2); backward by the
    compiled kernel."""

    @staticmethod
    def forward(ctx, mu_c, Rc, scales, opacities, colors, texel_size, textures, background,
                tex_res, tex_offset, camera, error_image, device, knob, poison, backward_stats):
        cam = (float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy), int(camera.width),
               int(camera.height), float(camera.near))
        forward_op, _ = _load(device)
        outs = forward_op(mu_c, Rc, scales, opacities, colors, texel_size, textures, tex_res, tex_offset, background,
                          *cam, error_image, knob, poison)
        (rgb, alpha, depth, final_T, n_contrib, tile_offsets, tile_list, count, contrib, err) = outs[:10]
        # the forward's per-primitive setup (opaque; empty on CUDA), handed back so the backward need not redo it
        setup = tuple(outs[10:12])
        median, depth2 = outs[12], outs[13]
        ctx.save_for_backward(mu_c, Rc, scales, opacities, colors, texel_size, textures, tex_res, tex_offset,
                              background, tile_offsets, tile_list, final_T, n_contrib, *setup)
        ctx.cam, ctx.device, ctx.knob, ctx.backward_stats = cam, device, knob, backward_stats
        ctx.mark_non_differentiable(count, contrib, err, tile_list, median)
        return rgb, alpha, depth, count, contrib, err, tile_list, median, depth2

    @staticmethod
    def backward(ctx, v_rgb, v_alpha, v_depth, _v_count, _v_contrib, _v_err, _v_tile_list, _v_median, v_depth2):
        (mu_c, Rc, scales, opacities, colors, texel_size, textures, tex_res, tex_offset, background,
         tile_offsets, tile_list, final_T, n_contrib, *setup) = ctx.saved_tensors
        H, W = final_T.shape
        v_rgb = final_T.new_zeros(H, W, 3) if v_rgb is None else v_rgb.contiguous()
        v_alpha = final_T.new_zeros(H, W) if v_alpha is None else v_alpha.contiguous()
        v_depth = final_T.new_zeros(H, W) if v_depth is None else v_depth.contiguous()
        v_depth2 = None if v_depth2 is None else v_depth2.contiguous()  # None: zero, nothing to add
        _, backward_op = _load(ctx.device)
        args = (mu_c, Rc, scales, opacities, colors, texel_size, textures, tex_res, tex_offset, background, *ctx.cam,
                tile_offsets, tile_list, final_T, n_contrib, v_rgb, v_alpha, v_depth, ctx.knob, *setup)
        sink = ctx.backward_stats
        if sink is not None and sink.error_image is not None and ctx.device == "cpu":
            e = sink.error_image.detach().to(final_T.dtype).contiguous()
            grads = torch.ops.ctgs.rasterize_backward_stats(*args, e, v_depth2)
            sink.contrib, sink.err = grads[8], grads[9]
        else:
            grads = backward_op(*args, v_depth2)
        v_mu_c, v_Rc, v_scales, v_opacities, v_colors, v_texel_size, v_textures, v_background = grads[:8]
        return (v_mu_c, v_Rc, v_scales, v_opacities, v_colors, v_texel_size, v_textures, v_background,
                None, None, None, None, None, None, None, None)


def rasterize(s: SurfelInputs, camera: Camera, sh_degree: int, background: torch.Tensor,
              error_image: torch.Tensor | None, *, device: str, knob: int, poison: bool,
              backward_stats: BackwardStats | None = None) -> RenderOutput:
    """Validated inputs -> RenderOutput through the compiled backend of `device` ("cpu" or "cuda"); backward_stats:
    filled by this render's backward on the CPU (BackwardStats)."""
    prims = to_camera_space(s.means, s.quats, s.sh, camera, sh_degree)
    k = s.texel_size if s.texel_size.ndim == 2 else s.texel_size[:, None].expand(-1, 2)
    rgb, alpha, depth, count, contrib, err, tile_list, median, depth2 = _Rasterize.apply(
        prims.mu_c.contiguous(), prims.Rc.contiguous(), s.scales.contiguous(), s.opacities.contiguous(),
        prims.colors.contiguous(), k.contiguous(), s.textures.contiguous(), background.contiguous(),
        s.tex_res.contiguous(), s.tex_offset.contiguous(), camera,
        None if error_image is None else error_image.detach().contiguous(), device, knob, poison, backward_stats)
    # Every primitive in some tile list: one scatter over the lists (a few per primitive), no PyTorch
    # replay of the binning's geometry per training step.
    rasterized = torch.zeros(s.num_primitives, dtype=torch.bool, device=rgb.device)
    if s.num_primitives > 0 and tile_list.numel() > 0:
        rasterized[tile_list.long()] = True
    if error_image is None:
        return RenderOutput(rgb=rgb, alpha=alpha, depth=depth, stats=None, rasterized=rasterized, median_depth=median,
                            depth2=depth2)
    if s.num_primitives == 0:  # the kernels return placeholder buffers for N = 0
        count, contrib, err = count.new_zeros(0), contrib.new_zeros(0), err.new_zeros(0)
    return RenderOutput(rgb=rgb, alpha=alpha, depth=depth, stats=ErrorStats(count=count, contrib=contrib, err=err),
                        rasterized=rasterized, median_depth=median, depth2=depth2)


def rasterize_error_fn(s: SurfelInputs, camera: Camera, sh_degree: int, background: torch.Tensor,
                       error_fn: Callable[[torch.Tensor], torch.Tensor], check_error, *, knob: int,
                       poison: bool) -> RenderOutput:
    """One CPU render whose error statistics use the error image error_fn(rgb) of that very render: the
    kernel lists every blended (pixel, primitive, w) and the statistics are sums over that list (the same
    pairs and weights a second render with the error image would blend). No gradients.
    check_error(e) validates the error image."""
    with torch.no_grad():
        prims = to_camera_space(s.means, s.quats, s.sh, camera, sh_degree)
        k = s.texel_size if s.texel_size.ndim == 2 else s.texel_size[:, None].expand(-1, 2)
        cam = (float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy), int(camera.width),
               int(camera.height), float(camera.near))
        load_cpu()
        rgb, alpha, depth, pix, prim, w = torch.ops.ctgs.rasterize_pairs(
            prims.mu_c.contiguous(), prims.Rc.contiguous(), s.scales.detach().contiguous(),
            s.opacities.detach().contiguous(), prims.colors.contiguous(), k.detach().contiguous(),
            s.textures.detach().contiguous(), s.tex_res.contiguous(), s.tex_offset.contiguous(),
            background.detach().contiguous(), *cam, knob, poison)
        e = error_fn(rgb)
        check_error(e)
        # One compiled pass over the pairs (one thread: the same sums, in the same order, as bincount /
        # index_add_; more: contiguous chunks in that order, added in order).
        count, contrib, err = torch.ops.ctgs.accumulate_pairs(pix, prim, w, e.detach().to(w.dtype).contiguous(),
                                                              s.num_primitives, knob)
    return RenderOutput(rgb=rgb, alpha=alpha, depth=depth, stats=ErrorStats(count=count, contrib=contrib, err=err))
