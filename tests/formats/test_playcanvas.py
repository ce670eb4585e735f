"""PlayCanvas's compressed PLY and SOG (ctgs.formats.playcanvas): layouts decoded by hand, round trips within the
quantisation, bad files refused, and PlayCanvas's own reader (`splat-transform`, from npm) decoding our files to
what our readers decode, and its files read by ours."""

from __future__ import annotations

import json
import math
import subprocess
import zipfile

import numpy as np
import pytest
import torch
from factory_io import random_model
from npm_cache import npm_package

from ctgs.errors import UserError
from ctgs.formats.plain_ply import SH_C0, surfels_from_gaussians, write_plain_ply
from ctgs.formats.playcanvas import (
    CHUNK,
    CHUNK_PROPS,
    gaussian_table,
    morton_order,
    palette_size,
    read_compressed_ply,
    read_sog,
    write_compressed_ply,
    write_sog,
)
from ctgs.formats.ply import read_ply


def _model(n: int = 300, sh_degree: int = 3, seed: int = 4):
    m = random_model(n=n, sh_degree=sh_degree, seed=seed)
    m.sh.data.clamp_(-0.9, 0.9)  # inside the compressed PLY's SH range (+-4) with room; SOG's codebook spans any
    return m


def _unit(q: torch.Tensor) -> torch.Tensor:
    q = torch.nn.functional.normalize(q.double(), dim=1)
    return q * torch.where(q[:, :1] < 0, -1.0, 1.0)  # q and -q are one rotation


def _table(m) -> dict:
    """The model as the formats hold it (Morton order), float64 tensors."""
    g = gaussian_table(m)
    return {k: torch.from_numpy(v) if isinstance(v, np.ndarray) else v for k, v in g.items()}


def test_morton_order_keeps_neighbours_together():
    rng = np.random.default_rng(0)
    pts = rng.uniform(size=(4096, 3))
    order = morton_order(pts)
    assert sorted(order.tolist()) == list(range(4096))
    step = np.linalg.norm(np.diff(pts[order], axis=0), axis=1).mean()
    assert step < 0.25 * np.linalg.norm(np.diff(pts, axis=0), axis=1).mean()  # random order: ~0.66, Z-curve: ~0.05


def test_compressed_ply_layout_by_hand(tmp_path):
    """Header, chunk bounds and the first splat's words decoded here from the documented layout, not by the reader."""
    m = _model(n=300, sh_degree=3)
    info = write_compressed_ply(m, str(tmp_path / "m.compressed.ply"))
    raw = (tmp_path / "m.compressed.ply").read_bytes()
    head, body = raw.split(b"end_header\n", 1)
    lines = head.decode().splitlines()
    assert "comment SplatRenderMode: 2dgs" in lines
    assert "element chunk 2" in lines and "element vertex 300" in lines and "element sh 300" in lines
    assert info["sh_degree"] == 2 and info["bytes"] == len(raw)  # the factory renders degree 2: 8 coefficients
    assert len(body) == 2 * 18 * 4 + 300 * 16 + 300 * 24
    chunks = np.frombuffer(body, "<f4", 36).reshape(2, 18)
    words = np.frombuffer(body, "<u4", 300 * 4, 2 * 18 * 4).reshape(300, 4)
    g = _table(m)
    first = slice(0, CHUNK)
    np.testing.assert_allclose(chunks[0, 0:3], g["means"][first].min(0).values.numpy(), rtol=1e-6)
    np.testing.assert_allclose(chunks[0, 3:6], g["means"][first].max(0).values.numpy(), rtol=1e-6)
    colour = 0.5 + SH_C0 * g["dc"]
    np.testing.assert_allclose(chunks[1, 15:18], colour[CHUNK:].max(0).values.numpy(), rtol=1e-6)
    w = int(words[0, 0])
    x = chunks[0, 0] + (chunks[0, 3] - chunks[0, 0]) * ((w >> 21) / 2047)
    y = chunks[0, 1] + (chunks[0, 4] - chunks[0, 1]) * (((w >> 11) & 1023) / 1023)
    assert abs(x - float(g["means"][0, 0])) <= (chunks[0, 3] - chunks[0, 0]) / 2047
    assert abs(y - float(g["means"][0, 1])) <= (chunks[0, 4] - chunks[0, 1]) / 1023
    assert (int(words[0, 3]) & 255) == round(float(g["opacity"][0]) * 255)
    rot = int(words[0, 1])
    q = _unit(g["quats"][:1])[0]
    assert rot >> 30 == int(q.abs().argmax())


