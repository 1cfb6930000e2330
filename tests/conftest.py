"""Shared fixtures."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch

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
