"""The training loop: the Trainer (one iteration = one random training view, loss, backward, Adam, the parts' hooks),
the calibration that times its steps, the progress display of its events, and the outputs of a finished run."""