def test_compressed_ply_round_trip_within_its_steps(tmp_path):
    m = _model(n=600, sh_degree=3)
    write_compressed_ply(m, str(tmp_path / "m.compressed.ply"))
    back = read_compressed_ply(str(tmp_path / "m.compressed.ply"))
    g = _table(m)
    assert back.num_primitives == 600 and back.texture_mode == "none" and back.sh.shape[1] == 9
    span = lambda x: (x.max(0).values - x.min(0).values)
    assert ((back.means.double() - g["means"]).abs() <= span(g["means"]) / 1023 + 1e-6).all()
    assert ((back.log_scales.double() - g["log_scales"][:, :2]).abs() <= span(g["log_scales"])[:2] / 1023 + 1e-5).all()
    assert (_unit(back.quats) - _unit(g["quats"])).abs().max() < 2e-3
    assert (back.opacities.double() - g["opacity"]).abs().max() <= 0.5 / 255 + 1e-6
    assert (back.sh[:, 0].double() - g["dc"]).abs().max() <= float(span(g["dc"]).max()) / 255
    assert (back.sh[:, 1:].double() - g["rest"]).abs().max() <= 8 / 256 + 1e-6


def test_sog_bundle_layout_and_round_trip(tmp_path):
    m = _model(n=600, sh_degree=3)
    info = write_sog(m, str(tmp_path / "m.sog"))
    with zipfile.ZipFile(tmp_path / "m.sog") as z:
        names = z.namelist()
        meta = json.loads(z.read("meta.json"))
    assert names[0] == "meta.json" and set(names) == {"meta.json", "means_l.webp", "means_u.webp", "quats.webp",
                                                       "scales.webp", "sh0.webp", "shN_centroids.webp",
                                                       "shN_labels.webp"}
    assert meta["version"] == 2 and meta["count"] == 600 and meta["model"] == "2dgs"
    assert len(meta["scales"]["codebook"]) == len(meta["sh0"]["codebook"]) == len(meta["shN"]["codebook"]) == 256
    assert meta["shN"]["bands"] == 2 and meta["shN"]["count"] == info["palette"] == palette_size(600) == 600
    from ctgs.formats.playcanvas import _decode_webp

    with zipfile.ZipFile(tmp_path / "m.sog") as z:  # entries in the order splats first use them: label i is splat i's
        lab = _decode_webp("m.sog", "shN_labels.webp", z.read("shN_labels.webp")).reshape(-1, 4)[:600].astype(int)
    assert (lab[:, 0] | (lab[:, 1] << 8)).tolist() == list(range(600))
    back = read_sog(str(tmp_path / "m.sog"))
    g = _table(m)
    lt = np.log1p(np.abs(g["means"].numpy()))
    step = (lt.max(0) - lt.min(0)) / 65535  # 16 bits of the log transform
    assert (np.abs(np.log1p(np.abs(back.means.double().numpy())) - lt) <= step + 1e-6).all()
    assert (_unit(back.quats) - _unit(g["quats"])).abs().max() < 8e-3  # 8 bits of (q sqrt2 + 1) / 2
    assert (back.opacities.double() - g["opacity"]).abs().max() <= 0.5 / 255 + 1e-6
    # 256-entry codebooks: every value decodes to its nearest entry (K-means' assignment), with a small RMS error
    for got, want, key in ((back.log_scales, g["log_scales"][:, :2], "scales"), (back.sh[:, 0], g["dc"], "sh0")):
        book = torch.tensor(meta[key]["codebook"], dtype=torch.float64)
        nearest = (want[..., None] - book).abs().min(-1).values
        torch.testing.assert_close((got.double() - want).abs(), nearest, atol=1e-6, rtol=0)
        assert float(((got.double() - want) ** 2).mean().sqrt()) < 0.01 * float(want.std())
    # a palette entry per distinct row: only the 256-entry codebook of the palette's values remains
    rms = float(((back.sh[:, 1:].double() - g["rest"]) ** 2).mean().sqrt())
    assert rms < 0.01 * float(g["rest"].std())


