"""Training strategies: how a run's primitives and textures change, one per config `method` (ctgs.train.hooks).

content_aware   the paper's routines: error E, splits, texel up/downscaling, texture reallocation (ContentAware)
2dgs            3DGS/2DGS adaptive density control on untextured surfels (Densify)
fixed_texture   the same densification, a fixed 16x16 texture per primitive from the start (FixedTexture)
"""

from __future__ import annotations

from ctgs.train.strategies.base import Strategy
from ctgs.train.strategies.content_aware import ContentAware
from ctgs.train.strategies.densify import Densify, FixedTexture

STRATEGIES: dict[str, type[Strategy]] = {"content_aware": ContentAware, "2dgs": Densify,
                                         "fixed_texture": FixedTexture}


def make_strategy(method: str) -> Strategy:
    return STRATEGIES[method]()


__all__ = ["STRATEGIES", "ContentAware", "Densify", "FixedTexture", "Strategy", "make_strategy"]
