"""What the verbs tell a user while they work: progress on long verbs."""

from __future__ import annotations

from contextlib import contextmanager

import numpy as np
import pytest

from tests.conftest import invoke


@pytest.fixture
def bars(monkeypatch) -> list[dict]:
    """Every `task_bar` a verb opens, with its description, `quiet` and each
    `progress(done, total)` call (the bar itself draws only on a terminal)."""
    from mpnode_cli.cli import common

    opened: list[dict] = []

    class Bar:
        def stop(self) -> None:
            pass

    @contextmanager
    def recording(description, columns=None, total=None, *, quiet=False):
        calls: list[tuple[float, float]] = []
        opened.append({"description": description, "quiet": quiet, "calls": calls})
        yield Bar(), lambda done, total: calls.append((done, total))

    monkeypatch.setattr(common, "task_bar", recording)
    return opened


def test_import_simulate_and_evaluate_show_progress(user_files, tmp_path, bars):
    f = user_files
    verbs = {
        "import": ["import", "--states", f["states"], "--adjacency", f["adjacency"], "--dt",
                   0.1, "--out", tmp_path / "d.h5", "--json"],
        "simulate": ["simulate", f["run"], "--x0", f["x0"], "--adjacency", f["adjacency"],
                     "--t-end", 0.4, "--dt", 0.1, "--batch-size", 1, "--out",
                     tmp_path / "p.h5"],
        "evaluate": ["evaluate", f["run"], f["data"], "--split", "all", "--batch-size", 2],
    }
    for name, args in verbs.items():
        start = len(bars)
        result = invoke(*args)
        assert result.exit_code == 0, result.output
        (bar,) = bars[start:]
        assert bar["calls"], f"{name}: the bar never moved"
        done, total = bar["calls"][-1]
        assert done == total > 0 and len(bar["calls"]) > 1, (name, bar["calls"])
        assert bar["quiet"] == ("--json" in args), name  # no bar beside --json output


def test_import_memory_maps_a_npy(tmp_path):
    from mpnode_cli.data.importers import load_states

    np.save(tmp_path / "s.npy", np.arange(2 * 3 * 2 * 1, dtype=np.float32).reshape(2, 3, 2, 1))
    assert isinstance(load_states(tmp_path / "s.npy").states, np.memmap)
