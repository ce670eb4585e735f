"""Launchers: running the Makefile's per-scene pipeline somewhere other than this machine (ctgs.launch.slurm:
one Slurm job per scene, `make all LAUNCHER=slurm`)."""
