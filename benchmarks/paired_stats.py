"""Paired comparison over seeds: mean difference, standard deviation, paired t, its two-sided p and the 95%
interval (Student t; scipy comes with scikit-learn). Used by equal_time_summary.py and paired.py; `group_specs`
parses the `--group NAME=RUN[,RUN...]` arguments of validation_runs.py and seen_pixels.py."""

from __future__ import annotations

import math
import statistics


def paired(diffs: list[float]) -> dict:
    """diffs: per-seed differences (A - B). Returns n, mean, sd, t, dof, p (two-sided), ci95 (lo, hi), wins."""
    from scipy import stats

    n = len(diffs)
    mean = statistics.mean(diffs) if n else float("nan")
    sd = statistics.stdev(diffs) if n > 1 else float("nan")
    out = {"n": n, "mean": mean, "sd": sd, "dof": n - 1, "wins": sum(d > 0 for d in diffs),
           "t": float("nan"), "p": float("nan"), "ci95": (float("nan"), float("nan")), "t_crit": float("nan")}
    if n > 1 and sd > 0:
        se = sd / math.sqrt(n)
        t = mean / se
        crit = float(stats.t.ppf(0.975, n - 1))
        out.update(t=t, p=float(2 * stats.t.sf(abs(t), n - 1)), ci95=(mean - crit * se, mean + crit * se),
                   t_crit=crit)
    return out


def sentence(label: str, s: dict) -> str:
    """One line: 'label: mean +x dB, sd y, A ahead on k of n seeds, paired t = .. (dof), p = .., 95% CI [..]'."""
    if s["n"] < 2:
        return f"{label}: {s['mean']:+.2f} dB from one seed (no spread: one pair is not evidence either way)."
    lo, hi = s["ci95"]
    return (f"{label}: mean {s['mean']:+.2f} dB, standard deviation {s['sd']:.2f} dB, ahead on {s['wins']} of {s['n']} "
            f"seeds, paired t = {s['t']:.2f} with {s['dof']} degrees of freedom (|t| > {s['t_crit']:.2f} for 5% "
            f"two-sided), p = {s['p']:.3f}, 95% interval [{lo:+.2f}, {hi:+.2f}] dB.")


def group_specs(specs: list[str], script: str) -> list[tuple[str, list[str]]]:
    """`--group NAME=RUN[,RUN...]` values -> [(name, [run dirs])] (one run per seed, empty entries dropped)."""
    groups = []
    for spec in specs:
        if "=" not in spec:
            raise SystemExit(f"{script}: write groups as NAME=RUN_DIR[,RUN_DIR...], got {spec!r}")
        name, dirs = spec.split("=", 1)
        groups.append((name, [d for d in dirs.split(",") if d]))
    return groups
