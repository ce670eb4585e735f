"""A real one-node Slurm cluster (slurm_cluster.py) for the launcher's tests, started once for the folder and
stopped at its end by the pids it started, whatever the tests did."""

from __future__ import annotations

import pytest

from slurm_cluster import Cluster, missing


@pytest.fixture(scope="module")
def slurm(tmp_path_factory):
    why = missing()
    if why:
        pytest.skip(why)
    cluster = Cluster(str(tmp_path_factory.mktemp("slurm")))
    try:
        cluster.start()
        yield cluster
    finally:
        cluster.stop()
