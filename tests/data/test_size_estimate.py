"""The one size estimate (`mpnode_cli.data.size`): fixed steps, graph sizes and time in it,
a job refused before it starts when it cannot finish, progress as it runs, and memory
running out named after the step that ran out, never blamed on a system's rhs."""

from __future__ import annotations

import networkx as nx
import pytest
from conftest import invoke, one_line_error

from mpnode_cli.config.generate import GenerateConfig
from mpnode_cli.data.generate import estimate, generate, resolve_generate_config
from mpnode_cli.systems.lorenz import Lorenz

TINY = ["lorenz", "--nodes", 3, "--trajectories", 2, "--t-end", 0.2, "--dt", 0.05]


def test_fixed_steps_are_counted_and_too_many_refused_before_any_solve(tmp_path):
    # 0.5 / 1e-12 = 5·10¹¹ steps: the grid alone once filled the memory before any step.
    out = tmp_path / "g.h5"
    line = one_line_error(invoke(
        "generate", "lorenz", "--nodes", 3, "--trajectories", 8, "--t-end", 0.5, "--dt",
        0.05, "--out", out, "--fixed-dt", 1e-12))
    assert "500,000,000,000 steps" in line and "max_steps (100,000)" in line, line
    assert "raise --fixed-dt (to at least 5e-06)" in line, line  # 0.5 / 100 000
    # A solver table that lowers max_steps: 0.5 / 1e-3 = 500 steps are more than 100.
    config = tmp_path / "c.toml"
    config.write_text("[solver]\nmax_steps = 100\n")
    line = one_line_error(invoke("generate", *TINY[:-4], "--t-end", 0.5, "--dt", 0.05,
                                 "--fixed-dt", 1e-3, "--config", config, "--out", out))
    assert "500 steps per trajectory" in line and "max_steps (100)" in line, line
    assert not out.exists()
    # The count, against its closed form: ⌈dt / fixed_dt⌉ equal steps per sample interval.
    for fixed_dt, steps in ((1e-3, 10 * 50), (0.03, 10 * 2), (0.05, 10)):
        size = estimate(resolve_generate_config(GenerateConfig(
            system="lorenz", nodes=3, trajectories=2, t_end=0.5, dt=0.05,
            solver={"fixed_dt": fixed_dt}), dry_run=False))
        assert (size.steps, size.fixed) == (steps, True)


def test_a_graph_is_sized_by_its_topology_not_a_guessed_degree():
    # Gene's Barabási–Albert graphs take m = n/2 edges per node: 900 nodes hold about
    # 4·10⁵ messages, not the 32 per node once assumed; each is two int64 in memory.
    config = resolve_generate_config(GenerateConfig(system="gene", grid=30, trajectories=2,
                                                    t_end=0.1), dry_run=False)
    built = nx.barabasi_albert_graph(900, 450, seed=0)
    messages = 2 * built.number_of_edges()
    assert estimate(config).memory_bytes > 2 * messages * 16


def test_a_graph_too_big_for_memory_is_refused_before_it_is_built(tmp_path, monkeypatch):
    # A million nodes of gene: 2.5·10¹¹ edges, never built (it once ran for minutes in
    # silence, its estimate about 1 GiB). The memory available is set, not measured.
    monkeypatch.setattr("mpnode_cli.data.size.available_memory", lambda: 8 * 2**30)
    out = tmp_path / "g.h5"
    line = one_line_error(invoke("generate", "gene", "--grid", 1000, "--trajectories", 2,
                                 "--t-end", 0.1, "--out", out))
    assert "TiB of memory, more than the 8 GiB" in line and "--nodes" in line, line
    assert not out.exists()


def test_a_slow_job_prints_its_time_and_its_steps_are_told_as_they_go(tmp_path, monkeypatch):
    monkeypatch.setattr("mpnode_cli.cli.common.SHOW_SECONDS", 0.0)  # every job is "slow"
    out = tmp_path / "g.h5"
    result = invoke("generate", *TINY, "--graphs", 2, "--fixed-dt", 0.01, "--out", out)
    assert result.exit_code == 0, result.output
    assert "this job: 2 trajectories × 5 samples × 3 nodes;" in result.output
    assert "20 fixed steps per trajectory, time roughly" in result.output  # 4 × 0.05/0.01
    stages, counts = [], []
    generate(GenerateConfig(system="lorenz", nodes=3, trajectories=4, graphs=2, t_end=0.2,
                            dt=0.05, chunk_size=2, out=tmp_path / "h.h5"),
             progress=lambda done, total: counts.append((done, total)), stage=stages.append)
    assert stages[:3] == ["building graph 1 of 2", "building graph 2 of 2",
                          "drawing the initial states"]
    assert stages[3:] == ["solving trajectories 1–2 of 4", "solving trajectories 3–4 of 4",
                          "writing the file"]
    assert counts[0] == (0, 4) and counts[-1] == (4, 4)
    assert [d for d, _ in counts] == sorted(d for d, _ in counts)  # it only moves forward


def _rhs_that_runs_out(error: BaseException):
    def rhs(self, adjacency, params):
        def f(t, y):
            raise error
        return f
    return rhs


@pytest.mark.parametrize("error", [
    MemoryError(),  # numpy, Python
    RuntimeError("[enforce fail at alloc_cpu.cpp:114] . DefaultCPUAllocator: can't "
                 "allocate memory: you tried to allocate 4000000000 bytes."),  # torch
])
def test_running_out_of_memory_names_the_step_not_the_systems_rhs(tmp_path, monkeypatch,
                                                                  error):
    monkeypatch.setattr(Lorenz, "rhs", _rhs_that_runs_out(error))
    out = tmp_path / "g.h5"
    line = one_line_error(invoke("generate", *TINY, "--out", out))
    assert "out of memory while solving trajectories 1–2 of 2 (about" in line, line
    assert "needed" in line and "--chunk-size" in line and "Lorenz.rhs" not in line, line
    assert not out.exists()


def test_simulate_and_train_name_the_step_that_ran_out(tmp_path, monkeypatch, user_files):
    def out_of_memory(*args, **kw):
        raise MemoryError

    monkeypatch.setattr("mpnode_cli.training.simulate.roll_out", out_of_memory)
    line = one_line_error(invoke(
        "simulate", user_files["checkpoint"], "--x0", user_files["x0"], "--adjacency",
        user_files["adjacency"], "--t-end", 0.2, "--dt", 0.1, "--out", tmp_path / "p.h5"))
    assert "out of memory while rolling out 2 trajectories in batches of" in line, line
    monkeypatch.setattr("mpnode_cli.training.loop.train_epoch", out_of_memory)
    line = one_line_error(invoke("train", user_files["data"], "--epochs", 1, "--no-plots",
                                 "--run-dir", tmp_path / "r"))
    assert "out of memory while training epoch 1" in line, line
