"""Shared fixtures."""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING

import pytest
import torch

if TYPE_CHECKING:
    from mpnode_cli.data.dataset import TrajectoryData

ROOT = Path(__file__).resolve().parents[1]


def child_env(**extra: str) -> dict[str, str]:
    """This interpreter's environment for a child process (`python -m mpnode_cli ...`):
    this checkout's package first on the path, one OpenMP thread, then `extra`."""
    path = os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH")) if p)
    return {**os.environ, "PYTHONPATH": path, "OMP_NUM_THREADS": "1", **extra}

if os.environ.get("PYTEST_XDIST_WORKER"):
    # `make test` runs two worker processes on a 2-core machine: at torch's default of one
    # thread per core they would oversubscribe it (the CLI's thread policy is the same rule).
    torch.set_num_threads(1)


@pytest.fixture
def float64_default():
    """Run a test with float64 as torch's default dtype (rollouts compared to ~1e-9)."""
    old = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    yield
    torch.set_default_dtype(old)


def synthetic(k: int, t: int, seed: int, dt: float = 0.1, nodes: int = 3) -> TrajectoryData:
    """K random trajectories of `nodes` nodes × 2 features on a complete graph, all "train",
    in memory (system "toy", file name `toy<seed>.h5`, fingerprint `str(seed)`)."""
    import numpy as np

    from mpnode_cli.data.dataset import TrajectoryData
    from mpnode_cli.graphs import Graphs

    rng = np.random.default_rng(seed)
    states = rng.normal(size=(k, t, nodes, 2)).cumsum(axis=1) * [1.0, 5.0] + [0.0, 2.0]
    return TrajectoryData(
        states=torch.tensor(states, dtype=torch.float32), controls=None,
        graphs=Graphs.from_adjacency(np.ones((1, nodes, nodes), np.uint8)),
        graph_index=torch.zeros(k, dtype=torch.long),
        time=torch.arange(t, dtype=torch.float64) * dt,
        split=torch.zeros(k, dtype=torch.uint8), system="toy", state_names=("a", "b"),
        control_names=(), path=Path(f"toy{seed}.h5"), fingerprint=str(seed))
