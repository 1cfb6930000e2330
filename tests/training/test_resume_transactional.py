"""A run folder survives a resume that is killed, refused, or run twice at once.

A resume is checked whole before it writes anything (a refusal leaves every file's bytes
as they were), holds the run's lock while it lasts (a second writer is refused), and a
resume killed anywhere (SIGKILL: no handler runs) resumes to the weights of a run that
was never stopped. The killed resumes run in a fork of this process, torch already
imported, so that each costs a fraction of a new interpreter.
"""

from __future__ import annotations

import gc
import hashlib
import json
import os
import random
import select
import shutil
import signal
import time
from pathlib import Path

import pytest
import torch
from conftest import invoke, one_line_error

from mpnode_cli.training.checkpoint import load_checkpoint
from mpnode_cli.training.run import checkpoint_path, read_metrics

# A model and a training small enough that a resume costs little more than its start.
TINY = ("--batch-size", 4, "--no-plots", "--fixed-dt", 0.1, "--hidden", 4, "--layers", 1)
EPOCHS = 3

pytestmark = pytest.mark.skipif(not hasattr(os, "fork"), reason="needs os.fork")


@pytest.fixture(scope="module")
def runs(user_files, tmp_path_factory) -> dict[str, Path]:
    """`base` (1 epoch, to be resumed), `whole` (EPOCHS epochs, never stopped: the
    reference), and the same of an ensemble of 2 members (`ensemble`, `ensemble-whole`;
    at an lr at which its members improve at different epochs), all of one small
    dataset."""
    root = tmp_path_factory.mktemp("resume")
    made = {"base": 1, "whole": EPOCHS, "ensemble": 1, "ensemble-whole": EPOCHS}
    for name, epochs in made.items():
        seeds = ("--seeds", 2, "--lr", 0.2) if name.startswith("ensemble") else ()
        result = invoke("train", user_files["data"], "--epochs", epochs, *TINY, *seeds,
                        "--run-dir", root / name)
        assert result.exit_code == 0, result.output
    return {name: root / name for name in made}


def _copy(run: Path, to: Path) -> Path:
    shutil.copytree(run, to)
    return to


