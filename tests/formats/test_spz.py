"""`ctgs export --format spz`: the bytes against the format's layout read by hand, a round trip within the
quantisation, the frame (spz stores RUB, ours is COLMAP's RDF), the fractional bits at other units, refusals,
and Niantic's own reader (its C++ compiled to WebAssembly, npm @spz-loader/core) on our file."""

from __future__ import annotations

import gzip
import json
import math
import struct
import subprocess

import numpy as np
import pytest
import torch
from factory_io import random_model
from npm_cache import npm_package

from ctgs.errors import UserError
from ctgs.formats.plain_ply import SH_C0, texture_means
from ctgs.formats.spz import HEADER, read_spz, sh_flips, write_spz
from ctgs.model.surfels import SurfelModel


def _model(n: int = 60, sh_degree: int = 3, scale: float = 1.0, seed: int = 3) -> SurfelModel:
    m = random_model(n=n, sh_degree=sh_degree, seed=seed)
    m.sh.data.clamp_(-0.9, 0.9)  # inside spz's SH range: the round trip is then within the quantisation step
    m.means.data.mul_(scale)
    m.log_scales.data.add_(math.log(scale))
    m.k_min.data.mul_(scale)
    return m


def _raw(path) -> tuple[tuple, bytes]:
    raw = gzip.decompress(open(path, "rb").read())
    return HEADER.unpack_from(raw), raw


def _unit(q: torch.Tensor) -> torch.Tensor:
    q = torch.nn.functional.normalize(q.double(), dim=1)
    return q * torch.where(q[:, :1] < 0, -1.0, 1.0)  # q and -q are one rotation


def test_header_and_array_sizes(tmp_path):
    m = _model(n=60, sh_degree=3)  # the factory renders degree 2: 8 band coefficients
    info = write_spz(m, str(tmp_path / "m.spz"))
    (magic, version, n, degree, fb, flags, reserved), raw = _raw(tmp_path / "m.spz")
    assert raw[:4] == b"NGSP" and magic == 0x5053474E and version == 3 and (n, degree) == (60, 2)
    assert fb == info["fractional_bits"] == 12 and flags == 0 and reserved == 0
    assert len(raw) == 16 + 60 * (9 + 1 + 3 + 3 + 4 + 8 * 3)
    assert info["bytes"] == (tmp_path / "m.spz").stat().st_size
    assert not list(tmp_path.glob("*.tmp"))


def test_arrays_read_by_hand_are_in_the_rub_frame(tmp_path):
    """Positions, alphas, colours and scales decoded here from the documented layout, not by read_spz: y and z
    change sign (RDF -> RUB), the DC colour carries the texture's mean."""
    m = _model(n=40)
    write_spz(m, str(tmp_path / "m.spz"))
    (_, _, n, _, fb, _, _), raw = _raw(tmp_path / "m.spz")
    b = np.frombuffer(raw, np.uint8, offset=16)
    p = b[: n * 9].reshape(n, 3, 3).astype(np.int64)
    fixed = p[..., 0] | (p[..., 1] << 8) | (p[..., 2] << 16)
    pos = np.where(fixed >= 1 << 23, fixed - (1 << 24), fixed) / 2.0**fb
    expect = m.means.double().numpy() * [1, -1, -1]
    np.testing.assert_allclose(pos, expect, atol=0.5 / 2**fb + 1e-9)
    alpha = b[n * 9: n * 10] / 255.0
    np.testing.assert_allclose(alpha, m.opacities.double().numpy(), atol=0.5 / 255 + 1e-9)
    dc = (b[n * 10: n * 13].reshape(n, 3) / 255.0 - 0.5) / 0.15
    want_dc = (m.sh[:, 0].double() + texture_means(m) / SH_C0).numpy()
    np.testing.assert_allclose(dc, want_dc, atol=0.5 / 255 / 0.15 + 1e-9)
    log_s = b[n * 13: n * 16].reshape(n, 3) / 16.0 - 10.0
    np.testing.assert_allclose(log_s[:, :2], m.log_scales.double().numpy(), atol=1 / 32 + 1e-9)
    assert (log_s[:, 2] < log_s[:, :2].min(1) - 5).all()  # the flat axis


