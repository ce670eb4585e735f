"""Measures the benchmarks and the tests apply to what ctgs makes, kept outside the package: ctgs itself never
imports them (an import-linter contract in pyproject.toml holds it).

- `allocation`: texels per unit area on each kind of surface of the demo scene (benchmarks/claims.py, trade.py)
- `mesh_accuracy`: a mesh against the demo scene's exact surfaces (benchmarks/mesh_quality.py)
- `align`: estimated cameras against reference cameras up to a similarity, Umeyama's (benchmarks/sfm_accuracy.py,
  sfm_modes.py)
- `demo_surfaces`: the demo scene's surfaces as demo_meta.json lists them, and which one a point lies on

Benchmarks import them as `measures.<name>` (their own folder is on sys.path); so do the tests (pyproject.toml's
[tool.pytest.ini_options] pythonpath)."""
