"""Run an experiment's steps through the library, each in its own folder, resuming.

A step's folder is `WORK/<id>-<fingerprint[:12]>`. The fingerprint hashes the step's
resolved options (`spec.resolve`: the scale and, for training, the recipe are in them) and
the fingerprints of the steps it reads, so a step is the same step wherever the same
options meet the same inputs: experiments that share a step (the Lorenz3 model of four
experiments) share its folder when they share a work folder.

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

`progress`, if given, gets one dict per event: `step` (index, total, id, verb, status:
run/resume/skip, folder; `worker` when a worker of this run ran it), `generate` (done,
total), `train` (the training loop's event, under `event_data`), `step-done` (id, seconds,
line), `waiting` (id, lock: another process holds the step).
"""

from __future__ import annotations

import hashlib
import json
import os
import platform
import shutil
import subprocess
import time
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager, nullcontext
from dataclasses import asdict, dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

from mpnode_cli import __version__
from mpnode_cli.experiments import commands
from mpnode_cli.experiments.spec import TRAINING, Experiment, Scale, resolve
from mpnode_cli.jsonable import jsonable

Progress = Callable[[dict[str, Any]], None]
STEP_JSON, PENDING_JSON = "step.json", "pending.json"
DATA_FILE, RUN_DIR, COMPARE_JSON = "data.h5", "run", "compare.json"
FINGERPRINT_FORMAT = 1  # bump when what a step writes changes meaning


class StepFailed(RuntimeError):
    """A step could not run (bad data, a refused option, a diverged training)."""


@dataclass
class StepRecord:
    """One step of a run: what it did (or found done) and its results."""

    id: str
    verb: str
    label: str
    status: str  # "ran", "resumed" or "skipped" (done by an earlier run)
    folder: str
    fingerprint: str
    options: dict[str, Any]
    seconds: float
    commands: list[str]
    result: dict[str, Any]
    figures: list[str] = field(default_factory=list)
    reported: dict[str, float] = field(default_factory=dict)
    reported_in: str | None = None


@dataclass
class RunRecord:
    """A whole run: `report.write_report` turns it into `report.md`."""

    experiment: str
    title: str
    scale: str
    recipe: str
    command: str
    started: str
    wall_seconds: float
    machine: dict[str, Any]
    steps: list[StepRecord]

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass(frozen=True)
class _Planned:
    """A step with its resolved options, fingerprint and folder, known before any runs."""

    index: int
    step: Any
    options: dict[str, Any]
    fingerprint: str
    folder: Path


def plan(experiment: Experiment, scale: Scale, recipe: str, work: Path) -> list[_Planned]:
    """Every step's options, fingerprint and folder, in the spec's order (a fingerprint
    depends on its inputs' fingerprints, not on their results, so nothing has to run)."""
    planned: dict[str, _Planned] = {}
    for index, step in enumerate(experiment.steps, start=1):
        options = resolve(step, scale, recipe)
        fingerprint = _fingerprint(step.verb, options, [planned[i].fingerprint
                                                        for i in step.inputs()])
        planned[step.id] = _Planned(index, step, options, fingerprint,
                                    Path(work) / f"{step.id}-{fingerprint[:12]}")
    return list(planned.values())


def run_experiment(experiment: Experiment, *, scale: Scale, recipe: str, work: Path,
                   command: str = "", progress: Progress | None = None,
                   jobs: int = 1) -> RunRecord:
    """Run (or resume) every step of `experiment` at `scale` with `recipe`.

    Args:
        work: the folder of step folders (shared by experiments).
        command: the command line to record (default: the `mpnode experiment run` that
            does the same).
        jobs: processes that run steps side by side (this one and `jobs - 1` workers, one
            torch pool each of this process's size). A step runs once its inputs are done;
            each process takes the first step, in the spec's order, that is ready and that
            no other process holds.

    Raises:
        ValueError: a work folder that cannot be made or written in (before any step).
        StepFailed: a step failed (its message names the step).
        TrainingInterrupted, KeyboardInterrupt: Ctrl-C; finished steps stay reusable and a
            training resumes from its last epoch on the next run.
    """
    from mpnode_cli.paths import check_output_folder

    emit = progress or (lambda event: None)
    command = command or (f"mpnode experiment run {experiment.name} --scale {scale} "
                          f"--recipe {recipe} --work {work}")
    work = Path(work)
    check_output_folder(work)
    work.mkdir(parents=True, exist_ok=True)
    machine = machine_facts()
    if jobs > 1:
        machine["jobs"] = jobs
    start = time.perf_counter()
    started = datetime.now().isoformat(timespec="seconds")
    steps = plan(experiment, scale, recipe, work)
    token = uuid.uuid4().hex  # marks in step.json the steps this run's processes ran
    workers = _start_workers(steps, token, jobs - 1)
    try:
        records = _take_steps(steps, token, emit)
    finally:
        _stop_workers(workers)
    machine["load_after"] = _load()
    return RunRecord(experiment=experiment.name, title=experiment.title, scale=scale,
                     recipe=recipe, command=command, started=started,
                     wall_seconds=time.perf_counter() - start, machine=machine,
                     steps=[records[entry.step.id] for entry in steps])


