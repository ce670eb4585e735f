"""Image reading and writing with OpenImageIO.

Pixel values: integer files (8/16-bit PNG, JPEG, TIFF) are returned as float32 in [0, 1]
(OIIO divides by 255 or 65535); float files (EXR, HDR) are returned as stored (linear, may exceed 1).

Alpha: `read_rgb` composites RGBA over a background colour exactly as 3DGS does
(`rgb * a + bg * (1 - a)`, with the file's unassociated alpha), black by default; `read_image`
returns all channels untouched. Grey images are replicated to three channels by `read_rgb`.

Writes are atomic (ctgs.io.atomic): an interrupted run never leaves a half-written image behind. Every write is
read back before it takes its final name (OIIO can report success for a file a full disk cut short).
"""

from __future__ import annotations

import contextlib
import errno
import functools
import os
import sys
import zlib
from dataclasses import dataclass

import numpy as np
import OpenImageIO as oiio

from ctgs.errors import UserError
from ctgs.io import atomic

# Extensions `list_images` treats as images (lower case).
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".exr", ".tif", ".tiff", ".bmp", ".hdr")


@dataclass(frozen=True)
class ImageInfo:
    width: int  # pixels
    height: int  # pixels
    channels: int
    format: str  # OIIO pixel type of the file, e.g. "uint8", "uint16", "half", "float"


def _open_config() -> oiio.ImageSpec:
    config = oiio.ImageSpec()
    # Keep PNG/TIFF alpha unassociated (as stored), so compositing matches 3DGS/PIL exactly.
    config.attribute("oiio:UnassociatedAlpha", 1)
    return config


def _bad(path: str, what: str) -> UserError:
    # OIIO messages span several lines; the CLI contract is one line per user error.
    what = " ".join(what.split())
    return UserError(f"{path}: {what}; replace or remove this file and run again")


def image_info(path: str) -> ImageInfo:
    """Header only (no pixel decoding): size and channel count."""
    if not os.path.isfile(path):
        raise UserError(f"{path}: image file not found; check the path or the image folder")
    inp = oiio.ImageInput.open(path, _open_config())
    if inp is None:
        raise _bad(path, f"cannot be opened as an image ({_oiio_message()})")
    try:
        spec = inp.spec()
        return ImageInfo(spec.width, spec.height, spec.nchannels, str(spec.format))
    finally:
        inp.close()


def read_image(path: str) -> np.ndarray:
    """All channels of `path` as float32 [H, W, C] (integer formats scaled to [0, 1])."""
    if not os.path.isfile(path):
        raise UserError(f"{path}: image file not found; check the path or the image folder")
    inp = oiio.ImageInput.open(path, _open_config())
    if inp is None:
        raise _bad(path, f"cannot be opened as an image ({_oiio_message()})")
    try:
        spec = inp.spec()
        pixels = inp.read_image(0, 0, 0, spec.nchannels, "float")
        # A truncated file decodes partially: OIIO reports it through has_error / a None result.
        if pixels is None or inp.has_error:
            detail = _first_line(inp.geterror() or _oiio_message())
            raise _bad(path, f"corrupt or truncated image ({detail})")
    finally:
        inp.close()
    pixels = np.asarray(pixels, dtype=np.float32)
    if pixels.ndim == 2:  # [H, W] for some single-channel readers
        pixels = pixels[:, :, None]
    if not np.isfinite(pixels).all():
        raise _bad(path, "contains NaN or infinite pixel values")
    return np.ascontiguousarray(pixels)


