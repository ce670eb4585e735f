"""`ctgs fetch` and ctgs.io.download against a local HTTP server on 127.0.0.1 (no internet)."""

from __future__ import annotations

import hashlib
import io
import os
import tarfile
import threading
import zipfile
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import pytest
from click.testing import CliRunner

from ctgs.cli import main
from ctgs.errors import UserError
from ctgs.io.download import download
from ctgs.scene.fetch import MARKER, _safe_relative, fetch_dataset
from ctgs.scene.manifests import load_manifest

SCENES = ("train", "truck")


class _Server:
    """Serves `files` (path -> bytes) with HTTP Range support; records the Range headers it saw."""

    def __init__(self):
        self.files: dict[str, bytes] = {}
        self.ranges: list[str | None] = []
        self.honour_range = True
        self.cut_after: int | None = None  # send only this many bytes once, then drop the connection
        server = self

        class Handler(BaseHTTPRequestHandler):
            def do_GET(self):  # noqa: N802 (http.server API)
                data = server.files.get(self.path)
                server.ranges.append(self.headers.get("Range"))
                if data is None:
                    self.send_error(404)
                    return
                start, status = 0, 200
                header = self.headers.get("Range")
                if header and server.honour_range:
                    start = int(header.split("=")[1].split("-")[0])
                    if start >= len(data):
                        self.send_error(416)
                        return
                    status = 206
                self.send_response(status)
                self.send_header("Content-Length", str(len(data) - start))
                if status == 206:
                    self.send_header("Content-Range", f"bytes {start}-{len(data) - 1}/{len(data)}")
                self.end_headers()
                if server.cut_after is not None:
                    self.wfile.write(data[start:start + server.cut_after])
                    server.cut_after = None
                    self.close_connection = True
                    return
                self.wfile.write(data[start:])

            def log_message(self, *args):
                pass

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)  # port 0: a free port
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}"
        self.thread = threading.Thread(target=self.httpd.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)

    def __enter__(self):
        self.thread.start()
        return self

    def __exit__(self, *exc):
        self.httpd.shutdown()
        self.httpd.server_close()
        self.thread.join(timeout=5)


@pytest.fixture
def server():
    with _Server() as s:
        yield s


def _fixture_archive(fmt: str = "zip") -> bytes:
    """Same layout as tandt_db.zip: tandt/<scene>/{images,sparse/0}/..., db/<scene>/... (bytes are dummies)."""
    files = {}
    for scene in SCENES:
        for i in range(3):
            files[f"tandt/{scene}/images/{i:05d}.jpg"] = os.urandom(3000)
        for name in ("cameras.bin", "images.bin", "points3D.bin"):
            files[f"tandt/{scene}/sparse/0/{name}"] = f"{scene}/{name}".encode()
    files["db/playroom/images/0.jpg"] = b"x" * 100
    buf = io.BytesIO()
    if fmt == "zip":
        with zipfile.ZipFile(buf, "w") as z:
            for name, data in files.items():
                z.writestr(name, data)
    else:
        with tarfile.open(fileobj=buf, mode="w:gz") as t:
            for name, data in files.items():
                info = tarfile.TarInfo(name)
                info.size = len(data)
                t.addfile(info, io.BytesIO(data))
    return buf.getvalue()


def _manifest(tmp_path, url: str, data: bytes, *, sha256: str | None = None, fmt: str = "zip") -> str:
    sha = hashlib.sha256(data).hexdigest() if sha256 is None else sha256
    folder = tmp_path / "manifests"
    folder.mkdir(exist_ok=True)
    (folder / "mini.toml").write_text(f"""
name = "mini"
holdout = 8
images = "images"

[archives.tandt_db]
url = "{url}"
size = {len(data)}
sha256 = "{sha}"
format = "{fmt}"

[scenes.train]
archive = "tandt_db"
path = "tandt/train"

[scenes.truck]
archive = "tandt_db"
path = "tandt/truck"
images = "images"
holdout = 4
""")
    return str(folder)


