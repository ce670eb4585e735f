"""Training: config, initialisation, optimiser, loss, texel-size adaptation routines, the trainer loop."""
