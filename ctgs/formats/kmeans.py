"""K-means codebooks for compression: a 1-D one over scalar values and a vector one over rows.

1-D (the authors' texel codebook: 256 centres over every activated texel channel value): Lloyd's
algorithm on a fine histogram. In one dimension every cluster is an interval, so one Lloyd step is a
`searchsorted` of the bin centres against the midpoints between centres plus prefix sums: O(bins + K)
per step after a single O(values) pass, instead of O(values * K) per step for sklearn's KMeans on
millions of values. It starts from the high-resolution optimum (level density ~ p^(1/3)), which Lloyd
then only polishes. Exact 1-D K-means (dynamic programming, Ckmeans.1d.dp) needs O(K * values) Python-
level steps; on small inputs tests/formats/test_kmeans.py checks this result against it. Measured on 200k
tanh-Gaussian values, K = 256: RMS error 0.00201 here vs 0.00207 for sklearn KMeans (k-means++ start),
in 0.3 s vs 6.6 s. The bins (2^16 over the value range, ~1/250 of a level) only steer the iterations:
the final assignment and centres use the exact values.

Vector (RGB texels, SH coefficient rows): scikit-learn. Small problems use exact KMeans; large ones fit
MiniBatchKMeans on a sample and then assign every row to its nearest centre with a KD-tree (3-D rows) or
chunked brute force (wide rows), so K = 65536 on millions of texels finishes in minutes on 2 cores.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ctgs.errors import UserError

# Histogram bins of the 1-D K-means: fine enough that a bin is far below a quantisation level.
SCALAR_BINS = 1 << 16
# The density for the start comes from a coarse histogram of 2 n^(1/3) bins (Rice's rule) within these
# bounds: fine bins are too noisy for p^(1/3) (4096 bins on 1500 values ended 1.4-3.3x above the exact
# optimum at K = 32; Rice's bins within 1.09x, tests/formats/test_kmeans.py).
INIT_BINS_MIN, INIT_BINS_MAX = 16, 4096
# Lloyd on the histogram reaches a fixed point in ~40-60 steps from the start below (measured on
# tanh-Gaussian, Laplace and bimodal values, K = 256); the cap only bounds pathological inputs.
SCALAR_MAX_ITER = 500
# Above this much work (rows * K) exact KMeans gets slow on 2 cores (measured: 34k x 4096 took 100 s):
# MiniBatchKMeans on a sample is used instead.
MINIBATCH_ABOVE_WORK = 5e7
# MiniBatchKMeans fits on at most this many sampled rows (and at least 4 per centre when there are).
FIT_SAMPLE = 250_000
FIT_PER_CENTRE = 4
# Low-dimensional rows (RGB texels) with many centres: hand-rolled Lloyd with a KD-tree search, as
# sklearn's MiniBatchKMeans with K = 65536 did not finish within 20 minutes on a busy 2-core machine.
KDTREE_MAX_DIM = 3
KDTREE_ABOVE_K = 4096
LLOYD_ITERS = 20
# Rows per chunk of the brute-force nearest-centre search (bounds the [chunk, K] distance matrix).
ASSIGN_CHUNK = 8192


@dataclass
class Codebook:
    centres: np.ndarray  # [K] (scalar) or [K, D] (vector), float64
    labels: np.ndarray  # same leading shape as the input, int64 indices into centres
    method: str
    seconds: float


def _check_k(k: int, n: int, what: str) -> None:
    if k < 1:
        raise UserError(f"--codebook-size {k}: must be at least 1")
    if k > n:
        raise UserError(f"--codebook-size {k} is larger than the {n} {what} to cluster; pick a size <= {n}")


def scalar_kmeans(values: np.ndarray, k: int) -> Codebook:
    """1-D K-means of all entries of `values` (any shape) into `k` centres; labels have `values`' shape."""
    start = time.perf_counter()
    flat = np.asarray(values, dtype=np.float64).ravel()
    if k < 1:
        raise UserError(f"--codebook-size {k}: must be at least 1")
    distinct = np.unique(flat)
    if len(distinct) <= k:  # every value gets its own centre: lossless
        centres = np.concatenate([distinct, np.full(k - len(distinct), distinct[-1] if len(distinct) else 0.0)])
        labels = np.searchsorted(distinct, flat)
        return Codebook(centres, labels.reshape(values.shape), "exact (<= K distinct values)",
                        time.perf_counter() - start)
    lo, hi = float(distinct[0]), float(distinct[-1])
    # Start: the high-resolution optimum (Panter-Dite): level density ~ p(x)^(1/3), p from a coarse
    # histogram. Lloyd from equal-mass quantiles stalls in poor fixed points in 1-D (measured: RMS error
    # 18% above this start's on a tanh-Gaussian; above a uniform quantiser too).
    init_bins = int(np.clip(2.0 * len(flat) ** (1.0 / 3.0), INIT_BINS_MIN, INIT_BINS_MAX))
    coarse, _ = np.histogram(flat, bins=init_bins, range=(lo, hi))
    cdf = np.concatenate([[0.0], np.cumsum(coarse.astype(np.float64) ** (1.0 / 3.0))])
    centres = np.interp((np.arange(k) + 0.5) / k * cdf[-1], cdf, np.linspace(lo, hi, init_bins + 1))
    width = (hi - lo) / SCALAR_BINS
    bin_of = np.minimum(((flat - lo) / width).astype(np.int64), SCALAR_BINS - 1)
    counts = np.bincount(bin_of, minlength=SCALAR_BINS).astype(np.float64)
    sums = np.bincount(bin_of, weights=flat, minlength=SCALAR_BINS)
    occupied = counts > 0
    x, w, s = (lo + (np.nonzero(occupied)[0] + 0.5) * width), counts[occupied], sums[occupied]
    cw, cs = np.concatenate([[0.0], np.cumsum(w)]), np.concatenate([[0.0], np.cumsum(s)])
    for _ in range(SCALAR_MAX_ITER):
        edges = np.searchsorted(x, (centres[1:] + centres[:-1]) / 2)  # first bin of clusters 1..K-1
        bounds = np.concatenate([[0], edges, [len(x)]])
        mass = cw[bounds[1:]] - cw[bounds[:-1]]
        new = np.sort(np.where(mass > 0, (cs[bounds[1:]] - cs[bounds[:-1]]) / np.maximum(mass, 1e-300), centres))
        if np.array_equal(new, centres):  # a fixed point: no histogram bin changes cluster any more
            break
        centres = new
    # Exact finish: nearest centre for every value, then the exact mean of each cluster.
    labels = np.searchsorted((centres[1:] + centres[:-1]) / 2, flat)
    n = np.bincount(labels, minlength=k)
    means = np.bincount(labels, weights=flat, minlength=k) / np.maximum(n, 1)
    centres = np.where(n > 0, means, centres)
    order = np.argsort(centres, kind="stable")  # keep the codebook sorted (nicer for the entropy coder)
    labels = np.argsort(order)[labels]
    return Codebook(centres[order], labels.reshape(values.shape), "1-D Lloyd on a histogram",
                    time.perf_counter() - start)


