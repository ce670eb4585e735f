"""Which photo pairs `ctgs sfm` matches, for captures too large to match every pair.

Retrieval: COLMAP's vocabulary-tree pairing needs a tree file trained on millions of descriptors, which cannot
be downloaded at run time here, and training one with pycolmap's `VisualIndex.build` measured 418 s for 1,024
words on 200k descriptors on the 2-core VM (faiss k-means, 100 iterations x 3 rounds). So the vocabulary is
the capture's own: k-means (scikit-learn's MiniBatchKMeans) on a sample of its SIFT descriptors, then each
photo a TF-IDF weighted bag of visual words, and a photo's most similar photos are those with the largest
cosine similarity of these vectors (Sivic and Zisserman's "Video Google", the scoring of COLMAP's tree).

Sequential: the pairs of COLMAP's sequential pairing (each photo with its next ones in name order, and with
quadratic overlap), plus loop closure from the same retrieval: each photo with its most similar photos outside
that neighbourhood (COLMAP's loop detection needs the vocabulary tree file).
"""

from __future__ import annotations

import os
import time

import numpy as np

from ctgs.scene.colmap import import_pycolmap

# Visual words of the capture's vocabulary, and the descriptors it is trained on / each photo is described by.
VOCABULARY_WORDS = 1024
VOCABULARY_SAMPLE = 60_000
DESCRIPTORS_PER_IMAGE = 1500
ASSIGN_CHUNK = 32_768


def read_descriptors(database_path: str) -> tuple[list[str], list[np.ndarray]]:
    """(image names sorted, each image's SIFT descriptors [N, 128] as stored: uint8) from a COLMAP database. Bytes,
    not floats: a 250-photo capture at 5,000 features holds 160 MB of them, 4x that as float32."""
    pycolmap = import_pycolmap()
    db = pycolmap.Database.open(database_path)
    try:
        images = sorted(db.read_all_images(), key=lambda im: im.name)
        names = [im.name for im in images]
        descriptors = [np.asarray(db.read_descriptors(im.image_id).data) for im in images]
    finally:
        db.close()
    return names, descriptors


def _nearest_word(x: np.ndarray, words: np.ndarray) -> np.ndarray:
    """Index of the nearest row of `words` [K, D] for each row of x [N, D] (squared L2, chunked)."""
    out = np.empty(len(x), dtype=np.int64)
    w2 = (words * words).sum(1)
    for start in range(0, len(x), ASSIGN_CHUNK):
        chunk = x[start:start + ASSIGN_CHUNK]
        out[start:start + len(chunk)] = np.argmin(w2[None, :] - 2.0 * chunk @ words.T, axis=1)
    return out


def similarity(descriptors: list[np.ndarray], *, seed: int = 0) -> np.ndarray:
    """[N, N] cosine similarity of the photos' TF-IDF bags of visual words (diagonal set to -inf)."""
    # scikit-learn takes about a second to import: loaded only where it is used
    from sklearn.cluster import MiniBatchKMeans

    rng = np.random.default_rng(seed)
    n = len(descriptors)
    subsets = [(d[rng.choice(len(d), DESCRIPTORS_PER_IMAGE, replace=False)] if len(d) > DESCRIPTORS_PER_IMAGE
                else d).astype(np.float32) for d in descriptors]
    pool = np.concatenate([s for s in subsets if len(s)]) if any(len(s) for s in subsets) else np.zeros((0, 128))
    k = int(min(VOCABULARY_WORDS, max(1, len(pool) // 8)))
    sample = pool[rng.choice(len(pool), VOCABULARY_SAMPLE, replace=False)] if len(pool) > VOCABULARY_SAMPLE else pool
    kmeans = MiniBatchKMeans(n_clusters=k, init="random", batch_size=4096, n_init=1, max_iter=20, random_state=seed,
                             compute_labels=False).fit(sample)
    words = kmeans.cluster_centers_.astype(np.float32)
    counts = np.zeros((n, k), dtype=np.float64)
    for i, s in enumerate(subsets):
        if len(s):
            np.add.at(counts[i], _nearest_word(s, words), 1.0)
    df = (counts > 0).sum(0)
    idf = np.log(n / np.maximum(df, 1))
    vectors = counts / np.maximum(counts.sum(1, keepdims=True), 1.0) * idf
    vectors /= np.maximum(np.linalg.norm(vectors, axis=1, keepdims=True), 1e-12)
    sim = vectors @ vectors.T
    np.fill_diagonal(sim, -np.inf)
    return sim


def retrieval_pairs(sim: np.ndarray, neighbours: int) -> set[tuple[int, int]]:
    """Each photo with its `neighbours` most similar photos (index pairs i < j)."""
    n = len(sim)
    k = min(neighbours, n - 1)
    top = np.argsort(-sim, axis=1)[:, :k]
    return {(min(i, int(j)), max(i, int(j))) for i in range(n) for j in top[i]}


def loop_pairs(sim: np.ndarray, neighbours: int, window: int) -> set[tuple[int, int]]:
    """Loop closure: each photo with its `neighbours` most similar photos more than `window` away in name order."""
    n = len(sim)
    idx = np.arange(n)
    far = np.where(np.abs(idx[:, None] - idx[None, :]) > window, sim, -np.inf)
    pairs = set()
    for i in range(n):
        for j in np.argsort(-far[i])[:neighbours]:
            if np.isfinite(far[i, j]):
                pairs.add((min(i, int(j)), max(i, int(j))))
    return pairs


def name_order_pairs(n: int, overlap: int, quadratic: bool) -> set[tuple[int, int]]:
    """Neighbours in name order, as COLMAP's sequential pairing makes them (pycolmap.SequentialPairingOptions:
    each photo with the next `overlap` photos, and with quadratic overlap also the photos 2^k ahead)."""
    pairs = set()
    for i in range(n):
        for d in range(1, overlap + 1):
            if i + d < n:
                pairs.add((i, i + d))
            if quadratic and i + 2 ** (d - 1) < n:
                pairs.add((i, i + 2 ** (d - 1)))
    return pairs


def write_pairs(path: str, names: list[str], pairs: set[tuple[int, int]]) -> None:
    """A COLMAP match list (`NAME1 NAME2` per line), sorted, written under a temporary name and renamed."""
    tmp = f"{path}.tmp{os.getpid()}"
    with open(tmp, "w") as f:
        for i, j in sorted(pairs):
            f.write(f"{names[i]} {names[j]}\n")
    os.replace(tmp, path)


def make_pairs(database_path: str, mode: str, *, neighbours: int, overlap: int, loop_neighbours: int,
               seed: int = 0) -> tuple[list[str], set[tuple[int, int]], dict]:
    """(image names, index pairs, figures) for mode "retrieval" (each photo's `neighbours` most similar photos and
    its next `overlap` in name order) or "sequential" (COLMAP's sequential pairs with `overlap`, plus each photo's
    `loop_neighbours` most similar photos outside that window: loop closure)."""
    start = time.perf_counter()
    names, descriptors = read_descriptors(database_path)
    sim = similarity(descriptors, seed=seed)
    if mode == "retrieval":
        pairs = retrieval_pairs(sim, neighbours) | name_order_pairs(len(names), overlap, quadratic=False)
    elif mode == "sequential":
        pairs = name_order_pairs(len(names), overlap, quadratic=True)
        pairs |= loop_pairs(sim, loop_neighbours, window=overlap)
    else:
        raise ValueError(f"make_pairs: unknown mode {mode!r}")
    return names, pairs, {"pairs": len(pairs), "pairing_seconds": time.perf_counter() - start}
