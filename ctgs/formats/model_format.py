"""The ctgs model folder (spec: docs/reference/model_format.md), in one of two layouts.

- version 1, written by `ctgs export`: manifest.json + primitives.ply + textures.bin. `write_model` /
  `read_model` round-trip a `SurfelModel` bit-exactly (raw parameters, dtypes kept). Folders from the
  first `ctgs compress` (codebook blob, float16 SH in the PLY) are version 1 too and still read.
- version 2, written by `ctgs compress`: manifest.json + model.bin, packed sections (ctgs.formats.packed)
  whose encodings the manifest states (ctgs.formats.compress).

Both read back as an ordinary `SurfelModel`, so eval, render and export never know the difference.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np
import torch

from ctgs.errors import UserError
from ctgs.formats.compress import unpack_model
from ctgs.formats.packed import decode_section, encode_section
from ctgs.formats.plain_ply import write_plain_ply
from ctgs.formats.ply import read_ply, write_ply
from ctgs.formats.texture_blob import TextureBlob, decode_blob, encode_blob
from ctgs.formats.web_bundle import WEB_SUBDIR, is_bundle
from ctgs.io import atomic, owner
from ctgs.io.versioned import VersionedJson
from ctgs.model.surfels import SurfelModel

FORMAT_NAME = "ctgs-model"
FORMAT_VERSION = 1
PACKED_VERSION = 2
# Version 2 plus position outliers (sections `means_outlier_rows` / `means_outliers`): written only by models that have
# them, so that a reader without them refuses the file instead of misplacing those primitives.
PACKED_OUTLIER_VERSION = 3
PACKED_VERSIONS = (PACKED_VERSION, PACKED_OUTLIER_VERSION)
READ_VERSIONS = (FORMAT_VERSION, *PACKED_VERSIONS)
PACKED = "model.bin"
MANIFEST = "manifest.json"
PRIMITIVES = "primitives.ply"
TEXTURES = "textures.bin"
PLAIN_PLY = "plain_3dgs.ply"
# Properties that `half=True` stores as IEEE binary16 bit patterns in PLY `ushort` (PLY has no half type).
HALF_CANDIDATES = ("f_dc_", "f_rest_")

_TORCH_TO_NP = {torch.float16: np.float16, torch.float32: np.float32, torch.float64: np.float64}


@dataclass
class ModelFiles:
    """What `read_model` found besides the model itself."""

    manifest: dict
    bytes_on_disk: int  # manifest + primitives PLY + blob, bytes (what loading needs; not the plain PLY)
    files: dict[str, int] = field(default_factory=dict)  # file name -> bytes


def _np(t: torch.Tensor) -> np.ndarray:
    return t.detach().cpu().numpy()


def check_replaceable(out_dir: str) -> None:
    """UserError unless `out_dir` may become a model folder: absent, empty or an earlier model folder. Replacing means
    deleting: never the run folder, never the user's files (ctgs.io.owner); `ctgs export --format web` adds web/."""
    owner.check_ours(out_dir, "model", "an earlier ctgs model folder",
                     also=lambda name: name == WEB_SUBDIR and is_bundle(os.path.join(out_dir, name)),
                     legacy=owner.names_within({MANIFEST, PRIMITIVES, TEXTURES, PLAIN_PLY, PACKED, WEB_SUBDIR},
                                               MANIFEST))


def primitive_columns(model: SurfelModel, half: bool = False) -> tuple[dict[str, np.ndarray], list[str]]:
    """The PLY columns of `model` (3DGS names where 3DGS has the quantity) and the half-stored names."""
    cols: dict[str, np.ndarray] = {}
    for i, axis in enumerate("xyz"):
        cols[axis] = _np(model.means[:, i])
    for i in range(2):
        cols[f"scale_{i}"] = _np(model.log_scales[:, i])
    for i in range(4):
        cols[f"rot_{i}"] = _np(model.quats[:, i])
    cols["opacity"] = _np(model.opacity_logits)
    sh = _np(model.sh)  # [N, K, 3]
    for c in range(3):
        cols[f"f_dc_{c}"] = sh[:, 0, c]
    rest = sh[:, 1:, :].transpose(0, 2, 1).reshape(len(sh), -1)  # [N, 3*(K-1)] channel-major (3DGS order)
    for j in range(rest.shape[1]):
        cols[f"f_rest_{j}"] = rest[:, j]
    cols["k_min"] = _np(model.k_min)
    cols["t2p_exp"] = _np(model.t2p_exp).astype(np.int32)
    cols["tex_res_u"] = _np(model.tex_res[:, 0]).astype(np.int32)
    cols["tex_res_v"] = _np(model.tex_res[:, 1]).astype(np.int32)
    off = _np(model.tex_offset).astype(np.int64)
    # PLY has no 64-bit integer type: the int64 offset is split into two uint32 halves.
    cols["tex_offset_lo"] = (off & 0xFFFFFFFF).astype(np.uint32)
    cols["tex_offset_hi"] = (off >> 32).astype(np.uint32)
    halves = []
    if half:
        for name in list(cols):
            if name.startswith(HALF_CANDIDATES):
                cols[name] = cols[name].astype(np.float16).view(np.uint16)
                halves.append(name)
    return cols, halves


