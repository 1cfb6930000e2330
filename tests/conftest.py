"""Shared fixtures."""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
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

def fhn(t, y, a_graph, p):
    """examples/fitzhugh_nagumo.py's equations, written again from FitzHugh (1961):
    y = [v (N), w (N)], `a_graph` `[N, N]`, `p` its parameters by name."""
    n = a_graph.shape[0]
    v, w = y[:n], y[n:]
    pull = a_graph @ v - a_graph.sum(axis=1) * v
    return np.concatenate([v - v**3 / 3 - w + p["I"] + p["c"] * pull,
                           p["eps"] * (v + p["a"] - p["b"] * w)])


def fhn_reference(ds, k: int) -> np.ndarray:
    """Trajectory k of an FHN dataset solved again by scipy from its stored initial state,
    on its stored graph: `[T, N, 2]`."""
    from scipy.integrate import solve_ivp

    x0 = ds.states[k, 0].astype(np.float64)  # (N, 2)
    n = x0.shape[0]
    a = ds.adjacency[ds.graph_index[k]].astype(np.float64)
    sol = solve_ivp(fhn, (ds.time[0], ds.time[-1]), np.concatenate([x0[:, 0], x0[:, 1]]),
                    t_eval=ds.time, args=(a, ds.scalar_params), rtol=1e-10, atol=1e-12,
                    method="DOP853")
    return np.stack([sol.y[:n].T, sol.y[n:].T], axis=-1)  # (T, N, 2)


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
