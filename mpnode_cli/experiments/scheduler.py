"""Which process runs which step, and when: step folders, fingerprints, locks and workers.

A step's folder is `WORK/<id>-<fingerprint[:12]>`. The fingerprint hashes the step's
resolved options (`spec.resolve`: the scale and, for training, the recipe and the members
of an ensemble, `--seeds`, are in them) and the fingerprints of the steps it reads, so a
step is the same step wherever the same options meet the same inputs: experiments that
share a step (the Lorenz3 model of four experiments) share its folder when they share a
work folder, and runs with different `--seeds` share only their datasets.

A finished step leaves `step.json` (written last, atomically): its fingerprint, options,
results, the equivalent commands and its seconds. A step whose folder holds a `step.json`
with its fingerprint and whose outputs exist is skipped; a folder without one is what an
interrupted step left, and is cleared and run again, except for training, which resumes
from its `last.pt` (`mpnode train --resume`). Changing a step's options changes its
fingerprint and those of every step that reads it, so exactly those run again.

Two runs may share a work folder at once (two experiments that share a step, started side
by side): each step is taken under an exclusive lock on `WORK/<folder name>.lock` (`flock`,
released when the process ends, however it ends), so the second run leaves a shared step
to the first and reuses it once done, instead of clearing or resuming it under the first.
A process takes the first step, in the spec's order, whose inputs are done and that no
other process holds (and waits, polling, when every ready step is held), so `jobs`
processes of one run (`run_experiment(jobs=...)`: the run and spawned workers) run
independent steps side by side. A step run by any process of this run carries the run's
token in its `step.json`; the run reports it as run, not reused.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
from collections.abc import Iterator
from contextlib import contextmanager, nullcontext
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from mpnode_cli.experiments.commands import from_work
from mpnode_cli.experiments.spec import Experiment, Scale, resolve
from mpnode_cli.experiments.steps import (
    RUN_DIR,
    VERBS,
    OnEvent,
    StepFailed,
    StepRecord,
    line,
)

STEP_JSON, PENDING_JSON, FAILED_JSON = "step.json", "pending.json", "failed.json"
FINGERPRINT_FORMAT = 1  # bump when what a step writes changes meaning
_POLL_SECONDS = 0.5


@dataclass(frozen=True)
class Planned:
    """A step with its resolved options, fingerprint and folder, known before any runs."""

    index: int
    step: Any
    options: dict[str, Any]
    fingerprint: str
    folder: Path


def plan_steps(experiment: Experiment, scale: Scale, recipe: str, work: Path,
               seeds: int = 1, draw: int = 0) -> list[Planned]:
    """Every step's options, fingerprint and folder, in the spec's order (a fingerprint
    depends on its inputs' fingerprints, not on their results, so nothing has to run);
    every training an ensemble of `seeds` members when that is over 1; the data of draw
    `draw` (`spec.DRAW_STRIDE`).

    Raises:
        ValueError: a step whose options do not resolve (e.g. its seeds past the largest).
    """
    planned: dict[str, Planned] = {}
    for index, step in enumerate(experiment.steps, start=1):
        try:
            options = resolve(step, scale, recipe, seeds, draw)
        except ValueError as exc:
            raise ValueError(f"{experiment.name}: step '{step.id}': {exc}") from None
        fingerprint = step_fingerprint(step.verb, options, [planned[i].fingerprint
                                                        for i in step.inputs()])
        planned[step.id] = Planned(index, step, options, fingerprint,
                                   Path(work) / f"{step.id}-{fingerprint[:12]}")
    return list(planned.values())


def take_steps(steps: list[Planned], token: str, emit: OnEvent,
               failed: dict[str, str] | None = None) -> dict[str, StepRecord]:
    """Run or collect every step: repeatedly the first step, in order, that is not done,
    whose inputs are done and whose lock is free. When none is, other processes hold the
    steps that are ready: say so once (a `waiting` event for the first of them) and look
    again shortly.

    Args:
        failed: None: the first step that fails raises `StepFailed`. A dict: keep going;
            a failed step (by any process of this run: its `FAILED_JSON`) goes in it with
            its message, and the steps that read it with "skipped"."""
    records: dict[str, StepRecord] = {}
    left = list(steps)
    total = len(steps)
    announced: set[str] = set()
    while left:
        for entry in left:
            ready = all(i in records for i in entry.step.inputs())
            # A marker is read only for a step that could run: not on every poll of all.
            if failed is not None and (why := _failure(entry, token, failed, ready)):
                failed[entry.step.id] = why
                emit({"event": "step-failed", "id": entry.step.id, "error": why})
                left = [e for e in left if e.step.id != entry.step.id]
                break
            if not ready:
                continue
            done = _finished_record(entry, token)
            if done is None:
                lock = _try_lock(entry.folder)
                if lock is None:
                    continue  # another process runs it
                with lock:
                    done = _finished_record(entry, token)  # finished while we looked
                    if done is None:
                        status = "resumed" if resumable(entry.folder, entry.fingerprint) \
                            else "ran"
                        emit({"event": "step", "index": entry.index, "total": total,
                              "id": entry.step.id, "verb": entry.step.verb,
                              "status": status, "folder": str(entry.folder)})
                        try:
                            record = run_step(entry.step, entry.options, entry.fingerprint,
                                              entry.folder, records, status, emit, token)
                        except StepFailed as exc:
                            if failed is None:
                                raise
                            _write_failure(entry, token, str(exc))
                            break
                        emit({"event": "step-done", "id": entry.step.id,
                              "status": record.status, "seconds": record.seconds,
                              "line": line(record)})
                        done = record
                        entry = None  # reported as it ran
            if entry is not None:
                elsewhere = done.status != "skipped"  # a worker of this run ran it
                emit({"event": "step", "index": entry.index, "total": total,
                      "id": entry.step.id, "verb": entry.step.verb, "status": done.status,
                      "folder": str(entry.folder), "worker": elsewhere})
                emit({"event": "step-done", "id": entry.step.id, "status": done.status,
                      "seconds": done.seconds, "line": line(done), "worker": elsewhere})
            records[done.id] = done
            left = [e for e in left if e.step.id != done.id]
            break
        else:
            first = left[0]  # its inputs come before it, so they are done: someone holds it
            if first.step.id not in announced:
                announced.add(first.step.id)
                emit({"event": "waiting", "id": first.step.id,
                      "lock": str(_lock_path(first.folder))})
            time.sleep(_POLL_SECONDS)
    return records


def _failure(entry: Planned, token: str, failed: dict[str, str],
             ready: bool) -> str | None:
    """Why `entry` cannot be done in this run: a step it reads failed, or (once `ready`,
    its inputs done) it failed itself, here or in another process of the run."""
    if bad := next((i for i in entry.step.inputs() if i in failed), None):
        return f"skipped: step '{bad}' failed"
    if not ready:
        return None
    try:
        mark = json.loads((entry.folder / FAILED_JSON).read_text())
    except (OSError, ValueError):
        return None
    same = mark.get("run_token") == token and mark.get("fingerprint") == entry.fingerprint
    return str(mark.get("error")) if same else None


def _write_failure(entry: Planned, token: str, error: str) -> None:
    from mpnode_cli.training.run import write_json

    write_json(entry.folder / FAILED_JSON, {"fingerprint": entry.fingerprint, "error": error,
                                            "run_token": token})


def _finished_record(entry: Planned, token: str) -> StepRecord | None:
    """`entry`'s record if its step is done: status as run if a process of this run (the
    same `token`) ran it, else "skipped". Names and the paper's numbers from today's spec."""
    done = _finished(entry.folder, entry.fingerprint)
    if done is None:
        return None
    ran_now = done.pop("run_token", None) == token
    # The folder is where the step is now (the work folder may have moved since), and its
    # commands as run from the work folder (step records before that held absolute paths).
    return StepRecord(**{**done, "status": done["status"] if ran_now else "skipped",
                         "folder": str(entry.folder),
                         "commands": [from_work(c, entry.folder.parent)
                                      for c in done["commands"]],
                         "label": entry.step.label or entry.step.id,
                         "reported": dict(entry.step.reported),
                         "reported_in": entry.step.reported_in})


def start_workers(steps: list[Planned], token: str, count: int,
                  keep_going: bool = False) -> list[Any]:
    """`count` worker processes (spawned: a fresh interpreter each, no forked torch
    state), each taking steps as `take_steps` does, silently (past failed steps, with
    `keep_going`)."""
    if count < 1:
        return []
    import multiprocessing

    import torch

    context = multiprocessing.get_context("spawn")
    workers = [context.Process(target=_worker, args=(steps, token, torch.get_num_threads(),
                                                     keep_going), daemon=True)
               for _ in range(count)]
    for worker in workers:
        worker.start()
    return workers


def _worker(steps: list[Planned], token: str, threads: int, keep_going: bool) -> None:
    """A worker process: take steps until every step is done. A step that fails here
    ends the worker; the run reaches that step itself and reports the failure."""
    from mpnode_cli.signals import interrupt_on_signals
    from mpnode_cli.threads import ThreadChoice, apply_threads

    apply_threads(ThreadChoice(threads, "the run's process"))
    _stop_when_orphaned(os.getppid())
    try:
        # SIGTERM (the run ending early, or gone) interrupts a training as Ctrl-C does: it
        # keeps its last epoch to resume from; a worker waiting for a step stops waiting.
        with interrupt_on_signals():
            take_steps(steps, token, lambda event: None, {} if keep_going else None)
    except (Exception, KeyboardInterrupt):  # the run meets the same error and reports it
        pass


def _stop_when_orphaned(parent: int) -> None:
    """SIGTERM this worker once its run's process has gone (killed outright, with no
    chance to stop its workers): a training in it then stops as on Ctrl-C, keeping its
    last epoch, instead of running on with nobody to report to."""
    import signal
    import threading

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(1.0)
        os.kill(os.getpid(), signal.SIGTERM)

    threading.Thread(target=watch, name="orphan-watch", daemon=True).start()


def stop_workers(workers: list[Any], grace: float = 30.0) -> None:
    """End the workers: they have finished when the run has; on an error or Ctrl-C they
    get SIGTERM (a training they run resumes from its last epoch next time), and one still
    running `grace` seconds later is killed (its last epoch on disk is whole: every file
    is written to a temporary name and renamed)."""
    for worker in workers:
        if worker.is_alive():
            worker.terminate()
    deadline = time.monotonic() + grace
    for worker in workers:
        worker.join(timeout=max(0.0, deadline - time.monotonic()))
        if worker.is_alive():
            worker.kill()
            worker.join(timeout=10)


def _lock_path(folder: Path) -> Path:
    return folder.with_name(folder.name + ".lock")


@contextmanager
def _held(handle) -> Iterator[None]:
    import fcntl

    try:
        yield
    finally:
        fcntl.flock(handle, fcntl.LOCK_UN)
        handle.close()


def _try_lock(folder: Path) -> Any:
    """`folder`'s step lock as a context manager if it is free now, else None (another
    process holds it). Where `fcntl` is missing (Windows), a no-op lock."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not on Linux or macOS
        return nullcontext()
    folder.parent.mkdir(parents=True, exist_ok=True)
    handle = open(_lock_path(folder), "a")  # closed by _held
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        handle.close()
        return None
    return _held(handle)


