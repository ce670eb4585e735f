"""K-means texel compression (paper sec. "Storage and Memory"): a codebook of K colours + an index per texel.

Texel offsets are activated with 2*sigmoid(x)-1, so they live in [-1, 1]^3: K-means runs on those
activated 3-vectors (the space the renderer adds to the colour), the centres go back to raw
(pre-activation) values so the blob keeps one encoding, and every texel stores only a uint8 (K <= 256),
uint16 (K <= 65536) or uint32 index.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from ctgs.errors import UserError
from ctgs.io.texture_blob import TextureBlob, index_dtype_for
from ctgs.model.surfels import SurfelModel

# Exact KMeans costs ~ T * K per Lloyd iteration: above this much work MiniBatchKMeans is used instead
# (measured: exact KMeans with T = 34k, K = 4096 took 100 s on 2 CPU cores).
MINIBATCH_ABOVE_WORK = 5e7
# MiniBatchKMeans fits on at most this many sampled texels, then assigns all of them.
FIT_SAMPLE = 250_000
# Centres are clamped inside (-1, 1) before the inverse activation so the raw value stays finite.
ACT_LIMIT = 1.0 - 1e-6


@dataclass
class CodebookResult:
    blob: TextureBlob  # codebook [K, 3] raw values + indices [T]
    codebook_size: int  # K
    rmse_activated: float  # RMS error of the quantised activated texels, in texture units ([-1, 1])
    method: str  # "KMeans" or "MiniBatchKMeans"
    seconds: float


def activated_to_raw(act: np.ndarray) -> np.ndarray:
    """Inverse of 2*sigmoid(x)-1 (clamped into the open interval)."""
    p = (np.clip(act, -ACT_LIMIT, ACT_LIMIT) + 1.0) / 2.0
    return np.log(p) - np.log1p(-p)


def kmeans_codebook(model: SurfelModel, k: int, *, seed: int = 0, half: bool = False) -> CodebookResult:
    """Cluster the activated texels of `model` into `k` colours. half: codebook stored as float16."""
    t = model.num_texels
    if k < 1:
        raise UserError(f"--codebook-size {k}: must be at least 1")
    if k > t:
        raise UserError(f"--codebook-size {k} is larger than the model's {t} texels; pick a size <= {t}")
    from sklearn.cluster import KMeans, MiniBatchKMeans

    start = time.perf_counter()
    act = model.textures.detach().cpu().to(torch.float64).numpy()  # [T, 3] in [-1, 1]
    if t * k <= MINIBATCH_ABOVE_WORK:
        km = KMeans(n_clusters=k, n_init=1, max_iter=50, random_state=seed).fit(act)
        labels, method = km.labels_, "KMeans"
    else:
        rng = np.random.default_rng(seed)
        sample = act if t <= FIT_SAMPLE else act[rng.choice(t, FIT_SAMPLE, replace=False)]
        km = MiniBatchKMeans(n_clusters=k, batch_size=max(4096, 2 * k), n_init=1, max_iter=20,
                             random_state=seed).fit(sample)
        labels = np.concatenate([km.predict(act[i:i + FIT_SAMPLE]) for i in range(0, t, FIT_SAMPLE)])
        method = "MiniBatchKMeans"
    centres = km.cluster_centers_  # [K, 3] activated
    raw = activated_to_raw(centres).astype(np.float16 if half else np.float32)
    # Error of what the reader will actually render: re-activate the stored (possibly fp16) raw values.
    decoded = 2.0 / (1.0 + np.exp(-raw.astype(np.float64))) - 1.0
    rmse = float(np.sqrt(np.mean((decoded[labels] - act) ** 2))) if t else 0.0
    indices = labels.astype(index_dtype_for(k))
    return CodebookResult(TextureBlob(raw, indices), k, rmse, method, time.perf_counter() - start)
