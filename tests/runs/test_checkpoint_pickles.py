"""Checkpoints are data: written as tensors and plain values, read with torch.load(weights_only=True). An earlier
ctgs's checkpoint (numpy's random state pickled as an array) is read with numpy arrays allowed and a note, once; a
pickle that names anything else is refused in one line and nothing in it runs (the CLI's case:
tests/faults/test_corrupt_inputs.py)."""

from __future__ import annotations

import os
import pickle
import random
import shutil

import numpy as np
import pytest
import torch

from ctgs.errors import UserError
from ctgs.runs import checkpoint as ckpt

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
EARLIER = os.path.join(ROOT, "tests", "data", "resume_736cf4e", "content_aware")  # written by an earlier ctgs


class CreatesAFile:
    """Unpickled, creates `path`: a pickle may call any function it names, here `open`."""

    def __init__(self, path: str):
        self.path = path

    def __reduce__(self):
        return open, (self.path, "w")


def _draws(gen: torch.Generator) -> tuple:
    return (torch.rand(3).tolist(), torch.rand(3, generator=gen).tolist(), np.random.rand(3).tolist(),
            random.random())


def test_a_checkpoint_is_tensors_and_plain_values_and_resumes_every_random_stream(tmp_path):
    run = str(tmp_path)
    os.makedirs(os.path.join(run, "checkpoints"))
    gen = torch.Generator().manual_seed(3)
    np.random.seed(4)
    np.random.normal()  # numpy keeps half of a Gaussian pair: part of its state
    ckpt.save_checkpoint(run, {"iteration": 7, "model": {"x": torch.arange(3)}, "rng": ckpt.rng_state(gen)})
    expected = _draws(gen)
    state = torch.load(ckpt.checkpoint_path(run), weights_only=True)  # no allowlist needed
    other = torch.Generator().manual_seed(99)
    ckpt.restore_rng(state["rng"], other)
    assert _draws(other) == expected


def test_an_earlier_checkpoint_is_read_once_with_a_note(tmp_path, capsys):
    with pytest.raises(pickle.UnpicklingError):  # the fixture is what this covers: an array weights_only refuses
        torch.load(os.path.join(EARLIER, "checkpoints", "last.pt"), weights_only=True)
    run = shutil.copytree(EARLIER, str(tmp_path / "run"))
    state = ckpt.load_checkpoint(run)
    note = capsys.readouterr().err.strip().splitlines()
    assert state["iteration"] == 30 and len(note) == 1 and "earlier ctgs" in note[0] and "last.pt" in note[0]
    assert ckpt.readable_checkpoint(run) == (ckpt.checkpoint_path(run), 30)
    gen = torch.Generator()
    ckpt.restore_rng(state["rng"], gen)  # numpy's state as the earlier tuple
    # the next checkpoint the resumed run writes has its random state as tensors: read without a note
    ckpt.save_checkpoint(run, state | {"iteration": 31, "rng": ckpt.rng_state(gen)})
    assert ckpt.load_checkpoint(run)["iteration"] == 31 and capsys.readouterr().err == ""
    torch.load(ckpt.checkpoint_path(run), weights_only=True)


def _crafted(path: str, marker: str, how: str) -> None:
    """A checkpoint-shaped file whose unpickling calls open(marker, "w")."""
    state = {"iteration": 5, "model": {}, "rng": {"extra": CreatesAFile(marker)}}
    if how == "torch.save":
        torch.save(state | {"model": {"x": torch.zeros(2)}}, path)
    else:  # a bare pickle: protocol 2 names the function by a GLOBAL opcode, protocol 4 by STACK_GLOBAL
        with open(path, "wb") as f:
            pickle.dump(state, f, protocol=int(how[-1]))


@pytest.mark.parametrize("how", ["torch.save", "pickle2", "pickle4"])
def test_a_crafted_pickle_is_refused_and_nothing_runs(tmp_path, capsys, how):
    control = str(tmp_path / "control.pt")
    _crafted(control, str(tmp_path / "control_ran"), how)
    with open(control, "rb") as f:
        if how == "torch.save":
            torch.load(f, weights_only=False)
        else:
            pickle.load(f)
    assert os.path.exists(tmp_path / "control_ran")  # the payload works: unpickled as-is, it creates its file

    run = str(tmp_path / "run")
    os.makedirs(os.path.join(run, "checkpoints"))
    ckpt.save_checkpoint(run, {"iteration": 4, "model": {}})  # a good prev.pt, which a refusal must not hide
    ckpt.save_checkpoint(run, {"iteration": 5, "model": {}})
    marker = str(tmp_path / "ran")
    _crafted(ckpt.checkpoint_path(run), marker, how)
    if how == "pickle4":  # no name weights_only can read before it stops: an unreadable file, prev.pt instead
        assert ckpt.load_checkpoint(run)["iteration"] == 4
        assert "unreadable" in capsys.readouterr().err
    else:
        with pytest.raises(ckpt.UntrustedCheckpoint) as refused:
            ckpt.load_checkpoint(run)
        line = str(refused.value)
        assert "\n" not in line and "last.pt" in line and "io.open" in line and "-o" in line, line
        assert isinstance(refused.value, UserError)  # the CLI prints it as its one error line
        with pytest.raises(ckpt.UntrustedCheckpoint):
            ckpt.readable_checkpoint(run)
        assert ckpt.main([run]) == 1
        out = capsys.readouterr()
        assert out.out == "" and len(out.err.strip().splitlines()) == 1 and "last.pt" in out.err  # no --resume
        assert os.path.exists(ckpt.checkpoint_path(run))  # kept where it is, for its owner to look at
    assert not os.path.exists(marker)


def test_the_package_unpickles_nothing_beyond_weights():
    """Every torch.load in ctgs reads with weights_only=True (checkpoints here, models in ctgs.runs.read), and no
    module unpickles with pickle's own loader (ctgs.metrics.vgg_weights has an Unpickler that allows numpy arrays
    only)."""
    found = []
    for folder, _, files in os.walk(os.path.join(ROOT, "ctgs")):
        for name in (n for n in files if n.endswith(".py")):
            path = os.path.join(folder, name)
            with open(path, encoding="utf-8") as f:
                for i, line in enumerate(f, 1):
                    if "weights_only=False" in line or "pickle.load(" in line or "pickle.loads(" in line:
                        found.append(f"{os.path.relpath(path, ROOT)}:{i}")
    assert not found, found
