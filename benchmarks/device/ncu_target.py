"""A short target for Nsight Compute: the bench_cuda.py scene (1920x1080), three fwd+bwd of our CUDA backend.

    ncu -k regex:"forward_kernel|backward_kernel" --launch-skip 4 --launch-count 2 \
        python3 benchmarks/device/ncu_target.py [--n 1000000] [--textured]

(launch-skip 4 = the first two iterations' forward and backward kernels: the third is profiled warm.)
"""

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bench_cuda import Ours, make_scene  # noqa: E402

ap = argparse.ArgumentParser()
ap.add_argument("--n", type=int, default=1_000_000)
ap.add_argument("--textured", action="store_true")
args = ap.parse_args()
dev = torch.device("cuda")
s, cam, _ = make_scene(args.n, 1920, 1080, seed=0, device=dev, depth_complexity=20.0, textured=args.textured)
runner = Ours(s, cam, args.textured, dev)
for _ in range(3):
    runner.fwd_bwd()
torch.cuda.synchronize()
print("ncu target done")
