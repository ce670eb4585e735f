"""Texture sparsity term: lambda_texture x sum |texel| of visible primitives (lambda resolved by
ctgs/train/config/rules.py)."""

from __future__ import annotations

import torch

import train_helpers as th
from ctgs.train.config import TrainConfig
from ctgs.train.step.loss import training_loss


def _reg_term(cfg: TrainConfig, m, gt: torch.Tensor) -> float:
    """The regulariser part of the loss: total with textures minus total with lambda_texture = 0."""
    off = TrainConfig(**{**cfg.to_dict(), "lambda_texture": 0.0})
    with torch.no_grad():
        return float(training_loss(gt, gt, m, th.camera(), cfg).total - training_loss(gt, gt, m, th.camera(), off).total)


def test_texture_reg_is_lambda_times_visible_abs_texels_and_its_rule_scales_with_image_size():
    m = th.model([[0.0, 0.0, 2.0]], [[0.3, 0.3]], [0.9], [[4, 4]])
    gt = torch.full((th.H, th.W, 3), 0.5)
    visible_abs = float(m.textures.detach().abs().sum())  # the one surfel is visible
    plain = _reg_term(TrainConfig(lambda_texture=1e-3), m, gt)
    assert abs(plain - 1e-3 * visible_abs) < 1e-6 * max(1.0, visible_abs)
    # The paper's weight is for ~1 Mpx images; on images of 1e5 pixels the rule gives 10x the weight.
    from ctgs.train.config.rules import resolve

    scaled = _reg_term(resolve(TrainConfig(lambda_texture=1e-3), 1e5), m, gt)
    assert abs(scaled - 10 * plain) < 1e-4 * abs(10 * plain)
    assert resolve(TrainConfig(lambda_texture=1e-3, scale_rules=False), 1e5).lambda_texture == 1e-3