def _take_steps(steps: list[_Planned], token: str, emit: Progress) -> dict[str, StepRecord]:
    """Run or collect every step: repeatedly the first step, in order, that is not done,
    whose inputs are done and whose lock is free. When none is, other processes hold the
    steps that are ready: say so once (a `waiting` event for the first of them) and look
    again shortly."""
    records: dict[str, StepRecord] = {}
    left = list(steps)
    total = len(steps)
    announced: set[str] = set()
    while left:
        for entry in left:
            if not all(i in records for i in entry.step.inputs()):
                continue
            done = _finished_record(entry, token)
            if done is None:
                lock = _try_lock(entry.folder)
                if lock is None:
                    continue  # another process runs it
                with lock:
                    done = _finished_record(entry, token)  # finished while we looked
                    if done is None:
                        status = "resumed" if _resumable(entry.folder, entry.fingerprint) \
                            else "ran"
                        emit({"event": "step", "index": entry.index, "total": total,
                              "id": entry.step.id, "verb": entry.step.verb,
                              "status": status, "folder": str(entry.folder)})
                        record = _run_step(entry.step, entry.options, entry.fingerprint,
                                           entry.folder, records, status, emit, token)
                        emit({"event": "step-done", "id": entry.step.id,
                              "status": record.status, "seconds": record.seconds,
                              "line": _line(record)})
                        done = record
                        entry = None  # reported as it ran
            if entry is not None:
                elsewhere = done.status != "skipped"  # a worker of this run ran it
                emit({"event": "step", "index": entry.index, "total": total,
                      "id": entry.step.id, "verb": entry.step.verb, "status": done.status,
                      "folder": str(entry.folder), "worker": elsewhere})
                emit({"event": "step-done", "id": entry.step.id, "status": done.status,
                      "seconds": done.seconds, "line": _line(done), "worker": elsewhere})
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


def _finished_record(entry: _Planned, token: str) -> StepRecord | None:
    """`entry`'s record if its step is done: status as run if a process of this run (the
    same `token`) ran it, else "skipped". Names and the paper's numbers from today's spec."""
    done = _finished(entry.folder, entry.fingerprint)
    if done is None:
        return None
    ran_now = done.pop("run_token", None) == token
    return StepRecord(**{**done, "status": done["status"] if ran_now else "skipped",
                         "label": entry.step.label or entry.step.id,
                         "reported": dict(entry.step.reported),
                         "reported_in": entry.step.reported_in})


_POLL_SECONDS = 0.5


def _start_workers(steps: list[_Planned], token: str, count: int) -> list[Any]:
    """`count` worker processes (spawned: a fresh interpreter each, no forked torch
    state), each taking steps as `_take_steps` does, silently."""
    if count < 1:
        return []
    import multiprocessing

    import torch

    context = multiprocessing.get_context("spawn")
    workers = [context.Process(target=_worker, args=(steps, token, torch.get_num_threads()),
                               daemon=True) for _ in range(count)]
    for worker in workers:
        worker.start()
    return workers


def _worker(steps: list[_Planned], token: str, threads: int) -> None:
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
            _take_steps(steps, token, lambda event: None)
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


def _stop_workers(workers: list[Any], grace: float = 30.0) -> None:
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


def _fingerprint(verb: str, options: dict[str, Any], inputs: list[str]) -> str:
    blob = json.dumps({"format": FINGERPRINT_FORMAT, "verb": verb, "options": options,
                       "inputs": inputs}, sort_keys=True, default=str)
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


def _resumable(folder: Path, fingerprint: str) -> bool:
    """An interrupted training of this very step, with a `last.pt` to continue from."""
    pending = folder / PENDING_JSON
    if not pending.is_file() or not (folder / RUN_DIR / "checkpoints" / "last.pt").is_file():
        return False
    try:
        return json.loads(pending.read_text()).get("fingerprint") == fingerprint
    except json.JSONDecodeError:
        return False