def test_real_manifests_are_valid():
    m360 = load_manifest("mipnerf360")
    assert len(m360["scenes"]) == 9
    assert {m360["scenes"][s]["images"] for s in ("bicycle", "garden", "stump", "flowers", "treehill")} == {"images_4"}
    assert {m360["scenes"][s]["images"] for s in ("room", "counter", "kitchen", "bonsai")} == {"images_2"}
    assert m360["scenes"]["flowers"]["archive"] == "360_extra_scenes"
    assert m360["archives"]["360_v2"]["size"] == 12535427936
    tandt, db = load_manifest("tandt"), load_manifest("deepblending")
    assert set(tandt["scenes"]) == {"train", "truck"} and set(db["scenes"]) == {"drjohnson", "playroom"}
    assert tandt["archives"]["tandt_db"]["sha256"].startswith("816e62f2")
    assert all(s["holdout"] == 8 for m in (m360, tandt, db) for s in m["scenes"].values())


def test_fetch_extracts_and_is_idempotent(tmp_path, server):
    data = _fixture_archive()
    server.files["/tandt_db.zip"] = data
    manifests = _manifest(tmp_path, server.url + "/tandt_db.zip", data)
    root = tmp_path / "data"
    got = fetch_dataset("mini", root=str(root), manifest_dir=manifests, quiet=True)
    assert [(s.scene, s.images, s.holdout, s.skipped) for s in got] == \
        [("train", "images", 8, False), ("truck", "images", 4, False)]
    for scene in SCENES:
        folder = root / "mini" / scene
        assert sorted(os.listdir(folder / "images")) == ["00000.jpg", "00001.jpg", "00002.jpg"]
        assert (folder / "sparse" / "0" / "cameras.bin").read_bytes() == f"{scene}/cameras.bin".encode()
        assert (folder / MARKER).is_file()
    assert not (root / "mini" / "playroom").exists()  # other prefixes of the archive stay packed
    assert (root / ".downloads" / "tandt_db.zip").read_bytes() == data
    assert not [n for n in os.listdir(root / "mini") if n.startswith(".")]

    requests = len(server.ranges)
    again = fetch_dataset("mini", root=str(root), manifest_dir=manifests, quiet=True)
    assert all(s.skipped for s in again) and len(server.ranges) == requests  # no network on a re-run


def test_download_resumes_a_partial_file(tmp_path, server):
    data = os.urandom(300_000)
    server.files["/a.bin"] = data
    dest = tmp_path / "a.bin"
    (tmp_path / "a.bin.part").write_bytes(data[:123_456])  # an interrupted earlier download
    result = download(server.url + "/a.bin", str(dest), size=len(data),
                      sha256=hashlib.sha256(data).hexdigest(), quiet=True)
    assert server.ranges == ["bytes=123456-"]
    assert result.resumed_from == 123_456 and dest.read_bytes() == data
    assert not (tmp_path / "a.bin.part").exists()
    assert download(server.url + "/a.bin", str(dest), size=len(data), quiet=True).skipped
    assert len(server.ranges) == 1


def test_interrupted_download_resumes_on_the_next_run(tmp_path, server):
    data = os.urandom(200_000)
    server.files["/a.bin"] = data
    server.cut_after = 70_000
    dest = tmp_path / "a.bin"
    sha = hashlib.sha256(data).hexdigest()
    with pytest.raises(UserError, match="interrupted.*resume"):
        download(server.url + "/a.bin", str(dest), size=len(data), sha256=sha, quiet=True)
    assert (tmp_path / "a.bin.part").stat().st_size == 70_000 and not dest.exists()
    result = download(server.url + "/a.bin", str(dest), size=len(data), sha256=sha, quiet=True)
    assert result.resumed_from == 70_000 and dest.read_bytes() == data
    assert server.ranges == [None, "bytes=70000-"]


