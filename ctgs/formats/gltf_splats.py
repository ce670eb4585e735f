"""Gaussians in glTF: the ratified KHR_gaussian_splatting extension (.glb), read by the PlayCanvas engine, Babylon.js,
CesiumJS and other glTF tools.

One mesh primitive of POINTS, one vertex per splat, float32 attributes (the extension's README, Khronos glTF
repository):

| attribute | type | value |
| --- | --- | --- |
| POSITION | VEC3 | centre (with min / max, as glTF requires) |
| COLOR_0 | VEC4 unsigned byte, normalised | fallback colour for viewers without the extension: DC colour and opacity |
| KHR_gaussian_splatting:ROTATION | VEC4 | unit quaternion, x y z w |
| KHR_gaussian_splatting:SCALE | VEC3 | standard deviations, linear (not log) |
| KHR_gaussian_splatting:OPACITY | SCALAR | opacity after the sigmoid |
| KHR_gaussian_splatting:SH_DEGREE_0_COEF_0 | VEC3 | DC coefficient (the texture mean folded in) |
| KHR_gaussian_splatting:SH_DEGREE_d_COEF_c | VEC3 | band d, coefficient c (the model's own bands only) |

and on the primitive `{"kernel": "ellipse", "colorSpace": "srgb_rec709_display", "sortingMethod": "cameraDistance",
"projection": "perspective"}`, as PlayCanvas's `splat-transform` writes them. What a surfel keeps is what the 3DGS
PLY keeps (ctgs.formats.plain_ply: the texture folded into one colour, or baked with --bake-textures; the flat axis a third
scale of FLAT_SCALE_RATIO x the smaller tangent one), in float32.

Frame: glTF is right-handed with +y up; a COLMAP / 3DGS PLY frame (ours) has y down. The writer turns the model half
a turn about z (x and y change sign; the rotations and the SH bands turned with it), the convention of PlayCanvas's
tools for PLY-space data, so the file matches what `splat-transform model.ply model.glb` writes from our 3DGS PLY
(tests/formats/test_gltf_splats.py). A recentred scene's origin goes into the scene's root node as a translation (in the
glTF frame), so glTF tools place the model where it lies in the COLMAP frame.
"""

from __future__ import annotations

import os

import numpy as np
import torch

from ctgs.errors import UserError
from ctgs.formats.gltf import _Blob, finish
from ctgs.formats.plain_ply import SH_C0, gaussian_view, surfels_from_gaussians
from ctgs.formats.splat import ALPHA_EPS
from ctgs.formats.spz import sh_flips
from ctgs.io import atomic
from ctgs.model.surfels import SurfelModel

EXTENSION = "KHR_gaussian_splatting"
PREFIX = EXTENSION + ":"
PRIMITIVE_EXTENSION = {"kernel": "ellipse", "colorSpace": "srgb_rec709_display", "sortingMethod": "cameraDistance",
                       "projection": "perspective"}
TURN = np.array([-1.0, -1.0, 1.0])  # COLMAP / PLY frame <-> glTF frame: a half turn about z
GENERATOR = "ctgs glb export (KHR_gaussian_splatting)"
FLOAT, UNSIGNED_BYTE = 5126, 5121
ARRAY_BUFFER = 34962
POINTS = 0
COEFS = {1: 3, 2: 5, 3: 7}  # coefficients of SH band d


def _turn_quats(q_wxyz: np.ndarray) -> np.ndarray:
    """Quaternions (w, x, y, z) of rotations R -> those of T R with T the half turn about z: (0, 0, 0, 1) * q."""
    w, x, y, z = q_wxyz.T
    return np.stack([-z, -y, x, w], 1)


def _unturn_quats(q_wxyz: np.ndarray) -> np.ndarray:
    """The inverse of _turn_quats (the half turn is its own inverse up to the sign of q)."""
    w, x, y, z = q_wxyz.T
    return np.stack([z, y, -x, -w], 1)


def build_gltf(model: SurfelModel, origin=None):
    """The pygltflib.GLTF2 document (binary blob set) of `model` with KHR_gaussian_splatting."""
    # pygltflib only where a glTF file is written or read (ctgs.formats loads every format)
    import pygltflib as g

    v = gaussian_view(model)  # what the 3DGS PLY holds, then turned into glTF's frame
    n, degree = model.num_primitives, v["degree"]
    means = v["means"] * TURN
    scales = np.exp(v["log_scales"])
    q = _turn_quats(v["quats"])
    opacity = v["opacity"]
    sh = np.concatenate([v["dc"][:, None], v["rest"] * sh_flips(degree, TURN)[None, :, None]], 1)  # [N, K, 3]
    colour = np.clip(np.round(np.concatenate([0.5 + SH_C0 * sh[:, 0], opacity[:, None]], 1) * 255), 0, 255)

    gltf = g.GLTF2(asset=g.Asset(generator=GENERATOR, version="2.0"), scene=0, extensionsUsed=[EXTENSION])
    gltf.asset.extras = {"ctgs": {"splats": n, "sh_degree": degree, "texture_mode": model.texture_mode,
                                  "frame": "COLMAP turned half a turn about z (x, y negated)"}}
    blob = _Blob(gltf)
    f32 = lambda a: np.ascontiguousarray(a, dtype=np.float32)  # noqa: E731
    attributes = g.Attributes(POSITION=blob.accessor(f32(means), FLOAT, "VEC3", ARRAY_BUFFER, minmax=True))
    attributes.COLOR_0 = blob.accessor(colour.astype(np.uint8), UNSIGNED_BYTE, "VEC4", ARRAY_BUFFER)
    gltf.accessors[attributes.COLOR_0].normalized = True
    custom = {"ROTATION": (f32(np.concatenate([q[:, 1:], q[:, :1]], 1)), "VEC4"),  # x y z w
              "SCALE": (f32(scales), "VEC3"), "OPACITY": (f32(opacity), "SCALAR"),
              "SH_DEGREE_0_COEF_0": (f32(sh[:, 0]), "VEC3")}
    at = 1
    for d in range(1, degree + 1):
        for c in range(COEFS[d]):
            custom[f"SH_DEGREE_{d}_COEF_{c}"] = (f32(sh[:, at]), "VEC3")
            at += 1
    for name, (array, kind) in custom.items():
        setattr(attributes, PREFIX + name, blob.accessor(array, FLOAT, kind, ARRAY_BUFFER))
    gltf.meshes = [g.Mesh(name="splats", primitives=[g.Primitive(attributes=attributes, mode=POINTS,
                                                                 extensions={EXTENSION: dict(PRIMITIVE_EXTENSION)})])]
    gltf.nodes = [g.Node(mesh=0, name="splats")]
    return finish(gltf, blob, [0], None if origin is None else np.asarray(origin, dtype=np.float64) * TURN)


