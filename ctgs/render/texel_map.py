"""Where a model spent its texels, as pictures: per pixel, the texel size in pixels, or the texture resolution, of the
surfels drawn there (`ctgs render --maps texels`, the fourth panel of `ctgs eval`'s strips, the viewer's overlay).

Each surfel gets a value t in [0, 1] on a fixed log2 scale, the same for every model and view:
- texel size: a texel's side in pixels at the surfel centre's depth, k * fx / z (k the mean of its texel sizes along
  u and v, world units; z its centre's camera-space depth), over TEXEL_PX_LOG2 (1/2 px to 128 px, two colour steps a
  doubling): flat regions with few large texels read red, detail with many small ones blue;
- texture resolution: its texels, res_u * res_v, over TEXRES_LOG2 (1 to 256 x 256).
The surfels are rendered as in the colour render (the same blending weights w) with the colour (t h, h, 0), h = 1 for
a textured surfel and 0 otherwise, over black; the picture is then turbo(R / G) G + UNTEXTURED (A - G), A the alpha:
the weighted mean of t over the textured surfels of a pixel, coloured, dimmed where the pixel is not covered, grey
where untextured surfels are seen. The viewer composes the same picture from its blended buffer (composite.frag),
with the same table (TURBO; a test checks the two stay equal).
"""

from __future__ import annotations

import numpy as np
import torch

from ctgs.render.api import render
from ctgs.render.sh import SH_C0
from ctgs.render.types import SurfelInputs

MAPS = ("texel_size", "texture_res")
TEXEL_PX_LOG2 = (-1.0, 7.0)  # log2 of the texel size in pixels at t = 0 and t = 1
TEXRES_LOG2 = (0.0, 16.0)  # log2 of a surfel's texel count at t = 0 and t = 1 (the 256 x 256 cap)
UNTEXTURED = 0.35  # grey level of untextured surfels
# Google's Turbo colour map (Mikhailov 2019) at 17 evenly spaced points, linearly interpolated (within 0.026 of its
# 256-entry table): blue for small values, red for large. static/composite.frag holds the same table.
TURBO = np.array([
    (0.188, 0.071, 0.231), (0.251, 0.251, 0.635), (0.275, 0.420, 0.890), (0.259, 0.580, 1.000),
    (0.157, 0.737, 0.922), (0.094, 0.867, 0.761), (0.196, 0.949, 0.596), (0.427, 0.996, 0.384),
    (0.643, 0.988, 0.235), (0.796, 0.929, 0.204), (0.925, 0.820, 0.227), (0.992, 0.682, 0.208),
    (0.984, 0.506, 0.133), (0.925, 0.325, 0.059), (0.824, 0.192, 0.020), (0.675, 0.090, 0.004),
    (0.478, 0.016, 0.012)], dtype=np.float32)
# Below this blended weight of textured surfels a pixel takes no colour from the scale (R / G is noise there).
MIN_WEIGHT = 1e-6


def turbo(t: torch.Tensor) -> torch.Tensor:
    """[..., 3] colours of t [...] in [0, 1] (clamped)."""
    lut = torch.as_tensor(TURBO, device=t.device, dtype=t.dtype)
    x = t.clamp(0.0, 1.0) * (len(TURBO) - 1)
    i = x.floor().clamp(max=len(TURBO) - 2).long()
    f = (x - i)[..., None]
    return lut[i] * (1.0 - f) + lut[i + 1] * f


def surfel_values(inputs: SurfelInputs, camera, which: str) -> tuple[torch.Tensor, torch.Tensor]:
    """(t [N] in [0, 1], textured [N] bool) of every surfel for the map `which` (MAPS) seen from `camera`."""
    if which not in MAPS:
        raise ValueError(f"map must be one of {MAPS}, got {which!r}")
    res = inputs.tex_res.to(inputs.means.device).long()
    textured = (res[:, 0] > 0) & (res[:, 1] > 0)
    if which == "texel_size":
        k = inputs.texel_size if inputs.texel_size.dim() == 1 else inputs.texel_size.mean(-1)
        vm = camera.viewmat.to(inputs.means.device, inputs.means.dtype)
        z = (inputs.means @ vm[2, :3] + vm[2, 3]).clamp_min(1e-12)
        value, (lo, hi) = torch.log2((k * camera.fx / z).clamp_min(1e-30)), TEXEL_PX_LOG2
    else:
        value, (lo, hi) = torch.log2((res[:, 0] * res[:, 1]).clamp_min(1).to(inputs.means.dtype)), TEXRES_LOG2
    return ((value - lo) / (hi - lo)).clamp(0.0, 1.0), textured


