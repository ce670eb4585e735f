"""Model folder: bit-exact round trip, plain 3DGS PLY readable without plyfile, bad inputs."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
import torch

from factory_io import assert_models_identical, random_model
from ctgs.errors import UserError
from ctgs.formats.model_format import MANIFEST, PLAIN_PLY, PRIMITIVES, TEXTURES, read_model, write_model
from ctgs.formats.plain_ply import FLAT_SCALE_RATIO, SH_C0, texture_means
from ctgs.formats.ply import read_ply
from ctgs.formats.texture_blob import HEADER


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("mode", ["content_aware", "fixed", "none"])
def test_round_trip_bit_exact(tmp_path, dtype, mode):
    model = random_model(dtype=dtype, texture_mode=mode, seed=3)
    model.textures_raw[0, 0] = float("nan")  # even a NaN texel must survive byte for byte
    model.textures_raw[1, 1] = -0.0
    write_model(model, str(tmp_path / "m"))
    back, files = read_model(str(tmp_path / "m"))
    assert_models_identical(model, back)
    assert files.manifest["num_params"] == model.num_params()
    assert files.bytes_on_disk == sum(os.path.getsize(tmp_path / "m" / f) for f in (MANIFEST, PRIMITIVES, TEXTURES))


def test_large_offsets_split_into_uint32_halves():
    # int64 offsets beyond 2^32 (models with > 4G texels) must survive the PLY's 32-bit integers.
    model = random_model(n=5)
    big = 2**33 + 7
    model.tex_offset = torch.tensor([0, 1, 2, 3, big], dtype=torch.int64)
    from ctgs.formats.model_format import primitive_columns

    cols, _ = primitive_columns(model)
    off = cols["tex_offset_lo"].astype(np.int64) | (cols["tex_offset_hi"].astype(np.int64) << 32)
    assert off.tolist() == [0, 1, 2, 3, big]


def test_plain_ply_numpy_readable_and_folds_texture_mean(tmp_path):
    model = random_model(n=12, sh_degree=1, seed=5)
    # Primitive 1: every texel offset = 0.25 -> its plain DC must grow by 0.25 / C0 exactly.
    a, b = int(model.tex_offset[1]), int(model.tex_offset[1] + model.tex_res[1].prod())
    assert b > a
    model.textures_raw[a:b] = float(np.log(0.625 / 0.375))  # 2*sigmoid(x)-1 = 0.25
    write_model(model, str(tmp_path / "m"))
    path = str(tmp_path / "m" / PLAIN_PLY)
    cols, _ = read_ply(path)
    assert len(cols["x"]) == 12
    assert sum(k.startswith("f_rest_") for k in cols) == 45  # padded to degree 3 for viewers
    assert {"scale_0", "scale_1", "scale_2", "rot_0", "rot_3", "opacity", "nx"} <= set(cols)
    np.testing.assert_allclose(cols["f_dc_0"][1], float(model.sh[1, 0, 0]) + 0.25 / SH_C0, rtol=1e-5)
    np.testing.assert_allclose(cols["f_dc_0"][0], float(model.sh[0, 0, 0]), rtol=1e-6)  # res (0,0): no texture
    flat = np.exp(cols["scale_2"])
    assert np.all(flat <= FLAT_SCALE_RATIO * 1.001 * np.exp(np.minimum(cols["scale_0"], cols["scale_1"])))
    # The header is plain ASCII and the body exactly N x 62 float32 (a viewer can read it with numpy alone).
    raw = open(path, "rb").read()
    body = raw[raw.index(b"end_header\n") + len(b"end_header\n"):]
    assert len(body) == 12 * 62 * 4
    assert np.allclose(np.frombuffer(body, "<f4").reshape(12, 62)[:, 0], cols["x"])


def test_plain_ply_reads_with_plyfile(tmp_path):
    # A cross-check with the reader 3DGS tools use; optional (plyfile is no dependency of ctgs), so only
    # this check skips without it, never the numpy checks above.
    plyfile = pytest.importorskip("plyfile", reason="plyfile not installed (optional cross-check)")
    write_model(random_model(n=12, sh_degree=1, seed=5), str(tmp_path / "m"))
    vertex = plyfile.PlyData.read(str(tmp_path / "m" / PLAIN_PLY))["vertex"]
    assert vertex.count == 12 and len(vertex.properties) == 62


def test_texture_mean_is_gaussian_weighted():
    model = random_model(n=3, seed=9)
    means = texture_means(model)
    assert means.shape == (3, 3)
    assert torch.all(means[0] == 0)  # primitive 0 has no texture
    assert torch.all(means.abs() <= 1)


# ---- bad inputs -----------------------------------------------------------------------------------
@pytest.fixture
def model_dir(tmp_path):
    write_model(random_model(n=10), str(tmp_path / "m"))
    return tmp_path / "m"


def test_truncated_ply(model_dir):
    p = model_dir / PRIMITIVES
    p.write_bytes(p.read_bytes()[:-5])
    with pytest.raises(UserError, match="truncated"):
        read_model(str(model_dir))


def test_foreign_ply_instead_of_primitives(model_dir):
    os.replace(model_dir / PLAIN_PLY, model_dir / PRIMITIVES)  # a 3DGS PLY lacks the texture properties
    with pytest.raises(UserError, match="missing"):
        read_model(str(model_dir))


def test_not_a_ply(model_dir):
    (model_dir / PRIMITIVES).write_bytes(b"hello world\n")
    with pytest.raises(UserError, match="not a PLY"):
        read_model(str(model_dir))


@pytest.mark.parametrize("cut", [10, HEADER.size + 3])
def test_truncated_blob(model_dir, cut):
    p = model_dir / TEXTURES
    p.write_bytes(p.read_bytes()[:cut])
    with pytest.raises(UserError, match="textures.bin"):
        read_model(str(model_dir))


def test_blob_bad_magic_version_and_corruption(model_dir):
    p = model_dir / TEXTURES
    data = bytearray(p.read_bytes())
    p.write_bytes(b"XXXX" + bytes(data[4:]))
    with pytest.raises(UserError, match="magic"):
        read_model(str(model_dir))
    v2 = bytearray(data)
    v2[8] = 2
    p.write_bytes(bytes(v2))
    with pytest.raises(UserError, match="version 2"):
        read_model(str(model_dir))
    flipped = bytearray(data)
    flipped[-1] ^= 0xFF
    p.write_bytes(bytes(flipped))
    with pytest.raises(UserError, match="checksum"):
        read_model(str(model_dir))


def test_manifest_version_mismatch_and_missing(model_dir, tmp_path):
    m = json.loads((model_dir / MANIFEST).read_text())
    m["version"] = 99
    (model_dir / MANIFEST).write_text(json.dumps(m))
    with pytest.raises(UserError, match="version 99"):
        read_model(str(model_dir))
    with pytest.raises(UserError, match="no manifest.json"):
        read_model(str(tmp_path))


def test_failed_write_leaves_nothing(tmp_path):
    model = random_model(n=4)
    from ctgs.formats.texture_blob import TextureBlob

    with pytest.raises(ValueError):
        write_model(model, str(tmp_path / "m"), blob=TextureBlob(np.zeros((1, 3), np.float32)))
    assert os.listdir(tmp_path) == []


def test_refuses_to_replace_a_folder_that_is_not_a_model(tmp_path):
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "model.pt").write_bytes(b"precious")
    with pytest.raises(UserError, match="not an earlier ctgs model folder"):
        write_model(random_model(n=3), str(tmp_path / "run"))
    assert (tmp_path / "run" / "model.pt").read_bytes() == b"precious"
    write_model(random_model(n=3), str(tmp_path / "m"))
    write_model(random_model(n=4), str(tmp_path / "m"))  # an earlier model folder is replaced
    assert read_model(str(tmp_path / "m"))[0].num_primitives == 4
