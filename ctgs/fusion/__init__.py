"""Surfaces from a trained model (`ctgs mesh`): TSDF fusion of its rendered depth, marching cubes, cleanup.

`domain` (where the voxels lie: a box from the cameras, or contracted space for unbounded captures), `volume` (the
block-sparse TSDF and its fusion of depth maps), `extract` (marching cubes over the blocks, welding, the largest
pieces), `pipeline` (a model and its cameras -> a coloured mesh).
"""