def write_model(model: SurfelModel, out_dir: str, *, blob: TextureBlob | None = None, half: bool = False,
                plain_ply: bool = True, extra: dict | None = None) -> dict:
    """Write `model` to the folder `out_dir` (replaced atomically). Returns the manifest.

    blob: the texel payload (default: the raw textures, bit-exact). half: SH coefficients as float16.
    plain_ply: also write the 3DGS-style approximation (ctgs.formats.plain_ply).
    """
    model.validate()
    check_replaceable(out_dir)
    if blob is None:
        blob = TextureBlob(_np(model.textures_raw))
    if blob.num_texels != model.num_texels:
        raise ValueError(f"texture blob has {blob.num_texels} texels, model {model.num_texels}")
    cols, halves = primitive_columns(model, half)
    with owner.owned_dir(out_dir, "model") as tmp:
        write_ply(os.path.join(tmp, PRIMITIVES), cols, comments=[f"{FORMAT_NAME} {FORMAT_VERSION}"])
        atomic.write_bytes(os.path.join(tmp, TEXTURES), encode_blob(blob))
        files = [PRIMITIVES, TEXTURES]
        if plain_ply:
            write_plain_ply(model, os.path.join(tmp, PLAIN_PLY),
                            origin=((extra or {}).get("source") or {}).get("world_origin"))
            files.append(PLAIN_PLY)
        manifest = {
            "format": FORMAT_NAME,
            "version": FORMAT_VERSION,
            "primitives": PRIMITIVES,
            "textures": TEXTURES,
            "plain_ply": PLAIN_PLY if plain_ply else None,
            "num_primitives": model.num_primitives,
            "num_texels": model.num_texels,
            "sh_degree": int(model.sh_degree),
            "max_sh_degree": model.max_sh_degree,
            "texture_mode": model.texture_mode,
            "float_dtype": str(model.means.dtype).replace("torch.", ""),
            "texture_encoding": blob.encoding,
            "codebook_size": len(blob.values) if blob.indices is not None else None,
            "half_properties": halves,
            "num_params": model.num_params(),
            "file_bytes": {name: os.path.getsize(os.path.join(tmp, name)) for name in files},
            **(extra or {}),
        }
        atomic.write_json(os.path.join(tmp, MANIFEST), manifest)
    return manifest


MANIFEST_FILE = VersionedJson(
    MANIFEST, FORMAT_NAME, READ_VERSIONS,
    missing=f"{{folder}}: no {MANIFEST}; pass a folder written by `ctgs export` or `ctgs compress`",
    unreadable="{path}: unreadable manifest ({exc}); re-export the model",
    other_format="{path}: not a ctgs model manifest; pass a folder written by `ctgs export`",
    other_version=f"{{path}}: model format version {{version}}, this ctgs reads versions "
                  f"{', '.join(map(str, READ_VERSIONS))}; re-export the model with this version of ctgs")


def read_manifest(model_dir: str) -> dict:
    return MANIFEST_FILE.read(model_dir)


def write_packed_model(packed, out_dir: str, *, extra: dict | None = None, jobs: int = 1) -> dict:
    """Write a `ctgs.formats.compress.Packed` as a version-2 folder (replaced atomically). Returns the manifest.
    jobs > 1: large xz sections coded as independent streams on that many threads (ctgs.formats.packed)."""
    spec = packed.header["spec"]
    check_replaceable(out_dir)
    with owner.owned_dir(out_dir, "model") as tmp:
        entries, offset = [], 0
        with open(os.path.join(tmp, PACKED), "wb") as f:
            for section in packed.sections:
                coded, entry = encode_section(section, spec["coder"], offset, jobs=jobs)
                f.write(coded)
                offset += len(coded)
                entries.append(entry)
        n, t = packed.header["num_primitives"], packed.header["num_texels"]
        # SurfelModel.num_params of the decoded model (SH counted as stored, up to max_sh_degree).
        per_prim = 10 + 3 * (packed.header["max_sh_degree"] + 1) ** 2 + (packed.header["texture_mode"] != "none")
        manifest = {
            "format": FORMAT_NAME, "layout": "packed", "packed": PACKED,
            "version": PACKED_OUTLIER_VERSION if any(e["name"] == "means_outlier_rows" for e in entries)
            else PACKED_VERSION,
            **packed.header,
            "num_params": per_prim * n + 3 * t,
            "file_bytes": {PACKED: offset},
            "sections": entries,
            **(extra or {}),
        }
        atomic.write_json(os.path.join(tmp, MANIFEST), manifest)
    return manifest


