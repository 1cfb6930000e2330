"""A clear answer to every bad input: one `Error:` line and exit 2, before any work starts.

Each test names the defect it guards against, as a new user met it: NaN data that "trained",
tracebacks on inconsistent files, unwritable outputs found out late, runs that resumed only
from their own folder, silent edge-list choices, another system's data accepted, numbers
that escaped validation, `--force` over a symlink, a progress bar that did not move, and
the smaller ones (help, plots, checkpoint messages).
"""

from __future__ import annotations

import importlib
import json
import os
import shutil

import h5py
import numpy as np
import pytest
from conftest import invoke, one_line_error

from mpnode_cli.config.generate import GenerateConfig
from mpnode_cli.data.generate import estimate, generate, resolve_generate_config
from mpnode_cli.graphs.edge_files import read_edge_list
from mpnode_cli.report import plots
from mpnode_cli.training import epoch_record

FAST = ["--batch-size", "8", "--lr", "1e-2", "--no-plots"]


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """Tiny lorenz (N=3) and kuramoto (N=6) sets: both have 3 states per node."""
    root = tmp_path_factory.mktemp("data")
    small = {"trajectories": 12, "t_end": 0.25, "dt": 0.05}
    return {
        "lorenz": generate(GenerateConfig(system="lorenz", nodes=3, out=root / "l3.h5",
                                          **small)).path,
        "kuramoto": generate(GenerateConfig(system="kuramoto", nodes=6, out=root / "k6.h5",
                                            **small)).path,
    }


@pytest.fixture(scope="module")
def run(data, tmp_path_factory):
    run = tmp_path_factory.mktemp("runs") / "l3"
    result = invoke("train", data["lorenz"], "--epochs", 2, "--run-dir", run, *FAST)
    assert result.exit_code == 0, result.output
    return run


def _copy_with(src, dst, edit):
    shutil.copy(src, dst)
    with h5py.File(dst, "r+") as f:
        edit(f)
    return dst


# 1. One NaN: training used to skip every batch and report a "trained" run with loss inf;
#    evaluate reported `MSE —` and exit 0.
def test_a_nan_refuses_train_and_evaluate_before_any_work(data, run, tmp_path):
    def nan_in_test_split(f):
        k = int(np.flatnonzero(f["split"][()] == 2)[0])
        f["states"][k, 2, 0, 0] = np.nan
    bad = _copy_with(data["lorenz"], tmp_path / "nan.h5", nan_in_test_split)
    line = one_line_error(invoke("train", bad, "--epochs", 1, "--run-dir", tmp_path / "r"))
    assert "non-finite" in line and "nan.h5" in line
    assert not (tmp_path / "r").exists()
    line = one_line_error(invoke("evaluate", run / "checkpoints" / "best.pt", bad))
    assert "non-finite" in line


# 2. A failed train used to leave a run folder holding only config.json, which could be
#    neither reused nor resumed.
def test_a_failed_train_leaves_no_husk(data, tmp_path, monkeypatch):
    def broken(*args, **kwargs):
        raise ValueError("validation rollout failed")

    folder = tmp_path / "r"
    with monkeypatch.context() as m:
        m.setattr(epoch_record, "evaluate", broken)
        assert "validation rollout failed" in one_line_error(
            invoke("train", data["lorenz"], "--epochs", 1, "--run-dir", folder, *FAST))
        assert not folder.exists()
        empty = tmp_path / "made-by-the-user"
        empty.mkdir()
        one_line_error(invoke("train", data["lorenz"], "--epochs", 1, "--run-dir", empty,
                              *FAST))
        assert empty.is_dir() and list(empty.iterdir()) == []  # emptied, not removed
    result = invoke("train", data["lorenz"], "--epochs", 1, "--run-dir", folder, *FAST)
    assert result.exit_code == 0, result.output  # the name is free again


# 3. Unwritable outputs used to give tracebacks, generate's only after the whole solve.
def test_unwritable_outputs_are_refused_first(data, run, tmp_path, monkeypatch):
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")

    def never(*args, **kwargs):
        raise AssertionError("solved although the output cannot be written")

    monkeypatch.setattr("mpnode_cli.data.solve_rounds.solve_chunk", never)
    line = one_line_error(invoke("generate", "lorenz", "--nodes", 3, "--trajectories", 4,
                                 "--out", blocker / "d.h5"))
    assert "cannot write in" in line and "not a folder" in line
    line = one_line_error(invoke("train", data["lorenz"], "--run-dir", blocker / "run"))
    assert "cannot write in" in line
    line = one_line_error(invoke("evaluate", run, data["lorenz"], "--plot", "--plot-dir",
                                 blocker / "plots"))
    assert "--plot-dir" in line and "cannot write in" in line


