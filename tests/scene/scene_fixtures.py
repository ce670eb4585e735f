"""Parameters shared by the scene tests (a uniquely named module: `conftest` is ambiguous on sys.path)."""

# The tiny demo scene of tests/scene: ~1 s to generate.
TINY = dict(num_views=10, width=64, height=48, seed=3, points=600, supersample=2)