def test_sh_signs_under_the_half_turn_about_x():
    """The basis-derived signs against the parity of each real SH polynomial in y and z (3DGS order)."""
    odd_in_y_plus_z = [1, 1, 0,  # y, z, x
                       1, 0, 0, 1, 0,  # xy, yz, 2zz-xx-yy, xz, xx-yy
                       1, 0, 1, 1, 0, 1, 0]  # y(3xx-yy), xyz, y(4zz-xx-yy), z(2zz-3xx-3yy), x(4zz-..), z(xx-yy), x(xx-3yy)
    np.testing.assert_array_equal(sh_flips(3), [-1.0 if odd else 1.0 for odd in odd_in_y_plus_z])
    assert sh_flips(1).tolist() == [-1.0, -1.0, 1.0] and sh_flips(0).size == 0


@pytest.mark.parametrize("sh_degree", [0, 1, 3])
def test_round_trip_within_quantisation(tmp_path, sh_degree):
    m = _model(n=80, sh_degree=sh_degree)
    info = write_spz(m, str(tmp_path / "m.spz"))
    back = read_spz(str(tmp_path / "m.spz"))
    k = (info["sh_degree"] + 1) ** 2
    assert back.num_primitives == 80 and back.sh.shape[1] == k and back.texture_mode == "none"
    assert (back.means - m.means).abs().max() <= 0.5 / 2 ** info["fractional_bits"] + 1e-6
    assert (back.log_scales - m.log_scales).abs().max() <= 1 / 32 + 1e-5
    assert (_unit(back.quats) - _unit(m.quats)).abs().max() < 2e-3  # 9 bits over [0, sqrt(1/2)]
    assert (back.opacities - m.opacities).abs().max() <= 0.5 / 255 + 1e-5
    want_dc = m.sh[:, 0].double() + texture_means(m) / SH_C0
    assert (back.sh[:, 0].double() - want_dc).abs().max() <= 0.5 / 255 / 0.15 + 1e-5
    if k > 1:
        band1 = (back.sh[:, 1:4] - m.sh[:, 1:4]).abs().max()
        assert band1 <= 4 / 128 + 0.5 / 128 + 1e-5  # buckets of 8 steps of 1/128, rounded to the nearest
    if k > 4:
        assert (back.sh[:, 4:k] - m.sh[:, 4:k]).abs().max() <= 8 / 128 + 0.5 / 128 + 1e-5


@pytest.mark.parametrize("scale", [1e-4, 1e3])
def test_other_units_keep_their_relative_precision(tmp_path, scale):
    """A model in small units gets more fractional bits, one in large units fewer (24 bits must hold it)."""
    m = _model(n=50, sh_degree=1, scale=scale)
    info = write_spz(m, str(tmp_path / "m.spz"))
    back = read_spz(str(tmp_path / "m.spz"))
    step = 2.0 ** -info["fractional_bits"]
    assert (info["fractional_bits"] > 12) if scale < 1 else (info["fractional_bits"] < 12)
    assert step <= float(m.scales.median()) / 64 or info["fractional_bits"] < 12
    assert float((back.means - m.means).abs().max()) <= step / 2 * (1 + 1e-6) + 1e-7 * scale
    assert float(m.means.abs().max()) * 2 ** info["fractional_bits"] < 2**23


def test_units_spz_cannot_hold_are_reported(tmp_path):
    far = _model(n=10, scale=1.0)
    far.means.data[0, 0] = 1e7
    with pytest.raises(UserError, match=r"past \.spz's 24-bit range .* export --format ply"):
        write_spz(far, str(tmp_path / "far.spz"))
    assert not list(tmp_path.iterdir())
    tiny = _model(n=10, scale=1e-5)  # log scales ~ -13.5: below spz's -10
    info = write_spz(tiny, str(tmp_path / "tiny.spz"))
    assert info["tangent_scales_clipped"] == 20 and info["sh_clipped"] == 0
    loud = _model(n=10, sh_degree=1)
    loud.sh.data[:, 1:] = 2.0  # past spz's SH range [-1, 1]
    assert write_spz(loud, str(tmp_path / "loud.spz"))["sh_clipped"] == 10 * 3 * 3


