"""What every training strategy has besides the hooks (ctgs.train.hooks): a strategy sees the run's TrainState and
keeps its own state, and names the config keys it reads (its Settings).

A strategy's `KEYS` are every TrainConfig key its code reads, directly, through the schedule (ctgs.train.config.schedule)
and through its routines (ctgs.train.routines); `Settings` is a frozen dataclass of exactly those fields, with the
config's types, defaults and help (TrainConfig and configs/default.toml stay the one source of both), so a reader sees
in one place what each method uses, as gsplat's DefaultStrategy and MCMCStrategy list their fields. Keys of the loop
itself (iterations, seed, backend, method, schedule_scale: RUN_KEYS) belong to no strategy.
tests/train/test_strategies.py checks each KEYS against what the code reads.
"""

from __future__ import annotations

from dataclasses import MISSING, field, fields, make_dataclass

from ctgs.train.config import TrainConfig
from ctgs.train.hooks import Component

RUN_KEYS = ("iterations", "seed", "backend", "method", "schedule_scale")


def settings_class(name: str, keys: tuple[str, ...], doc: str) -> type:
    """A frozen dataclass `name` of the TrainConfig fields `keys` (their types, defaults and help), with
    `of(cfg)`: the values a config holds."""
    base = {f.name: f for f in fields(TrainConfig)}
    unknown = sorted(set(keys) - set(base))
    if unknown:
        raise ValueError(f"{name}: not config keys: {unknown}")
    specs = []
    for k in keys:
        f = base[k]
        kw = {"default_factory": f.default_factory} if f.default_factory is not MISSING else {"default": f.default}
        specs.append((k, f.type, field(metadata=f.metadata, **kw)))
    cls = make_dataclass(name, specs, frozen=True)
    cls.__doc__ = doc
    cls.of = classmethod(lambda c, cfg: c(**{k: getattr(cfg, k) for k in keys}))
    return cls


class Strategy(Component):
    KEYS: tuple[str, ...] = ()  # the config keys it reads (module docstring)
    Settings: type = settings_class("Settings", (), "No keys.")
    texture_mode = "content_aware"  # the model's texture mode (ctgs.train.start.init.init_model)
    starts_textures = False  # textures allocated partway (at texture_start), not with the model
    # what its pruning removes (said when a routine leaves no primitive)
    prune_rules = "opacity below its threshold"

    @classmethod
    def settings(cls, cfg):
        """This strategy's values of a config (a `Settings`)."""
        return cls.Settings.of(cfg)

    def step_stats(self, st):
        """A ctgs.render.BackwardStats for this step's render to fill in its backward, or None (no statistics)."""
        return None
