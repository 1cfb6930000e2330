"""SIGINT and SIGTERM alike in generate and train: the real CLI in a subprocess, stopped
while it works. Nothing half-written, no stray temporary files, outputs that agree."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import child_env
from typer.testing import CliRunner

from mpnode_cli.cli.app import app
from mpnode_cli.config.generate import GenerateConfig
from mpnode_cli.data import hdf5_write
from mpnode_cli.data.generate import generate
from mpnode_cli.training.checkpoint import load_checkpoint
from mpnode_cli.training.run import read_metrics

SIGNALS = [signal.SIGINT, signal.SIGTERM]
pytestmark = pytest.mark.skipif(not Path("/proc/self/status").exists(),
                                reason="waits on /proc/<pid>/status (Linux)")


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return generate(GenerateConfig(system="lorenz", nodes=3, trajectories=16, t_end=0.25,
                                   dt=0.05, out=tmp_path_factory.mktemp("d") / "l3.h5")).path


def _start(*args) -> subprocess.Popen:
    env = child_env()
    return subprocess.Popen([sys.executable, "-m", "mpnode_cli.cli.app", *map(str, args)],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _catches_sigterm(proc: subprocess.Popen) -> bool:
    """Whether the process has installed its SIGTERM handler (the work has begun)."""
    try:
        status = Path(f"/proc/{proc.pid}/status").read_text()
    except FileNotFoundError:
        return False
    caught = next(line for line in status.splitlines() if line.startswith("SigCgt:"))
    return bool(int(caught.split()[1], 16) >> (signal.SIGTERM - 1) & 1)


def _wait_for(condition, proc: subprocess.Popen, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        if proc.poll() is not None:
            pytest.fail(f"exited early ({proc.returncode}): {proc.communicate()[1]}")
        if time.monotonic() > deadline:
            proc.kill()
            pytest.fail("timed out waiting for the work to start")
        time.sleep(0.05)


def _stray(folder: Path) -> list[Path]:
    return [p for p in folder.rglob("*") if p.name.endswith(".tmp") or "probe" in p.name]


@pytest.mark.parametrize("signum", SIGNALS, ids=lambda s: signal.Signals(s).name)
def test_generate_stopped_while_solving_writes_nothing(tmp_path, signum):
    out = tmp_path / "big.h5"
    proc = _start("generate", "lorenz", "--nodes", 10, "--trajectories", 3000, "--t-end", 20,
                  "--dt", 0.1, "--out", out)
    _wait_for(lambda: _catches_sigterm(proc), proc)
    time.sleep(0.5)  # into the solve
    proc.send_signal(signum)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 128 + signum, err
    assert f"Interrupted ({signal.Signals(signum).name}): nothing written" in err
    assert "Traceback" not in err and "Exception ignored" not in err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("signum", SIGNALS, ids=lambda s: signal.Signals(s).name)
def test_a_signal_during_the_hdf5_write_is_not_swallowed(tmp_path, monkeypatch, signum):
    """h5py used to swallow Ctrl-C in its calls ("Exception ignored") and finish the file;
    the signal now stops the write and the temporary file goes."""
    real = hdf5_write._write

    def write_and_signal(f, ds, *args):
        os.kill(os.getpid(), signum)  # arrives while the file is being written
        real(f, ds, *args)

    monkeypatch.setattr(hdf5_write, "_write", write_and_signal)
    with pytest.raises(KeyboardInterrupt):
        generate(GenerateConfig(system="lorenz", nodes=3, trajectories=4, t_end=0.2, dt=0.1,
                                out=tmp_path / "d.h5"))
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("signum", SIGNALS, ids=lambda s: signal.Signals(s).name)
def test_train_stopped_leaves_a_summary_and_a_resumable_checkpoint(dataset, tmp_path, signum):
    run = tmp_path / "run"
    # 20 000 optimizer steps would compile the solver's step (`compile = "auto"`), which
    # takes longer than the epochs this test waits for; the signals are what is tested.
    config = tmp_path / "eager.toml"
    config.write_text("[solver]\ncompile = false\n")
    proc = _start("train", dataset, "--epochs", 5000, "--batch-size", 4, "--no-plots",
                  "--run-dir", run, "--config", config)
    _wait_for(lambda: len(read_metrics(run)) >= 3, proc)  # epochs 0, 1 and 2 done
    proc.send_signal(signum)
    _, err = proc.communicate(timeout=60)
    name = signal.Signals(signum).name
    assert proc.returncode == 128 + signum, err
    assert f"Interrupted ({name})" in err and "Traceback" not in err
    summary = json.loads((run / "summary.json").read_text())
    last = load_checkpoint(run / "checkpoints" / "last.pt")
    epochs = [row["epoch"] for row in read_metrics(run)]
    assert summary["finished"] is False and summary["interrupted"] == name
    assert summary["epochs"] == last.epoch == epochs[-1] and epochs == list(range(last.epoch + 1))
    assert _stray(run) == []
    result = CliRunner().invoke(app, ["train", "--resume", str(run), "--epochs",
                                      str(last.epoch + 1)])
    assert result.exit_code == 0, result.output
    summary = json.loads((run / "summary.json").read_text())
    assert summary["finished"] is True and "interrupted" not in summary
    assert summary["epochs"] == last.epoch + 1


@pytest.mark.parametrize("verb", ["import", "simulate"])
def test_import_and_simulate_stopped_while_writing_leave_nothing(tmp_path, monkeypatch, verb,
                                                                 dataset):
    """SIGTERM while the file is written (h5py would swallow it): held until a field is
    done, then the write stops, the temporary file goes, and the verb exits 143."""
    import numpy as np

    write = hdf5_write._write

    def interrupted_write(f, ds, *args):
        os.kill(os.getpid(), signal.SIGTERM)  # arrives inside the write
        write(f, ds, *args)

    out = tmp_path / "out" / "x.h5"
    if verb == "import":
        np.save(tmp_path / "s.npy", np.zeros((4, 3, 2, 1)))
        np.save(tmp_path / "a.npy", np.ones((2, 2)) - np.eye(2))
        args = ["import", "--states", tmp_path / "s.npy", "--adjacency", tmp_path / "a.npy",
                "--dt", 0.1, "--out", out]
    else:
        run = tmp_path / "run"
        trained = CliRunner().invoke(app, [str(a) for a in (
            "train", dataset, "--epochs", 1, "--batch-size", 8, "--no-plots", "--run-dir",
            run)])
        assert trained.exit_code == 0, trained.output
        np.save(tmp_path / "x0.npy", np.zeros((2, 4, 3)))
        np.save(tmp_path / "a.npy", np.ones((4, 4)) - np.eye(4))
        args = ["simulate", run, "--x0", tmp_path / "x0.npy", "--adjacency",
                tmp_path / "a.npy", "--t-end", 0.2, "--dt", 0.05, "--out", out]
    monkeypatch.setattr(hdf5_write, "_write", interrupted_write)
    result = CliRunner().invoke(app, [str(a) for a in args])
    assert result.exit_code == 128 + signal.SIGTERM, result.output
    assert "Interrupted (SIGTERM): nothing written" in result.output
    assert not out.exists() and _stray(out.parent) == []


def test_a_swallowed_interrupt_is_raised_again_at_the_next_check():
    """A library that catches every exception can swallow the `Interrupted` the handler
    raised inside it; the training loop's check after each batch raises it again, and
    nothing is left pending once the block ends."""
    from mpnode_cli.signals import Interrupted, interrupt_on_signals, raise_if_interrupted

    with interrupt_on_signals():
        raise_if_interrupted()  # nothing received yet
        try:
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(5)  # the handler raises here
        except BaseException:  # what a careless library does
            pass
        with pytest.raises(Interrupted) as caught:
            raise_if_interrupted()
        assert caught.value.signum == signal.SIGTERM
    raise_if_interrupted()  # outside the block: nothing pending


def test_an_interrupt_in_a_callback_python_only_prints_is_quiet_and_raised_later(monkeypatch):
    """A signal that lands in a weakref callback (torch's compiler keeps such callbacks)
    raises `Interrupted` where Python can only print it: it does not reach the
    unraisable-exception hook (which prints it on stderr by default), and the next check
    raises it; any other exception there still reaches the hook."""
    import gc
    import weakref

    from mpnode_cli.signals import Interrupted, interrupt_on_signals, raise_if_interrupted

    reported = []
    monkeypatch.setattr(sys, "unraisablehook", lambda u: reported.append(type(u.exc_value)))

    class Thing:
        pass

    def dropped(callback) -> None:
        thing = Thing()
        ref = weakref.ref(thing, callback)  # noqa: F841 (kept alive until `thing` goes)
        del thing
        gc.collect()

    with interrupt_on_signals():
        dropped(lambda _: os.kill(os.getpid(), signal.SIGTERM) or time.sleep(5))
        assert reported == []
        with pytest.raises(Interrupted):
            raise_if_interrupted()
        dropped(lambda _: 1 / 0)
        assert reported == [ZeroDivisionError]


@pytest.mark.parametrize("signum", SIGNALS, ids=lambda s: signal.Signals(s).name)
def test_a_signal_while_an_epoch_is_saved_leaves_its_files_in_step(dataset, tmp_path,
                                                                    monkeypatch, signum):
    """The signal arrives as epoch 2's metrics row is about to be written. The row,
    `last.pt` and (if it improved) `best.pt` are all written before the interrupt is
    raised, so the checkpoint the run resumes from is the metrics' last epoch (a signal
    between the writes once left `last.pt` at epoch 2 and the metrics at epoch 1)."""
    from mpnode_cli.training import run as runs

    real = runs.append_metrics

    def signal_then_append(run_dir, row):
        if row["epoch"] == 2:
            os.kill(os.getpid(), signum)  # the handler would raise here, before the write
        real(run_dir, row)

    monkeypatch.setattr(runs, "append_metrics", signal_then_append)
    run = tmp_path / "run"
    result = CliRunner().invoke(app, [str(a) for a in (
        "train", dataset, "--epochs", 50, "--batch-size", 8, "--no-plots", "--run-dir", run)])
    assert result.exit_code == 128 + signum, result.output
    last = load_checkpoint(run / "checkpoints" / "last.pt")
    best = load_checkpoint(run / "checkpoints" / "best.pt")
    epochs = [row["epoch"] for row in read_metrics(run)]
    assert last.epoch == 2 and epochs == [0, 1, 2]
    improved = [row["epoch"] for row in read_metrics(run) if row["improved"]]
    assert best.epoch == improved[-1]
    assert json.loads((run / "summary.json").read_text())["epochs"] == 2
    assert _stray(run) == []


def test_a_nested_deferred_block_leaves_the_signal_to_the_outer_one():
    """Writes grouped in one block are all done before the interrupt, even where each
    write holds signals on its own."""
    from mpnode_cli.signals import Interrupted, deferred_signals

    done = []
    with pytest.raises(Interrupted) as caught:
        with deferred_signals():
            with deferred_signals() as inner:
                os.kill(os.getpid(), signal.SIGTERM)
                inner.check()  # the outer block decides: no raise here
                done.append("first")
            done.append("second")  # the inner block's end did not raise either
    assert caught.value.signum == signal.SIGTERM and done == ["first", "second"]
