"""The model a run starts from: SfM points, optional far-shell and fill points, as surfels (init.py, fill.py)."""