def nearest_centre(x: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """[N] index of the nearest (L2) row of centres [K, D] for every row of x [N, D]."""
    if x.shape[1] <= 3:
        # scikit-learn takes about a second to import: loaded only where it is used
        from sklearn.neighbors import KDTree

        tree = KDTree(centres)
        return np.concatenate([tree.query(x[i:i + FIT_SAMPLE], k=1, return_distance=False)[:, 0]
                               for i in range(0, len(x), FIT_SAMPLE)]) if len(x) else np.zeros(0, np.int64)
    c2 = (centres ** 2).sum(1)
    out = np.empty(len(x), dtype=np.int64)
    for i in range(0, len(x), ASSIGN_CHUNK):
        chunk = x[i:i + ASSIGN_CHUNK]
        out[i:i + ASSIGN_CHUNK] = np.argmin(c2[None, :] - 2.0 * chunk @ centres.T, axis=1)
    return out


def _lloyd_kdtree(sample: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    """Lloyd iterations with a KD-tree nearest-centre search: [k, D] centres of sample [S, D] (D <= 3).

    Each step costs O(S log K) instead of the O(S * K) of sklearn's (MiniBatch)KMeans distance matrices;
    empty clusters restart at random sample rows.
    """
    # scikit-learn takes about a second to import: loaded only where it is used
    from sklearn.neighbors import KDTree

    centres = sample[rng.choice(len(sample), k, replace=False)].copy()
    for _ in range(LLOYD_ITERS):
        labels = KDTree(centres).query(sample, k=1, return_distance=False)[:, 0]
        n = np.bincount(labels, minlength=k)
        sums = np.stack([np.bincount(labels, weights=sample[:, d], minlength=k) for d in range(sample.shape[1])], 1)
        empty = n == 0
        centres = np.where(empty[:, None], centres, sums / np.maximum(n, 1)[:, None])
        if empty.any():
            centres[empty] = sample[rng.choice(len(sample), int(empty.sum()), replace=False)]
    return centres


def vector_kmeans(x: np.ndarray, k: int, *, seed: int = 0) -> Codebook:
    """K-means of the rows of x [N, D] into k centres [k, D]; labels [N]."""
    # scikit-learn takes about a second to import: loaded only where it is used
    from sklearn.cluster import KMeans, MiniBatchKMeans

    start = time.perf_counter()
    x = np.ascontiguousarray(x, dtype=np.float64)
    _check_k(k, len(x), "rows")
    if len(x) * k <= MINIBATCH_ABOVE_WORK:
        km = KMeans(n_clusters=k, n_init=1, max_iter=50, random_state=seed).fit(x)
        return Codebook(km.cluster_centers_, km.labels_.astype(np.int64), "KMeans", time.perf_counter() - start)
    rng = np.random.default_rng(seed)
    n_fit = min(len(x), max(FIT_SAMPLE, FIT_PER_CENTRE * k))
    sample = x if n_fit == len(x) else x[rng.choice(len(x), n_fit, replace=False)]
    if x.shape[1] <= KDTREE_MAX_DIM and k > KDTREE_ABOVE_K:
        centres, method = _lloyd_kdtree(sample, k, rng), f"Lloyd + KD-tree on {n_fit} rows"
    else:
        km = MiniBatchKMeans(n_clusters=k, batch_size=max(4096, 2 * k), n_init=1, max_iter=20,
                             random_state=seed).fit(sample)
        centres, method = km.cluster_centers_, f"MiniBatchKMeans on {n_fit} rows"
    labels = nearest_centre(x, centres)
    return Codebook(centres, labels, method + ", then nearest-centre assignment of all", time.perf_counter() - start)
