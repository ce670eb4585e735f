"""The floors of the package hold (docs/reference/architecture.md): import-linter checks the contracts of
pyproject.toml ([tool.importlinter]) on the code, and fails on a copy of it with one import planted the wrong way.
Imports inside functions are only for what is loaded late on purpose, each with a comment saying why."""

from __future__ import annotations

import ast
import os
import re
import shutil
import subprocess
import sys

import importlinter  # noqa: F401  (the test extra installs it: without it this module fails, it never skips)
import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
# The stages are loaded one at a time by the CLI (ctgs/cli.py): what a stage imports inside its command is its own
# start-up cost, not a floor's.
LATE_BY_DESIGN = ("ctgs/stages/", "ctgs/cli.py")


def _lint(root: str) -> subprocess.CompletedProcess:
    """import-linter on the ctgs package under `root` with root's pyproject.toml (a subprocess: its own sys.path)."""
    code = ("import sys; from importlinter.cli import lint_imports; "
            "sys.exit(lint_imports(config_filename='pyproject.toml', no_cache=True))")
    env = {**os.environ, "PYTHONPATH": root}
    return subprocess.run([sys.executable, "-c", code], cwd=root, env=env, capture_output=True, text=True)


def test_the_floors_hold():
    out = _lint(ROOT)
    assert out.returncode == 0, out.stdout + out.stderr
    assert "BROKEN" not in out.stdout


@pytest.mark.parametrize("lower, upper", [("ctgs/io/atomic.py", "ctgs.formats.spz"),
                                          ("ctgs/model/jagged.py", "ctgs.train.routines.texels"),
                                          ("ctgs/runs/read.py", "ctgs.train.loop.trainer"),
                                          ("ctgs/render/sh.py", "ctgs.model.surfels")])
def test_an_upward_import_breaks_them(tmp_path, lower, upper):
    shutil.copytree(os.path.join(ROOT, "ctgs"), tmp_path / "ctgs", ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(os.path.join(ROOT, "pyproject.toml"), tmp_path)
    # Inside a function, where such imports used to hide: the linter sees them there too.
    with open(tmp_path / lower, "a") as f:
        f.write(f"\n\ndef _planted():\n    import {upper}  # noqa: F401\n")
    out = _lint(str(tmp_path))
    assert out.returncode != 0, out.stdout
    module = lower[:-3].replace("/", ".")
    assert f"{module} -> {upper}" in out.stdout, out.stdout


@pytest.mark.parametrize("planted", ["measures.allocation", "benchmarks.measures.align"])
def test_a_package_module_importing_study_code_breaks_them(tmp_path, planted):
    """The measures of benchmarks/ stay outside the package, as the tests do: a module of ctgs that imports one
    (by either name it is reachable under) breaks the last contract."""
    shutil.copytree(os.path.join(ROOT, "ctgs"), tmp_path / "ctgs", ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(os.path.join(ROOT, "pyproject.toml"), tmp_path)
    with open(tmp_path / "ctgs/scene/demo.py", "a") as f:
        f.write(f"\n\ndef _planted():\n    import {planted}  # noqa: F401\n")
    out = _lint(str(tmp_path))
    assert out.returncode != 0, out.stdout
    assert f"ctgs.scene.demo -> {planted.split('.')[0]}" in out.stdout, out.stdout


def test_kernel_comments_cite_no_benchmark_record():
    """A kernel comment says why; how much is the record's to say (the docs cite records, kernels/ does not)."""
    record = re.compile(r"benchmarks/results/|results/\w+/|\w+_[0-9a-f]{7}\.(md|json|txt|log)\b")
    found = []
    for folder, _, files in os.walk(os.path.join(ROOT, "kernels")):
        for name in files:
            if name.endswith((".h", ".cpp", ".cu", ".cuh")):
                path = os.path.join(folder, name)
                with open(path, encoding="utf-8") as f:
                    found += [f"{os.path.relpath(path, ROOT)}:{i}" for i, line in enumerate(f, 1) if record.search(line)]
    assert not found, f"kernel comments citing benchmark records (keep the reason, drop the record): {found}"


def _late_imports():
    """(path, line, module) of every import made inside a function in the package, stages and cli aside."""
    for folder, _, files in os.walk(os.path.join(ROOT, "ctgs")):
        for name in files:
            path = os.path.join(folder, name)
            rel = os.path.relpath(path, ROOT).replace(os.sep, "/")
            if not name.endswith(".py") or rel.startswith(LATE_BY_DESIGN) or "/_kernels/" in rel:
                continue
            with open(path) as f:
                source = f.read()
            lines = source.splitlines()

            def visit(node, inside):
                for child in ast.iter_child_nodes(node):
                    if inside and isinstance(child, (ast.Import, ast.ImportFrom)):
                        yield rel, child.lineno, lines
                    yield from visit(child, inside or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)))

            yield from visit(ast.parse(source), False)


def _says_why(lines: list[str], lineno: int) -> bool:
    """A comment on the import's line or on the lines right above it (an import under another one shares it)."""
    if "#" in lines[lineno - 1]:
        return True
    i = lineno - 2
    while i >= 0 and lines[i].strip().startswith(("import ", "from ")):
        i -= 1
    return i >= 0 and lines[i].strip().startswith("#")


def test_imports_inside_functions_say_why():
    silent = [f"{rel}:{lineno}" for rel, lineno, lines in _late_imports() if not _says_why(lines, lineno)]
    assert not silent, ("an import inside a function without a comment saying why (an optional or heavy "
                        "dependency loaded late): move it to the top of the module, or say why: " + ", ".join(silent))