def _hashes(folder: Path) -> dict[str, str]:
    """Every file under `folder` by its relative path: its bytes' SHA-256."""
    return {p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def _rows(run: Path) -> list[dict]:
    """Metrics rows without their timings (which differ between identical runs)."""
    return [{k: v for k, v in r.items() if not k.endswith("seconds")}
            for r in read_metrics(run)]


def _finished(run: Path) -> bool:
    """Whether the run's summary is that of all EPOCHS (the base's says 1)."""
    path = run / "summary.json"
    summary = json.loads(path.read_text()) if path.is_file() else {}
    return summary.get("finished") is True and summary.get("epochs") == EPOCHS


def _assert_same_run(run: Path, whole: Path) -> None:
    """`run` holds what the never-stopped `whole` does: bit-identical weights and Adam
    moments in last.pt and best.pt, one metrics row per epoch with the same numbers, a
    finished summary, and no temporary left by a killed write."""
    for which in ("last", "best"):
        a, b = (load_checkpoint(checkpoint_path(r, which)) for r in (run, whole))
        assert a.epoch == b.epoch, which
        assert a.state_dict.keys() == b.state_dict.keys(), which
        for name, value in b.state_dict.items():
            assert torch.equal(a.state_dict[name], value), (which, name)
        for key, state in b.optimizer["state"].items():
            for name, value in state.items():
                assert torch.equal(a.optimizer["state"][key][name], value), (which, key)
    assert _rows(run) == _rows(whole)
    assert _finished(run)
    assert [p.name for p in run.rglob("*.tmp")] == []


def _fork() -> int:
    """`os.fork()`, with this process's objects kept out of the child's garbage
    collections (`gc.freeze`), which would otherwise copy every page they touch."""
    gc.freeze()
    pid = os.fork()
    if pid:  # this process: the child keeps them frozen
        gc.unfreeze()
    return pid


def _resume_in_child(run: Path, *, kill_after: float | None = None,
                     dies_at: tuple[str, int] | None = None) -> bool:
    """`mpnode train --resume RUN --epochs EPOCHS` in a fork of this process, SIGKILLed
    by this one after `kill_after` seconds, or by itself at `dies_at` (`_die_at`).

    Returns:
        Whether it was killed (else it exited, and with 0).
    """
    pid = _fork()
    if pid == 0:  # the child: never returns into pytest
        code = 1
        try:
            if dies_at is not None:
                _die_at(*dies_at)
            code = invoke("train", "--resume", run, "--epochs", EPOCHS).exit_code
        finally:
            os._exit(code)
    return _killed(pid, kill_after)


def _killed(pid: int, kill_after: float | None) -> bool:
    """SIGKILL child `pid` after `kill_after` seconds (None: let it run); wait for it.
    Returns whether it was killed (else it exited, and with 0)."""
    if kill_after is not None:
        time.sleep(kill_after)
        os.kill(pid, signal.SIGKILL)  # an exited child is a zombie until waited for
    _, status = os.waitpid(pid, 0)
    if os.WIFSIGNALED(status):
        return True
    assert os.WEXITSTATUS(status) == 0
    return False


def _die_at(where: str, n: int) -> None:
    """Make this (child) process SIGKILL itself at the `n`-th `where`: "row" (a metrics
    row appended), "last.pt temporary" (last.pt written, not yet renamed into place),
    "last.pt" (renamed) or "best.pt" (renamed)."""
    from mpnode_cli.training import run as runs

    replace, append, seen = os.replace, runs.append_metrics, []

    def at(what: str) -> None:
        seen.append(what)
        if seen.count(where) == n and what == where:
            os.kill(os.getpid(), signal.SIGKILL)

    def replacing(src, dst, **kwargs):
        at(f"{Path(dst).name} temporary")
        replace(src, dst, **kwargs)
        at(Path(dst).name)

    def appending(run_dir, row):
        append(run_dir, row)
        at("row")

    os.replace, runs.append_metrics = replacing, appending


def test_a_resume_killed_at_random_resumes_to_the_weights_of_an_unstopped_run(runs,
                                                                               tmp_path):
    """20 resumes SIGKILLed after a random delay (seeded), from the start of the run up
    to its whole length; each killed folder is resumed again (and perhaps killed again)
    until one resume finishes, which must give what the never-stopped run gave."""
    start = time.perf_counter()
    run = _copy(runs["base"], tmp_path / "run")
    assert not _resume_in_child(run)  # once through: how long a whole resume takes
    _assert_same_run(run, runs["whole"])
    length = time.perf_counter() - start
    rng = random.Random(20261127)
    kills = finished = 0
    run = _copy(runs["base"], tmp_path / "run-0")
    while kills < 20:
        if _resume_in_child(run, kill_after=rng.uniform(0, length)):
            kills += 1
        if _finished(run):  # a resume got to the end (or was killed after it wrote all)
            _assert_same_run(run, runs["whole"])
            finished += 1
            run = _copy(runs["base"], tmp_path / f"run-{finished}")
    if not _finished(run):
        assert not _resume_in_child(run)
    _assert_same_run(run, runs["whole"])
    print(f"20 kills, {finished} resumes through, {time.perf_counter() - start:.1f} s")


@pytest.mark.parametrize(("where", "epoch"), [
    ("row", 2), ("last.pt temporary", EPOCHS), ("last.pt", 2), ("last.pt", EPOCHS),
    ("best.pt", EPOCHS)])
def test_a_resume_killed_between_an_epochs_writes_resumes_exactly(runs, tmp_path, where,
                                                                   epoch):
    """Killed at each step of an epoch's commit: its row, last.pt's temporary, last.pt,
    best.pt (every epoch improves here, so best.pt is written each time). At the last
    epoch, the summary is yet to be written, and the resume finishes the run."""
    run = _copy(runs["base"], tmp_path / "run")
    assert _resume_in_child(run, dies_at=(where, epoch - 1))  # the base did epoch 1
    result = invoke("train", "--resume", run, "--epochs", EPOCHS)
    assert result.exit_code == 0, result.output
    _assert_same_run(run, runs["whole"])


def test_an_ensemble_killed_before_its_best_pt_keeps_each_members_best(runs, tmp_path):
    """Epoch 2 improves member 1 alone. Killed after its last.pt and before its best.pt,
    the resume writes best.pt again from member 1's epoch-2 weights (last.pt's) and
    member 0's epoch-1 ones (the best.pt there)."""
    assert read_metrics(runs["ensemble-whole"])[2]["improved_members"] == [1]
    run = _copy(runs["ensemble"], tmp_path / "run")
    assert _resume_in_child(run, dies_at=("last.pt", 1))
    assert load_checkpoint(checkpoint_path(run, "best")).epoch == 1
    result = invoke("train", "--resume", run, "--epochs", EPOCHS)
    assert result.exit_code == 0, result.output
    _assert_same_run(run, runs["ensemble-whole"])


def test_two_resumes_of_one_run_at_once_one_is_refused(runs, tmp_path):
    """A resume holds the run while it trains; a second one is refused in one line that
    names the first's process, and writes nothing. The first goes on to the end."""
    from mpnode_cli.training.loop import train
    from mpnode_cli.training.resume import resume_config

    run = _copy(runs["base"], tmp_path / "run")
    ready_r, ready_w = os.pipe()
    go_r, go_w = os.pipe()
    pid = _fork()
    if pid == 0:
        code = 1
        try:
            os.close(ready_r)

            def wait_at_start(event):
                if event["event"] == "start":  # the run folder is the child's now
                    os.write(ready_w, b"1")
                    os.read(go_r, 1)

            train(resume_config(run, None, {"epochs": EPOCHS}), resume=True,
                  progress=wait_at_start)
            code = 0
        finally:
            os._exit(code)
    os.close(ready_w)
    try:
        assert select.select([ready_r], [], [], 60)[0] and os.read(ready_r, 1) == b"1"
        before = _hashes(run)
        line = one_line_error(invoke("train", "--resume", run, "--epochs", EPOCHS))
        assert f"run {run} is in use by another mpnode process (pid {pid})" in line
        assert _hashes(run) == before
    finally:
        os.write(go_w, b"1")
        _, status = os.waitpid(pid, 0)
    assert os.WIFEXITED(status) and os.WEXITSTATUS(status) == 0
    assert [r["epoch"] for r in read_metrics(run)] == list(range(EPOCHS + 1))
    _assert_same_run(run, runs["whole"])


def _other_runs_checkpoint(runs: dict[str, Path], run: Path, which: str) -> None:
    shutil.copy(checkpoint_path(runs["ensemble"], which), checkpoint_path(run, which))


def _weights_of_another_model(runs: dict[str, Path], run: Path, which: str) -> None:
    """The ensemble's last.pt, whole and valid, with this run's train config."""
    ours = torch.load(checkpoint_path(run, which), weights_only=True)
    theirs = torch.load(checkpoint_path(runs["ensemble"], which), weights_only=True)
    theirs.pop("payload_sha256")  # a file of its own making: no digest to disagree with
    torch.save(theirs | {"train_config": ours["train_config"]}, checkpoint_path(run, which))


def _ahead_of_its_metrics(runs: dict[str, Path], run: Path, which: str) -> None:
    shutil.copy(checkpoint_path(runs["whole"], which), checkpoint_path(run, which))


@pytest.mark.parametrize(("which", "damage", "words"), [
    ("last", _other_runs_checkpoint, "last.pt is not this run's checkpoint: it and"),
    ("best", _other_runs_checkpoint, "best.pt is not this run's checkpoint: it and"),
    ("last", _weights_of_another_model, "last.pt does not fit the model"),
    ("last", _ahead_of_its_metrics, "metrics.jsonl ends at epoch 1, but"),
])
def test_a_foreign_or_damaged_run_folder_is_refused_before_anything_is_written(
        runs, tmp_path, which, damage, words):
    run = _copy(runs["base"], tmp_path / "run")
    damage(runs, run, which)
    before = _hashes(run)
    result = invoke("train", "--resume", run, "--epochs", 2)
    assert _hashes(run) == before
    assert words in one_line_error(result)


def _as_written_before(path: Path, option: str, value=None) -> None:
    """The checkpoint as an mpnode written before model option `option` existed (left out
    of its train config), or with another value of it."""
    payload = torch.load(path, weights_only=True)
    options = payload["train_config"]["model_options"]
    options.pop(option) if value is None else options.update({option: value})
    payload.pop("payload_sha256")  # written before checkpoints carried their digest
    torch.save(payload, path)


def test_a_checkpoint_from_before_a_model_option_resumes_as_its_default(runs, tmp_path):
    """A run resumed across a version that added a model option: its older best.pt (no
    better epoch since) lacks the option, which means its default, so the resume goes on
    exactly as the never-stopped run; another value of an option is still refused."""
    run = _copy(runs["base"], tmp_path / "run")
    for which in ("best", "last"):
        _as_written_before(checkpoint_path(run, which), "backend")
    result = invoke("train", "--resume", run, "--epochs", EPOCHS)
    assert result.exit_code == 0, result.output
    _assert_same_run(run, runs["whole"])
    other = _copy(runs["base"], tmp_path / "other")
    _as_written_before(checkpoint_path(other, "best"), "backend", "scatter")
    before = _hashes(other)
    result = invoke("train", "--resume", other, "--epochs", EPOCHS)
    assert "best.pt is not this run's checkpoint" in one_line_error(result)
    assert _hashes(other) == before


@pytest.mark.parametrize(("path", "mode", "words"), [
    ("checkpoints", 0o555, "cannot write in"),
    ("metrics.jsonl", 0o444, "metrics.jsonl: it is read-only"),
])
def test_a_run_folder_that_cannot_be_written_is_refused_before_anything_is_written(
        runs, tmp_path, path, mode, words):
    run = _copy(runs["base"], tmp_path / "run")
    target = run / path
    old = target.stat().st_mode
    target.chmod(mode)
    try:
        if os.access(target, os.W_OK):  # the superuser writes anyway
            pytest.skip("permission bits do not stop this user (root)")
        before = _hashes(run)
        result = invoke("train", "--resume", run, "--epochs", 2)
        assert _hashes(run) == before
        assert words in one_line_error(result)
    finally:
        target.chmod(old)


def test_a_config_file_on_resume_is_refused_unless_it_is_the_runs(runs, user_files,
                                                                  tmp_path):
    run = _copy(runs["base"], tmp_path / "run")
    before = _hashes(run)
    other = tmp_path / "other.toml"
    other.write_text("lr = 0.5\n")
    refused = invoke("train", "--resume", run, "--epochs", 2, "--config", other)
    assert _hashes(run) == before
    assert f"(got --config {other} with other lr)" in one_line_error(refused)
    refused = invoke("train", "--resume", run, "--epochs", 2, "--config", user_files["data"])
    assert _hashes(run) == before
    assert "is not UTF-8 text" in one_line_error(refused)
    # The run's own settings, and a total of epochs (which a resume may change): taken.
    same = tmp_path / "same.toml"
    same.write_text("batch_size = 4\nepochs = 2\n[solver]\nfixed_dt = 0.1\n"
                    "[model_options]\nhidden = 4\n")
    result = invoke("train", "--resume", run, "--config", same)
    assert result.exit_code == 0, result.output
    assert [r["epoch"] for r in read_metrics(run)] == [0, 1, 2]
