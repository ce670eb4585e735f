"""K-means codebooks: the 1-D histogram Lloyd against the exact optimum, the vector paths' assignments."""

from __future__ import annotations

import numpy as np
import pytest

from ctgs.errors import UserError
from ctgs.formats import kmeans
from ctgs.formats.kmeans import nearest_centre, scalar_kmeans, vector_kmeans

# The histogram Lloyd may end in a local optimum; on these inputs it stays within this factor of the exact
# minimum of the squared error (observed: 1.000-1.089, worst bimodal K=32).
SCALAR_VS_OPTIMUM = 1.10


def _exact_1d(values: np.ndarray, k: int) -> float:
    """Minimum total squared error of k clusters of 1-D values (dynamic programming over sorted values)."""
    x = np.sort(values)
    n = len(x)
    c1, c2 = np.concatenate([[0], np.cumsum(x)]), np.concatenate([[0], np.cumsum(x * x)])
    i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
    m = np.maximum(j - i, 1)
    cost = np.where(j > i, c2[j] - c2[i] - (c1[j] - c1[i]) ** 2 / m, np.inf)  # [i, j]: one cluster x[i:j]
    best = cost[0].copy()  # best[j]: one cluster over x[:j]
    for _ in range(1, k):  # one more cluster: the last one is x[i:j]
        best = np.min(best[:, None] + cost, axis=0)
    return float(best[n])


@pytest.mark.parametrize("dist,k", [("normal", 4), ("normal", 32), ("bimodal", 12), ("bimodal", 32),
                                    ("laplace", 12), ("laplace", 32)])
def test_scalar_kmeans_near_the_exact_optimum(dist, k):
    rng = np.random.default_rng(1)
    v = {"normal": lambda: rng.normal(0, 0.3, 1500),
         "bimodal": lambda: np.concatenate([rng.normal(-0.5, 0.05, 750), rng.normal(0.3, 0.2, 750)]),
         "laplace": lambda: rng.laplace(0, 0.1, 1500)}[dist]()
    cb = scalar_kmeans(v, k)
    sse = float(((cb.centres[cb.labels] - v) ** 2).sum())
    assert sse <= SCALAR_VS_OPTIMUM * _exact_1d(v, k)
    # Every value sits at its nearest centre and every centre is the mean of its values (a Lloyd fixed point).
    assert np.array_equal(cb.labels, np.abs(v[:, None] - cb.centres[None]).argmin(1))
    for c in range(k):
        if (cb.labels == c).any():
            assert abs(cb.centres[c] - v[cb.labels == c].mean()) < 1e-12
    assert np.all(np.diff(cb.centres) >= 0)  # sorted codebook


def test_scalar_kmeans_keeps_shape_and_is_lossless_with_few_values():
    v = np.array([[0.5, -0.25, 0.5], [0.0, 0.0, -0.25]])
    cb = scalar_kmeans(v, 4)
    assert cb.labels.shape == v.shape and np.array_equal(cb.centres[cb.labels], v)


def test_scalar_kmeans_beats_uniform_levels_on_peaked_values():
    # Texel offsets pile up near 0: K-means levels follow the density, a uniform quantiser does not.
    rng = np.random.default_rng(0)
    v = np.tanh(rng.laplace(0, 0.05, 200_000))
    cb = scalar_kmeans(v, 256)
    lo, hi = v.min(), v.max()
    uniform = lo + np.round((v - lo) / (hi - lo) * 255) / 255 * (hi - lo)
    assert np.sqrt(np.mean((cb.centres[cb.labels] - v) ** 2)) < 0.7 * np.sqrt(np.mean((uniform - v) ** 2))


def test_nearest_centre_matches_brute_force():
    rng = np.random.default_rng(2)
    for d in (3, 7):  # KD-tree path and chunked brute force
        x, c = rng.normal(size=(2000, d)), rng.normal(size=(100, d))
        want = ((x[:, None, :] - c[None]) ** 2).sum(-1).argmin(1)
        assert np.array_equal(nearest_centre(x, c), want)


@pytest.mark.parametrize("path", ["exact", "minibatch", "kdtree"])
def test_vector_kmeans_paths(monkeypatch, path):
    rng = np.random.default_rng(3)
    x = np.tanh(rng.normal(0, 0.5, (4000, 3)))
    if path != "exact":  # force the large-problem paths on a small input
        monkeypatch.setattr(kmeans, "MINIBATCH_ABOVE_WORK", 0)
        monkeypatch.setattr(kmeans, "KDTREE_ABOVE_K", 0 if path == "kdtree" else 10 ** 9)
    errors = []
    for k in (8, 64):
        cb = vector_kmeans(x, k, seed=0)
        assert cb.centres.shape == (k, 3) and cb.labels.shape == (4000,)
        assert np.array_equal(cb.labels, nearest_centre(x, cb.centres))
        errors.append(float(np.mean((cb.centres[cb.labels] - x) ** 2)))
        assert {"exact": "KMeans", "minibatch": "MiniBatchKMeans", "kdtree": "KD-tree"}[path] in cb.method
    assert errors[1] < 0.5 * errors[0]  # more centres, smaller error


def test_codebook_size_checks():
    with pytest.raises(UserError, match="at least 1"):
        scalar_kmeans(np.zeros(3), 0)
    with pytest.raises(UserError, match="larger than"):
        vector_kmeans(np.zeros((3, 3)), 4)
