"""`make table`: the paper's per-scene layout, with the paper's own row beside a benchmark scene, labelled with the
size the paper trained at."""

from __future__ import annotations

import pytest

from ctgs.errors import UserError
from ctgs.evaluation.report import build_table
from ctgs.scene.manifests import load_manifest
from ctgs.stages.eval import _paper_rows


def _metrics(**kw):
    m = {"schema": "ctgs-metrics", "dataset": "mipnerf360", "scene": "bonsai", "psnr": 27.123, "ssim": 0.85,
         "lpips": 0.2, "points": 30500, "texels": 1_200_000, "params": 4_100_000, "fps": 12.0,
         "model_memory_bytes": 16_400_000, "bytes_on_disk": 17_000_000, "texels_per_primitive": 39.3,
         "resolution": [200, 133], "train_seconds": 900.0}
    return {**m, **kw}


def test_the_shipped_manifests_hold_the_papers_per_scene_rows():
    rows = _paper_rows([_metrics(), _metrics(dataset="tandt", scene="truck"), _metrics(scene="unknown")])
    assert set(rows) == {("mipnerf360", "bonsai"), ("tandt", "truck")}
    bonsai = rows[("mipnerf360", "bonsai")]
    assert (bonsai["psnr"], bonsai["ssim"], bonsai["points"], bonsai["params"]) == (31.46, 0.933, 291_000, 44_100_000)
    assert bonsai["resolution"] == "1559x1039"  # the size the paper trained bonsai at
    assert rows[("tandt", "truck")]["resolution"] == "images"  # elsewhere: the protocol's image folder


def test_table_prints_our_row_the_papers_beside_it_and_a_mean_of_ours_only():
    ref = _paper_rows([_metrics()])
    md, csv_text = build_table([_metrics(), _metrics(compressed=True, compression_target="balanced")], ref)
    lines = md.splitlines()
    assert lines[0].startswith("| Dataset | Scene | Resolution | SSIM | PSNR | LPIPS | Points | Texels | Params | FPS")
    assert "Train min" in lines[0]
    ours = next(line for line in lines if line.startswith("| mipnerf360 | bonsai |"))
    paper = next(line for line in lines if "bonsai (paper, all photos)" in line)
    assert "| 200x133 |" in ours and "| 27.12 |" in ours and "| 15.0 |" in ours  # 900 s: 15.0 train minutes
    assert "| 1559x1039 |" in paper and "| 31.46 |" in paper and "| 291K |" in paper and "176MB" in paper
    assert lines.index(paper) == lines.index(ours) + 1
    # the mean is ours alone (1 scene), and the compressed group has no paper row
    assert "**mean (1)**" in md and md.count("(paper, all photos)") == 1
    assert "bonsai (paper, all photos)" in csv_text


def test_a_manifest_paper_row_with_an_unknown_key_is_named(tmp_path):
    bad = tmp_path / "m.toml"
    bad.write_text('[archives.a]\nurl = "http://x/a.zip"\n[scenes.s]\narchive = "a"\npaper = { psnr = 30.0, foo = 1 }\n')
    with pytest.raises(UserError, match=r"scenes.s.paper: a table of"):
        load_manifest(str(bad))
