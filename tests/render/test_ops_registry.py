"""The ops both backends have are declared once (ctgs.ops.dispatch.SCHEMAS); the CPU extension registers a kernel for
each, and so does the CUDA binding (compiled by `make cuda-check`, run where a GPU is)."""

from __future__ import annotations

import re
from pathlib import Path

import torch

from ctgs.ops import dispatch, fused
from ctgs.resources import kernels_dir

NAMES = [re.match(r"(\w+)\(", s).group(1) for s in dispatch.SCHEMAS]


def test_every_declared_op_has_a_cpu_kernel():
    assert fused.cpu_ext() is not None
    for name in NAMES:
        assert torch._C._dispatch_has_kernel_for_dispatch_key(f"ctgs::{name}", "CPU"), name


def test_each_binding_registers_every_declared_op_and_no_other():
    for binding, key in (("bindings.cpp", "CPU"), ("bindings_cuda.cpp", "CUDA")):
        source = (Path(kernels_dir()) / binding).read_text()
        block = re.search(r"TORCH_LIBRARY_IMPL\(ctgs, " + key + r", m\) \{(.*?)\n\}", source, re.S)
        assert block, binding
        assert sorted(re.findall(r'm\.impl\("(\w+)"', block.group(1))) == sorted(NAMES), binding