def _run_step(step, options: dict[str, Any], fingerprint: str, folder: Path,
              records: dict[str, StepRecord], status: str, emit: Progress,
              token: str = "") -> StepRecord:
    from mpnode_cli.data.generate import GenerateError
    from mpnode_cli.training.run import write_json

    if status != "resumed":
        shutil.rmtree(folder, ignore_errors=True)
        folder.mkdir(parents=True)
        write_json(folder / PENDING_JSON, {"fingerprint": fingerprint})
    start = time.perf_counter()
    inputs = {i: records[i] for i in step.inputs()}
    try:
        runner = _VERBS[step.verb]
        result, outputs, cmds, figures = runner(step, options, folder, inputs, status, emit)
    except (ValueError, FileNotFoundError, GenerateError) as exc:
        raise StepFailed(f"step '{step.id}' ({step.verb}): {exc}") from None
    record = StepRecord(
        id=step.id, verb=step.verb, label=step.label or step.id, status=status,
        folder=str(folder), fingerprint=fingerprint, options=options,
        seconds=time.perf_counter() - start, commands=cmds, result=result, figures=figures,
        reported=dict(step.reported), reported_in=step.reported_in)
    write_json(folder / STEP_JSON, {**asdict(record), "outputs": outputs, "run_token": token})
    (folder / PENDING_JSON).unlink(missing_ok=True)
    return record


# -------------------------------------------------------------------------------- verbs


def _generate(step, options, folder: Path, inputs, status, emit):
    from mpnode_cli.config import GenerateConfig
    from mpnode_cli.data.generate import generate

    config = GenerateConfig(**{**options["config"], "out": folder / DATA_FILE})
    summary = generate(config, overwrite=True,
                       progress=lambda done, total: emit({"event": "generate", "done": done,
                                                          "total": total}))
    train, val, test = summary.split_counts
    result = {"system": config.system, "nodes": config.nodes, "topology": config.topology,
              "trajectories": summary.trajectories, "split": [train, val, test],
              "samples": config.num_steps + 1, "dt": config.dt, "t_end": config.t_end,
              "seed": config.seed, "graph_seed": config.graph_seed,
              "seconds": summary.seconds}
    return result, [DATA_FILE], [commands.generate(step, options, folder / DATA_FILE)], []


def _train(step, options, folder: Path, inputs, status, emit):
    from mpnode_cli.config import TrainConfig
    from mpnode_cli.training.loop import TrainingDiverged, train
    from mpnode_cli.training.run import read_config

    run_dir = folder / RUN_DIR
    data = Path(inputs[step.data].folder) / DATA_FILE
    fields = {"plots": False, **options["config"], "dataset": data, "run_dir": run_dir,
              "recipe": options["recipe"]}
    if step.verb == "finetune":
        fields["init_checkpoint"] = _best(inputs[step.checkpoint])
    try:
        if status == "resumed":
            # A training that finished before its step record was written trains no more
            # epochs and writes its summary again.
            train(read_config(run_dir), resume=True, progress=_forward(emit),
                  finished_ok=True)
        else:
            train(TrainConfig(**fields), progress=_forward(emit))
    except TrainingDiverged as exc:
        raise ValueError(f"training diverged: {exc}") from None
    result = training_result(run_dir, data)
    return (result, [f"{RUN_DIR}/summary.json", f"{RUN_DIR}/checkpoints/best.pt"],
            [commands.train(step, options, data, run_dir, fields.get("init_checkpoint"))], [])


def _forward(emit: Progress) -> Callable[[dict[str, Any]], None]:
    return lambda event: emit({"event": "train", "event_data": event})


def _best(record: StepRecord) -> Path:
    return Path(record.folder) / RUN_DIR / "checkpoints" / "best.pt"


