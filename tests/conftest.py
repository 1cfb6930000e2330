"""Shared fixtures."""

from __future__ import annotations

import os

import pytest
import torch

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