def to_rgb(pixels: np.ndarray, background: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """[H, W, C] -> [H, W, 3] float32: grey replicated, alpha composited over `background` (3DGS rule)."""
    c = pixels.shape[2]
    if c == 1:
        return np.repeat(pixels, 3, axis=2)
    if c == 2:  # grey + alpha
        grey, alpha = pixels[:, :, :1], pixels[:, :, 1:2]
        rgb = np.repeat(grey, 3, axis=2)
    elif c == 3:
        return pixels
    else:  # RGBA (extra channels beyond the 4th are ignored)
        rgb, alpha = pixels[:, :, :3], pixels[:, :, 3:4]
    bg = np.asarray(background, dtype=np.float32).reshape(1, 1, 3)
    return (rgb * alpha + bg * (1.0 - alpha)).astype(np.float32)


def read_rgb(path: str, background: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """`path` as float32 [H, W, 3]; RGBA composited over `background` (black by default)."""
    return to_rgb(read_image(path), background)


def write_image(path: str, array: np.ndarray, *, bits: int | None = None, half: bool = True) -> None:
    """Write [H, W, C] or [H, W] (C in 1..4) atomically.

    Float input is taken as [0, 1] and clipped for integer files; uint8/uint16 input is written as is.
    The file type follows the extension; `bits` (8 or 16) picks the integer depth for PNG/TIFF
    (default: 16 for uint16 input, else 8). EXR is written as half floats (`half=False`: 32-bit floats), unclipped.
    """
    arr = np.asarray(array)
    if arr.ndim == 2:
        arr = arr[:, :, None]
    if arr.ndim != 3 or not 1 <= arr.shape[2] <= 4:
        raise ValueError(f"write_image: array must have shape [H, W] or [H, W, 1..4], got {arr.shape}")
    ext = os.path.splitext(path)[1].lower()
    if ext in (".exr", ".hdr"):
        fmt = "half" if ext == ".exr" and half else "float"
        data = arr.astype(np.float32)
    else:
        if bits is None:
            bits = 16 if arr.dtype == np.uint16 else 8
        if bits not in (8, 16):
            raise ValueError(f"write_image: bits must be 8 or 16, got {bits}")
        if ext in (".jpg", ".jpeg", ".bmp"):
            bits = 8
        fmt = "uint8" if bits == 8 else "uint16"
        if arr.dtype == np.uint8:
            data = arr.astype(np.float32) / 255.0
        elif arr.dtype == np.uint16:
            data = arr.astype(np.float32) / 65535.0
        else:
            data = np.clip(arr.astype(np.float32), 0.0, 1.0)
    h, w, c = data.shape
    spec = oiio.ImageSpec(w, h, c, fmt)
    if c == 4 or c == 2:
        spec.attribute("oiio:UnassociatedAlpha", 1)
    if ext in (".jpg", ".jpeg"):
        spec.attribute("Compression", "jpeg:95")

    # The temporary name keeps the extension: OIIO picks the file format from it.
    with atomic.atomic_path(path) as tmp:
        out = oiio.ImageOutput.create(tmp)
        if out is None or not out.open(tmp, spec):
            detail = _first_line((out.geterror() if out is not None else "") or _oiio_message())
            raise _write_error(path, tmp, f"OpenImageIO cannot write this file ({detail})")
        ok = out.write_image(np.ascontiguousarray(data, dtype=np.float32))
        # OIIO reports a short write (a full disk) only through geterror() while write_image still returns True
        # (and so does close(), at which PNGs are written), and geterror() also holds harmless notes (TIFF's Exif
        # directory): the file is read back instead, and the notes are kept to explain a failure.
        err = out.geterror()
        closed = out.close()
        err = err or out.geterror()
        if not ok or not closed:
            raise _write_error(path, tmp, f"write failed ({_first_line(err or 'unknown OpenImageIO error')})")
        _verify_written(path, tmp, w, h, c, err)


def _write_error(path: str, tmp: str, detail: str) -> OSError:
    """An OSError for a failed image write: ENOSPC when the disk holding `path` is full (OIIO does not pass on
    errno), EIO otherwise. The CLI prints it as one line naming `path`."""
    try:
        st = os.statvfs(os.path.dirname(os.path.abspath(tmp)))
        full = st.f_bavail * st.f_frsize < 64 * 1024
    except OSError:
        full = False
    if full:
        return OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), path)
    return OSError(errno.EIO, " ".join(detail.split()), path)


