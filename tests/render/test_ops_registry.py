"""Every compiled op is declared once (ctgs.ops.schemas); the CPU extension registers a kernel for each, the CUDA
binding for each op both backends have (compiled by `make cuda-check`, run where a GPU is), and neither module
exposes an op by a name of its own."""

from __future__ import annotations

import re
from pathlib import Path

import torch

from ctgs.ops import fused, schemas
from ctgs.resources import kernels_dir

BOTH = [s.split("(", 1)[0] for s in schemas.BOTH]
CPU_ONLY = [s.split("(", 1)[0] for s in schemas.CPU_ONLY]


def test_every_declared_op_has_a_cpu_kernel_and_the_shared_ones_only_a_cuda_one():
    assert fused.cpu_ext() is not None
    assert schemas.op_names() == BOTH + CPU_ONLY and len(set(BOTH + CPU_ONLY)) == len(BOTH + CPU_ONLY)
    for name in BOTH + CPU_ONLY:
        assert torch._C._dispatch_has_kernel_for_dispatch_key(f"ctgs::{name}", "CPU"), name


def test_each_binding_registers_its_declared_ops_and_no_other():
    for binding, key, names in (("bindings.cpp", "CPU", BOTH + CPU_ONLY), ("bindings_cuda.cpp", "CUDA", BOTH)):
        source = (Path(kernels_dir()) / binding).read_text()
        block = re.search(r"TORCH_LIBRARY_IMPL\(ctgs, " + key + r", m\) \{(.*?)\n\}", source, re.S)
        assert block, binding
        assert sorted(re.findall(r'm\.impl\("(\w+)"', block.group(1))) == sorted(names), binding
        # the Python module keeps helpers only (tile size, profile counters): no op under a name of its own
        module = re.search(r"PYBIND11_MODULE\(TORCH_EXTENSION_NAME, m\) \{(.*?)\n\}", source, re.S)
        assert module, binding
        assert set(re.findall(r'm\.def\("(\w+)"', module.group(1))) <= {"tile_size", "profile_counters"}, binding


def test_declaring_twice_is_harmless():
    schemas.declare()
    schemas.declare()
    assert torch._C._dispatch_has_kernel_for_dispatch_key("ctgs::rasterize_forward", "CPU")