def test_reader_refuses_other_files(tmp_path):
    path = tmp_path / "x.spz"
    path.write_bytes(b"not gzip")
    with pytest.raises(UserError, match=r"x.spz: not a .spz file \(not a gzip stream"):
        read_spz(str(path))
    path.write_bytes(gzip.compress(struct.pack("<IIIBBBB", 0x12345678, 3, 0, 0, 12, 0, 0)))
    with pytest.raises(UserError, match=r"x.spz: magic 0x12345678 is not .spz's"):
        read_spz(str(path))
    write_spz(_model(n=5), str(path))
    raw = gzip.decompress(path.read_bytes())
    path.write_bytes(gzip.compress(raw[:-3]))
    with pytest.raises(UserError, match=r"truncated or not a .spz file"):
        read_spz(str(path))
    path.write_bytes(gzip.compress(raw[:4] + struct.pack("<I", 1) + raw[8:]))
    with pytest.raises(UserError, match=r"version 1; this reader reads versions 2 and 3"):
        read_spz(str(path))


DECODE_JS = """
process.type = "renderer";  // the bundle's node branch needs a createRequire it does not ship: the browser path
const { loadSpz } = require(process.argv[1]);
const bytes = require("fs").readFileSync(process.argv[2]);
loadSpz(bytes, { colorScaleFactor: 1, unpackOptions: { coordinateSystem: "RDF" } }).then(g => {
  const a = x => Array.from(x);
  console.log(JSON.stringify({ numPoints: g.numPoints, shDegree: g.shDegree, positions: a(g.positions),
    scales: a(g.scales), rotations: a(g.rotations), alphas: a(g.alphas), colors: a(g.colors), sh: a(g.sh) }));
}, e => { console.error(String(e)); process.exit(2); });
"""


@pytest.fixture(scope="session")
def spz_reader() -> tuple[str, str]:
    return npm_package("@spz-loader/core@0.3.1", "@spz-loader/core", "Niantic's spz reader")


def test_niantics_reader_gets_our_model_back(tmp_path, spz_reader):
    """Niantic's C++ reader (WebAssembly build), asked for the RDF frame, returns what read_spz returns and the
    model within the quantisation: the layout, the frame change and the quaternion packing agree with it."""
    m = _model(n=70, sh_degree=3)
    write_spz(m, str(tmp_path / "m.spz"))
    node, package = spz_reader
    p = subprocess.run([node, "-e", DECODE_JS, package, str(tmp_path / "m.spz")], capture_output=True, text=True,
                       timeout=300)
    assert p.returncode == 0, p.stderr
    ref = json.loads(p.stdout)
    ours = read_spz(str(tmp_path / "m.spz"))
    n = 70
    assert (ref["numPoints"], ref["shDegree"]) == (n, 2)
    f = lambda key, *shape: torch.tensor(ref[key], dtype=torch.float64).reshape(n, *shape)  # noqa: E731
    torch.testing.assert_close(f("positions", 3), ours.means.double(), atol=1e-6, rtol=0)
    torch.testing.assert_close(f("scales", 3).log()[:, :2], ours.log_scales.double(), atol=1e-5, rtol=0)
    xyzw = f("rotations", 4)
    torch.testing.assert_close(_unit(torch.cat([xyzw[:, 3:], xyzw[:, :3]], 1)), _unit(ours.quats), atol=1e-5, rtol=0)
    assert (_unit(torch.cat([xyzw[:, 3:], xyzw[:, :3]], 1)) - _unit(m.quats.double())).abs().max() < 2e-3
    torch.testing.assert_close(f("alphas"), ours.opacities.double(), atol=1e-5, rtol=0)
    torch.testing.assert_close(f("colors", 3) - 0.5, ours.sh[:, 0].double(), atol=1e-5, rtol=0)
    torch.testing.assert_close(f("sh", 8, 3), ours.sh[:, 1:].double(), atol=1e-6, rtol=0)
    assert (f("positions", 3) - m.means.double()).abs().max() < 2.0**-12


def test_niantics_reader_sees_a_wrong_frame(tmp_path, spz_reader):
    """The check can fail: a file written without the RDF -> RUB change decodes with y and z negated."""
    m = _model(n=10, sh_degree=1)
    from ctgs.formats import spz

    flip = spz.FLIP.copy()
    try:
        spz.FLIP[:] = 1.0
        write_spz(m, str(tmp_path / "m.spz"))
    finally:
        spz.FLIP[:] = flip
    node, package = spz_reader
    p = subprocess.run([node, "-e", DECODE_JS, package, str(tmp_path / "m.spz")], capture_output=True, text=True,
                       timeout=300)
    pos = torch.tensor(json.loads(p.stdout)["positions"], dtype=torch.float64).reshape(10, 3)
    torch.testing.assert_close(pos[:, 1:], -m.means.double()[:, 1:], atol=1e-3, rtol=0)
