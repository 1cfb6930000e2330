"""Unbounded memory: every size a user's input sets is bounded, or estimated and refused,
before anything is allocated from it.

The inputs that once ran a verb out of memory (a stray node id of 20 digits, a horizon of
10⁷ samples) or crashed it (`--threads 100000`) run in a child process with a capped
address space (`conftest.guarded_cli`), so that a regression fails its test and nothing
else.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import guarded_cli, invoke, one_line_error

HUGE = 99999999999999999999


@pytest.fixture
def x0(tmp_path):
    """Initial states of 2 trajectories on 3 nodes (the tiny checkpoint's D = 3)."""
    path = tmp_path / "x0.npy"
    np.save(path, np.random.default_rng(0).normal(size=(2, 3, 3)))
    return path


# An edge list's one stray id (`1 99999999999999999999`) used to make `import`, `generate`
# and `simulate` build `set(range(max id + 1))` until the kernel killed them; a CSV's stray
# node id made `import` build `np.arange(max id + 1)`.
def test_a_stray_huge_id_is_refused_before_anything_is_sized_by_it(tmp_path, x0,
                                                                    tiny_checkpoint):
    edges = tmp_path / "g.txt"
    edges.write_text(f"0 1\n1 2\n1 {HUGE}\n")
    states = tmp_path / "s.npy"
    np.save(states, np.zeros((2, 3, 3, 1)))
    long = tmp_path / "long.csv"
    long.write_text("trajectory,time,node,x\n" + "".join(
        f"0,{t},{node},0.5\n" for t in (0, 1) for node in (0, 1e15)))
    out = tmp_path / "out.h5"
    results = guarded_cli(
        ["import", "--states", states, "--edge-list", edges, "--dt", 0.1, "--out", out],
        ["generate", "kuramoto", "--edge-list", edges, "--trajectories", 2, "--out", out],
        ["simulate", tiny_checkpoint, "--x0", x0, "--edge-list", edges, "--t-end", 0.2,
         "--dt", 0.1, "--out", out],
        ["import", "--states", long, "--edge-list", edges, "--dt", 1, "--out", out])
    for result in results[:3]:
        line = one_line_error(result)
        assert f"g.txt:3: node id {HUGE}" in line and "16,777,216 nodes" in line, line
    line = one_line_error(results[3])
    assert "long.csv: node ids are 0-based and contiguous, but 1, 2, 3, 4, 5" in line, line
    assert not out.exists()


def test_gaps_are_found_among_the_ids_present():
    from mpnode_cli.graphs.edge_files import missing_ids

    assert missing_ids(np.array([0, 1, 2]), 3) == []
    assert missing_ids(np.array([2, 0, 5, 5]), 6) == [1, 3, 4]
    assert missing_ids(np.array([3]), 4, count=2) == [0, 1]
    assert missing_ids(np.array([0]), 10**30, count=3) == [1, 2, 3]  # no range of 10³⁰


# `simulate --t-end 1e6` was killed for memory and `1e9` gave a numpy traceback: simulate
# had no size estimate; `generate` had one, and `1e300 / 1e-300` steps crashed both.
def test_absurd_horizons_are_one_line(tmp_path, x0, tiny_checkpoint):
    edges = tmp_path / "g.txt"
    edges.write_text("0 1\n1 2\n")
    out = tmp_path / "p.h5"
    simulate = ["simulate", tiny_checkpoint, "--x0", x0, "--edge-list", edges, "--out", out]
    results = guarded_cli(
        [*simulate, "--t-end", "1e6", "--dt", 0.1],
        [*simulate, "--t-end", "1e9", "--dt", 0.1],
        [*simulate, "--t-end", "1e300", "--dt", "1e-300"],
        ["generate", "lorenz", "--t-end", "1e300", "--dt", "1e-300", "--out", out])
    # 10⁷ samples: above this machine's memory, or above the size that needs --yes.
    assert "of memory" in one_line_error(results[0])
    assert "this simulation needs about" in one_line_error(results[1])
    for result in results[2:]:
        assert "t_end / dt is inf steps" in one_line_error(result)
    assert not out.exists()


def test_simulate_prints_its_size_and_asks(tmp_path, x0, tiny_checkpoint, monkeypatch):
    # Thresholds lowered so that a small job counts as big (the real ones are GiB).
    monkeypatch.setattr("mpnode_cli.cli.common.SHOW_BYTES", 2**10, raising=False)
    monkeypatch.setattr("mpnode_cli.cli.common.CONFIRM_BYTES", 2**16, raising=False)
    edges = tmp_path / "g.txt"
    edges.write_text("0 1\n1 2\n")
    out = tmp_path / "p.h5"
    args = ["simulate", tiny_checkpoint, "--x0", x0, "--edge-list", edges, "--t-end", 20,
            "--dt", 0.1, "--out", out]
    result = invoke(*args, input="")  # stdin is no terminal: no one to ask
    assert "pass --yes" in one_line_error(result)
    assert "this job: 2 trajectories × 201 samples × 3 nodes" in result.output
    assert not out.exists()
    result = invoke(*args, "--yes")
    assert result.exit_code == 0, result.output
    assert "this job: 2 trajectories" in result.output and out.exists()
    from mpnode_cli.data.size import simulate_estimate
    from mpnode_cli.training.checkpoint import load_checkpoint

    size = simulate_estimate(load_checkpoint(tiny_checkpoint), 2, 201, 3)
    assert size.values == 2 * 201 * 3 * 3
    assert size.file_bytes == 2 * 201 * 3 * (3 + 3) * 4  # float32 states and messages


# `--threads 100000` was accepted, and the process crashed creating threads; `--jobs` of an
# experiment started as many processes as asked.
def test_thread_and_process_counts_are_bounded(tmp_path):
    tiny = ["lorenz", "--nodes", 2, "--trajectories", 2, "--t-end", 0.1, "--dt", 0.05,
            "--out", tmp_path / "d.h5"]
    flag, variable = guarded_cli(["generate", *tiny, "--threads", 100000],
                                 ["generate", *tiny], MPNODE_THREADS="100000")
    assert "--threads must be at most 256" in one_line_error(flag)
    assert "MPNODE_THREADS must be at most 256" in one_line_error(variable)
    # Refused before the experiment is even looked up (this one does not exist).
    line = one_line_error(invoke("experiment", "run", "no-such-experiment", "--jobs", 100000))
    assert "--jobs must be at most" in line and "the CPUs this process may use" in line
    from mpnode_cli.threads import MAX_THREADS, choose_threads

    assert choose_threads(str(MAX_THREADS), {}).count == MAX_THREADS == 256
