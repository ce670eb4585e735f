"""Virtual-view coverage (`virtual_coverage` > 0; not in the paper, off in every preset).

Surfels that only one or two training views constrain can tile those views and still part from a viewpoint
half a camera step away: on herzjesu25 at 384x256 that is where the content-aware model loses to 2dgs
(benchmarks/results/archive/seen_pixels/herzjesu25_384_4f6edb4.md). This term asks for coverage there without asking for
any colour: for each training camera, two virtual cameras with its orientation and intrinsics, moved half the way
to its nearest training camera and as far the other way; in each, the pixels whose ray lies inside some training
image at every sampled depth (ctgs.scene.coverage: classes seen and few; with `virtual_pixels = "few"` only those
some depth of which only one or two training images hold) must be covered. Every
`virtual_every` steps one virtual view (in a fixed shuffled cycle) adds

    virtual_coverage * mean over its held pixels of (1 - alpha)   ("few": sum over them / all pixels)

to the training loss (its own render and backward). No photometric target: what covers a pixel is left to the
training views. `VirtualCoverage` is the component that adds it in a run.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch

from ctgs.errors import UserError
from ctgs.render.camera import Camera
from ctgs.scene.coverage import FEW_CLASS, seen_classes
from ctgs.train.components.budget import median_seconds
from ctgs.train.hooks import Component

STEP = 0.5  # fraction of the distance to the nearest training camera
MASK_CELL = 4  # the held-pixel mask is classified on cells of this many pixels across
PIXEL_KINDS = ("held", "few")


@dataclass
class VirtualView:
    name: str  # "<training view>+" (towards its nearest camera) or "<training view>-" (away from it)
    camera: Camera
    mask: torch.Tensor  # [H, W] float32: 1 on the pixels the term covers (virtual_views' `pixels`)
    held: int  # number of such pixels
    norm: int  # what the term's sum is divided by: `held` for "held" pixels (their mean), H x W for "few" ones
    #            (a view where few pixels are few does not weigh each of them more)


def _moved(cam: Camera, centre: torch.Tensor) -> Camera:
    """`cam` with its orientation and intrinsics, centred at `centre`."""
    vm = cam.viewmat.detach().cpu().double().clone()
    vm[:3, 3] = -vm[:3, :3] @ centre
    return replace(cam, viewmat=vm.to(cam.viewmat.dtype))


def virtual_views(names: list[str], cameras: list[Camera], points: np.ndarray, step: float = STEP,
                  pixels: str = "held") -> list[VirtualView]:
    """Two virtual views per training camera (module docstring); a virtual camera into which fewer than 10 SfM
    points project, or with no pixel of the kind asked for, is left out. Needs at least two training cameras.
    pixels: "held" (classes seen and few: some training image holds the pixel at every sampled depth) or "few"
    (class few alone: held at every depth, but at some depth by only one or two training images)."""
    if pixels not in PIXEL_KINDS:
        raise ValueError(f"pixels must be one of {PIXEL_KINDS}, got {pixels!r}")
    if len(cameras) < 2:
        return []
    centres = torch.stack([c.center.detach().cpu().double() for c in cameras])  # [C, 3]
    dist = torch.cdist(centres, centres)
    dist.fill_diagonal_(float("inf"))
    nearest = dist.argmin(1)
    out = []
    for i, cam in enumerate(cameras):
        delta = centres[int(nearest[i])] - centres[i]
        if float(delta.norm()) == 0.0:
            continue
        for sign, suffix in ((1.0, "+"), (-1.0, "-")):
            vcam = _moved(cam, centres[i] + sign * step * delta)
            # classes on a grid of MASK_CELL x MASK_CELL pixels (16x fewer rays), each cell's class for all its pixels
            coarse = vcam.scaled(1.0 / MASK_CELL)
            try:
                cls = seen_classes(coarse, cameras, points)
            except ValueError:
                continue
            held_coarse = ((cls <= FEW_CLASS) if pixels == "held" else (cls == FEW_CLASS)).float()[None, None]
            mask = torch.nn.functional.interpolate(held_coarse, size=(vcam.height, vcam.width), mode="nearest")[0, 0]
            held = int(mask.sum())
            if held:
                norm = held if pixels == "held" else mask.numel()
                out.append(VirtualView(names[i] + suffix, vcam, mask, held, norm))
    return out


def coverage_loss(alpha: torch.Tensor, view: VirtualView) -> torch.Tensor:
    """Sum of (1 - alpha) over the view's masked pixels / view.norm (the weight is applied by the caller)."""
    return ((1.0 - alpha) * view.mask).sum() / view.norm


class VirtualCoverage(Component):
    """virtual_coverage: virtual views half a camera step from each training camera, with the pixels the training
    cameras hold (virtual_views), visited in a fixed shuffled cycle (resume-safe: by iteration)."""

    def __init__(self, cfg, scene, train_views, device):
        cameras = [v.camera for v in train_views]
        self.views = [replace(vv, camera=vv.camera.to(device), mask=vv.mask.to(device))
                      for vv in virtual_views([v.name for v in train_views], cameras, scene.points,
                                              pixels=cfg.virtual_pixels)]
        if not self.views:
            raise UserError(f"{scene.root}: virtual_coverage found no virtual view with {cfg.virtual_pixels} pixels "
                            "(it needs two training cameras with SfM points in view); set virtual_coverage = 0")
        self.order = torch.randperm(len(self.views), generator=torch.Generator().manual_seed(cfg.seed + 1))

    def post_backward(self, st, it: int, view) -> None:
        """Every virtual_every-th step, one virtual view's coverage term, rendered and back-propagated on its own."""
        every = st.cfg.virtual_every
        if it % every:
            return
        vv = self.views[int(self.order[(it // every) % len(self.views)])]
        alpha = st.render_fn(st.model.render_inputs(), vv.camera).alpha
        (st.cfg.virtual_coverage * coverage_loss(alpha, vv)).backward()

    def step_seconds(self, st, view) -> float:
        every = st.cfg.virtual_every
        return median_seconds(lambda: self.post_backward(st, every, view), device=st.device) / every
