"""A run's config: its keys, defaults and loading (keys.py), the rules that resolve it for a scene's image size and
size budget (rules.py), and the calendar of its steps in paper-scale iterations (schedule.py)."""

from __future__ import annotations

from ctgs.train.config.keys import (METHODS, PRESETS, TrainConfig, apply_overrides, config_path, describe_keys,
                                    field_names, load_config, load_toml, parse_set)

__all__ = ["METHODS", "PRESETS", "TrainConfig", "apply_overrides", "config_path", "describe_keys", "field_names",
           "load_config", "load_toml", "parse_set"]