def test_sog_palette_sizes_and_a_merged_palette(tmp_path, monkeypatch):
    """Every distinct row up to the 65,536 entries SOG's 16-bit labels address; past that, K-means merges rows (shown
    here with the cap lowered to 2048 for 3000 rows): the SH error is then K-means', small against the rows' spread."""
    import ctgs.formats.playcanvas as pc

    assert [palette_size(n) for n in (1, 200, 5000, 65536, 10**7)] == [1, 200, 5000, 65536, 65536]
    monkeypatch.setattr(pc, "PALETTE_MAX", 2048)
    m = _model(n=3000, sh_degree=1)
    info = write_sog(m, str(tmp_path / "m.sog"))
    assert info["palette"] == 2048 and info["sh_degree"] == 1
    back = read_sog(str(tmp_path / "m.sog"))
    g = _table(m)
    rms = float(((back.sh[:, 1:].double() - g["rest"]) ** 2).mean().sqrt())
    assert 0.0 < rms < 0.5 * float(g["rest"].std())


def test_degree_zero_has_no_sh_element_or_palette(tmp_path):
    m = _model(n=40, sh_degree=0)
    write_compressed_ply(m, str(tmp_path / "m.compressed.ply"))
    assert b"element sh" not in (tmp_path / "m.compressed.ply").read_bytes()[:2000]
    assert read_compressed_ply(str(tmp_path / "m.compressed.ply")).sh.shape[1] == 1
    info = write_sog(m, str(tmp_path / "m.sog"))
    assert info["palette"] == 0 and "shN" not in json.loads(zipfile.ZipFile(tmp_path / "m.sog").read("meta.json"))
    assert read_sog(str(tmp_path / "m.sog")).sh.shape[1] == 1


def test_bad_files_are_refused_with_the_file_named(tmp_path):
    write_compressed_ply(_model(n=20), str(tmp_path / "m.compressed.ply"))
    raw = (tmp_path / "m.compressed.ply").read_bytes()
    (tmp_path / "cut.compressed.ply").write_bytes(raw[:-5])
    with pytest.raises(UserError, match=r"cut.compressed.ply: .*truncated"):
        read_compressed_ply(str(tmp_path / "cut.compressed.ply"))
    write_plain_ply(_model(n=20), str(tmp_path / "plain.ply"))
    with pytest.raises(UserError, match=r"plain.ply: no `chunk` element.*--format ply"):
        read_compressed_ply(str(tmp_path / "plain.ply"))
    (tmp_path / "x.sog").write_bytes(b"not a zip")
    with pytest.raises(UserError, match=r"x.sog: not a SOG bundle"):
        read_sog(str(tmp_path / "x.sog"))
    write_sog(_model(n=20), str(tmp_path / "m.sog"))
    with zipfile.ZipFile(tmp_path / "m.sog") as z, zipfile.ZipFile(tmp_path / "v1.sog", "w") as out:
        for name in z.namelist():
            data = z.read(name)
            if name == "meta.json":
                meta = json.loads(data)
                meta["version"] = 1
                data = json.dumps(meta).encode()
            if name != "quats.webp":
                out.writestr(name, data)
    with pytest.raises(UserError, match=r"v1.sog: SOG version 1"):
        read_sog(str(tmp_path / "v1.sog"))
    with pytest.raises(UserError, match=r"no such file"):
        read_sog(str(tmp_path / "missing.sog"))