def render_map(inputs: SurfelInputs, camera, which: str, backend: str = "auto") -> torch.Tensor:
    """[H, W, 3] the picture of map `which` (MAPS) from `camera`, values in [0, 1] (see the module's docstring)."""
    return compose(*blend(inputs, camera, which, backend))


def blend(inputs: SurfelInputs, camera, which: str, backend: str = "auto") -> tuple[torch.Tensor, ...]:
    """(R, G, A), each [H, W]: the blended sum w t h, sum w h and alpha of map `which` (MAPS) from `camera`. R / G is
    the weighted mean of t over a pixel's textured surfels (`value_of` turns it back into pixels or texels)."""
    t, textured = surfel_values(inputs, camera, which)
    h = textured.to(t.dtype)
    colour = torch.stack([t * h, h, torch.zeros_like(h)], -1)  # what each surfel blends
    sh = ((colour - 0.5) / SH_C0)[:, None, :]  # sh_to_color: SH_C0 * dc + 0.5
    plain = SurfelInputs(means=inputs.means, quats=inputs.quats, scales=inputs.scales, opacities=inputs.opacities,
                         sh=sh, texel_size=inputs.texel_size, textures=inputs.textures[:0],
                         tex_res=torch.zeros_like(inputs.tex_res), tex_offset=torch.zeros_like(inputs.tex_offset))
    out = render(plain, camera, backend=backend, sh_degree=0, background=inputs.means.new_zeros(3))
    return out.rgb[..., 0], out.rgb[..., 1], out.alpha


def value_of(t: torch.Tensor, which: str) -> torch.Tensor:
    """A map's t in [0, 1] as what it measures: the texel size in pixels, or the texels per surfel (a mean of t is a
    geometric mean of these)."""
    lo, hi = TEXEL_PX_LOG2 if which == "texel_size" else TEXRES_LOG2
    return torch.exp2(lo + t * (hi - lo))


def compose(r: torch.Tensor, g: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
    """[H, W, 3] the map's picture from the blended R = sum w t h, G = sum w h and alpha A = sum w, each [H, W]."""
    covered = g > MIN_WEIGHT
    mean = torch.where(covered, r / g.clamp_min(MIN_WEIGHT), torch.zeros_like(r))
    scale = turbo(mean) * torch.where(covered, g, torch.zeros_like(g))[..., None]
    return (scale + (UNTEXTURED * (a - g).clamp_min(0.0))[..., None]).clamp(0.0, 1.0)


def legend(which: str, width: int, height: int = 28) -> np.ndarray:
    """[height, width, 3] float32 the colour scale of map `which` with its end and middle values written under it."""
    # OpenCV: a dependency, loaded only where a legend is drawn
    import cv2

    x = torch.linspace(0.0, 1.0, width)
    bar = turbo(x)[None].expand(height // 2, width, 3).numpy()
    img = np.zeros((height, width, 3), np.uint8)  # (OpenCV writes text into 8-bit images only)
    img[: height // 2] = np.rint(bar * 255.0).astype(np.uint8)
    lo, hi = TEXEL_PX_LOG2 if which == "texel_size" else TEXRES_LOG2
    labels = ([(0.0, f"{2 ** lo:g} px"), (0.5, f"{2 ** ((lo + hi) / 2):g} px"), (1.0, f"{2 ** hi:g} px per texel")]
              if which == "texel_size" else
              [(0.0, f"{2 ** lo:g}"), (0.5, f"{2 ** ((lo + hi) / 2):g}"), (1.0, f"{2 ** hi:g} texels per surfel")])
    for pos, text in labels:
        (tw, _), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.35, 1)
        x0 = int(min(max(pos * width - tw / 2, 0), width - tw))
        cv2.putText(img, text, (x0, height - 3), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (255, 255, 255), 1, cv2.LINE_AA)
    return img.astype(np.float32) / 255.0
