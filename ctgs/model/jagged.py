"""Vectorised operations on jagged texture storage (flat [T, C] rows + per-primitive res and offsets).

Every function here works on a *list* of flat buffers laid out the same way (texel values and their two
Adam moments), so resizing a texture moves its optimiser state with it.
"""

from __future__ import annotations

import torch

from ctgs.model.surfels import jagged_offsets
from ctgs.ops.ext_cuda import cuda_fusable
from ctgs.ops.fused import fusable


def texel_coords(tex_res: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """For the packed layout of `tex_res` [N, 2]: per texel its primitive id, iu, iv (each [T] int64)."""
    res = tex_res.long()
    sizes = res[:, 0] * res[:, 1]
    n = res.shape[0]
    pid = torch.repeat_interleave(torch.arange(n, device=res.device), sizes)  # [T]
    local = torch.arange(pid.numel(), device=res.device) - (torch.cumsum(sizes, 0) - sizes)[pid]
    ru = res[pid, 0].clamp_min(1)
    return pid, local % ru, local // ru


def remap(buffers: list[torch.Tensor], old_res: torch.Tensor, old_off: torch.Tensor, src: torch.Tensor,
          shift: torch.Tensor, new_res: torch.Tensor) -> tuple[list[torch.Tensor], torch.Tensor]:
    """Build new jagged buffers where new primitive j copies primitive src[j]'s texels, re-centred.

    The new texture keeps texel centres at the same world positions (same texel size): new texel (iu, iv)
    reads old texel (iu + (R_old - R_new)//2 + shift_u, ...); taps outside the old grid become 0 (raw 0 =
    activated 0 = plain SH colour). With power-of-two resolutions both sizes are even, so the re-centring
    is exact. `shift` [N', 2] int64 moves the content by whole texels (split children).
    Returns (new buffers, new offsets [N'] int64).
    """
    new_res = new_res.to(torch.int32)
    new_off = jagged_offsets(new_res)
    fast = _compiled_remap(buffers, old_res, old_off, src, shift, new_res, new_off)
    if fast is not None:
        return fast, new_off
    return _torch_remap(buffers, old_res, old_off, src, shift, new_res, new_off), new_off


def _torch_remap(buffers, old_res, old_off, src, shift, new_res, new_off) -> list[torch.Tensor]:
    """remap's copies in PyTorch index arithmetic, on any device (the definition the compiled passes match)."""
    pid, iu, iv = texel_coords(new_res)
    s = src.long()[pid]
    ro = old_res.long()[s]  # [T', 2]
    rn = new_res.long()[pid]
    ou = iu + torch.div(ro[:, 0] - rn[:, 0], 2, rounding_mode="floor") + shift[pid, 0].long()
    ov = iv + torch.div(ro[:, 1] - rn[:, 1], 2, rounding_mode="floor") + shift[pid, 1].long()
    valid = (ou >= 0) & (ou < ro[:, 0]) & (ov >= 0) & (ov < ro[:, 1])
    idx = (old_off.long()[s] + ov * ro[:, 0] + ou).clamp(min=0)
    out = []
    for buf in buffers:
        if buf.shape[0] == 0:
            vals = buf.new_zeros((pid.numel(), buf.shape[1]))
        else:
            vals = buf[idx.clamp(max=buf.shape[0] - 1)] * valid[:, None].to(buf.dtype)
        out.append(vals)
    return out


def _compiled_remap(buffers, old_res, old_off, src, shift, new_res, new_off) -> list[torch.Tensor] | None:
    """remap's copies in one compiled pass (CPU or CUDA extension), or None where neither applies."""
    out = _cpu_remap(buffers, old_res, old_off, src, shift, new_res, new_off)
    return out if out is not None else _cuda_remap(buffers, old_res, old_off, src, shift, new_res, new_off)


def _cuda_remap(buffers, old_res, old_off, src, shift, new_res, new_off) -> list[torch.Tensor] | None:
    """remap on CUDA tensors in one kernel (kernels/cuda/dense.cu jagged_remap_kernel): the PyTorch index
    arithmetic below makes ~15 [T']-sized int64 temporaries, GBs at the paper's texel counts."""
    if (not buffers or len(buffers) > 4 or not buffers[0].is_cuda
            or any(b.dtype != buffers[0].dtype or b.shape[1] != buffers[0].shape[1] for b in buffers)):
        return None
    if not cuda_fusable(*buffers):
        return None
    return torch.ops.ctgs.jagged_remap([b.contiguous() for b in buffers], old_res.to(torch.int32).contiguous(),
                                       old_off.long().contiguous(), src.long().contiguous(), shift.long().contiguous(),
                                       new_res.to(torch.int32).contiguous(), new_off.long().contiguous(),
                                       _rows(new_res, new_off), 0)


def _cpu_remap(buffers, old_res, old_off, src, shift, new_res, new_off) -> list[torch.Tensor] | None:
    """remap in one compiled pass of row copies (kernels/cpu/dense.cpp) for CPU tensors: the index
    arithmetic below makes ~15 [T]-sized int64 temporaries, which dominated the routines."""
    if not buffers or not fusable(*buffers) or old_res.device.type != "cpu":
        return None
    return torch.ops.ctgs.jagged_remap(list(buffers), old_res.to(torch.int32).contiguous(), old_off.long().contiguous(),
                                       src.long().contiguous(), shift.long().contiguous(), new_res.contiguous(),
                                       new_off.contiguous(), _rows(new_res, new_off), torch.get_num_threads())


def _rows(new_res: torch.Tensor, new_off: torch.Tensor) -> int:
    """The texel count of a packed layout (jagged_offsets of new_res): its last offset plus its last size."""
    if new_res.shape[0] == 0:
        return 0
    return int(new_off[-1] + new_res[-1, 0].long() * new_res[-1, 1].long())


def blocks(buf: torch.Tensor, offsets: torch.Tensor, prims: torch.Tensor, ru: int, rv: int) -> torch.Tensor:
    """Texels of `prims` (all of resolution ru x rv) as [G, rv, ru, C]."""
    idx = offsets.long()[prims][:, None] + torch.arange(ru * rv, device=buf.device)[None]  # [G, rv*ru]
    return buf[idx].reshape(len(prims), rv, ru, buf.shape[1])


def replace_blocks(buffers: list[torch.Tensor], old_res: torch.Tensor, old_off: torch.Tensor,
                   new_res: torch.Tensor, new_blocks: list[tuple[torch.Tensor, list[torch.Tensor]]]
                   ) -> tuple[list[torch.Tensor], torch.Tensor]:
    """Copy unchanged primitives' texels into a layout for `new_res`, then write replaced ones.

    new_blocks: list of (prims [G], [values [G, rv, ru, C] per buffer]) whose resolution changed to
    new_res[prims]; every other primitive must keep its resolution.
    """
    n = old_res.shape[0]
    src = torch.arange(n, device=old_res.device)
    zero = torch.zeros(n, 2, dtype=torch.long, device=old_res.device)
    new_off = jagged_offsets(new_res)
    out = _compiled_remap(buffers, old_res, old_off, src, zero, new_res.to(torch.int32), new_off)
    if out is None:
        changed = torch.zeros(n, dtype=torch.bool, device=old_res.device)
        for prims, _ in new_blocks:
            changed[prims] = True
        keep_res = torch.where(changed[:, None], torch.zeros_like(new_res), new_res)
        # Unchanged primitives: identity remap (changed ones get 0 texels for now).
        kept, _ = remap(buffers, old_res, old_off, src, zero, keep_res)
        out = [b.new_zeros((int((new_res.long()[:, 0] * new_res.long()[:, 1]).sum()), b.shape[1])) for b in buffers]
        pid, _, _ = texel_coords(keep_res)
        local = torch.arange(pid.numel(), device=old_res.device) - jagged_offsets(keep_res)[pid]
        dst = new_off[pid] + local
        for o, k in zip(out, kept):
            o[dst] = k
    # (The compiled path remaps the changed primitives too, cropped or padded; every one of their texels
    # is overwritten here.)
    for prims, vals in new_blocks:
        if len(prims) == 0:
            continue
        size = vals[0].shape[1] * vals[0].shape[2]
        dst = (new_off[prims][:, None] + torch.arange(size, device=old_res.device)[None]).reshape(-1)
        for o, v in zip(out, vals):
            o[dst] = v.reshape(-1, v.shape[-1])
    return out, new_off
