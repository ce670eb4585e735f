"""`ctgs compress`: texel modes, attribute codecs, Morton sort, the packed folder, bad and corrupt input."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from factory_io import random_model
from ctgs.cli import main
from ctgs.errors import UserError
from ctgs.formats.compress import TARGETS, Spec, compress_model, morton_order
from ctgs.formats.model_format import read_model, write_model, write_packed_model
from ctgs.metrics.psnr import psnr
from ctgs.render.camera import Camera
from ctgs.render.reference import render_reference

# float16 keeps 11 significant bits: relative error <= 2^-11 (plus the absolute floor of subnormals).
F16_REL = 2.0 ** -11


def _camera() -> Camera:
    view = torch.eye(4)
    view[2, 3] = 5.0  # world origin 5 units in front of the camera
    return Camera(fx=40.0, fy=40.0, cx=24.0, cy=24.0, width=48, height=48, viewmat=view)


def _render(model) -> torch.Tensor:
    with torch.no_grad():
        return render_reference(model.render_inputs(), _camera(), sh_degree=model.sh_degree).rgb


def _model(seed: int = 11):
    model = random_model(n=120, seed=seed)
    model.opacity_logits.fill_(3.0)
    model.log_scales.add_(1.0)  # large, opaque surfels so the textures dominate the image
    return model


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    root = tmp_path_factory.mktemp("cmp")
    model = _model()
    write_model(model, str(root / "model"))
    return root, model


def _cli(root, name: str, *args: str) -> str:
    out = str(root / name)
    res = CliRunner().invoke(main, ["compress", str(root / "model"), "-o", out, *args])
    assert res.exit_code == 0, res.output
    return out


def _by_position(model) -> dict:
    """Primitive index keyed by its exact centre (compression sorts primitives)."""
    return {tuple(p.tolist()): i for i, p in enumerate(model.means)}


def _texture(model, i: int) -> torch.Tensor:
    n = int(model.tex_res[i, 0] * model.tex_res[i, 1])
    return model.textures_raw[int(model.tex_offset[i]):int(model.tex_offset[i]) + n]


def test_f32_packed_is_the_model_up_to_primitive_order(exported, tmp_path):
    # Everything float32: only the Morton sort and the texture repacking change anything, so every primitive
    # must come back bit-exact with its own texture.
    root, model = exported
    back, files = read_model(_cli(root, "f32", "--texels", "f32", *sum((["--attr", f"{a}=f32"] for a in (
        "means", "scales", "quats", "opacity", "sh_dc", "sh_rest", "k_min")), [])))
    assert files.manifest["version"] == 2 and back.num_params() == model.num_params()
    where = _by_position(model)
    order = [where[tuple(p.tolist())] for p in back.means]
    assert sorted(order) == list(range(model.num_primitives)) and order != sorted(order)  # permuted, all kept
    for j, i in enumerate(order):
        for name in ("log_scales", "quats", "opacity_logits", "sh", "k_min", "t2p_exp", "tex_res"):
            assert torch.equal(getattr(back, name)[j], getattr(model, name)[i]), name
        assert torch.equal(_texture(back, j), _texture(model, i))
    assert back.sh_degree == model.sh_degree and back.texture_mode == model.texture_mode
    torch.testing.assert_close(_render(back), _render(model), atol=1e-5, rtol=0)


@pytest.mark.parametrize("mode,k,index_dtype", [("scalar", 256, np.uint8), ("scalar", 16, np.uint8),
                                                 ("vector", 256, np.uint8), ("vector", 300, np.uint16)])
def test_texel_codebooks(exported, mode, k, index_dtype):
    root, model = exported
    out = _cli(root, f"{mode}{k}", "--target", "lossless-ish", "--texels", mode, "-k", str(k))
    back, files = read_model(out)
    manifest = files.manifest
    assert manifest["texture_encoding"] == mode and manifest["codebook_size"] == k
    sections = {s["name"]: s for s in manifest["sections"]}
    assert sections["textures"]["dtype"] == np.dtype(index_dtype).newbyteorder("<").str.lstrip("|")
    act = back.textures
    if mode == "scalar":  # one 1-D codebook for all channels, one index per channel
        assert sections["textures"]["shape"] == [model.num_texels, 3]
        assert len(torch.unique(back.textures_raw)) <= k
    else:  # one RGB entry per texel
        assert sections["textures"]["shape"] == [model.num_texels]
        assert len(torch.unique(back.textures_raw, dim=0)) <= k
    rmse = float((act.sort(0).values - model.textures.sort(0).values).pow(2).mean().sqrt())
    assert rmse <= manifest["compression"]["texels"]["rmse_activated"] + 1e-6  # sorted columns: a lower bound


def test_more_levels_render_closer(exported):
    root, model = exported
    reference = _render(model)
    got = {}
    for mode, k in (("scalar", 4), ("scalar", 256), ("vector", 4), ("vector", 256)):
        back, _ = read_model(_cli(root, f"q{mode}{k}", "--target", "lossless-ish", "--texels", mode, "-k", str(k)))
        got[(mode, k)] = psnr(_render(back), reference)
    assert got[("scalar", 256)] > got[("scalar", 4)] + 3.0
    assert got[("vector", 256)] > got[("vector", 4)] + 3.0
    # The paper's scalar codebook (3 bytes per texel) is the near-lossless one on random RGB texels.
    assert got[("scalar", 256)] > got[("vector", 256)]
    assert got[("scalar", 256)] > 40.0 and got[("vector", 4)] < 40.0


@pytest.mark.parametrize("attr,codec", [("means", "q16"), ("means", "f16"), ("scales", "q8"), ("scales", "q16"),
                                        ("quats", "q8"), ("opacity", "q8"), ("opacity", "f16"), ("sh_dc", "q8"),
                                        ("sh_rest", "q8"), ("sh_rest", "f16"), ("k_min", "f16")])
def test_attribute_codec_error_bounds(attr, codec):
    model = random_model(n=120, seed=5)
    spec = Spec(texels="f32", sort=False, **{attr: codec})
    packed = compress_model(model, spec)
    arrays = {s.name: s for s in packed.sections}
    from ctgs.formats.compress import unpack_model

    back = unpack_model(packed.header, {k: v.array for k, v in arrays.items()},
                        {k: v.encoding for k, v in arrays.items()})
    pick = {"means": lambda m: m.means, "scales": lambda m: m.log_scales, "quats": lambda m: m.quats,
            "opacity": (lambda m: m.opacities) if codec == "q8" else (lambda m: m.opacity_logits), "sh_dc": lambda m: m.sh[:, 0], "sh_rest": lambda m: m.sh[:, 1:],
            "k_min": lambda m: m.k_min}[attr]
    a, b = pick(model).double(), pick(back).double()
    if attr == "quats":  # the unit quaternion is what gets quantised
        a = a / a.norm(dim=1, keepdim=True)
    if codec == "f16":
        bound = a.abs() * F16_REL + 1e-7
    else:
        levels = 2 ** int(codec[1:]) - 1
        if attr in ("quats", "opacity"):  # stated ranges [-1, 1] and [0, 1]
            span = 2.0 if attr == "quats" else 1.0
        else:  # the data range of each column
            flat = a.reshape(len(a), -1)
            span = (flat.max(0).values - flat.min(0).values).reshape(a.shape[1:])
        bound = span / levels / 2 + 1e-6
    assert bool(((a - b).abs() <= bound).all()), float((a - b).abs().max())
    assert float((a - b).abs().max()) > 0  # the codec did quantise (the test can fail)
    # Nothing else changed.
    assert torch.equal(back.textures_raw, model.textures_raw) and torch.equal(back.tex_res, model.tex_res)


def test_sh_rest_kmeans_and_degree_drop():
    model = _model(seed=6)
    for spec, rows in ((Spec(texels="f32", sh_rest="kmeans:8"), 8), (Spec(texels="f32", sh_degree=1), None)):
        packed = compress_model(model, spec)
        from ctgs.formats.compress import unpack_model

        back = unpack_model(packed.header, {s.name: s.array for s in packed.sections},
                            {s.name: s.encoding for s in packed.sections})
        if rows:
            assert len(torch.unique(back.sh[:, 1:].reshape(len(back.sh), -1), dim=0)) <= rows
            assert back.max_sh_degree == model.max_sh_degree
        else:
            assert back.max_sh_degree == 1 and back.sh.shape[1] == 4 and back.sh_degree == min(model.sh_degree, 1)
            assert back.num_params() < model.num_params()


def test_targets_order_by_size(exported):
    root, model = exported
    sizes = {t: read_model(_cli(root, f"t_{t}", "--target", t))[1].bytes_on_disk for t in TARGETS}
    raw = read_model(str(root / "model"))[1].bytes_on_disk
    assert sizes["small"] < sizes["balanced"] < sizes["lossless-ish"] < raw


def test_coders_decode_to_the_same_model(exported):
    root, _ = exported
    # float16 attributes leave the coder redundancy to find even in this model's random values (its 8-bit
    # codes are near incompressible noise, where xz's own header outweighs what it saves).
    models = {c: read_model(_cli(root, f"c_{c}", "--target", "lossless-ish", "--coder", c))
              for c in ("xz", "zlib", "none")}
    for c in ("zlib", "none"):
        for name, t in models["xz"][0].state_dict().items():
            assert (torch.equal(t, models[c][0].state_dict()[name]) if isinstance(t, torch.Tensor)
                    else t == models[c][0].state_dict()[name]), name
    assert models["xz"][1].bytes_on_disk < models["none"][1].bytes_on_disk


def test_morton_order_groups_neighbours():
    rng = np.random.default_rng(0)
    pts = rng.uniform(0, 1, (4096, 3))
    order = morton_order(pts)
    assert sorted(order.tolist()) == list(range(4096))
    step = lambda p: float(np.linalg.norm(np.diff(p, axis=0), axis=1).mean())  # noqa: E731
    assert step(pts[order]) < 0.25 * step(pts)  # consecutive primitives are close in space


def test_corrupt_packed_model_is_user_error(exported, tmp_path):
    root, _ = exported
    src = _cli(root, "to_corrupt")
    data = open(os.path.join(src, "model.bin"), "rb").read()
    cases = {"flip": data[:100] + bytes([data[100] ^ 0xFF]) + data[101:], "truncated": data[: len(data) // 2]}
    for name, blob in cases.items():
        bad = tmp_path / name
        bad.mkdir()
        (bad / "manifest.json").write_text(open(os.path.join(src, "manifest.json")).read())
        (bad / "model.bin").write_bytes(blob)
        with pytest.raises(UserError, match="model.bin"):
            read_model(str(bad))
    manifest = json.load(open(os.path.join(src, "manifest.json")))
    manifest["sections"] = [s for s in manifest["sections"] if s["name"] != "texel_codebook"]
    bad = tmp_path / "no_codebook"
    bad.mkdir()
    (bad / "manifest.json").write_text(json.dumps(manifest))
    (bad / "model.bin").write_bytes(data)
    with pytest.raises(UserError, match="inconsistent compressed model"):
        read_model(str(bad))


@pytest.mark.parametrize("args,message", [
    (["--attr", "means=q4"], "means=q4"), (["--attr", "colour=f16"], "colour=f16"),
    (["--attr", "sh_rest=kmeans:0"], "sh_rest=kmeans:0"), (["--attr", "sh_degree=x"], "sh_degree"),
    (["--texels", "scalar", "-k", "70000"], "--codebook-size 70000"),
])
def test_bad_options_are_user_errors(exported, args, message):
    root, _ = exported
    out = root / "bad"
    res = CliRunner().invoke(main, ["compress", str(root / "model"), "-o", str(out), *args])
    assert res.exit_code == 2 and message in res.output, res.output
    assert not out.exists()


def test_codebook_larger_than_texels_is_user_error(exported):
    root, model = exported
    out = root / "too_big"
    res = CliRunner().invoke(main, ["compress", str(root / "model"), "-o", str(out), "--texels", "vector",
                                    "-k", str(model.num_texels + 1)])
    assert res.exit_code == 2 and "larger than" in res.output
    assert not out.exists()
    assert not [p for p in os.listdir(root) if p.startswith(".tmp")]


def test_compressed_is_not_recompressed(exported):
    root, _ = exported
    src = _cli(root, "once", "-k", "8")
    res = CliRunner().invoke(main, ["compress", src, "-o", str(root / "again")])
    assert res.exit_code == 2 and "already compressed" in res.output


def test_untextured_model_compresses_without_codebook(tmp_path):
    model = random_model(n=10, texture_mode="none")
    model.tex_res.zero_()
    model.tex_offset.zero_()
    model.textures_raw = model.textures_raw[:0]
    write_model(model, str(tmp_path / "m"))
    res = CliRunner().invoke(main, ["compress", str(tmp_path / "m"), "-o", str(tmp_path / "c")])
    assert res.exit_code == 0, res.output
    back, files = read_model(str(tmp_path / "c"))
    assert back.num_texels == 0 and files.manifest["texture_encoding"] == "none"


def test_first_format_compressed_folders_still_read(tmp_path):
    # Folders of the first `ctgs compress` (version 1: codebook blob + float16 SH in the PLY) stay readable.
    from ctgs.formats.texture_blob import TextureBlob

    model = _model(seed=2)
    codebook = model.textures_raw[:8].numpy().astype(np.float16)
    idx = (np.arange(model.num_texels) % 8).astype(np.uint8)
    write_model(model, str(tmp_path / "v1"), blob=TextureBlob(codebook, idx), half=True, plain_ply=False,
                extra={"compression": {"codebook_size": 8}})
    back, files = read_model(str(tmp_path / "v1"))
    assert files.manifest["version"] == 1 and files.manifest["texture_encoding"] == "codebook"
    assert torch.equal(back.textures_raw, torch.from_numpy(codebook[idx].astype(np.float32)))


def test_write_packed_refuses_foreign_folder(tmp_path):
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "model.pt").write_bytes(b"x")
    packed = compress_model(_model(seed=3), TARGETS["balanced"])
    with pytest.raises(UserError, match="not an earlier ctgs model folder"):
        write_packed_model(packed, str(tmp_path / "run"))
    assert (tmp_path / "run" / "model.pt").read_bytes() == b"x"


def _unpack(packed):
    from ctgs.formats.compress import unpack_model

    arrays = {s.name: s for s in packed.sections}
    return unpack_model(packed.header, {k: v.array for k, v in arrays.items()}, {k: v.encoding for k, v in arrays.items()})


def _shift_px(model, back):
    return ((back.means.double() - model.means.double()).abs().amax(1) / model.k_min.double()).numpy()


def test_far_primitive_stored_apart(tmp_path):
    """One primitive 1000 units out would make one q16 range coarse for every other: it is stored apart as float32
    (exactly), the others keep q16 within MEANS_MAX_SHIFT_PX of their closest camera, the file says version 3, and
    the stage says so. Without it: plain q16, version 2, no outlier sections."""
    from ctgs.formats.compress import MEANS_MAX_SHIFT_PX

    model = random_model(n=120, seed=5)
    normal = compress_model(model, Spec(texels="f32", sort=False, means="q16"))
    assert "means_outliers" not in normal.stats and "means_fallback" not in normal.stats
    assert "means_outlier_rows" not in {s.name for s in normal.sections}
    model.means.data[7] = torch.tensor([1000.0, -20.0, 3.0], dtype=model.means.dtype)
    full = compress_model(model, Spec(texels="f32", sort=False, means="f32"))
    packed = compress_model(model, Spec(texels="f32", sort=False, means="q16"))
    far = packed.stats["means_outliers"]
    assert far["outliers"] == 1 and far["full_range_shift_px"] > MEANS_MAX_SHIFT_PX >= far["max_shift_px"]
    assert packed.header["spec"]["means"] == "q16"
    back = _unpack(packed)
    shift = _shift_px(model, back)
    assert shift[7] == 0 and shift.max() <= MEANS_MAX_SHIFT_PX
    assert sum(s.array.nbytes for s in packed.sections) < sum(s.array.nbytes for s in full.sections)
    rows = next(s for s in packed.sections if s.name == "means_outlier_rows")
    rows.array = np.array([120], dtype="<u4")  # beyond the model: refused, not silently dropped
    with pytest.raises(ValueError, match="means_outlier_rows"):
        _unpack(packed)
    # Morton-sorted too: the outlier rows follow the primitive order.
    back_sorted = _unpack(compress_model(model, Spec(texels="f32", sort=True, means="q16")))
    assert (back_sorted.means.double()[:, 0] == model.means.double()[7, 0]).sum() == 1
    write_model(model, str(tmp_path / "model"))
    res = CliRunner().invoke(main, ["compress", str(tmp_path / "model"), "-o", str(tmp_path / "c")])
    assert res.exit_code == 0, res.output
    assert "1 primitive(s) stored apart as f32" in res.output
    manifest = json.load(open(tmp_path / "c" / "manifest.json"))
    assert manifest["version"] == 3 and manifest["compression"]["means_outliers"]["outliers"] == 1
    assert torch.equal(read_model(str(tmp_path / "c"))[0].means.float().sort(0).values,
                       back_sorted.means.float().sort(0).values)


def test_positions_fall_back_to_float_when_q16_cannot_hold_them(tmp_path):
    """Closest-camera pixels far smaller than q16's step for most primitives: float32 for all is smaller than
    storing them apart, so positions are float32, bit-exact, and the stage says so."""
    model = random_model(n=120, seed=5)
    model.k_min.data[:] = 1e-9
    packed = compress_model(model, Spec(texels="f32", sort=False, means="q16"))
    fb = packed.stats["means_fallback"]
    assert fb["stored"] == "f32" and fb["outliers"] == 120 and packed.header["spec"]["means"] == "f32"
    assert torch.equal(_unpack(packed).means.float(), model.means.float())
    write_model(model, str(tmp_path / "model"))
    res = CliRunner().invoke(main, ["compress", str(tmp_path / "model"), "-o", str(tmp_path / "c")])
    assert res.exit_code == 0, res.output
    assert "positions stored as f32, not q16" in res.output
    assert json.load(open(tmp_path / "c" / "manifest.json"))["compression"]["means_fallback"]["stored"] == "f32"


def test_jobs_code_large_sections_as_streams_and_read_back_the_same(exported, monkeypatch):
    """`--jobs 2` with sections above the stream size: the texel indices become several xz streams, the model
    reads back identical to the one-stream file, and the manifest records the jobs."""
    from ctgs.formats import packed

    root, model = exported
    monkeypatch.setattr(packed, "XZ_STREAM_BYTES", 1000)
    one = _cli(root, "jobs1", "-k", "16")
    two = _cli(root, "jobs2", "-k", "16", "--jobs", "2")
    m1, f1 = read_model(one)
    m2, f2 = read_model(two)
    tex = next(e for e in f2.manifest["sections"] if e["name"] == "textures")
    assert len(tex["streams"]) == -(-model.num_texels * 3 // 1000)
    assert not any("streams" in e for e in f1.manifest["sections"])
    assert f2.manifest["compression"]["jobs"] == 2
    for name in ("means", "textures_raw", "sh", "log_scales", "quats", "opacity_logits", "tex_res", "tex_offset"):
        assert torch.equal(getattr(m1, name), getattr(m2, name)), name