def _verify_written(path: str, tmp: str, width: int, height: int, channels: int, notes: str = "") -> None:
    """Check the just-written file whole: a write that failed silently (an empty or cut file) is an OSError here,
    before the temporary becomes `path`. PNG and JPEG (renders, strips, image pyramids) are checked by their structure
    (every PNG chunk's CRC, the JPEG end marker, the size in the header) without decoding: a decoder's read-back needs
    stderr silenced for libpng's own line on a cut file, and that silence is process-wide (a progress display in
    another thread would lose its output). Other formats are read back through OpenImageIO."""
    if os.path.getsize(tmp) == 0:
        raise _write_error(path, tmp, "the written file is empty")
    ext = os.path.splitext(tmp)[1].lower()
    if ext in (".png", ".jpg", ".jpeg"):
        with open(tmp, "rb") as f:
            data = f.read()
        problem = _png_problem(data, width, height, channels) if ext == ".png" else _jpeg_problem(data, width, height)
        if problem:
            raise _write_error(path, tmp, f"the written file does not read back whole ({problem}"
                               + (f"; {_first_line(notes)}" if notes else "") + ")")
        return
    inp = oiio.ImageInput.open(tmp)
    if inp is None:
        raise _write_error(path, tmp, f"the written file does not read back ({_oiio_message()})")
    try:
        spec = inp.spec()
        pixels = inp.read_image(0, 0, 0, spec.nchannels, "uint8")
        if pixels is None or inp.has_error or (spec.width, spec.height, spec.nchannels) != (width, height, channels):
            raise _write_error(path, tmp, f"the written file does not read back whole "
                               f"({_first_line(notes or inp.geterror() or 'size differs')})")
    finally:
        inp.close()


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_CHANNELS = {0: 1, 2: 3, 3: 3, 4: 2, 6: 4}  # colour type -> channels


def _png_problem(data: bytes, width: int, height: int, channels: int) -> str | None:
    """Why `data` is not a whole PNG of this size, or None: the signature, IHDR, every chunk's CRC and IEND last."""
    if not data.startswith(_PNG_SIGNATURE):
        return "no PNG signature"
    pos, seen_ihdr = len(_PNG_SIGNATURE), False
    while pos + 12 <= len(data):
        length = int.from_bytes(data[pos:pos + 4], "big")
        kind, end = data[pos + 4:pos + 8], pos + 12 + length
        if end > len(data):
            return f"chunk {kind!r} cut short"
        if zlib.crc32(data[pos + 4:pos + 8 + length]) != int.from_bytes(data[end - 4:end], "big"):
            return f"chunk {kind!r} damaged"
        if kind == b"IHDR":
            w, h = int.from_bytes(data[pos + 8:pos + 12], "big"), int.from_bytes(data[pos + 12:pos + 16], "big")
            c = _PNG_CHANNELS.get(data[pos + 17], 0)
            if (w, h, c) != (width, height, channels):
                return f"{w}x{h}x{c} written, {width}x{height}x{channels} meant"
            seen_ihdr = True
        if kind == b"IEND":
            return None if seen_ihdr and end == len(data) else "IEND before the image header or not last"
        pos = end
    return "no IEND chunk (cut short)"


_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


def _jpeg_problem(data: bytes, width: int, height: int) -> str | None:
    """Why `data` is not a whole JPEG of this size, or None: SOI first, a frame header of this size, EOI last."""
    if not data.startswith(b"\xff\xd8"):
        return "no JPEG start marker"
    if not data.endswith(b"\xff\xd9"):
        return "no JPEG end marker (cut short)"
    pos = 2
    while pos + 4 <= len(data) and data[pos] == 0xFF:
        marker, length = data[pos + 1], int.from_bytes(data[pos + 2:pos + 4], "big")
        if marker in _JPEG_SOF:
            h, w = int.from_bytes(data[pos + 5:pos + 7], "big"), int.from_bytes(data[pos + 7:pos + 9], "big")
            return None if (w, h) == (width, height) else f"{w}x{h} written, {width}x{height} meant"
        pos += 2 + length
    return "no JPEG frame header"


# OpenImageIO's default filter when an image shrinks: Lanczos-3 stretched by the shrink ratio, pixels beyond the edge
# taken as the edge pixel. OIIO evaluates it as a 2D filter, every tap of a window 6 ratios wide in both axes (0.2-0.3 s
# a level of a 798x531 photo); the filter is separable, so shrinking applies it as two sparse matrix products, one per
# axis (2-12 ms), with OIIO's weights: the same values within 1e-5 (tests/io/test_images_resize.py).
LANCZOS_LOBES = 3