@pytest.mark.skipif(os.geteuid() == 0, reason="the superuser writes in read-only folders")
def test_a_read_only_folder_is_refused(tmp_path):
    folder = tmp_path / "ro"
    folder.mkdir()
    folder.chmod(0o555)
    try:
        line = one_line_error(invoke("generate", "lorenz", "--nodes", 3, "--trajectories", 4,
                                     "--out", folder / "d.h5"))
        assert "cannot write in" in line
    finally:
        folder.chmod(0o755)


# 4. Resume used to work only from the folder the run started in (relative path, compared
#    as a string despite the fingerprint).
def test_resume_from_any_folder_and_a_moved_dataset(data, tmp_path, monkeypatch):
    start, elsewhere = tmp_path / "start", tmp_path / "elsewhere"
    start.mkdir()
    elsewhere.mkdir()
    shutil.copy(data["lorenz"], start / "d.h5")
    monkeypatch.chdir(start)
    assert invoke("train", "d.h5", "--epochs", 1, "--run-dir", "run", *FAST).exit_code == 0
    config = json.loads((start / "run" / "config.json").read_text())
    assert config["dataset"] == str(start / "d.h5")  # absolute
    monkeypatch.chdir(elsewhere)
    result = invoke("train", "--resume", start / "run", "--epochs", 2)
    assert result.exit_code == 0, result.output
    # The dataset moves: the run finds it no more, but takes it at its new path.
    (start / "d.h5").rename(elsewhere / "moved.h5")
    line = one_line_error(invoke("train", "--resume", start / "run", "--epochs", 3))
    assert "not there any more" in line
    result = invoke("train", "moved.h5", "--resume", start / "run", "--epochs", 3)
    assert result.exit_code == 0, result.output
    assert json.loads((start / "run" / "summary.json").read_text())["epochs"] == 3
    # Other data under the run is refused by its fingerprint.
    line = one_line_error(invoke("train", data["kuramoto"], "--resume", start / "run",
                                 "--epochs", 4))
    assert "fingerprint" in line


# 5. Edge lists used to be made undirected silently, and gaps in node ids silently made
#    isolated nodes.
def test_edge_lists_directed_undirected_and_gaps(tmp_path):
    path = tmp_path / "g.txt"
    path.write_text("0 1\n1 2\n")
    undirected = read_edge_list(path)
    directed = read_edge_list(path, directed=True)
    # A[i, j] = 1 iff j sends to i: the edge 0 → 1 is row 1, column 0.
    assert directed[1, 0] == 1 and directed[0, 1] == 0 and directed.sum() == 2
    np.testing.assert_array_equal(undirected, directed | directed.T)
    path.write_text("0 2\n")
    with pytest.raises(ValueError, match="node ids 1 appear on no line"):
        read_edge_list(path)
    path.write_text("0 2\n1  # on its own: a node without edges\n")
    assert read_edge_list(path).shape == (3, 3) and read_edge_list(path)[1].sum() == 0
    path.write_text("1 2\n2 3\n")  # a 1-based file
    with pytest.raises(ValueError, match="0-based and contiguous"):
        read_edge_list(path)
    assert "edge list only" in one_line_error(invoke("generate", "lorenz", "--directed"))


def test_generate_with_a_directed_edge_list(tmp_path):
    path = tmp_path / "g.txt"
    path.write_text("0 1\n1 2\n2 0\n")
    out = tmp_path / "d.h5"
    result = invoke("generate", "kuramoto", "--edge-list", path, "--directed", "--trajectories",
                    3, "--t-end", 0.2, "--dt", 0.1, "--out", out)
    assert result.exit_code == 0, result.output
    with h5py.File(out) as f:
        a = f["graph/adjacency"][0]
    assert (a[1, 0], a[2, 1], a[0, 2]) == (1, 1, 1) and a.sum() == 3  # a directed cycle
    assert "directed edges" in invoke("info", out).output