def test_download_restarts_when_the_server_ignores_range(tmp_path, server):
    data = os.urandom(50_000)
    server.files["/a.bin"] = data
    server.honour_range = False
    (tmp_path / "a.bin.part").write_bytes(b"stale bytes that must not be kept")
    result = download(server.url + "/a.bin", str(tmp_path / "a.bin"), size=len(data),
                      sha256=hashlib.sha256(data).hexdigest(), quiet=True)
    assert result.resumed_from == 0 and (tmp_path / "a.bin").read_bytes() == data


def test_checksum_mismatch_deletes_the_download(tmp_path, server):
    data = _fixture_archive()
    server.files["/tandt_db.zip"] = data
    manifests = _manifest(tmp_path, server.url + "/tandt_db.zip", data, sha256="0" * 64)
    root = tmp_path / "data"
    with pytest.raises(UserError, match="sha256 mismatch"):
        fetch_dataset("mini", root=str(root), manifest_dir=manifests, quiet=True)
    assert os.listdir(root / ".downloads") == []  # neither the .part nor a final file survives
    assert not (root / "mini").exists()


def test_size_mismatch_and_http_errors(tmp_path, server):
    server.files["/a.bin"] = b"x" * 1000
    with pytest.raises(UserError, match="got 1000 bytes, the manifest says 2000"):
        download(server.url + "/a.bin", str(tmp_path / "a.bin"), size=2000, quiet=True)
    with pytest.raises(UserError, match="HTTP 404"):
        download(server.url + "/missing.bin", str(tmp_path / "m.bin"), quiet=True)


def test_tar_archives_and_the_cli(tmp_path, server):
    data = _fixture_archive("tar")
    server.files["/tandt_db.tar.gz"] = data
    manifests = _manifest(tmp_path, server.url + "/tandt_db.tar.gz", data, fmt="tar")
    root = tmp_path / "data"
    runner = CliRunner()
    result = runner.invoke(main, ["fetch", "mini", "truck", "--root", str(root), "--manifest-dir", manifests,
                                  "--quiet", "--delete-archive"])
    assert result.exit_code == 0, result.output
    assert (root / "mini" / "truck" / "sparse" / "0" / "points3D.bin").is_file()
    assert not (root / "mini" / "train").exists()
    assert os.listdir(root / ".downloads") == []  # --delete-archive
    printed = runner.invoke(main, ["fetch", "mini", "truck", "--root", str(root), "--manifest-dir", manifests,
                                   "--print-scene-dir", "--print-images-dir", "--print-holdout"])
    assert printed.exit_code == 0 and printed.stdout.split() == [str(root / "mini" / "truck"), "images", "4"]
    bad = runner.invoke(main, ["fetch", "mini", "nosuch", "--manifest-dir", manifests])
    assert bad.exit_code == 2 and "unknown scene" in bad.stderr and len(bad.stderr.strip().splitlines()) == 1


def test_manifest_env_override_and_errors(tmp_path, monkeypatch):
    folder = tmp_path / "m"
    folder.mkdir()
    (folder / "broken.toml").write_text('name = "broken"\n[archives.a]\nurl = "http://x/a.zip"\n'
                                        '[scenes.s]\narchive = "zzz"\n')
    monkeypatch.setenv("CTGS_MANIFEST_DIR", str(folder))
    with pytest.raises(UserError, match="scenes.s: archive 'zzz'"):
        load_manifest("broken")
    with pytest.raises(UserError, match="known datasets: broken"):
        load_manifest("mipnerf360")


def test_archive_members_cannot_escape_the_scene_folder():
    assert str(_safe_relative("tandt/train/images/a.jpg", "tandt/train")) == "images/a.jpg"
    assert _safe_relative("tandt/truck/images/a.jpg", "tandt/train") is None
    assert _safe_relative("tandt/train", "tandt/train") is None
    with pytest.raises(UserError, match="unsafe"):
        _safe_relative("tandt/train/../../etc/passwd", "tandt/train")
