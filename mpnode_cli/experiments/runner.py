"""Run an experiment's steps through the library, each in its own folder, resuming.

`run_experiment` plans every step (`scheduler.plan_steps`: its options, fingerprint and
folder), takes them in order with any workers (`schedule`: a finished step is reused, an
interrupted training resumed, a step another process holds left to it), runs each through
its verb (`steps`) and returns the run's record for `report.write_report`.

`progress`, if given, gets one dict per event: `step` (index, total, id, verb, status:
run/resume/skip, folder; `worker` when a worker of this run ran it), `generate` (done,
total), `train` (the training loop's event, under `event_data`), `step-done` (id, seconds,
line), `waiting` (id, lock: another process holds the step).
"""

from __future__ import annotations

import os
import platform
import subprocess
import time
import uuid
from dataclasses import asdict, dataclass
from datetime import datetime
from pathlib import Path
from typing import Any

from mpnode_cli import __version__
from mpnode_cli.experiments.scheduler import (
    PENDING_JSON,
    STEP_JSON,
    plan_steps,
    start_workers,
    stop_workers,
    take_steps,
)
from mpnode_cli.experiments.spec import Experiment, Scale
from mpnode_cli.experiments.steps import OnEvent, StepFailed, StepRecord

__all__ = ["PENDING_JSON", "STEP_JSON", "RunRecord", "StepFailed", "StepRecord", "plan_steps",
           "run_experiment"]


@dataclass
class RunRecord:
    """A whole run: `report.write_report` turns it into `report.md`."""

    experiment: str
    title: str
    scale: str
    recipe: str
    command: str
    work: str  # the folder of step folders, as given (`report` records it relative)
    started: str
    wall_seconds: float
    machine: dict[str, Any]
    steps: list[StepRecord]
    seeds: int = 1  # members of every training's ensemble (`--seeds`)
    draw: int = 0  # the data draw (`--draw`, `spec.DRAW_STRIDE`); 0: the experiment's data

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def run_experiment(experiment: Experiment, *, scale: Scale, recipe: str, work: Path,
                   command: str = "", progress: OnEvent | None = None,
                   jobs: int = 1, seeds: int = 1, draw: int = 0) -> RunRecord:
    """Run (or resume) every step of `experiment` at `scale` with `recipe`.

    Args:
        work: the folder of step folders (shared by experiments).
        command: the command line to record (default: the `mpnode experiment run` that
            does the same; an absolute path in it is shown as `mpnode_cli.file_records.shown_path`
            shows it, since reports are committed).
        jobs: processes that run steps side by side (this one and `jobs - 1` workers, one
            torch pool each of this process's size). A step runs once its inputs are done;
            each process takes the first step, in the spec's order, that is ready and that
            no other process holds.
        seeds: S, the members of every training (`mpnode train --seeds S`: member k has
            the step's seed + k; a finetune's members start from their parent's). Every
            step that reads a trained model then reports each member's numbers too
            (`mpnode_cli.experiments.members`). 1: a single model, as before seeds.
        draw: the data draw: every generated dataset's seed and graph seed offset by
            `draw` × `spec.DRAW_STRIDE` (0: the experiment's own data). Its report
            section goes beside draw 0's, and the claims get intervals over the draws
            (`claims.interval`).

    Raises:
        ValueError: a work folder that cannot be made or written in, or options that do
            not resolve with `seeds` (before any step).
        StepFailed: a step failed (its message names the step).
        TrainingInterrupted, KeyboardInterrupt: Ctrl-C; finished steps stay reusable and a
            training resumes from its last epoch on the next run.
    """
    from mpnode_cli.file_records import shown_path
    from mpnode_cli.paths import check_output_folder

    emit = progress or (lambda event: None)
    command = command or (f"mpnode experiment run {experiment.name} --scale {scale} "
                          f"--recipe {recipe} --seeds {seeds} "
                          + (f"--draw {draw} " if draw else "")
                          + f"--work {shown_path(work, '<work>')}")
    work = Path(work)
    check_output_folder(work)
    work.mkdir(parents=True, exist_ok=True)
    machine = machine_facts()
    if jobs > 1:
        machine["jobs"] = jobs
    start = time.perf_counter()
    started = datetime.now().isoformat(timespec="seconds")
    steps = plan_steps(experiment, scale, recipe, work, seeds, draw)
    token = uuid.uuid4().hex  # marks in step.json the steps this run's processes ran
    workers = start_workers(steps, token, jobs - 1)
    try:
        records = take_steps(steps, token, emit)
    finally:
        stop_workers(workers)
    machine["load_after"] = _load()
    return RunRecord(experiment=experiment.name, title=experiment.title, scale=scale,
                     recipe=recipe, command=command, work=str(work), started=started,
                     wall_seconds=time.perf_counter() - start, machine=machine,
                     steps=[records[entry.step.id] for entry in steps], seeds=seeds,
                     draw=draw)


# ------------------------------------------------------------------------------ machine


def machine_facts() -> dict[str, Any]:
    """Where and with what a run ran: cores, torch threads, load, versions, git commit."""
    import torch

    return {"cores": os.cpu_count(), "threads": torch.get_num_threads(),
            "torch": torch.__version__, "python": platform.python_version(),
            "mpnode": __version__, "platform": platform.platform(terse=True),
            "commit": git_commit(), "load_before": _load()}


def _load() -> str:
    return "/".join(f"{x:.2f}" for x in os.getloadavg())


def git_commit() -> str:
    """The package's git commit (`+dirty` with uncommitted changes to tracked files), or
    "unknown" outside a git checkout."""
    root = Path(__file__).resolve().parents[2]

    def git(*args: str) -> str:
        try:
            return subprocess.run(["git", *args], capture_output=True, text=True, cwd=root,
                                  timeout=10).stdout.strip()
        except (OSError, subprocess.SubprocessError):
            return ""

    commit = git("rev-parse", "--short=10", "HEAD")
    if not commit:
        return "unknown"
    return commit + ("+dirty" if git("status", "--porcelain", "--untracked-files=no") else "")
