"""Every result file, benchmark script and local link the README and the docs name exists (a figure points to the
file a command wrote). A result named at a commit (`git show <commit>:benchmarks/results/...`, a record kept in git
history only) must exist at that commit."""

from __future__ import annotations

import os
import re
import subprocess

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
DOCS = os.path.join(ROOT, "docs")
PAGES = ["README.md", "CHANGELOG.md", "benchmarks/README.md"] + sorted(
    os.path.relpath(os.path.join(d, f), ROOT) for d, _, files in os.walk(DOCS) for f in files if f.endswith(".md"))
RESULT_PATH = re.compile(r"benchmarks/results/[A-Za-z0-9_.\-/]+")
SCRIPT_PATH = re.compile(r"benchmarks/[A-Za-z0-9_/]+\.(?:py|sh)\b")
MD_LINK = re.compile(r"\]\(([^)#\s]+)(?:#[^)]*)?\)")
AT_COMMIT = re.compile(r"\b([0-9a-f]{7,40}):$")
GENERATED = {os.path.join(DOCS, "reference", "config.md")}  # made by the docs build (docs/_hooks/config_keys.py)


@pytest.mark.parametrize("page", PAGES)
def test_named_result_files_and_local_links_exist(page):
    text = open(os.path.join(ROOT, page), encoding="utf-8").read()
    missing = []
    for m in RESULT_PATH.finditer(text):
        path = m.group(0).rstrip(".,/")
        at = AT_COMMIT.search(text[max(0, m.start() - 41):m.start()])
        if at:  # kept in git history only (a shallow clone without that commit cannot tell)
            def known(obj):
                return subprocess.run(["git", "cat-file", "-e", obj], cwd=ROOT, capture_output=True).returncode == 0
            if known(at.group(1)) and not known(f"{at.group(1)}:{path}"):
                missing.append(f"{at.group(1)}:{path}")
            continue
        if text[m.end():m.end() + 1] in ("*", "{", "<"):  # a pattern (train_speed_*.md, x.{md,json}): a prefix
            folder, prefix = os.path.split(os.path.join(ROOT, m.group(0)))
            if not os.path.isdir(folder) or not any(f.startswith(prefix) for f in os.listdir(folder)):
                missing.append(m.group(0) + "...")
        elif not os.path.exists(os.path.join(ROOT, path)):
            missing.append(path)
    for m in SCRIPT_PATH.finditer(text):
        if not os.path.exists(os.path.join(ROOT, m.group(0))):
            missing.append(m.group(0))
    for m in MD_LINK.finditer(text):
        target = m.group(1)
        if "://" in target or target.startswith("mailto:"):
            continue
        resolved = os.path.normpath(os.path.join(ROOT, os.path.dirname(page), target))
        if not os.path.exists(resolved) and resolved not in GENERATED:
            missing.append(target)
    assert not missing, f"{page} names files that do not exist: {missing}"
