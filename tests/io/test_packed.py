"""The packed container: every dtype/layout/coder round-trips; corruption is a UserError naming the file."""

from __future__ import annotations

import numpy as np
import pytest

from ctgs.errors import UserError
from ctgs.io.packed import CODERS, DTYPES, Section, decode_section, encode_section, layout_bytes, unlayout_bytes


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
