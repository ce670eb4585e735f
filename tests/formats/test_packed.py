"""The packed container: every dtype/layout/coder round-trips; corruption is a UserError naming the file."""

from __future__ import annotations

import numpy as np
import pytest

from ctgs.errors import UserError
from ctgs.formats.packed import CODERS, DTYPES, Section, decode_section, encode_section, layout_bytes, unlayout_bytes


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("shape", [(0,), (7,), (5, 3), (0, 3)])
def test_layouts_round_trip(dtype, shape):
    rng = np.random.default_rng(0)
    a = (rng.normal(size=shape) * 100).astype(dtype)
    for order in ("row", "column"):
        for shuffle in (False, True):
            raw = layout_bytes(a, order, shuffle)
            assert len(raw) == a.nbytes
            assert np.array_equal(unlayout_bytes(raw, np.dtype(dtype), list(shape), order, shuffle), a)


def test_shuffle_groups_bytes():
    a = np.array([0x0102, 0x0304], dtype="<u2")
    assert layout_bytes(a, "row", True) == bytes([0x02, 0x04, 0x01, 0x03])
    b = np.array([[1, 2], [3, 4]], dtype="u1")
    assert layout_bytes(b, "column", False) == bytes([1, 3, 2, 4])


@pytest.mark.parametrize("coder", CODERS)
def test_sections_round_trip_with_every_coder(coder):
    rng = np.random.default_rng(1)
    arrays = [rng.integers(0, 9, (1000, 3)).astype("u1"), rng.normal(size=(300, 4)).astype("<f2"),
              np.arange(50, dtype="<i4")]
    blob, entries = b"", []
    for i, a in enumerate(arrays):
        coded, entry = encode_section(Section(f"s{i}", a, {"kind": "float"}), coder, len(blob))
        blob += coded
        entries.append(entry)
    for a, e in zip(arrays, entries):
        assert np.array_equal(decode_section(blob, e, "model.bin"), a)
    if coder != "none":  # low-entropy indices shrink
        assert entries[0]["bytes"] < arrays[0].nbytes / 2


def test_corrupt_section_is_user_error():
    a = np.arange(1000, dtype="<u2")
    coded, entry = encode_section(Section("s", a, {"kind": "float"}), "none", 0)
    bad = bytearray(coded)
    bad[10] ^= 1
    with pytest.raises(UserError, match="checksum"):
        decode_section(bytes(bad), entry, "x/model.bin")
    with pytest.raises(UserError, match="truncated"):
        decode_section(coded[:-1], entry, "x/model.bin")
    with pytest.raises(UserError, match="unsupported"):
        decode_section(coded, {**entry, "dtype": "<c8"}, "x/model.bin")
    coded, entry = encode_section(Section("s", a, {"kind": "float"}), "xz", 0)
    with pytest.raises(UserError, match="corrupt xz"):
        decode_section(coded[:20] + bytes(len(coded) - 20), entry, "x/model.bin")


def test_large_sections_coded_as_parallel_streams(monkeypatch):
    """jobs > 1: a section above XZ_STREAM_BYTES becomes independent xz streams, concatenated: the same decoded
    bytes, one valid .xz file for readers that ignore `streams`, and a bad stream list is a UserError."""
    import lzma

    from ctgs.formats import packed

    monkeypatch.setattr(packed, "XZ_STREAM_BYTES", 5000)
    rng = np.random.default_rng(2)
    a = rng.integers(0, 16, (12_001,)).astype("u1")  # 3 streams of 5000, 5000, 2001 bytes
    single, e1 = encode_section(Section("s", a, {"kind": "codebook"}), "xz", 0)
    coded, entry = encode_section(Section("s", a, {"kind": "codebook"}), "xz", 0, jobs=2)
    assert "streams" not in e1 and len(entry["streams"]) == 3 and sum(entry["streams"]) == len(coded)
    assert entry["crc32"] == e1["crc32"]
    assert np.array_equal(decode_section(coded, entry, "model.bin"), a)
    assert lzma.decompress(coded, format=lzma.FORMAT_XZ) == a.tobytes()  # concatenated streams: one .xz file
    no_streams = {k: v for k, v in entry.items() if k != "streams"}
    assert np.array_equal(decode_section(coded, no_streams, "model.bin"), a)
    small, e_small = encode_section(Section("t", a[:4000], {"kind": "codebook"}), "xz", 0, jobs=2)
    assert "streams" not in e_small  # below the stream size: one stream as before
    for bad in ([entry["streams"][0], entry["streams"][1]], [0] + entry["streams"], "x"):
        with pytest.raises(UserError, match="stream sizes"):
            decode_section(coded, {**entry, "streams": bad}, "x/model.bin")
