"""What one training step computes: the loss (loss.py) and the optimiser (adam.py)."""
