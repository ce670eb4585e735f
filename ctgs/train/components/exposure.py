"""Per-training-image exposure compensation (config `exposure_comp`), off by default (the paper has none).

Photos of one capture need not share an exposure: on herzjesu25 a single gain per view, fitted after training, moves
the training views by up to +-5% and the validation views by 0.90-1.17 (`benchmarks/results/archive/exposure_gap/herzjesu25_192_balanced_2ef536c.md`). A model
without compensation can only fit those differences with view-dependent colour, textures and extra surfels that
draw one view brighter than its neighbours. With it, each training image i gets a per-channel gain
g_i = exp(l_i - mean_j l_j) (log-parameterised; centred over the images, so the gains cannot trade brightness with
the model), multiplied into that image's training render before the loss. Evaluation, E (the routines' error) and
exports use no gain: the model is what the images share.

The log-gains have their own Adam (bias-corrected, the optimiser's usual betas), stepped every iteration; only the
step's image has a gradient (the centring spreads a 1/V share to the others).
"""

from __future__ import annotations

import math

import torch

BETAS = (0.9, 0.999)
EPS = 1e-15


class Exposure:
    def __init__(self, num_images: int, device, lr: float, channels: int = 3):
        self.log_gain = torch.zeros(num_images, channels, device=device, requires_grad=True)
        self.m = torch.zeros(num_images, channels, device=device)
        self.v = torch.zeros(num_images, channels, device=device)
        self.t = 0
        self.lr = lr
        self.checked = False  # exposure_check done (Trainer): gains kept, or frozen at 1
        self.frozen = False

    @torch.no_grad()
    def check(self, min_gain: float) -> dict:
        """The capture's exposures, judged once (config exposure_check): if no learned gain is more than `min_gain`
        (relative) from 1, the photos share one exposure in practice and the gains are frozen at 1 from here on (a free
        gain per photo would only absorb the model's view-dependent errors). Returns what it saw and did."""
        dev = float(self.gains().log().abs().max()) if self.log_gain.numel() else 0.0
        self.checked = True
        if dev < math.log1p(min_gain):
            self.log_gain.zero_()
            self.m.zero_()
            self.v.zero_()
            self.frozen = True
        return {"max_gain_deviation": round(math.expm1(dev), 5), "min_gain": min_gain, "frozen": self.frozen}

    def gains(self) -> torch.Tensor:
        """[V, C] gains (C = 3 per channel, or 1 for all three), geometric mean 1 over the images in each channel
        (differentiable)."""
        lg = self.log_gain
        return torch.exp(lg - lg.mean(0, keepdim=True))

    def apply(self, rgb: torch.Tensor, index: int) -> torch.Tensor:
        """rgb [H, W, 3] of training image `index` -> rgb x its gain."""
        return rgb * self.gains()[index]

    @torch.no_grad()
    def step(self) -> None:
        g = self.log_gain.grad
        if g is None:
            return
        if self.frozen:
            self.log_gain.grad = None
            return
        self.t += 1
        b1, b2 = BETAS
        self.m.mul_(b1).add_(g, alpha=1 - b1)
        self.v.mul_(b2).addcmul_(g, g, value=1 - b2)
        m_hat = self.m / (1 - b1 ** self.t)
        v_hat = self.v / (1 - b2 ** self.t)
        self.log_gain -= self.lr * m_hat / (v_hat.sqrt() + EPS)
        self.log_gain.grad = None

    def state_dict(self) -> dict:
        return {"log_gain": self.log_gain.detach().cpu(), "m": self.m.cpu(), "v": self.v.cpu(), "t": self.t,
                "checked": self.checked, "frozen": self.frozen}

    def load_state_dict(self, state: dict) -> None:
        dev = self.log_gain.device
        with torch.no_grad():
            self.log_gain.copy_(state["log_gain"].to(dev))
        self.m = state["m"].to(dev)
        self.v = state["v"].to(dev)
        self.t = int(state["t"])
        self.checked = bool(state.get("checked", False))
        self.frozen = bool(state.get("frozen", False))