# 6. A Lorenz model on Kuramoto data (both D = 3) used to report an MSE without a word.
def test_another_system_needs_allow_other_system(data, run, tmp_path):
    best = run / "checkpoints" / "best.pt"
    for verb in ("zeroshot", "evaluate"):
        line = one_line_error(invoke(verb, best, data["kuramoto"]))
        assert "'kuramoto'" in line and "'lorenz'" in line and "--allow-other-system" in line
    result = invoke("zeroshot", best, data["kuramoto"], "--allow-other-system")
    assert result.exit_code == 0, result.output
    line = one_line_error(invoke("finetune", best, data["kuramoto"], "--epochs", 1,
                                 "--run-dir", tmp_path / "ft"))
    assert "--allow-other-system" in line and not (tmp_path / "ft").exists()
    result = invoke("finetune", best, data["kuramoto"], "--epochs", 1, "--run-dir",
                    tmp_path / "ft", "--allow-other-system", *FAST)
    assert result.exit_code == 0, result.output


# 7. Values that escaped validation and crashed, or failed without naming the option.
@pytest.mark.parametrize(("args", "words"), [
    (["generate", "lorenz", "--t-end", "inf"], "t_end"),
    (["generate", "lorenz", "--t-end", "1e9"], "of memory"),
    (["generate", "lorenz", "--trajectories", "1e9"], "of memory"),
    (["generate", "lorenz", "--trajectories", "2.5"], "--trajectories expects a whole number"),
    (["generate", "lorenz", "--nodes", "100000"], "of memory"),
    (["generate", "lorenz", "--seed", "-1"], "seed"),
    (["generate", "lorenz", "--seed", str(2**70)], "seed"),
    (["generate", "lorenz", "--rtol", "nan"], "rtol"),
    (["train", "{lorenz}", "--hidden", "10000000"], "hidden"),
    (["train", "{lorenz}", "--epochs", "0"], "epochs"),
    (["train", "{lorenz}", "--message-dim", "0"], "message_dim"),
    (["train", "{lorenz}", "--seed", "-1"], "seed"),
    (["train", "{lorenz}", "--lr", "inf"], "lr"),
    (["evaluate", "{run}", "{lorenz}", "--batch-size", "0"], "--batch-size"),
    (["evaluate", "{run}", "{lorenz}", "--batch-size", "-1"], "--batch-size"),
    (["zeroshot", "{run}", "{lorenz}", "--batch-size", "0"], "--batch-size"),
])
def test_numbers_out_of_range_name_their_option(data, run, tmp_path, args, words):
    args = [a.format(lorenz=data["lorenz"], run=run) for a in args]
    if args[0] == "train":
        args += ["--run-dir", str(tmp_path / "r")]
    line = one_line_error(invoke(*args, input=""))
    assert words in line, line
    assert not (tmp_path / "r").exists()


def test_big_jobs_print_their_size_and_ask(tmp_path, monkeypatch):
    # Thresholds lowered so that a small job counts as big (the real ones are GiB).
    monkeypatch.setattr("mpnode_cli.cli.common.SHOW_BYTES", 2**10)
    monkeypatch.setattr("mpnode_cli.cli.common.CONFIRM_BYTES", 2**20)
    out = tmp_path / "big.h5"
    args = ["generate", "lorenz", "--nodes", 3, "--trajectories", 2000, "--t-end", 1,
            "--dt", 0.1, "--out", out]
    result = invoke(*args, input="")  # stdin is no terminal: no one to ask
    line = one_line_error(result)
    assert "pass --yes" in line and "this job: 2000 trajectories × 11 samples" in result.output
    assert not out.exists()
    result = invoke(*args, "--yes")
    assert result.exit_code == 0, result.output
    assert "this job: 2000 trajectories" in result.output and out.exists()
    config = resolve_generate_config(GenerateConfig(system="lorenz", nodes=3, trajectories=2000,
                                                    t_end=1, dt=0.1), dry_run=False)
    size = estimate(config)
    assert size.values == 2000 * 11 * 3 * 3
    assert size.file_bytes == size.values * 4 + 3 * 3  # float32 states and a uint8 graph
    assert size.memory_bytes >= size.values * (8 + 4)  # float64 solve and its float32 cast


# 9. --force used to replace whatever sat at the output path.
@pytest.mark.parametrize("kind", ["symlink", "folder", "fifo"])
def test_force_replaces_only_regular_files(tmp_path, kind):
    target = tmp_path / "precious.txt"
    target.write_text("keep me")
    out = tmp_path / "out.h5"
    if kind == "symlink":
        out.symlink_to(target)
    elif kind == "folder":
        out.mkdir()
    else:
        os.mkfifo(out)
    line = one_line_error(invoke("generate", "lorenz", "--nodes", 3, "--trajectories", 4,
                                 "--out", out, "--force"))
    assert "only replaces regular files" in line
    assert target.read_text() == "keep me"
    assert out.is_symlink() if kind == "symlink" else out.exists()


