"""The textured 2D Gaussian surfel model (paper section 3.1).

Parameters are stored raw (pre-activation), as the optimiser sees them:

| field | shape | activation / meaning |
| --- | --- | --- |
| means | [N,3] | world units |
| log_scales | [N,2] | scales = exp(log_scales), world units |
| quats | [N,4] | (w,x,y,z), normalised when rendering |
| opacity_logits | [N] | opacity = sigmoid |
| sh | [N,K,3] | K = (max_sh_degree+1)^2; sh[:,0] is the DC band |
| textures_raw | [T,3] | texel offsets = 2*sigmoid(textures_raw) - 1, range [-1, 1] |

Non-optimised buffers:

| field | shape | meaning |
| --- | --- | --- |
| k_min | [N] | world size of one pixel of the closest training camera at the centre's depth |
| t2p_exp | [N] int32 | texel size = k_min * 2**t2p_exp (paper's t2p_r = 2**t2p_exp) |
| tex_res | [N,2] int32 | (res_u, res_v) allocated texels along tangent u, v; (0,0) = no texture |
| tex_offset | [N] int64 | start row of primitive i in textures_raw |

`texture_mode` says how textures map: "content_aware" (texel size fixed in world space, the paper's
method), "fixed" (paper eq. 3, a fixed grid stretched over +-3 sigma: the `fixed_texture` baseline)
or "none" (plain 2DGS).
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import torch

from ctgs.ops.fused import texel_activation
from ctgs.render.types import SurfelInputs

TEXTURE_MODES = ("content_aware", "fixed", "none")
# Texel extent of the fixed-texture baseline: the grid covers +-FIXED_EXTENT_SIGMA standard deviations.
FIXED_EXTENT_SIGMA = 3.0


def params_per_primitive(max_sh_degree: int, textured: bool) -> int:
    """SurfelModel.num_params per primitive: 3 position, 2 scale, 4 rotation, 1 opacity, 3 per SH coefficient
    ((max_sh_degree + 1)^2 of them), and the texel-size exponent of a textured model."""
    return 10 + 3 * (max_sh_degree + 1) ** 2 + (1 if textured else 0)


@dataclass
class SurfelModel:
    means: torch.Tensor
    log_scales: torch.Tensor
    quats: torch.Tensor
    opacity_logits: torch.Tensor
    sh: torch.Tensor
    textures_raw: torch.Tensor
    k_min: torch.Tensor
    t2p_exp: torch.Tensor
    tex_res: torch.Tensor
    tex_offset: torch.Tensor
    sh_degree: int = 0  # active SH degree (grows during training)
    texture_mode: str = "content_aware"

    # ---- sizes -------------------------------------------------------------------------------
    @property
    def num_primitives(self) -> int:
        return int(self.means.shape[0])

    @property
    def num_texels(self) -> int:
        return int(self.textures_raw.shape[0])

    @property
    def max_sh_degree(self) -> int:
        return int(round(self.sh.shape[1] ** 0.5)) - 1

    def num_params(self) -> int:
        """The paper's count: 59 per primitive (58 of 2DGS + texel size) + 3 per texel.

        2DGS counts 58 (3 position, 2 scale, 4 rotation, 1 opacity, 48 SH at degree 3); the `none` mode has no
        texel size. SH are counted as stored: 3 per coefficient, (max_sh_degree + 1)^2 coefficients.
        """
        per_prim = params_per_primitive(self.max_sh_degree, self.texture_mode != "none")
        return per_prim * self.num_primitives + 3 * self.num_texels

    # ---- activations -------------------------------------------------------------------------
    @property
    def scales(self) -> torch.Tensor:
        return torch.exp(self.log_scales)

    @property
    def opacities(self) -> torch.Tensor:
        return torch.sigmoid(self.opacity_logits)

    @property
    def textures(self) -> torch.Tensor:
        return texel_activation(self.textures_raw)  # 2 sigmoid(raw) - 1, one fused pass on the CPU

    @property
    def texel_size(self) -> torch.Tensor:
        """[N, 2] world units per texel along (u, v)."""
        if self.texture_mode == "fixed":
            res = self.tex_res.to(self.log_scales.dtype).clamp_min(1.0)
            return 2.0 * FIXED_EXTENT_SIGMA * self.scales / res
        k = self.k_min * torch.pow(2.0, self.t2p_exp.to(self.k_min.dtype))
        return k[:, None].expand(-1, 2)

    def render_inputs(self) -> SurfelInputs:
        """Activated inputs for `ctgs.render.render`, differentiable w.r.t. the raw parameters."""
        sh = self.sh[:, : (self.sh_degree + 1) ** 2]
        if self.texture_mode == "none":
            tex_res = torch.zeros_like(self.tex_res)
        else:
            tex_res = self.tex_res
        return SurfelInputs(
            means=self.means, quats=self.quats, scales=self.scales, opacities=self.opacities, sh=sh,
            texel_size=self.texel_size, textures=self.textures, tex_res=tex_res, tex_offset=self.tex_offset,
        )

    # ---- (de)serialisation -------------------------------------------------------------------
    def state_dict(self) -> dict:
        out = {f.name: getattr(self, f.name) for f in fields(self)}
        return {k: (v.detach().cpu() if isinstance(v, torch.Tensor) else v) for k, v in out.items()}

    @classmethod
    def from_state_dict(cls, state: dict, device: torch.device | str = "cpu") -> "SurfelModel":
        names = {f.name for f in fields(cls)}
        missing = names - set(state)
        if missing:
            raise KeyError(f"model state lacks {sorted(missing)}")
        kwargs = {k: (v.to(device) if isinstance(v, torch.Tensor) else v) for k, v in state.items() if k in names}
        model = cls(**kwargs)
        model.validate()
        return model

    def validate(self) -> None:
        """Raise ValueError if shapes or the jagged layout are inconsistent."""
        n = self.num_primitives
        checks = [
            ("means", self.means, (n, 3)), ("log_scales", self.log_scales, (n, 2)), ("quats", self.quats, (n, 4)),
            ("opacity_logits", self.opacity_logits, (n,)), ("k_min", self.k_min, (n,)),
            ("t2p_exp", self.t2p_exp, (n,)), ("tex_res", self.tex_res, (n, 2)), ("tex_offset", self.tex_offset, (n,)),
        ]
        for name, t, shape in checks:
            if tuple(t.shape) != shape:
                raise ValueError(f"{name} must have shape {list(shape)}, got {list(t.shape)}")
        if self.sh.ndim != 3 or self.sh.shape[0] != n or self.sh.shape[2] != 3:
            raise ValueError(f"sh must have shape [N, K, 3], got {list(self.sh.shape)}")
        if self.textures_raw.ndim != 2 or self.textures_raw.shape[1] != 3:
            raise ValueError(f"textures_raw must have shape [T, 3], got {list(self.textures_raw.shape)}")
        if self.texture_mode not in TEXTURE_MODES:
            raise ValueError(f"texture_mode must be one of {TEXTURE_MODES}, got {self.texture_mode!r}")
        sizes = self.tex_res[:, 0].long() * self.tex_res[:, 1].long()
        if n and int((self.tex_offset + sizes).max()) > self.num_texels:
            raise ValueError("jagged textures: tex_offset + res_u*res_v exceeds the texel count")
        if bool((self.tex_offset < 0).any()):
            raise ValueError("jagged textures: negative tex_offset")


def jagged_offsets(tex_res: torch.Tensor) -> torch.Tensor:
    """Packed int64 start offsets for resolutions [N, 2] (exclusive cumulative sum of res_u*res_v)."""
    sizes = tex_res[:, 0].long() * tex_res[:, 1].long()
    return torch.cumsum(sizes, 0) - sizes
