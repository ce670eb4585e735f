"""Adam over the surfel model's tensors, with state that can follow structural edits.

A hand-written Adam (same update as torch.optim.Adam, eps 1e-15 by default) because primitives are
added, removed and re-ordered, and textures change size: the moments live here as plain tensors laid
out exactly like the parameters, so the editing code (ctgs/train/routines/edit.py) moves them the same way.
"""

from __future__ import annotations

import torch

from ctgs.ops import fused

PRIM_PARAMS = ("means", "log_scales", "quats", "opacity_logits", "sh")
TEX_PARAM = "textures_raw"
ALL_PARAMS = PRIM_PARAMS + (TEX_PARAM,)
BETA1, BETA2 = 0.9, 0.999


class SurfelAdam:
    def __init__(self, model, eps: float = 1e-15):
        self.eps = eps
        self.nonfinite: list[str] = []
        self.unchecked: list[str] = list(ALL_PARAMS)
        self.exp_avg = {n: torch.zeros_like(getattr(model, n)) for n in ALL_PARAMS}
        self.exp_avg_sq = {n: torch.zeros_like(getattr(model, n)) for n in ALL_PARAMS}
        self.steps = {n: 0 for n in ALL_PARAMS}
        self._lr_cache: dict = {}

    @torch.no_grad()
    def step(self, model, lrs: dict) -> None:
        """One Adam step; lrs maps a parameter name to a float or a broadcastable tensor (SH bands).

        On the CPU one fused pass per parameter (ctgs.ops.fused), which also counts the non-finite
        results: afterwards `nonfinite` names the parameters the step made NaN/Inf and `unchecked` those it
        updated without counting (the PyTorch path), for the trainer's guard.
        """
        self.nonfinite: list[str] = []
        self.unchecked: list[str] = []
        for name in ALL_PARAMS:
            p = getattr(model, name)
            lr = lrs.get(name, 0.0)
            if p.grad is None or p.numel() == 0 or (isinstance(lr, float) and lr == 0.0):
                continue
            g = p.grad
            m, v = self.exp_avg[name], self.exp_avg_sq[name]
            self.steps[name] += 1
            t = self.steps[name]
            if fused.fusable(p, g, m, v) and p.dtype == g.dtype == m.dtype == v.dtype:
                lr_t = None if not torch.is_tensor(lr) else self._expanded_lr(name, lr, p)
                bad = torch.ops.ctgs.adam_step(p.detach(), g, m, v, lr_t, float(lr) if lr_t is None else 0.0,
                                               BETA1, BETA2, t, self.eps, torch.get_num_threads())
                if bad:
                    self.nonfinite.append(name)
                continue
            self.unchecked.append(name)
            if p.is_cuda and torch_fused_step(p.detach(), g, m, v, lr, t, self.eps):
                continue
            m.mul_(BETA1).add_(g, alpha=1 - BETA1)
            v.mul_(BETA2).addcmul_(g, g, value=1 - BETA2)
            bc1 = 1 - BETA1 ** t
            bc2 = 1 - BETA2 ** t
            denom = (v / bc2).sqrt_().add_(self.eps)
            p.sub_(lr * (m / bc1) / denom)

    def _expanded_lr(self, name: str, lr: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
        """lr broadcast to p's shape as one contiguous tensor (the fused step reads one lr per element),
        kept while p's shape and the lr values stay the same (the SH bands' lrs are constant): building it
        is a [N, K, 3] copy, ~0.25 ms per step at 18k primitives."""
        key = (tuple(p.shape), p.dtype, tuple(lr.shape), tuple(lr.detach().flatten().tolist()))
        hit = self._lr_cache.get(name)
        if hit is not None and hit[0] == key:
            return hit[1]
        t = lr.to(p.dtype).expand_as(p).contiguous()
        self._lr_cache[name] = (key, t)
        return t

    def state_dict(self) -> dict:
        return {"eps": self.eps, "exp_avg": dict(self.exp_avg), "exp_avg_sq": dict(self.exp_avg_sq),
                "steps": dict(self.steps)}

    def load_state_dict(self, state: dict, device="cpu") -> None:
        self.eps = state["eps"]
        self.exp_avg = {k: v.to(device) for k, v in state["exp_avg"].items()}
        self.exp_avg_sq = {k: v.to(device) for k, v in state["exp_avg_sq"].items()}
        self.steps = dict(state["steps"])


def torch_fused_step(p: torch.Tensor, g: torch.Tensor, m: torch.Tensor, v: torch.Tensor, lr, t: int,
                     eps: float) -> bool:
    """One Adam step of p in place with torch's fused kernel (what torch.optim.Adam(fused=True) runs: one pass
    over p, g, m, v), if it applies: a float lr, one dtype, contiguous. The same update as SurfelAdam's PyTorch
    lines up to rounding (sqrt(v) / sqrt(1 - b2^t) for sqrt(v / (1 - b2^t))); those lines make ~10 passes and 3
    temporaries the size of p (on a GPU at the paper's 29M texels: ~1 GB and ~2 ms per step). Returns False
    (nothing done) where it does not apply."""
    if (torch.is_tensor(lr) or not all(x.is_contiguous() and x.dtype == p.dtype for x in (g, m, v))
            or p.dtype not in (torch.float32, torch.float64) or not hasattr(torch, "_fused_adam_")):
        return False
    step = torch.full((), float(t), dtype=torch.float32, device=p.device)
    torch._fused_adam_([p], [g], [m], [v], [], [step], lr=float(lr), beta1=BETA1, beta2=BETA2, weight_decay=0.0,
                       eps=eps, amsgrad=False, maximize=False)
    return True
