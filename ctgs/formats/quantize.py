"""Per-attribute codecs of compressed models: float32/float16 storage and b-bit fixed point.

Every codec is a pair: `encode(values [rows, cols]) -> (stored array, encoding dict)` and
`decode(stored, encoding) -> values [rows, cols]` (float64). The encoding dict goes to the manifest and
is all a reader needs (docs/reference/model_format.md, "Compressed models"):

- `{"kind": "float"}`: the stored float16/float32 values are the values.
- `{"kind": "fixed", "levels": L, "min": [...], "max": [...]}`: stored unsigned integers q in [0, L],
  value = min + q * (max - min) / L per column (L = 2^bits - 1; min/max one per column).
- `{"kind": "codebook", "codebook": NAME}`: stored indices into the rows of section NAME
  (written by ctgs.formats.compress).
"""

from __future__ import annotations

import numpy as np

FLOAT_CODECS = {"f32": np.dtype("<f4"), "f16": np.dtype("<f2")}
FIXED_CODECS = {"q8": 8, "q16": 16}


def fixed_dtype(bits: int) -> np.dtype:
    return np.dtype("u1") if bits <= 8 else np.dtype("<u2")


def encode(values: np.ndarray, codec: str, lo: np.ndarray | None = None,
           hi: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
    """Store values [rows, cols] with `codec`; fixed point over [lo, hi] per column (default: data range)."""
    values = np.asarray(values, dtype=np.float64)
    if codec in FLOAT_CODECS:
        return values.astype(FLOAT_CODECS[codec]), {"kind": "float"}
    if codec not in FIXED_CODECS:
        raise ValueError(f"unknown codec {codec!r}; expected one of {sorted(FLOAT_CODECS) + sorted(FIXED_CODECS)}")
    bits = FIXED_CODECS[codec]
    levels = (1 << bits) - 1
    cols = values.shape[1] if values.ndim == 2 else 1
    v2 = values.reshape(len(values), cols)
    if lo is None:
        lo = v2.min(0) if len(v2) else np.zeros(cols)
    if hi is None:
        hi = v2.max(0) if len(v2) else np.ones(cols)
    lo, hi = np.broadcast_to(np.asarray(lo, np.float64), (cols,)), np.broadcast_to(np.asarray(hi, np.float64), (cols,))
    span = np.where(hi > lo, hi - lo, 1.0)  # a constant column stores q = 0
    q = np.clip(np.rint((v2 - lo) / span * levels), 0, levels).astype(fixed_dtype(bits))
    enc = {"kind": "fixed", "levels": levels, "min": [float(x) for x in lo], "max": [float(x) for x in hi]}
    return q.reshape(values.shape), enc


def decode(stored: np.ndarray, encoding: dict) -> np.ndarray:
    """Values (float64, same shape as `stored`) of a float or fixed-point section."""
    kind = encoding.get("kind")
    if kind == "float":
        return stored.astype(np.float64)
    if kind == "fixed":
        levels = float(encoding["levels"])
        lo, hi = np.asarray(encoding["min"], np.float64), np.asarray(encoding["max"], np.float64)
        cols = stored.shape[1] if stored.ndim == 2 else 1
        if lo.shape != (cols,) or hi.shape != (cols,) or levels <= 0:
            raise ValueError(f"fixed-point range has {lo.size}/{hi.size} entries for {cols} columns")
        q = stored.reshape(len(stored), cols).astype(np.float64)
        return (lo + q * ((hi - lo) / levels)).reshape(stored.shape)
    raise ValueError(f"encoding kind {kind!r} is not a float or fixed-point one")
