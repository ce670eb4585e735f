"""Compression of a SurfelModel into packed sections, and back (spec: docs/reference/model_format.md).

Texels (paper sec. "Storage and Memory"; offsets are 2*sigmoid(x)-1, so they live in [-1, 1]):
- `scalar` (the authors' release, the default): one 1-D codebook of K <= 256 values fitted to every
  activated texel channel value; each channel stores a 1-byte index (3 bytes per texel).
- `vector`: a codebook of K RGB triples (K-means on activated 3-vectors); one index per texel
  (uint8 for K <= 256, uint16 for K <= 65536).
- `f32` / `f16`: the raw values.
Codebook centres are stored as raw (pre-activation) values, clamped to +-ACT_LIMIT before the inverse
activation so they stay finite.

Per-primitive attributes each pick a codec (ctgs.formats.quantize): f32, f16, or fixed point q16/q8 over a
stated range (positions, log-scales, SH DC: each column's data range; unit quaternions: [-1, 1];
opacity: sigmoid(logit) in [0, 1]); the higher SH bands can also be K-means coded (codebook of
K rows of 3*(K_sh-1) coefficients in float16 + one index per primitive, as gsplat's PNG compression
does) or dropped above a degree. Primitives are sorted along a Morton curve of their quantised
positions (neighbours in space become neighbours in the file) and their textures repacked in that
order, so `tex_offset` needs no storage; then every section is coded with xz (ctgs.formats.packed).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field, replace

import numpy as np
import torch

from ctgs.errors import UserError
from ctgs.formats import quantize
from ctgs.formats.kmeans import scalar_kmeans, vector_kmeans
from ctgs.formats.packed import CODERS, Section
from ctgs.model.surfels import SurfelModel, jagged_offsets

TEXEL_MODES = ("scalar", "vector", "f16", "f32")
# Codecs each attribute accepts (sh_rest also "kmeans:K").
ATTRIBUTE_CODECS = {
    "means": ("f32", "f16", "q16"),
    "scales": ("f32", "f16", "q16", "q8"),
    "quats": ("f32", "f16", "q8"),
    "opacity": ("f32", "f16", "q8"),
    "sh_dc": ("f32", "f16", "q8"),
    "sh_rest": ("f32", "f16", "q8"),
    "k_min": ("f32", "f16"),
}
SCALAR_MAX_K = 1 << 16  # scalar indices are uint8 (K <= 256) or uint16
VECTOR_MAX_K = 1 << 16
# Codebook centres are clamped inside (-1, 1) before the inverse activation so the raw value stays finite.
ACT_LIMIT = 1.0 - 1e-6
# Opacity stored as sigmoid in [0, 1] (q8) is clamped into [OPACITY_EPS, 1 - OPACITY_EPS] before the logit:
# opacity 1e-4 is invisible, and 1 - 1e-4 differs from 1 by less than one 8-bit step in the image.
OPACITY_EPS = 1e-4
# Morton sort: bits per axis of the quantised position (30-bit codes).
MORTON_BITS = 10
MORTON_TRIM = 1e-3


@dataclass(frozen=True)
class Spec:
    """What `ctgs compress` stores, one field per choice (defaults: the `balanced` target)."""

    texels: str = "scalar"  # one of TEXEL_MODES
    codebook_size: int = 256  # K of the scalar/vector texel codebook
    means: str = "f32"
    scales: str = "f32"
    quats: str = "f32"
    opacity: str = "f32"
    sh_dc: str = "f32"
    sh_rest: str = "f32"  # f32 | f16 | q8 | kmeans:K
    sh_degree: int | None = None  # keep SH bands up to this degree (None: all the model has)
    k_min: str = "f32"
    coder: str = "xz"
    sort: bool = True

    def validate(self) -> None:
        if self.texels not in TEXEL_MODES:
            raise UserError(f"--texels {self.texels}: expected one of {', '.join(TEXEL_MODES)}")
        limit = SCALAR_MAX_K if self.texels == "scalar" else VECTOR_MAX_K
        if self.texels in ("scalar", "vector") and not 1 <= self.codebook_size <= limit:
            raise UserError(f"--codebook-size {self.codebook_size}: {self.texels} codebooks hold 1..{limit} entries")
        for name, codecs in ATTRIBUTE_CODECS.items():
            codec = getattr(self, name)
            if codec not in codecs and not (name == "sh_rest" and _kmeans_k(codec) is not None):
                extra = " or kmeans:K" if name == "sh_rest" else ""
                raise UserError(f"--attr {name}={codec}: expected one of {', '.join(codecs)}{extra}")
        if self.sh_degree is not None and not 0 <= self.sh_degree <= 3:
            raise UserError(f"--attr sh_degree={self.sh_degree}: expected 0..3")
        if self.coder not in CODERS:
            raise UserError(f"--coder {self.coder}: expected one of {', '.join(CODERS)}")

    def with_overrides(self, pairs: list[str]) -> "Spec":
        """Apply `--attr NAME=VALUE` overrides (NAME: an attribute of ATTRIBUTE_CODECS or sh_degree)."""
        changes: dict = {}
        for pair in pairs:
            name, sep, value = pair.partition("=")
            if not sep or name not in (*ATTRIBUTE_CODECS, "sh_degree"):
                raise UserError(f"--attr {pair}: expected NAME=CODEC with NAME one of "
                                f"{', '.join((*ATTRIBUTE_CODECS, 'sh_degree'))}")
            if name == "sh_degree":
                try:
                    changes[name] = int(value)
                except ValueError:
                    raise UserError(f"--attr {pair}: sh_degree must be an integer 0..3") from None
            else:
                changes[name] = value
        spec = replace(self, **changes)
        spec.validate()
        return spec


def _kmeans_k(codec: str) -> int | None:
    head, _, k = codec.partition(":")
    return int(k) if head == "kmeans" and k.isdigit() and int(k) >= 1 else None


# The --target presets: measured points of the size-quality curve (benchmarks/results/compress_curve/demo_c42d198.md,
# compress_curve/herzjesu25_c42d198.md), chosen on training views. Per-attribute train-PSNR costs on the demo, each on
# top of scalar K=256 texels: every f16, sh_rest q8, opacity q8, scales q8/q16, means q16 <= 0.001 dB;
# sh_dc q8 0.001, quats q8 0.016 dB; scalar K=256 / 64 / 32 texels 0.001 / 0.010 / 0.044 dB vs raw.
# K-means SH (demo: 0.017 dB at K=1024 for <1% fewer bytes than q8; herzjesu25 0.08 dB for 22% fewer) and
# vector texel codebooks (demo: 0.025 dB at K=65536 for 1.6x scalar's bytes; 0.32 dB at K=4096) lose more
# per byte saved, so no preset uses them; dropping SH bands costs 0.26-0.8 dB (train) and is opt-in.
TARGETS: dict[str, Spec] = {
    # float16 where it costs nothing measurable; positions and texel sizes stay float32.
    "lossless-ish": Spec(texels="scalar", scales="f16", quats="f16", opacity="f16", sh_dc="f16", sh_rest="f16"),
    # the default: the paper's 256-level scalar texel codebook, attributes quantised except rotations, which
    # stay float16: on `make demo`'s model (7535 iterations, 1013 surfels carrying 169 texels each) 8-bit
    # rotations cost 0.105 dB of train PSNR (raw 32.954 -> 32.795 with q8, 32.900 with f16, for 3 KB of
    # 278 KB): a rotation error moves every texel of a large textured surfel.
    "balanced": Spec(texels="scalar", means="q16", scales="q16", quats="f16", opacity="q8", sh_dc="q8",
                     sh_rest="q8", k_min="f16"),
    # 32 texel levels and 8-bit scales on top of balanced.
    "small": Spec(texels="scalar", codebook_size=32, means="q16", scales="q8", quats="q8", opacity="q8",
                  sh_dc="q8", sh_rest="q8", k_min="f16"),
}
DEFAULT_TARGET = "balanced"


@dataclass
class Packed:
    sections: list[Section]
    header: dict  # manifest fields describing the model (counts, SH degrees, texture mode, encodings)
    stats: dict = field(default_factory=dict)  # informative: timings, K-means methods, texel RMSE


def activated_to_raw(act: np.ndarray) -> np.ndarray:
    """Inverse of 2*sigmoid(x)-1 (clamped into the open interval)."""
    p = (np.clip(act, -ACT_LIMIT, ACT_LIMIT) + 1.0) / 2.0
    return np.log(p) - np.log1p(-p)


def raw_to_activated(raw: np.ndarray) -> np.ndarray:
    return 2.0 / (1.0 + np.exp(-np.asarray(raw, np.float64))) - 1.0


def morton_order(means: np.ndarray) -> np.ndarray:
    """[N] permutation sorting positions [N, 3] along a Z-order curve over their bounding box."""
    if len(means) == 0:
        return np.zeros(0, np.int64)
    # Box of the 0.1-99.9% quantiles, not the extremes: a few far primitives would otherwise squeeze everything else
    # into a handful of cells (positions outside are clamped to the box's faces).
    lo, hi = np.quantile(means, MORTON_TRIM, 0), np.quantile(means, 1 - MORTON_TRIM, 0)
    span = hi - lo
    q = np.clip((means - lo) / np.where(span > 0, span, 1.0) * ((1 << MORTON_BITS) - 1), 0,
                (1 << MORTON_BITS) - 1).astype(np.uint64)
    code = np.zeros(len(means), np.uint64)
    for bit in range(MORTON_BITS):
        for axis in range(3):
            code |= ((q[:, axis] >> np.uint64(bit)) & np.uint64(1)) << np.uint64(3 * bit + axis)
    return np.argsort(code, kind="stable")


def texel_rows(tex_res: np.ndarray, tex_offset: np.ndarray, order: np.ndarray) -> np.ndarray:
    """Rows of the texel array in the order of primitives `order`, each texture contiguous: [T']."""
    sizes = (tex_res[:, 0].astype(np.int64) * tex_res[:, 1].astype(np.int64))[order]
    starts = tex_offset.astype(np.int64)[order]
    total = int(sizes.sum())
    packed_start = np.cumsum(sizes) - sizes
    return np.repeat(starts - packed_start, sizes) + np.arange(total, dtype=np.int64)


def _smallest_int(values: np.ndarray) -> np.ndarray:
    lo, hi = (int(values.min()), int(values.max())) if values.size else (0, 0)
    for dt in ("u1", "<u2", "<u4") if lo >= 0 else ("i1", "<i2", "<i4"):
        info = np.iinfo(np.dtype(dt))
        if info.min <= lo and hi <= info.max:
            return values.astype(dt)
    raise ValueError(f"integers {lo}..{hi} do not fit 32 bits")


def _index_array(labels: np.ndarray, k: int) -> np.ndarray:
    return labels.astype("u1" if k <= 1 << 8 else "<u2" if k <= 1 << 16 else "<u4")


# Largest position shift fixed-point means may cause, in pixels of the primitive's closest training camera. A primitive
# q16 would move further is stored apart, as float32 (`means_outliers`); the fixed-point range is chosen to minimise
# the bytes of both (_encode_means). Normal ranges stay far below (demo 192 px: ~0.005 px).
MEANS_MAX_SHIFT_PX = 0.1
# Ranges tried for fixed-point positions: the bounding box of all centres but the m farthest from their median
# (Chebyshev distance), m = 0, 1, 2, 4, ... up to this fraction of the primitives.
MEANS_MAX_TRIM = 0.1


def _encode_means(means: np.ndarray, k_min: np.ndarray, codec: str) -> tuple[np.ndarray, dict, np.ndarray, dict]:
    """Fixed-point positions with a guaranteed error: (stored [N, 3], encoding, outlier rows [M], stats).

    One range for every position lets a single far primitive (a stray floater hundreds of scene units out) make
    the step coarse for all the others. Each candidate range (MEANS_MAX_TRIM) stores the primitives inside it
    in fixed point and every primitive that would move by more than MEANS_MAX_SHIFT_PX pixels of its closest
    training camera (k_min = world size of one of its pixels) as float32; the candidate with the fewest bytes
    wins. Outlier rows of `stored` hold 0 (the reader overwrites them). M = N means "all float32"."""
    n = len(means)
    scale = np.maximum(k_min, 1e-12)
    elem = 2 if quantize.FIXED_CODECS[codec] > 8 else 1
    by_distance = np.argsort(np.abs(means - np.median(means, 0)).max(1), kind="stable")
    trims = [0] + [1 << i for i in range(64) if (1 << i) <= MEANS_MAX_TRIM * n]
    best = None
    for m in trims:
        kept = means[by_distance[:n - m]]
        lo, hi = kept.min(0), kept.max(0)
        stored, enc = quantize.encode(np.clip(means, lo, hi), codec, lo=lo, hi=hi)
        shift = np.abs(quantize.decode(stored, enc) - means).max(1) / scale  # large outside the box
        out = np.flatnonzero(shift > MEANS_MAX_SHIFT_PX)
        cost = 3 * elem * n + 16 * len(out)  # fixed rows + (float32 row + uint32 index) per outlier
        if best is None or cost < best[0]:
            inside = np.setdiff1d(np.arange(n), out)
            best = (cost, m, stored, enc, out, float(shift[inside].max()) if len(inside) else 0.0)
    cost, m, stored, enc, out, inlier_shift = best
    stored[out] = 0
    full = quantize.encode(means, codec)
    full_shift = float((np.abs(quantize.decode(*full) - means).max(1) / scale).max())
    stats = {"asked": codec, "outliers": int(len(out)), "range_trimmed": int(m), "max_shift_px": inlier_shift,
             "full_range_shift_px": full_shift, "limit_px": MEANS_MAX_SHIFT_PX,
             "range": [[float(x) for x in means.min(0)], [float(x) for x in means.max(0)]]}
    if cost >= 12 * n:  # float32 for every primitive is no larger
        out = np.arange(n)
    return stored, enc, out, stats


def compress_model(model: SurfelModel, spec: Spec, *, seed: int = 0) -> Packed:
    """Encode `model` per `spec` into sections (primitives Morton-sorted when spec.sort)."""
    spec.validate()
    start = time.perf_counter()
    n, t_count = model.num_primitives, model.num_texels
    means = _f64(model.means)
    order = morton_order(means) if spec.sort else np.arange(n)
    sections: list[Section] = []
    stats: dict = {}

    def add(name: str, array: np.ndarray, encoding: dict) -> None:
        sections.append(Section(name, array, encoding))

    spec = _encode_geometry(model, means, spec, order, add, stats)
    degree = _encode_sh(model, spec, order, add, stats, seed)
    add("k_min", *quantize.encode(_f64(model.k_min)[order][:, None], spec.k_min))
    sections[-1].array = sections[-1].array[:, 0]
    add("t2p_exp", _smallest_int(model.t2p_exp.cpu().numpy()[order]), {"kind": "int"})
    tex_res = model.tex_res.cpu().numpy()
    add("tex_res", _smallest_int(tex_res[order]), {"kind": "int"})
    rows = texel_rows(tex_res, model.tex_offset.cpu().numpy(), order)
    texel_info = _encode_textures(model.textures_raw.detach().cpu().numpy()[rows], spec, add, seed)
    stats["texels"] = texel_info
    stats["seconds"] = time.perf_counter() - start
    header = {
        "num_primitives": n, "num_texels": int(len(rows)), "sh_degree": int(min(model.sh_degree, degree)),
        "max_sh_degree": int(degree), "texture_mode": model.texture_mode,
        "float_dtype": str(model.means.dtype).replace("torch.", ""),
        "texture_encoding": texel_info["mode"], "codebook_size": texel_info["codebook_size"],
        "spec": asdict(spec),
    }
    if len(rows) != t_count:
        stats["unreferenced_texels_dropped"] = t_count - len(rows)
    return Packed(sections, header, stats)


def _f64(t) -> np.ndarray:
    return t.detach().cpu().numpy().astype(np.float64)


def _encode_geometry(model: SurfelModel, means: np.ndarray, spec: Spec, order: np.ndarray, add, stats: dict) -> Spec:
    """Sections means (the model's, float64; with outlier rows where a fixed-point grid cannot hold every mean),
    log_scales, quats and opacity, in `order`. Returns the spec, its means codec f32 where no mean fitted the grid."""
    n = model.num_primitives
    if spec.means in quantize.FIXED_CODECS and n:
        stored, enc, outliers, mstats = _encode_means(means[order], _f64(model.k_min)[order], spec.means)
        if len(outliers) == n:
            stats["means_fallback"] = {**mstats, "stored": "f32"}
            spec = replace(spec, means="f32")
            add("means", *quantize.encode(means[order], "f32"))
        else:
            add("means", stored, enc)
            if len(outliers):
                stats["means_outliers"] = mstats
                add("means_outlier_rows", outliers.astype("<u4"), {"kind": "int"})
                add("means_outliers", means[order][outliers].astype("<f4"), {"kind": "float"})
    else:
        add("means", *quantize.encode(means[order], spec.means))
    add("log_scales", *quantize.encode(_f64(model.log_scales)[order], spec.scales))
    quats = _f64(model.quats)[order]
    if spec.quats in quantize.FIXED_CODECS:  # unit quaternions: every component in [-1, 1]
        quats = quats / np.maximum(np.linalg.norm(quats, axis=1, keepdims=True), 1e-12)
        stored, enc = quantize.encode(quats, spec.quats, lo=-1.0, hi=1.0)
    else:
        stored, enc = quantize.encode(quats, spec.quats)
    add("quats", stored, enc)
    logits = _f64(model.opacity_logits)[order]
    if spec.opacity in quantize.FIXED_CODECS:
        stored, enc = quantize.encode((1.0 / (1.0 + np.exp(-logits)))[:, None], spec.opacity, lo=0.0, hi=1.0)
        enc["space"] = "sigmoid"
    else:
        stored, enc = quantize.encode(logits[:, None], spec.opacity)
        enc["space"] = "logit"
    add("opacity", stored[:, 0], enc)
    return spec


def _encode_sh(model: SurfelModel, spec: Spec, order: np.ndarray, add, stats: dict, seed: int) -> int:
    """Sections sh_dc and sh_rest (a k-means codebook or quantised rows) up to the kept degree; returns it."""
    n = model.num_primitives
    sh = _f64(model.sh)[order]  # [N, K, 3]
    degree = model.max_sh_degree if spec.sh_degree is None else min(spec.sh_degree, model.max_sh_degree)
    k_sh = (degree + 1) ** 2
    add("sh_dc", *quantize.encode(sh[:, 0, :], spec.sh_dc))
    if k_sh > 1:
        rest = sh[:, 1:k_sh, :].transpose(0, 2, 1).reshape(n, 3 * (k_sh - 1))  # channel-major (3DGS order)
        k = _kmeans_k(spec.sh_rest)
        if k is not None:
            k = min(k, n)  # fewer primitives than centres: every primitive keeps its own row
            cb = vector_kmeans(rest, k, seed=seed)
            add("sh_rest", _index_array(cb.labels, k), {"kind": "codebook", "codebook": "sh_rest_codebook"})
            add("sh_rest_codebook", cb.centres.astype("<f2"), {"kind": "float"})
            stats["sh_rest_kmeans"] = {"k": k, "method": cb.method, "seconds": cb.seconds}
        else:
            add("sh_rest", *quantize.encode(rest, spec.sh_rest))
    return degree


def _encode_textures(raw: np.ndarray, spec: Spec, add, seed: int) -> dict:
    """Sections of the texels raw [T', 3] (in the new primitive order): floats, or indices into a scalar or a
    vector codebook of activated values. Returns the texel statistics (mode, codebook size, error)."""
    texel_info: dict = {"mode": spec.texels if len(raw) else "none", "codebook_size": None}
    if not len(raw):  # untextured model (2DGS baseline, a run stopped before texturing): no texel sections
        return texel_info
    if spec.texels in ("f32", "f16"):
        add("textures", raw.astype(quantize.FLOAT_CODECS[spec.texels]), {"kind": "float"})
        decoded = raw.astype(quantize.FLOAT_CODECS[spec.texels])
    else:
        act = raw_to_activated(raw)
        k = spec.codebook_size
        if spec.texels == "scalar":
            cb = scalar_kmeans(act, k)
            k = len(cb.centres)
            centres = activated_to_raw(cb.centres).astype("<f4")  # [K]
        else:
            if k > len(act):
                raise UserError(f"--codebook-size {k} is larger than the model's {len(act)} texels; "
                                f"pick a size <= {len(act)}")
            cb = vector_kmeans(act, k, seed=seed)
            centres = activated_to_raw(cb.centres).astype("<f2")  # [K, 3]
        add("textures", _index_array(cb.labels, k), {"kind": "codebook", "codebook": "texel_codebook"})
        add("texel_codebook", centres, {"kind": "float"})
        decoded = centres[cb.labels]
        texel_info.update(codebook_size=k, method=cb.method, kmeans_seconds=cb.seconds)
    err = raw_to_activated(decoded.astype(np.float64)) - raw_to_activated(raw)
    texel_info["rmse_activated"] = float(np.sqrt(np.mean(err ** 2)))
    return texel_info


def _values(name: str, arrays: dict[str, np.ndarray], encodings: dict[str, dict]) -> np.ndarray:
    """Decoded values of section `name` (float64; codebook sections resolved through their codebook)."""
    enc = encodings[name]
    if enc.get("kind") == "codebook":
        book = enc.get("codebook")
        if book not in arrays or encodings[book].get("kind") == "codebook":
            raise ValueError(f"section {name}: codebook section {book!r} missing or itself indexed")
        centres = _values(book, arrays, encodings)
        idx = arrays[name].astype(np.int64)
        if idx.size and int(idx.max()) >= len(centres):
            raise ValueError(f"section {name}: index {int(idx.max())} beyond the {len(centres)}-entry codebook")
        return centres[idx]
    if enc.get("kind") == "int":
        return arrays[name].astype(np.int64)
    return quantize.decode(arrays[name], enc)


def unpack_model(header: dict, arrays: dict[str, np.ndarray], encodings: dict[str, dict],
                 device: torch.device | str = "cpu") -> SurfelModel:
    """Rebuild a SurfelModel from decoded sections (raises ValueError/KeyError on inconsistencies)."""
    n, t = int(header["num_primitives"]), int(header["num_texels"])
    fdt = getattr(torch, header.get("float_dtype", "float32"))
    val = lambda name: _values(name, arrays, encodings)  # noqa: E731
    f = lambda a: torch.from_numpy(np.ascontiguousarray(a)).to(fdt)  # noqa: E731

    opacity = val("opacity").reshape(n)
    if encodings["opacity"].get("space") == "sigmoid":
        p = np.clip(opacity, OPACITY_EPS, 1.0 - OPACITY_EPS)
        opacity = np.log(p) - np.log1p(-p)
    k_sh = (int(header["max_sh_degree"]) + 1) ** 2
    sh = np.zeros((n, k_sh, 3))
    sh[:, 0, :] = val("sh_dc").reshape(n, 3)
    if k_sh > 1:
        sh[:, 1:, :] = val("sh_rest").reshape(n, 3, k_sh - 1).transpose(0, 2, 1)
    means = val("means").reshape(n, 3)
    if "means_outlier_rows" in arrays:  # primitives stored apart from the fixed-point range (_encode_means)
        rows, far = val("means_outlier_rows").reshape(-1), val("means_outliers").reshape(-1, 3)
        if len(rows) != len(far) or (len(rows) and (rows.min() < 0 or rows.max() >= n)):
            raise ValueError(f"means_outlier_rows: {len(rows)} rows for {len(far)} positions, or a row beyond {n}")
        means[rows] = far
    tex_res = torch.from_numpy(val("tex_res").reshape(n, 2).astype(np.int32))
    textures = val("textures") if "textures" in arrays else np.zeros((0, 3))
    textures = textures.reshape(t, 3)
    model = SurfelModel(
        means=f(means), log_scales=f(val("log_scales").reshape(n, 2)),
        quats=f(val("quats").reshape(n, 4)), opacity_logits=f(opacity), sh=f(sh), textures_raw=f(textures),
        k_min=f(val("k_min").reshape(n)), t2p_exp=torch.from_numpy(val("t2p_exp").reshape(n).astype(np.int32)),
        tex_res=tex_res, tex_offset=jagged_offsets(tex_res),
        sh_degree=int(header["sh_degree"]), texture_mode=header["texture_mode"],
    )
    return SurfelModel.from_state_dict(model.state_dict(), device=device)