def training_result(run_dir: Path, data: Path) -> dict[str, Any]:
    """What the report needs of a finished run: its summary's numbers, the lowest training
    loss, and the best checkpoint's validation MSE beside the naive predictors."""
    from mpnode_cli.data.dataset import TrajectoryData
    from mpnode_cli.training.checkpoint import load_checkpoint
    from mpnode_cli.training.evaluate import baseline_mse, train_reference
    from mpnode_cli.training.run import read_config, read_metrics, read_summary

    summary = read_summary(run_dir)
    config = read_config(run_dir)
    metrics = read_metrics(run_dir)
    train_losses = [r["train_loss"] for r in metrics if r.get("train_loss") is not None]
    best = load_checkpoint(Path(run_dir) / "checkpoints" / "best.pt")
    dataset = TrajectoryData.load(data)
    reference, _ = train_reference(best, dataset)
    val = baseline_mse(reference, dataset.subset("validation"), best.build_normalizer())
    test = summary.get("test") or {}
    return {
        "model": summary["model"], "loss": summary["loss"], "epochs": summary["epochs"],
        "best_epoch": summary["best_epoch"], "min_val_loss": summary["min_val_loss"],
        "table2": summary["table2"], "min_train_loss": min(train_losses, default=None),
        "val": {"mse": summary.get("min_val_mse"), **jsonable(val)},
        "test": {"mse": test.get("mse"), "failed": test.get("failed"),
                 **(summary.get("baselines") or {})},
        "wall_seconds": summary["wall_seconds"],
        "seconds_per_epoch": summary["seconds_per_epoch"],
        "parameters": summary["parameters"], "seed": config.seed,
        "trajectories": len(reference), "recipe": config.recipe,
        "model_options": config.model_options,
    }  # fmt: skip


def _zeroshot(step, options, folder: Path, inputs, status, emit):
    from mpnode_cli.data.dataset import TrajectoryData
    from mpnode_cli.training.checkpoint import load_checkpoint
    from mpnode_cli.training.evaluate import evaluate_checkpoint

    ckpt = load_checkpoint(_best(inputs[step.checkpoint]))
    result, figures, paths = {}, [], []
    for data_id in step.data:
        path = Path(inputs[data_id].folder) / DATA_FILE
        paths.append(path)
        data = TrajectoryData.load(path)
        row = evaluate_checkpoint(ckpt, data, split=step.split, verb="zeroshot")
        result[data_id] = _row(row)
        if step.plot:
            figures.append(_rollout_figure(ckpt, data, step.split,
                                           folder / f"{step.id}-{data_id}-rollout.png"))
    return (result, [Path(f).name for f in figures],
            [commands.zeroshot(_best(inputs[step.checkpoint]), paths, step.split)], figures)


def _evaluate(step, options, folder: Path, inputs, status, emit):
    from mpnode_cli.data.dataset import TrajectoryData
    from mpnode_cli.training.checkpoint import load_checkpoint
    from mpnode_cli.training.evaluate import evaluate_checkpoint

    best = _best(inputs[step.checkpoint])
    ckpt = load_checkpoint(best)
    if step.zero_messages:
        if "messages" not in ckpt.model_config:
            raise ValueError(f"model '{ckpt.model_kind}' has no messages to zero")
        # messages=False clamps incoming messages to zero and changes no weight, so the
        # trained weights load unchanged (MP-NODE's `messages` option).
        ckpt.model_config = {**ckpt.model_config, "messages": False}
    path = Path(inputs[step.data].folder) / DATA_FILE
    data = TrajectoryData.load(path)
    row = evaluate_checkpoint(ckpt, data, split=step.split)
    result = {**_row(row), "zero_messages": step.zero_messages}
    figures = []
    if step.plot:
        figures.append(_rollout_figure(ckpt, data, step.split, folder / f"{step.id}-rollout.png"))
    if step.pca:
        result["pca"] = _message_pca(ckpt, data, step, folder / f"{step.id}-pca.png")
        figures.append(str(folder / f"{step.id}-pca.png"))
    return (result, [Path(f).name for f in figures],
            [commands.evaluate(best, path, step)], figures)