def test_an_empty_model_is_refused_and_nothing_is_written(tmp_path):
    z = torch.zeros
    empty = surfels_from_gaussians(z(0, 3), z(0, 3), z(0, 4), z(0), z(0, 1, 3))
    for write, name in ((write_sog, "e.sog"), (write_compressed_ply, "e.compressed.ply")):
        with pytest.raises(UserError, match="no primitives"):
            write(empty, str(tmp_path / name))
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------ PlayCanvas's reader and writer (splat-transform)

@pytest.fixture(scope="session")
def splat_transform() -> tuple[str, str]:
    # its one install script (webgpu's) only clears a macOS quarantine flag: not needed to read and write files
    node, package = npm_package("@playcanvas/splat-transform@3.7.0", "@playcanvas/splat-transform",
                                "PlayCanvas's reader and writer", ignore_scripts=True)
    return node, f"{package}/bin/cli.mjs"


def _convert(tool, src, dst, *extra):
    node, cli = tool
    p = subprocess.run([node, cli, "-q", "-w", *extra, str(src), str(dst)], capture_output=True, text=True,
                       timeout=300)
    assert p.returncode == 0, p.stderr + p.stdout


def _ply_columns(path) -> tuple[dict, list]:
    cols, comments = read_ply(str(path))
    return {k: torch.from_numpy(v.astype(np.float64)) for k, v in cols.items()}, comments


@pytest.mark.parametrize("fmt", ["compressed-ply", "sog"])
def test_playcanvas_reader_decodes_what_ours_decodes(tmp_path, splat_transform, fmt):
    """splat-transform reads our file and writes a plain PLY: the same splats in the same order as our reader gives,
    to float32, and it reads the 2DGS tag (its PLY then holds the two tangent scales only)."""
    m = _model(n=700, sh_degree=3)
    path = tmp_path / ("m.compressed.ply" if fmt == "compressed-ply" else "m.sog")
    (write_compressed_ply if fmt == "compressed-ply" else write_sog)(m, str(path))
    ours = (read_compressed_ply if fmt == "compressed-ply" else read_sog)(str(path))
    _convert(splat_transform, path, tmp_path / "st.ply")
    cols, comments = _ply_columns(tmp_path / "st.ply")
    assert "SplatRenderMode: 2dgs" in comments and "scale_2" not in cols
    n = 700
    f = lambda *names: torch.stack([cols[c] for c in names], 1)
    torch.testing.assert_close(f("x", "y", "z"), ours.means.double(), atol=1e-6, rtol=1e-6)
    torch.testing.assert_close(f("scale_0", "scale_1"), ours.log_scales.double(), atol=1e-5, rtol=0)
    torch.testing.assert_close(_unit(f("rot_0", "rot_1", "rot_2", "rot_3")), _unit(ours.quats), atol=1e-5, rtol=0)
    torch.testing.assert_close(torch.sigmoid(cols["opacity"]), ours.opacities.double(), atol=1e-5, rtol=0)
    torch.testing.assert_close(f("f_dc_0", "f_dc_1", "f_dc_2"), ours.sh[:, 0].double(), atol=1e-5, rtol=0)
    rest = f(*[f"f_rest_{i}" for i in range(24)]).reshape(n, 3, 8).transpose(1, 2)
    torch.testing.assert_close(rest, ours.sh[:, 1:].double(), atol=1e-5, rtol=0)