@functools.lru_cache(maxsize=64)
def _shrink_matrix(n_in: int, n_out: int):
    """[n_out, n_in] sparse weights of OIIO's shrinking filter along one axis (rows sum to 1)."""
    import scipy.sparse  # scikit-learn's dependency, loaded only when a pyramid level is made

    ratio = n_in / n_out
    centres = (np.arange(n_out) + 0.5) * ratio  # output pixel centres, in input pixels
    taps = int(np.ceil(2 * LANCZOS_LOBES * ratio)) + 2
    x = np.floor(centres - LANCZOS_LOBES * ratio).astype(np.int64)[:, None] + np.arange(taps)[None, :]  # [n_out, taps]
    d = (x + 0.5 - centres[:, None]) / ratio
    weights = np.where(np.abs(d) < LANCZOS_LOBES, np.sinc(d) * np.sinc(d / LANCZOS_LOBES), 0.0)
    weights /= weights.sum(1, keepdims=True)
    rows = np.repeat(np.arange(n_out), taps)
    m = scipy.sparse.csr_matrix((weights.ravel().astype(np.float32), (rows, np.clip(x, 0, n_in - 1).ravel())),
                                shape=(n_out, n_in))
    m.sum_duplicates()  # taps beyond an edge fold onto the edge pixel
    return m


def _shrink(pixels: np.ndarray, width: int, height: int) -> np.ndarray:
    h, w, c = pixels.shape
    rows = _shrink_matrix(h, height) @ np.ascontiguousarray(pixels, dtype=np.float32).reshape(h, w * c)
    cols = rows.reshape(height, w, c).transpose(1, 0, 2).reshape(w, height * c)
    out = _shrink_matrix(w, width) @ cols  # [width, height * c]
    return np.ascontiguousarray(out.reshape(width, height, c).transpose(1, 0, 2), dtype=np.float32)


def resize_image(pixels: np.ndarray, width: int, height: int) -> np.ndarray:
    """Antialiased resize of float32 [H, W, C] to [height, width, C] (OIIO's default filter: Lanczos-3 when it
    shrinks, applied per axis here; OIIO itself when either side grows)."""
    h, w, c = pixels.shape
    if width <= w and height <= h:
        return _shrink(pixels, width, height)
    src = oiio.ImageBuf(oiio.ImageSpec(w, h, c, "float"))
    src.set_pixels(oiio.ROI(0, w, 0, h, 0, 1, 0, c), np.ascontiguousarray(pixels, dtype=np.float32))
    dst = oiio.ImageBuf(oiio.ImageSpec(width, height, c, "float"))
    if not oiio.ImageBufAlgo.resize(dst, src):
        raise RuntimeError(f"resize failed: {dst.geterror()}")
    return np.asarray(dst.get_pixels(oiio.FLOAT), dtype=np.float32).reshape(height, width, c)


def list_images(folder: str) -> list[str]:
    """Image file names (not paths) directly in `folder`, sorted; hidden/temporary files skipped."""
    return sorted(
        name for name in os.listdir(folder)
        if not name.startswith(".") and os.path.splitext(name)[1].lower() in IMAGE_EXTENSIONS
        and os.path.isfile(os.path.join(folder, name))
    )


def _first_line(message: str) -> str:
    """OIIO repeats one failure over several lines; the first says it best."""
    lines = [line.strip() for line in message.splitlines() if line.strip()]
    return (lines[0] if lines else "unknown OpenImageIO error")[:200]


def _oiio_message() -> str:
    return _first_line(oiio.geterror() or "")


@contextlib.contextmanager
def stderr_silenced():
    """Point file descriptor 2 at /dev/null, then restore it: libpng/libjpeg print their own line for a
    corrupt file, while our UserError already names the file. Wrap whole batches (not single reads
    from several threads): the redirection is process-wide."""
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError):  # no real stderr (e.g. embedded): nothing to silence
        yield
        return
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(devnull)