def _read_packed(model_dir: str, manifest: dict, device) -> SurfelModel:
    path = os.path.join(model_dir, manifest.get("packed", PACKED))
    try:
        with open(path, "rb") as f:
            blob = f.read()
    except OSError as exc:
        raise UserError(f"{path}: cannot read packed model ({exc.strerror}); re-compress the model") from exc
    entries = manifest.get("sections")
    if not isinstance(entries, list) or not all(isinstance(e, dict) and "name" in e for e in entries):
        raise UserError(f"{model_dir}/{MANIFEST}: no valid section list; re-compress the model")
    arrays = {e["name"]: decode_section(blob, e, path) for e in entries}
    encodings = {e["name"]: e.get("encoding", {}) for e in entries}
    try:
        return unpack_model(manifest, arrays, encodings, device=device)
    except (KeyError, ValueError, TypeError) as exc:
        raise UserError(f"{model_dir}: inconsistent compressed model ({type(exc).__name__}: {exc}); "
                        "re-compress it") from exc


def read_model(model_dir: str, device: torch.device | str = "cpu") -> tuple[SurfelModel, ModelFiles]:
    """Load a model folder (exported or compressed, any layout) as a SurfelModel."""
    manifest = read_manifest(model_dir)
    if manifest["version"] in PACKED_VERSIONS:
        model = _read_packed(model_dir, manifest, device)
        return model, _model_files(model_dir, manifest, (MANIFEST, manifest.get("packed", PACKED)))
    ply_path = os.path.join(model_dir, manifest.get("primitives", PRIMITIVES))
    blob_path = os.path.join(model_dir, manifest.get("textures", TEXTURES))
    cols, _ = read_ply(ply_path)
    n = manifest["num_primitives"]
    if any(len(c) != n for c in cols.values()):
        raise UserError(f"{ply_path}: {len(next(iter(cols.values())))} primitives, manifest says {n}; "
                        "the folder mixes files from different exports")
    for name in manifest.get("half_properties", []):
        if name not in cols or cols[name].dtype != np.uint16:
            raise UserError(f"{ply_path}: half property {name} missing or not ushort; re-compress the model")
        cols[name] = cols[name].view(np.float16)
    fdt = getattr(torch, manifest.get("float_dtype", "float32"))

    def col(name: str) -> np.ndarray:
        if name not in cols:
            raise UserError(f"{ply_path}: property {name!r} missing; not a ctgs model PLY (a plain 3DGS PLY?)")
        return cols[name]

    def stack(names: list[str]) -> torch.Tensor:
        return torch.from_numpy(np.stack([col(n_) for n_ in names], 1)).to(fdt) if names else \
            torch.zeros(n, 0, dtype=fdt)

    k = (manifest["max_sh_degree"] + 1) ** 2
    dc = stack([f"f_dc_{c}" for c in range(3)])  # [N, 3]
    rest = stack([f"f_rest_{j}" for j in range(3 * (k - 1))]).reshape(n, 3, k - 1).transpose(1, 2)
    sh = torch.cat([dc[:, None, :], rest], 1).contiguous()  # [N, K, 3]
    off = col("tex_offset_lo").astype(np.int64) | (col("tex_offset_hi").astype(np.int64) << 32)
    try:
        with open(blob_path, "rb") as f:
            blob = decode_blob(f.read(), blob_path)
    except OSError as exc:
        raise UserError(f"{blob_path}: cannot read texture blob ({exc.strerror}); re-export the model") from exc
    if blob.num_texels != manifest["num_texels"]:
        raise UserError(f"{blob_path}: {blob.num_texels} texels, manifest says {manifest['num_texels']}; "
                        "the folder mixes files from different exports")
    textures = blob.decode()
    model = SurfelModel(
        means=stack(["x", "y", "z"]).contiguous(),
        log_scales=stack(["scale_0", "scale_1"]),
        quats=stack([f"rot_{i}" for i in range(4)]),
        opacity_logits=torch.from_numpy(col("opacity")).to(fdt),
        sh=sh,
        textures_raw=torch.from_numpy(np.ascontiguousarray(textures)).to(fdt).reshape(-1, 3),
        k_min=torch.from_numpy(col("k_min")).to(fdt),
        t2p_exp=torch.from_numpy(col("t2p_exp").astype(np.int32)),
        tex_res=torch.from_numpy(np.stack([col("tex_res_u"), col("tex_res_v")], 1).astype(np.int32)),
        tex_offset=torch.from_numpy(off),
        sh_degree=int(manifest["sh_degree"]),
        texture_mode=manifest["texture_mode"],
    )
    try:
        model.validate()
    except ValueError as exc:
        raise UserError(f"{model_dir}: inconsistent model ({exc}); re-export it") from exc
    model = SurfelModel.from_state_dict(model.state_dict(), device=device)
    return model, _model_files(model_dir, manifest, (MANIFEST, manifest.get("primitives"), manifest.get("textures"),
                                                     manifest.get("plain_ply")))


def _model_files(model_dir: str, manifest: dict, names: tuple) -> ModelFiles:
    files = {}
    for name in os.listdir(model_dir):
        p = os.path.join(model_dir, name)
        if os.path.isfile(p) and name in names:
            files[name] = os.path.getsize(p)
    needed = sum(b for name, b in files.items() if name != manifest.get("plain_ply"))
    return ModelFiles(manifest=manifest, bytes_on_disk=needed, files=files)
