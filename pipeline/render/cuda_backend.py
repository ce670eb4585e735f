"""The CUDA backend behind `render(..., backend="cuda")`: the autograd bridge to kernels/cuda.

Mirrors the CPU path in pipeline.render.api (same camera-space preprocessing in PyTorch, same extension
arguments and outputs), with the tensors on a GPU. Semantics: docs/renderer.md.
"""

from __future__ import annotations

import torch

from pipeline.render.camera import Camera
from pipeline.render.preprocess import to_camera_space
from pipeline.render.types import ErrorStats, RenderOutput, SurfelInputs


class _RasterizeCUDA(torch.autograd.Function):
    """Camera-space primitives -> (rgb, alpha, depth, count, contrib, err); backward by the CUDA kernel."""

    @staticmethod
    def forward(ctx, mu_c, Rc, scales, opacities, colors, texel_size, textures, background,
                tex_res, tex_offset, camera, error_image, poison):
        from pipeline.render._ext_cuda import load_cuda

        cam = (float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy), int(camera.width),
               int(camera.height), float(camera.near))
        ext = load_cuda()
        (rgb, alpha, depth, final_T, n_contrib, tile_offsets, tile_list, count, contrib, err) = ext.forward_cuda(
            mu_c, Rc, scales, opacities, colors, texel_size, textures, tex_res, tex_offset, background, *cam,
            error_image, 0, poison)
        ctx.save_for_backward(mu_c, Rc, scales, opacities, colors, texel_size, textures, tex_res, tex_offset,
                              background, tile_offsets, tile_list, final_T, n_contrib)
        ctx.cam = cam
        ctx.mark_non_differentiable(count, contrib, err)
        return rgb, alpha, depth, count, contrib, err

    @staticmethod
    def backward(ctx, v_rgb, v_alpha, v_depth, _v_count, _v_contrib, _v_err):
        from pipeline.render._ext_cuda import load_cuda

        (mu_c, Rc, scales, opacities, colors, texel_size, textures, tex_res, tex_offset, background,
         tile_offsets, tile_list, final_T, n_contrib) = ctx.saved_tensors
        H, W = final_T.shape
        v_rgb = final_T.new_zeros(H, W, 3) if v_rgb is None else v_rgb.contiguous()
        v_alpha = final_T.new_zeros(H, W) if v_alpha is None else v_alpha.contiguous()
        v_depth = final_T.new_zeros(H, W) if v_depth is None else v_depth.contiguous()
        grads = load_cuda().backward_cuda(mu_c, Rc, scales, opacities, colors, texel_size, textures, tex_res,
                                          tex_offset, background, *ctx.cam, tile_offsets, tile_list, final_T,
                                          n_contrib, v_rgb, v_alpha, v_depth, 0)
        v_mu_c, v_Rc, v_scales, v_opacities, v_colors, v_texel_size, v_textures, v_background = grads
        return (v_mu_c, v_Rc, v_scales, v_opacities, v_colors, v_texel_size, v_textures, v_background,
                None, None, None, None, None)


def render_cuda(s: SurfelInputs, camera: Camera, sh_degree: int, background: torch.Tensor,
                error_image: torch.Tensor | None, poison: bool = False) -> RenderOutput:
    """Validated inputs on one CUDA device -> RenderOutput (see pipeline.render.render)."""
    from pipeline.render._ext_cuda import load_cuda

    load_cuda()  # no GPU or no toolkit: a one-line UserError before anything else
    if not s.means.is_cuda:
        raise ValueError(f"the cuda backend needs CUDA tensors (means is on {s.means.device}); move the surfels "
                         "with .to('cuda') or pass backend='auto'")
    prims = to_camera_space(s.means, s.quats, s.sh, camera, sh_degree)
    k = s.texel_size if s.texel_size.ndim == 2 else s.texel_size[:, None].expand(-1, 2)
    rgb, alpha, depth, count, contrib, err = _RasterizeCUDA.apply(
        prims.mu_c.contiguous(), prims.Rc.contiguous(), s.scales.contiguous(), s.opacities.contiguous(),
        prims.colors.contiguous(), k.contiguous(), s.textures.contiguous(), background.contiguous(),
        s.tex_res.contiguous(), s.tex_offset.contiguous(), camera,
        None if error_image is None else error_image.detach().contiguous(), poison)
    stats = ErrorStats(count=count, contrib=contrib, err=err) if error_image is not None else None
    return RenderOutput(rgb=rgb, alpha=alpha, depth=depth, stats=stats)