def _message_pca(ckpt, data, step, path: Path) -> dict[str, Any]:
    """PCA of all nodes' messages over time (the paper's Fig. 12): each sample time of each
    trajectory is one point of N·M message values."""
    import torch

    from mpnode_cli.config import stored_solver, train_solver
    from mpnode_cli.report.plots import plot_components
    from mpnode_cli.training.evaluate import predict

    subset = data.subset(step.split)
    n = min(step.trajectories, len(subset))
    model, normalizer = ckpt.build_model(), ckpt.build_normalizer()
    pred = predict(model, subset, normalizer, torch.arange(n),
                   solver=stored_solver(ckpt.train_config, train_solver))
    if pred.messages is None or pred.messages.shape[-1] == 0:
        raise ValueError(f"model '{ckpt.model_kind}' has no message states")
    b, t, nodes, m = pred.messages.shape
    flat = pred.messages.double().reshape(b * t, nodes * m)  # (B·T, N·M)
    centred = flat - flat.mean(dim=0)
    _, s, v = torch.linalg.svd(centred, full_matrices=False)
    k = min(step.pca, v.shape[0])
    scores = (centred @ v[:k].T).reshape(b, t, k)  # (B, T, k)
    explained = (s**2 / (s**2).sum()).tolist()
    plot_components(pred.time, scores, path, dpi=FIGURE_DPI,
                    title=f"PCA of {nodes}×{m} messages, {b} trajectories")
    # How far the components have moved from where each trajectory started, early and
    # late in the horizon: the paper reads growth as the messages countering drift.
    moved = (scores - scores[:, :1]).abs().mean(dim=(0, 2))  # (T,)
    quarter = max(1, t // 4)
    return {"trajectories": b, "messages": nodes * m, "explained": explained[:k],
            "spread_first": float(moved[:quarter].mean()),
            "spread_last": float(moved[-quarter:].mean())}


def _compare(step, options, folder: Path, inputs, status, emit):
    from mpnode_cli.report.plots import plot_bars, plot_curves
    from mpnode_cli.training.run import read_metrics

    labels = {i: inputs[i].label for i in step.runs}
    metrics = {i: read_metrics(Path(inputs[i].folder) / RUN_DIR) for i in step.runs}
    curves = folder / f"{step.id}-loss.png"
    plot_curves({labels[i]: metrics[i] for i in step.runs}, curves, dpi=FIGURE_DPI)
    figures = [str(curves)]
    result = {"runs": {i: {k: inputs[i].result.get(k) for k in
                           ("best_epoch", "min_val_loss", "table2", "min_train_loss")}
                       for i in step.runs}}
    if step.groups:
        bars = folder / f"{step.id}-bars.png"
        first = next(iter(step.groups.values()))
        series = step.series or [labels[i] for i in first]
        plot_bars({group: {series[j] if j < len(series) else labels[i]:
                           inputs[i].result.get("table2") for j, i in enumerate(members)}
                   for group, members in step.groups.items()}, bars, dpi=FIGURE_DPI,
                  ylabel="best epoch × min validation loss",
                  title="Table-2 figure (lower is better)")
        figures.append(str(bars))
        result["groups"] = step.groups
    runs = [Path(inputs[i].folder) / RUN_DIR for i in step.runs]
    return result, [Path(f).name for f in figures], [commands.compare(runs)], figures


FIGURE_DPI = 80
_VERBS = {"generate": _generate, "train": _train, "finetune": _train, "zeroshot": _zeroshot,
          "evaluate": _evaluate, "compare": _compare}


def _row(row: dict[str, Any]) -> dict[str, Any]:
    """The numbers of an `evaluate_checkpoint` row."""
    result, base = row["result"], row.get("baselines") or {}
    return {"dataset": Path(row["dataset"]).parent.name, "split": row["split"],
            "num_nodes": row["num_nodes"], "topology": row["topology"],
            "mse": result["mse"], "failed": result["failed"], "huber": result["huber"],
            "trajectories": result["trajectories"],
            "hold_x0": base.get("hold_x0"), "time_mean": base.get("time_mean")}


def _rollout_figure(ckpt, data, split: str, path: Path) -> str:
    """The first trajectory of `split`, predicted against true, message norms beneath (the
    paper's Fig. 2, 3b and 11)."""
    import torch

    from mpnode_cli.config import stored_solver, train_solver
    from mpnode_cli.report.plots import plot_rollout
    from mpnode_cli.training.evaluate import predict

    subset = data.subset(split)
    pred = predict(ckpt.build_model(), subset, ckpt.build_normalizer(), torch.arange(1),
                   solver=stored_solver(ckpt.train_config, train_solver))
    messages = None if pred.messages is None else pred.messages[0]
    title = f"{data.system}, N={data.num_nodes} ({split}), trajectory 0"
    return str(plot_rollout(pred.time, pred.true[0], pred.pred[0], messages, data.state_names,
                            path, title=title, dpi=FIGURE_DPI))


def _line(record: StepRecord) -> str:
    """One line of a finished step's main number."""
    r = record.result
    if record.verb in TRAINING:
        return (f"best epoch {r['best_epoch']}/{r['epochs']}, min val loss "
                f"{_g(r['min_val_loss'])}, test MSE {_g(r['test'].get('mse'))}")
    if record.verb == "generate":
        return f"{r['trajectories']} trajectories × {r['samples']} samples"
    if record.verb == "evaluate":
        return f"{r['split']} MSE {_g(r['mse'])} (hold x(0) {_g(r['hold_x0'])})"
    if record.verb == "zeroshot":
        return ", ".join(f"{k} MSE {_g(v['mse'])}" for k, v in r.items())
    return f"{len(record.figures)} figures"


def _g(value: Any) -> str:
    return "—" if value is None else f"{value:.4g}"


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
