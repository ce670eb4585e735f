"""The product names no history of its making (numbered work sessions, VM tags, borrowed machines: WORDS) in README,
docs, the package, tests, configs, the benchmark scripts or the recorded results (names and contents). History lives in
CHANGELOG.md (by version and date) and in git; a machine is named by what it is, a run by its commit and date."""

from __future__ import annotations

import os
import re
import subprocess

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
WORDS = re.compile(r"[Ss]ession [0-9]|_vm[0-9]|\blent\b|_s[0-9]{2}[_.]")
TEXT_PATHS = ["README.md", "docs", "ctgs", "tests", "configs", "benchmarks"]
THIS = os.path.relpath(os.path.abspath(__file__), ROOT)


def _tracked(paths):
    out = subprocess.run(["git", "ls-files", "-z", "--", *paths], cwd=ROOT, capture_output=True, check=True)
    return [p for p in out.stdout.decode().split("\0") if p]


def _text_files():
    """Tracked text files of the product, the records in benchmarks/results included (their commands, notes and
    sources name records by their current names and runs by commit and date)."""
    for path in _tracked(TEXT_PATHS):
        if path == THIS:
            continue
        if os.path.exists(os.path.join(ROOT, path)):
            yield path


def test_no_history_words_in_text():
    hits = []
    for path in _text_files():
        try:
            text = open(os.path.join(ROOT, path), encoding="utf-8").read()
        except UnicodeDecodeError:
            continue
        for n, line in enumerate(text.splitlines(), 1):
            if WORDS.search(line):
                hits.append(f"{path}:{n}: {line.strip()[:120]}")
    assert not hits, "history words (name the machine and the commit instead):\n" + "\n".join(hits[:50])


def test_no_history_words_in_result_names():
    hits = [p for p in _tracked(["benchmarks/results"]) if WORDS.search(p) or re.search(r"session[0-9]", p)]
    assert not hits, "result files named by their making:\n" + "\n".join(hits[:50])
