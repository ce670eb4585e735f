"""ctgs: content-aware textured 2D Gaussian Splatting (Papantonakis et al., EGSR 2025)."""

__version__ = "0.1.0"