@pytest.mark.parametrize("fmt", ["compressed-ply", "sog"])
def test_our_reader_decodes_playcanvas_files(tmp_path, splat_transform, fmt):
    """PlayCanvas's writer makes the file from our plain PLY (degree 3 there, padded); our reader gives what its own
    reader gives from it. Its SOG encoder runs on the CPU (`-g cpu`)."""
    m = _model(n=500, sh_degree=3)
    write_plain_ply(m, str(tmp_path / "m.ply"))
    path = tmp_path / ("pc.compressed.ply" if fmt == "compressed-ply" else "pc.sog")
    _convert(splat_transform, tmp_path / "m.ply", path, *(["-g", "cpu"] if fmt == "sog" else []))
    ours = (read_compressed_ply if fmt == "compressed-ply" else read_sog)(str(path))
    _convert(splat_transform, path, tmp_path / "back.ply")
    cols, _ = _ply_columns(tmp_path / "back.ply")
    f = lambda *names: torch.stack([cols[c] for c in names], 1)
    assert ours.num_primitives == 500 and ours.sh.shape[1] == 16
    torch.testing.assert_close(f("x", "y", "z"), ours.means.double(), atol=1e-6, rtol=1e-6)
    assert "scale_2" not in cols  # the 2DGS tag of our PLY went through PlayCanvas's file and back
    torch.testing.assert_close(f("scale_0", "scale_1"), ours.log_scales.double(), atol=1e-5, rtol=0)
    torch.testing.assert_close(torch.sigmoid(cols["opacity"]), ours.opacities.double(), atol=1e-5, rtol=0)
    torch.testing.assert_close(f("f_dc_0", "f_dc_1", "f_dc_2"), ours.sh[:, 0].double(), atol=1e-5, rtol=0)
    rest = f(*[f"f_rest_{i}" for i in range(45)]).reshape(500, 3, 15).transpose(1, 2)
    torch.testing.assert_close(rest, ours.sh[:, 1:].double(), atol=1e-5, rtol=0)


def test_compressed_ply_carries_a_recentred_scenes_origin(tmp_path):
    """As the 3DGS PLY does: a header comment (viewers skip it; positions stay in the model's frame)."""
    m = _model(n=30)
    write_compressed_ply(m, str(tmp_path / "m.compressed.ply"), origin=[120000.0, 0.0, -5.0])
    head = (tmp_path / "m.compressed.ply").read_bytes().split(b"end_header")[0].decode()
    assert "comment world_origin 120000.0 0.0 -5.0" in head.splitlines()
    write_compressed_ply(m, str(tmp_path / "n.compressed.ply"), origin=[0.0, 0.0, 0.0])
    assert b"world_origin" not in (tmp_path / "n.compressed.ply").read_bytes()[:3000]


def test_the_3dgs_ply_is_tagged_2dgs_and_playcanvas_reads_the_tag(tmp_path, splat_transform):
    """Our 3DGS PLY carries Brush's `SplatRenderMode: 2dgs`; splat-transform keeps the tag through a conversion to
    SOG (meta.json `model`), so the surfels stay surfels in PlayCanvas's tools."""
    write_plain_ply(_model(n=50), str(tmp_path / "m.ply"))
    _, comments = read_ply(str(tmp_path / "m.ply"))
    assert "SplatRenderMode: 2dgs" in comments
    _convert(splat_transform, tmp_path / "m.ply", tmp_path / "m.sog", "-g", "cpu")
    assert json.loads(zipfile.ZipFile(tmp_path / "m.sog").read("meta.json"))["model"] == "2dgs"


def test_sog_keeps_shared_sh_rows_exactly(tmp_path):
    """A baked model's texel splats share their surfel's SH rows: when the distinct rows fit the palette, the palette
    is those rows (no K-means), so only the 256-entry codebook of their values remains."""
    m = _model(n=3000, sh_degree=1)
    m.sh.data[:, 1:] = m.sh.data[torch.arange(3000) % 40, 1:]  # 40 distinct rows over 3000 splats
    info = write_sog(m, str(tmp_path / "m.sog"))
    assert info["palette"] == 40
    back = read_sog(str(tmp_path / "m.sog"))
    g = _table(m)
    assert (back.sh[:, 1:].double() - g["rest"]).abs().max() < 1e-6 + 0.5 * float(g["rest"].max() - g["rest"].min()) / 255