def write_glb_splats(model: SurfelModel, path: str, origin=None) -> dict:
    """Write `model` as a KHR_gaussian_splatting .glb (atomically). Returns {"bytes", "splats", "sh_degree"}."""
    gltf = build_gltf(model, origin)
    with atomic.atomic_path(path) as tmp:
        gltf.save_binary(tmp)
    return {"bytes": os.path.getsize(path), "splats": model.num_primitives,
            "sh_degree": gltf.asset.extras["ctgs"]["sh_degree"]}


def read_glb_splats(path: str) -> SurfelModel:
    """The first KHR_gaussian_splatting primitive of a .glb (ours or another tool's; float32 attributes) as untextured
    surfels in the COLMAP frame (the model's own frame: a root translation is not applied); UserError naming the file
    otherwise."""
    # pygltflib only where a glTF file is written or read (ctgs.formats loads every format)
    import pygltflib as g

    try:
        gltf = g.GLTF2().load(path)
    except Exception as exc:  # pygltflib raises bare Exceptions of several kinds on foreign bytes
        raise UserError(f"{path}: not a readable glTF binary ({type(exc).__name__}: {exc})") from exc
    blob = gltf.binary_blob()
    prim = next((p for m in gltf.meshes for p in m.primitives if EXTENSION in (p.extensions or {})), None)
    if blob is None or prim is None:
        raise UserError(f"{path}: no {EXTENSION} primitive; pass a .glb written by `ctgs export --format glb-splats` "
                        "(the textured-quad .glb of --format glb holds no Gaussians)")
    widths = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}
    attrs = {k: v for k, v in prim.attributes.__dict__.items() if v is not None}

    def read(name: str) -> np.ndarray:
        if name not in attrs:
            raise UserError(f"{path}: attribute {name} missing from the {EXTENSION} primitive; not a splat .glb")
        a = gltf.accessors[attrs[name]]
        if a.componentType != FLOAT or a.bufferView is None:
            raise UserError(f"{path}: {name} is not a float32 accessor (quantised attributes, e.g. from "
                            "KHR_mesh_quantization, are not read here); convert it with `splat-transform`")
        v = gltf.bufferViews[a.bufferView]
        w = widths[a.type]
        stride = v.byteStride or 4 * w
        start = (v.byteOffset or 0) + (a.byteOffset or 0)
        end = start + (a.count - 1) * stride + 4 * w if a.count else start
        if a.count < 0 or start < 0 or stride < 4 * w or end > len(blob):
            # (as_strided would read past the buffer: memory that is not the file's)
            raise UserError(f"{path}: {name} ({a.count} rows) reaches past the {len(blob)}-byte binary chunk; the "
                            "file is truncated or corrupt, re-export it")
        rows = np.lib.stride_tricks.as_strided(np.frombuffer(blob, np.uint8, offset=start), (a.count, 4 * w),
                                               (stride, 1)) if a.count else np.zeros((0, 4 * w), np.uint8)
        return np.ascontiguousarray(rows).view("<f4").reshape(a.count, w).astype(np.float64)

    means = read("POSITION") * TURN
    xyzw = read(PREFIX + "ROTATION")
    q = _unturn_quats(np.concatenate([xyzw[:, 3:], xyzw[:, :3]], 1))
    scales = read(PREFIX + "SCALE")
    if (scales <= 0).any() or not np.isfinite(scales).all():
        raise UserError(f"{path}: non-positive or non-finite scales; not a splat .glb")
    opacity = np.clip(read(PREFIX + "OPACITY")[:, 0], ALPHA_EPS, 1 - ALPHA_EPS)
    coefs = [read(PREFIX + "SH_DEGREE_0_COEF_0")]
    degree = 0
    for d in (1, 2, 3):
        names = [f"{PREFIX}SH_DEGREE_{d}_COEF_{c}" for c in range(COEFS[d])]
        if not all(n in attrs for n in names):
            break
        coefs += [read(n) for n in names]
        degree = d
    sh = np.stack(coefs, 1)  # [N, K, 3]
    sh[:, 1:] *= sh_flips(degree, TURN)[None, :, None]
    t = lambda a: torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))  # noqa: E731
    return surfels_from_gaussians(t(means), t(np.log(scales)), t(q), t(np.log(opacity / (1 - opacity))), t(sh))
