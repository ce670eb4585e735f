"""Cross-check ctgs' LPIPS against the original `lpips` package code, given the same VGG16 weights.

torchvision cannot be installed here, so a stand-in `torchvision.models.vgg16` is built from the weights
ctgs uses; the original lpips.LPIPS (scaling layer, normalisation, linear layers, averaging) then runs
unchanged. Usage (needs the lpips wheel or sdist unpacked, e.g. `pip download --no-deps lpips` + unzip):

    python benchmarks/lpips_crosscheck.py /path/to/unpacked/lpips_wheel
Prints the largest absolute difference; 0 means identical to float rounding.
"""

from __future__ import annotations

import sys
import types

import torch
import torch.nn as nn

from ctgs.metrics.lpips import load_lpips
from ctgs.metrics.vgg_weights import find_vgg16


def _fake_torchvision(state: dict) -> None:
    def vgg16(*args, **kwargs):
        cfg = [64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512, "M"]
        layers, c = [], 3
        for v in cfg:
            if v == "M":
                layers.append(nn.MaxPool2d(2, 2))
            else:
                layers += [nn.Conv2d(c, v, 3, padding=1), nn.ReLU(inplace=True)]
                c = v
        net = types.SimpleNamespace(features=nn.Sequential(*layers))
        net.features.load_state_dict({k[len("features."):]: v for k, v in state.items()})
        return net

    tv = types.ModuleType("torchvision")
    tv.models = types.SimpleNamespace(vgg16=vgg16, alexnet=None, squeezenet1_1=None)
    sys.modules.update({"torchvision": tv, "torchvision.models": tv.models,
                        "tqdm": types.SimpleNamespace(tqdm=None)})


def main(lpips_src: str) -> None:
    found = find_vgg16()
    if found.state is None:
        sys.exit(found.source)
    _fake_torchvision(found.state)
    sys.path.insert(0, lpips_src)
    import lpips

    ref = lpips.LPIPS(net="vgg", version="0.1", verbose=False).eval()
    mine, _ = load_lpips()
    g = torch.Generator().manual_seed(1)
    worst = 0.0
    for shape in [(1, 3, 64, 64), (2, 3, 97, 131)]:
        a = torch.rand(shape, generator=g)
        b = (a + 0.2 * torch.randn(shape, generator=g)).clamp(0, 1)
        with torch.no_grad():
            for norm in (False, True):
                r, m = ref(a, b, normalize=norm).flatten(), mine(a, b, normalize=norm).flatten()
                print(f"{shape} normalize={norm}: lpips package {r.tolist()} ctgs {m.tolist()}")
                worst = max(worst, float((r - m).abs().max()))
    print(f"max abs difference: {worst:.3g} (weights: {found.source})")


if __name__ == "__main__":
    main(sys.argv[1])