@pytest.mark.parametrize("units", [1e-4, 1e4])
def test_scenes_in_very_small_or_large_units(tmp_path, units):
    """Both formats at the extremes of scene scale: positions come back within their quantisation relative to the
    scene (compressed PLY: a chunk's extent / 2^10; SOG: 16 bits of the log transform), rotations and opacities as at
    unit scale, nothing non-finite."""
    m = _model(n=600)
    m.means.data.mul_(units)
    m.log_scales.data.add_(math.log(units))
    g = _table(m)
    extent = float((g["means"].max(0).values - g["means"].min(0).values).max())
    for write, read, name in ((write_compressed_ply, read_compressed_ply, "m.compressed.ply"),
                              (write_sog, read_sog, "m.sog")):
        write(m, str(tmp_path / name))
        back = read(str(tmp_path / name))
        for t in (back.means, back.log_scales, back.quats, back.opacity_logits, back.sh):
            assert torch.isfinite(t).all(), name
        assert float((back.means.double() - g["means"]).abs().max()) < 2e-3 * extent, name
        assert (_unit(back.quats) - _unit(g["quats"])).abs().max() < 8e-3, name
        assert float((back.log_scales.double() - g["log_scales"][:, :2]).abs().max()) < 0.1, name


def test_sog_merges_distinct_rows_and_keeps_shared_rows_together(tmp_path, monkeypatch):
    """Past the palette's size the K-means runs on the distinct rows (a baked model repeats its surfels' rows per
    texel): splats that share a row share its entry."""
    import ctgs.formats.playcanvas as pc
    from ctgs.formats.playcanvas import _decode_webp

    monkeypatch.setattr(pc, "PALETTE_MAX", 64)
    m = _model(n=3000, sh_degree=1)
    m.sh.data[:, 1:] = m.sh.data[torch.arange(3000) % 200, 1:]  # 200 distinct rows, 15 splats each
    assert write_sog(m, str(tmp_path / "m.sog"))["palette"] == 64
    g = _table(m)
    with zipfile.ZipFile(tmp_path / "m.sog") as z:
        lab = _decode_webp("m.sog", "shN_labels.webp", z.read("shN_labels.webp")).reshape(-1, 4)[:3000].astype(int)
    label = lab[:, 0] | (lab[:, 1] << 8)
    rows = g["rest"].reshape(3000, -1).numpy()
    _, inverse = np.unique(rows, axis=0, return_inverse=True)
    for r in range(200):
        assert len(set(label[inverse.reshape(-1) == r].tolist())) == 1
    assert len(set(label.tolist())) > 32  # the entries are used, not collapsed


def test_supersplats_first_files_without_colour_bounds(tmp_path):
    """SuperSplat's first compressed PLYs had 12 chunk properties (no colour bounds: colour a plain 8-bit unorm of
    0.5 + C0 dc). Built here from one of ours: the header and chunk records cut to 12 properties, the colour bytes
    re-encoded plainly; the reader gives the same splats, colours to 8 bits."""
    m = _model(n=300, sh_degree=0)
    write_compressed_ply(m, str(tmp_path / "m.compressed.ply"))
    raw = (tmp_path / "m.compressed.ply").read_bytes()
    head, body = raw.split(b"end_header\n", 1)
    lines = [x for x in head.decode().splitlines() if not any(x == f"property float {p}" for p in CHUNK_PROPS[12:])]
    chunks = np.frombuffer(body, "<f4", 2 * 18).reshape(2, 18)
    words = np.frombuffer(body, "<u4", 300 * 4, 2 * 18 * 4).reshape(300, 4).copy()
    ours = read_compressed_ply(str(tmp_path / "m.compressed.ply"))
    colour = np.clip(0.5 + SH_C0 * ours.sh[:, 0].double().numpy(), 0, 1)
    c8 = np.round(colour * 255).astype(np.uint32)
    words[:, 3] = (c8[:, 0] << 24) | (c8[:, 1] << 16) | (c8[:, 2] << 8) | (words[:, 3] & 255)
    old = "\n".join(lines).encode() + b"\nend_header\n" + np.ascontiguousarray(chunks[:, :12]).tobytes() + words.tobytes()
    (tmp_path / "old.compressed.ply").write_bytes(old)
    back = read_compressed_ply(str(tmp_path / "old.compressed.ply"))
    torch.testing.assert_close(back.means, ours.means)
    torch.testing.assert_close(back.opacities, ours.opacities)
    assert float((0.5 + SH_C0 * back.sh[:, 0].double() - torch.from_numpy(colour)).abs().max()) <= 0.5 / 255 + 1e-6
