"""kill -9 inside a stage, then the same command again: the kill leaves nothing half-written under a final name
(at most a hidden temporary), and the second run completes and sweeps the dead run's temporaries.

The kill lands inside an atomic write chosen at random (seeded per stage), once its temporary is complete and
before the rename (tests/faults/kill_hook.py): the moment a kill hurts most. One child process per case (~3 s).
"""

from __future__ import annotations

import os
import random

import pytest

from fault_helpers import STAGES, cli, ctgs_subprocess, inject_enospc, stage_commands, temporaries

# train twice: inside a checkpoint, and inside the last writes (the summary and model.pt)
CASES = [(stage, "random") for stage in STAGES] + [("train", "last")]


def _whole(stage: str, out: str) -> bool:
    """Whether `out` holds a complete output (what a successful run leaves)."""
    if not os.path.exists(out):
        return False
    if stage == "train":
        return os.path.isfile(os.path.join(out, "model.pt")) and os.path.isfile(os.path.join(out, "train_summary.json"))
    return os.path.isfile(out) and os.path.getsize(out) > 0 or os.path.isdir(out) and bool(os.listdir(out))


@pytest.mark.parametrize(("stage", "where"), CASES, ids=[f"{s}-{w}" for s, w in CASES])
def test_kill_9_then_the_same_command(stage, where, pipeline, tmp_path, monkeypatch):
    with monkeypatch.context() as m:
        calls = inject_enospc(m, None)
        assert cli(stage_commands(pipeline, str(tmp_path / "count"))[stage][0]).exit_code == 0
    total = calls[0]
    at = total if where == "last" else random.Random(stage).randint(1, total)
    dest = str(tmp_path / "out")
    os.makedirs(dest)
    args, out = stage_commands(pipeline, dest)[stage]
    killed = ctgs_subprocess(args, kill_at_write=at)
    assert killed.returncode == -9, (at, total, killed.returncode, killed.stderr[-2000:])
    left = temporaries(dest)
    assert left, "the kill inside a write left no temporary: it did not land where intended"
    if stage == "train":
        assert not os.path.exists(os.path.join(out, "model.pt"))
    else:
        assert not os.path.lexists(out), f"{out} stands after a kill before its rename"
    again = cli(args)
    assert again.exit_code == 0, again.stderr
    assert _whole(stage, out)
    assert temporaries(dest) == [], f"not swept: {temporaries(dest)} (left by the kill: {left})"