# Options added after steps were first fingerprinted, left out of the fingerprint at their
# default so that a new option does not make every finished step run again: the solver's
# `compact` (on by default; it changes results by rounding only) and `checkpoints` (off).
_LATER_DEFAULTS = {"solver": {"compact": True, "checkpoints": None}}


def _without_later_defaults(value: Any) -> Any:
    """`value` with the `_LATER_DEFAULTS` that hold their default taken out, at any depth."""
    if isinstance(value, list):
        return [_without_later_defaults(v) for v in value]
    if not isinstance(value, dict):
        return value
    out = {}
    for key, v in value.items():
        later = _LATER_DEFAULTS.get(key)
        if later and isinstance(v, dict):
            v = {k: x for k, x in v.items() if not (k in later and x == later[k])}
        out[key] = _without_later_defaults(v)
    return out


def step_fingerprint(verb: str, options: dict[str, Any], inputs: list[str]) -> str:
    blob = json.dumps({"format": FINGERPRINT_FORMAT, "verb": verb,
                       "options": _without_later_defaults(options), "inputs": inputs},
                      sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()


def _finished(folder: Path, fingerprint: str) -> dict[str, Any] | None:
    """The step record in `folder` if it is this step's and its outputs exist."""
    path = folder / STEP_JSON
    if not path.is_file():
        return None
    try:
        record = json.loads(path.read_text())
    except json.JSONDecodeError:
        return None
    if record.get("fingerprint") != fingerprint:
        return None
    if not all((folder / name).exists() for name in record.pop("outputs", [])):
        return None
    return record


def resumable(folder: Path, fingerprint: str) -> bool:
    """An interrupted training of this very step, with a `last.pt` to continue from."""
    pending = folder / PENDING_JSON
    if not pending.is_file() or not (folder / RUN_DIR / "checkpoints" / "last.pt").is_file():
        return False
    try:
        return json.loads(pending.read_text()).get("fingerprint") == fingerprint
    except json.JSONDecodeError:
        return False


def run_step(step, options: dict[str, Any], fingerprint: str, folder: Path,
             records: dict[str, StepRecord], status: str, emit: OnEvent,
             token: str = "") -> StepRecord:
    """Run `step`'s verb in `folder` (cleared first unless `status` is "resumed") and
    record it in `step.json`, with the run's `token`.

    Raises:
        StepFailed: the verb refused its data or options (its message names the step).
    """
    from mpnode_cli.data.generate import GenerateError
    from mpnode_cli.training.run import write_json

    if status != "resumed":
        shutil.rmtree(folder, ignore_errors=True)
        folder.mkdir(parents=True)
        write_json(folder / PENDING_JSON, {"fingerprint": fingerprint})
    start = time.perf_counter()
    inputs = {i: records[i] for i in step.inputs()}
    try:
        verb = VERBS[step.verb]
        result, outputs, cmds, figures = verb(step, options, folder, inputs, status, emit)
    except (ValueError, FileNotFoundError, GenerateError) as exc:
        raise StepFailed(f"step '{step.id}' ({step.verb}): {exc}") from None
    record = StepRecord(
        id=step.id, verb=step.verb, label=step.label or step.id, status=status,
        folder=str(folder), fingerprint=fingerprint, options=options,
        seconds=time.perf_counter() - start, commands=[from_work(c, folder.parent) for c in cmds],
        result=result, figures=figures,
        reported=dict(step.reported), reported_in=step.reported_in)
    write_json(folder / STEP_JSON, {**asdict(record), "outputs": outputs, "run_token": token})
    (folder / PENDING_JSON).unlink(missing_ok=True)
    return record
