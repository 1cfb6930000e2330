"""A training killed anywhere (SIGKILL: no handler runs), from its first moment on, and
resumed each time ends with the weights of a training that was never stopped, bit for bit.

`test_resume_transactional` kills resumes of a run that has a checkpoint; here the first
`mpnode train` is killed too, before and while its folder and first checkpoint are made.
A folder killed before its first `last.pt` cannot be resumed (nothing to resume from): as
its refusal advises, it is deleted and the training started again.
"""

from __future__ import annotations

import os
import random
import shutil
import time

import pytest
from conftest import invoke
from test_resume_transactional import (  # noqa: F401 (runs: the module's fixture)
    EPOCHS,
    TINY,
    _assert_same_run,
    _finished,
    _fork,
    _killed,
    runs,
)

from mpnode_cli.training.run import checkpoint_path

pytestmark = pytest.mark.skipif(not hasattr(os, "fork"), reason="needs os.fork")
KILLS = 12


def _train_in_child(data, run, kill_after: float | None) -> bool:
    """`mpnode train` into `run` (a resume once it has a `last.pt`) in a fork of this
    process, SIGKILLed after `kill_after` seconds. Returns whether it was killed."""
    if run.exists() and not checkpoint_path(run, "last").is_file():
        shutil.rmtree(run)  # killed before its first checkpoint: start again
    args = (["--resume", run] if run.exists()
            else [data, *TINY, "--run-dir", run])
    pid = _fork()
    if pid == 0:  # the child: never returns into pytest
        code = 1
        try:
            code = invoke("train", *args, "--epochs", EPOCHS).exit_code
        finally:
            os._exit(code)
    return _killed(pid, kill_after)


def test_a_training_killed_anywhere_and_resumed_ends_as_one_never_stopped(
        runs, user_files, tmp_path):  # noqa: F811 (the imported fixture)
    start = time.perf_counter()
    assert not _train_in_child(user_files["data"], tmp_path / "once", None)
    _assert_same_run(tmp_path / "once", runs["whole"])  # the fresh training is the reference's
    length = time.perf_counter() - start
    rng = random.Random(20261208)  # the kill times: fixed, so a failure can be rerun
    kills, through, run = 0, 0, tmp_path / "run-0"
    while kills < KILLS:
        if _train_in_child(user_files["data"], run, rng.uniform(0, length)):
            kills += 1
        if _finished(run):  # a training got to its end (or was killed after it wrote all)
            _assert_same_run(run, runs["whole"])
            through += 1
            run = tmp_path / f"run-{through}"
    if not _finished(run):
        assert not _train_in_child(user_files["data"], run, None)
    _assert_same_run(run, runs["whole"])
    assert through >= 1
    print(f"{kills} kills, {through} trainings through, {time.perf_counter() - start:.1f} s")
