"""HTTP(S) download with resume, progress bar and size/sha256 verification (urllib only).

`download(url, dest)` streams into `dest + ".part"`; an existing .part is resumed with an HTTP Range
request (a server that ignores Range answers 200 and the download restarts from zero). The finished
file is verified (size, then sha256 when known) before it is renamed to `dest`; a file that fails
verification is deleted, so the next run starts clean. A verified download leaves `dest + ".sha256"`
beside it, so re-runs skip hashing multi-gigabyte archives again.
"""

from __future__ import annotations

import hashlib
import http.client
import os
import urllib.error
import urllib.request
from dataclasses import dataclass

from ctgs.errors import UserError
from ctgs.io import atomic

CHUNK = 1 << 20  # bytes per read
TIMEOUT_S = 60  # socket timeout per read, seconds


@dataclass
class DownloadResult:
    path: str
    size: int  # bytes
    sha256: str
    resumed_from: int  # bytes already on disk when this call started (0: fresh)
    skipped: bool  # already downloaded and verified earlier


def sha256_file(path: str, progress=None) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(CHUNK), b""):
            digest.update(block)
            if progress:
                progress(len(block))
    return digest.hexdigest()


def _progress_bar(quiet: bool):
    # rich only where a progress bar is drawn
    from rich.progress import (BarColumn, DownloadColumn, Progress, TextColumn, TimeRemainingColumn,
                               TransferSpeedColumn)

    return Progress(TextColumn("{task.description}"), BarColumn(), DownloadColumn(), TransferSpeedColumn(),
                    TimeRemainingColumn(), transient=True, disable=quiet)


def _open(url: str, offset: int):
    request = urllib.request.Request(url, headers={"User-Agent": "ctgs-fetch/1"})
    if offset:
        request.add_header("Range", f"bytes={offset}-")
    try:
        return urllib.request.urlopen(request, timeout=TIMEOUT_S)
    except urllib.error.HTTPError as exc:
        if exc.code == 416:  # range starts at/after the end: the .part already holds the whole file
            return None
        raise UserError(f"{url}: HTTP {exc.code} {exc.reason}; check the URL in the manifest or try later") from None
    except (urllib.error.URLError, OSError) as exc:
        reason = getattr(exc, "reason", exc)
        raise UserError(f"{url}: cannot connect ({reason}); check the network and run again (it resumes)") from None


class _WriteFailed(Exception):
    """A write to the .part file failed (args[0]: the OSError), told apart from the network's errors."""


def download(url: str, dest: str, *, size: int | None = None, sha256: str | None = None,
             quiet: bool = False) -> DownloadResult:
    """Download `url` to `dest` (resuming dest.part), verify, rename. Raises UserError on failures."""
    sidecar = dest + ".sha256"
    if os.path.isfile(dest):
        if os.path.isfile(sidecar) and (size is None or os.path.getsize(dest) == size):
            with open(sidecar) as f:
                known = f.read().strip()
            if sha256 is None or known == sha256:
                return DownloadResult(dest, os.path.getsize(dest), known, 0, True)
        os.replace(dest, dest + ".part")  # unverified leftover: verify it like a finished partial
    os.makedirs(os.path.dirname(os.path.abspath(dest)) or ".", exist_ok=True)
    part = dest + ".part"
    offset = os.path.getsize(part) if os.path.isfile(part) else 0
    if size is not None and offset > size:
        os.remove(part)
        offset = 0
    resumed_from = offset

    if size is None or offset < size:
        response = _open(url, offset)
        if response is not None:
            with response:
                if offset and response.status != 206:  # server ignored Range: start over
                    offset = resumed_from = 0
                length = response.headers.get("Content-Length")
                total = size or ((int(length) + offset) if length else None)
                try:
                    with _progress_bar(quiet) as bar, open(part, "ab" if offset else "wb") as out:
                        task = bar.add_task(os.path.basename(dest), total=total, completed=offset)
                        received = 0
                        try:
                            while block := response.read(CHUNK):
                                try:
                                    out.write(block)
                                except OSError as exc:  # the disk, not the network: said as such below
                                    raise _WriteFailed(exc) from None
                                received += len(block)
                                bar.advance(task, len(block))
                            # A dropped connection can look like a clean end of file: compare with the header.
                            if length and received < int(length):
                                raise http.client.IncompleteRead(b"", int(length) - received)
                        except (OSError, http.client.HTTPException) as exc:  # IncompleteRead, reset, timeout
                            raise UserError(f"{url}: download interrupted ({type(exc).__name__}); run the same "
                                            f"command again to resume from {part}") from None
                except _WriteFailed as exc:  # a full disk: the CLI's line names the .part file and the fix
                    raise atomic.named(exc.args[0], part) from None
                except OSError as exc:  # flushing at close on a full disk
                    raise atomic.named(exc, part) from None

    got = os.path.getsize(part)
    if size is not None and got != size:
        if got > size:
            os.remove(part)
        raise UserError(f"{url}: got {got} bytes, the manifest says {size}; run again to resume "
                        f"(if it persists the file on the server changed: update the manifest)")
    with _progress_bar(quiet) as bar:
        task = bar.add_task(f"sha256 {os.path.basename(dest)}", total=got)
        digest = sha256_file(part, progress=lambda n: bar.advance(task, n))
    if sha256 is not None and digest != sha256.lower():
        os.remove(part)
        raise UserError(f"{url}: sha256 mismatch (got {digest[:12]}..., expected {sha256[:12]}...); the corrupt "
                        f"download was deleted, run again")
    os.replace(part, dest)
    atomic.write_text(sidecar, digest + "\n")
    return DownloadResult(dest, got, digest, resumed_from, False)
