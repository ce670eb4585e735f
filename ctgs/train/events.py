"""Typed events the trainer yields; the CLI renders them (rich progress) and the log records them."""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class Step:
    it: int
    loss: float
    psnr: float
    num_primitives: int
    num_texels: int
    seconds: float  # training seconds so far (excludes evaluation and checkpoints)


@dataclass
class Routine:
    it: int
    kind: str  # texture_start | full | late | realloc | densify | opacity_reset
    stats: dict = field(default_factory=dict)


@dataclass
class Planned:
    it: int
    iterations: int  # the planned run length (`--time-budget`)
    budget_s: float


@dataclass
class Estimated:
    it: int  # 0: from the calibration; later: from the measured steps
    iterations: int  # the run's fixed length
    wall_s: float  # predicted wall seconds of the whole run, command start to outputs written


@dataclass
class Eval:
    it: int
    test_psnr: float
    test_ssim: float


@dataclass
class Checkpoint:
    it: int
    path: str


@dataclass
class Done:
    it: int
    summary: dict