# 10. The progress bar used to sit at 0/K until a whole 1024-trajectory chunk was done.
def test_progress_moves_within_a_chunk(tmp_path, monkeypatch):
    solve_module = importlib.import_module("mpnode_cli.solver.solve")
    monkeypatch.setattr(solve_module, "PROGRESS_SECONDS", 0.0)  # report every step
    calls = []
    generate(GenerateConfig(system="lorenz", nodes=3, trajectories=6, t_end=0.5, dt=0.05,
                            out=tmp_path / "d.h5"), progress=lambda *a: calls.append(a))
    inside = [done for done, total in calls if 0 < done < 6]  # one chunk of all six
    assert len(inside) >= 5 and inside == sorted(inside)


# 11. The smaller ones.
def test_resume_with_no_more_epochs_says_so(data, tmp_path):
    folder = tmp_path / "r"
    assert invoke("train", data["lorenz"], "--epochs", 2, "--run-dir", folder,
                  *FAST).exit_code == 0
    for epochs in (1, 2):
        line = one_line_error(invoke("train", "--resume", folder, "--epochs", epochs))
        assert "trained 2 epochs already" in line and "more than 2" in line


def test_checkpoint_messages_and_run_folders(data, run, tmp_path):
    line = one_line_error(invoke("evaluate", data["lorenz"], data["lorenz"]))
    assert "not an mpnode checkpoint" in line
    assert not any(name in line for name in ("UnpicklingError", "RuntimeError", "BadZipFile"))
    result = invoke("evaluate", run, data["lorenz"], "--json")  # the run folder: its best.pt
    assert result.exit_code == 0, result.output
    assert json.loads(result.output)["checkpoint"].endswith("checkpoints/best.pt")
    empty = tmp_path / "empty"
    empty.mkdir()
    assert "checkpoints/best.pt" in one_line_error(invoke("evaluate", empty, data["lorenz"]))


def test_help_shows_no_bool_and_finetune_no_resume():
    for verb in ("generate", "train", "finetune", "evaluate", "check"):
        assert "<bool>" not in invoke(verb, "--help").output, verb
    assert "--resume" not in invoke("finetune", "--help").output
    assert "--resume" in invoke("train", "--help").output


def test_shell_completion_is_on():
    assert "--install-completion" in invoke("--help").output


def test_plots_say_which_trajectory_and_nodes(data, run, tmp_path, monkeypatch):
    titles = []
    save = plots._save

    def keep_title(fig, path, *args, **kwargs):
        titles.append(fig._suptitle.get_text() if fig._suptitle else fig.axes[0].get_title())
        return save(fig, path, *args, **kwargs)

    monkeypatch.setattr(plots, "_save", keep_title)
    result = invoke("evaluate", run, data["lorenz"], "--plot", "--plot-dir", tmp_path)
    assert result.exit_code == 0, result.output
    with h5py.File(data["lorenz"]) as f:
        first_test = int(np.flatnonzero(f["split"][()] == 2)[0])
    assert f"trajectory {first_test} (the first of the test split)" in titles[0]
    assert "all 3 nodes" in titles[0]
    titles.clear()
    plots.plot_rollout(np.arange(4.0), np.zeros((4, 10, 1)), np.zeros((4, 10, 1)), None, ["x"],
                       tmp_path / "p.png", title="ten nodes")
    assert "nodes 0–5 of 10" in titles[0]


# --json on info, check, generate and train: one object on stdout, the file's own facts.
def test_json_summaries(data, tmp_path):
    info = json.loads(invoke("info", data["lorenz"], "--json").output)
    assert (info["system"], info["num_nodes"], info["node_dim"], info["trajectories"]) == (
        "lorenz", 3, 3, 12)
    out = tmp_path / "d.h5"
    result = invoke("generate", "lorenz", "--nodes", 3, "--trajectories", 5, "--t-end", 0.2,
                    "--dt", 0.1, "--out", out, "--json")
    assert result.exit_code == 0, result.output
    made = json.loads(result.stdout)
    with h5py.File(out) as f:
        assert made["trajectories"] == f["states"].shape[0] == 5
        assert made["samples"] == f["time"].shape[0] == 3
    result = invoke("train", out, "--epochs", 1, "--run-dir", tmp_path / "r", "--json", *FAST)
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    assert summary == json.loads((tmp_path / "r" / "summary.json").read_text())
    assert summary["finished"] and summary["epochs"] == 1

