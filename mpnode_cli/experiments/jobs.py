"""Benchmarks' jobs on the experiments' engine: one runner, one record, one plan.

A benchmark (`bench/transfer.py`, `bench/quality.py`) is a list of `spec.CallStep`s: each a
function `module:name` with JSON arguments, the steps it reads, and its planned seconds.
They run as every experiment's steps do (`scheduler`): each in its folder
`WORK/<id>-<fingerprint[:12]>`, the fingerprint hashing the function, its arguments and its
inputs' fingerprints; done once its `step.json` (the one record format: the function's
record under `result`) is written; a training cut off in `RUN/run` resumes; `jobs`
processes side by side, each step under its lock. A failed job does not stop the others:
the steps that read it are skipped, and the next run tries it again.

`plan` gives the core-hours before anything runs: per group (a system), per set of groups,
in all, and what is left, with the wall time on the workers by list scheduling in the order
the steps run (`order`: the most held-up work first).
"""

from __future__ import annotations

import uuid
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

from mpnode_cli.experiments.scheduler import (
    STEP_JSON,
    plan_steps,
    start_workers,
    stop_workers,
    take_steps,
)
from mpnode_cli.experiments.spec import CallStep, Experiment


def priorities(jobs: dict[str, tuple[float, tuple[str, ...]]]) -> dict[str, float]:
    """A job's seconds plus those of the jobs waiting for it: what it holds up."""
    return {name: seconds + sum(s for s, deps in jobs.values() if name in deps)
            for name, (seconds, _) in jobs.items()}


def schedule(jobs: dict[str, tuple[float, tuple[str, ...]]], workers: int) -> float:
    """Makespan of list scheduling: the ready job of highest priority first, on the first
    free worker.

    Args:
        jobs: name → (seconds, names it waits for; a name not in `jobs` is done).
    """
    done: dict[str, float] = {}
    free = [0.0] * max(1, workers)
    pending = dict(jobs)
    rank = priorities(jobs)
    while pending:
        ready = [(n, s, deps) for n, (s, deps) in pending.items()
                 if all(d in done or d not in jobs for d in deps)]
        name, seconds, deps = max(ready, key=lambda job: rank[job[0]])
        w = min(range(len(free)), key=free.__getitem__)
        start = max([free[w], *(done[d] for d in deps if d in done)])
        done[name] = free[w] = start + seconds
        del pending[name]
    return max(done.values(), default=0.0)


def order(steps: Iterable[CallStep]) -> list[CallStep]:
    """The steps in the order the engine takes them (the first ready one): each after the
    steps it reads, the most held-up work (`priorities`) first."""
    steps = list(steps)
    rank = priorities({s.id: (s.seconds, tuple(s.needs)) for s in steps})
    out: list[CallStep] = []
    placed: set[str] = set()
    pending = sorted(steps, key=lambda s: -rank[s.id])
    while pending:
        step = next(s for s in pending if all(n in placed for n in s.needs))
        out.append(step)
        placed.add(step.id)
        pending.remove(step)
    return out


def done_ids(steps: list[CallStep], work: Path) -> set[str]:
    """The steps whose record is in `work` (as they are specified now)."""
    planned = plan_steps(_experiment(steps), "paper", "mpnode", work)
    return {p.step.id for p in planned if (p.folder / STEP_JSON).is_file()}


def plan(steps: list[CallStep], work: Path, workers: int,
         sets: dict[str, Iterable[str]] | None = None) -> str:
    """Core-hours expected (the caps' in brackets) and left, per group, per set of groups
    and in all; then the wall time left on `workers` processes."""
    done = done_ids(steps, work)

    def line(label: str, chosen: list[CallStep]) -> str:
        exp = sum(s.seconds for s in chosen) / 3600
        cap = sum(s.cap or s.seconds for s in chosen) / 3600
        left = sum(s.seconds for s in chosen if s.id not in done) / 3600
        return f"{label:18s} {len(chosen):5d} {exp:9.2f} {cap:8.2f} {left:8.2f}"

    lines = [f"{'core-hours':18s} {'jobs':>5s} {'expected':>9s} {'(cap)':>8s} {'left':>8s}"]
    groups = list(dict.fromkeys(s.group for s in steps))
    lines += [line(g, [s for s in steps if s.group == g]) for g in groups]
    for name, members in (sets or {}).items():
        members = set(members)
        lines.append(line(f"set {name}", [s for s in steps if s.group in members]))
    lines.append(line("total", steps))
    left = {s.id: (s.seconds, tuple(n for n in s.needs if n not in done))
            for s in steps if s.id not in done}
    lines.append(f"wall time left on {workers} workers (one thread each): about "
                 f"{schedule(left, workers) / 3600:.2f} h (expected)")
    return "\n".join(lines)


def run_jobs(steps: list[CallStep], work: Path, workers: int,
             emit: Callable[[dict[str, Any]], None]) -> dict[str, str]:
    """Run the steps not done yet in `work`, `workers` processes at a time (this one and
    spawned ones; a spawned process imports a step's module from this one's `sys.path`).
    Returns the failed or skipped steps with why; `emit` gets the engine's events
    (`step-done` after each step, run here or by a worker)."""
    planned = plan_steps(_experiment(steps), "paper", "mpnode", work)
    token = uuid.uuid4().hex
    failed: dict[str, str] = {}
    processes = start_workers(planned, token, workers - 1, keep_going=True)
    try:
        take_steps(planned, token, emit, failed)
    finally:
        stop_workers(processes)
    return failed


def reporter(report: Callable[[str], None],
             done: Callable[[str], None] | None = None) -> Callable[[dict[str, Any]], None]:
    """The engine's events as a bench's lines (`report`): a step started here or resumed,
    done (by any process of the run; then `done(id)`), failed or skipped."""
    def event(e: dict[str, Any]) -> None:
        if e["event"] == "step" and e["status"] in ("ran", "resumed") and not e.get("worker"):
            report(f"{'start ' if e['status'] == 'ran' else 'resume'} {e['id']}")
        elif e["event"] == "step-done" and e["status"] != "skipped":
            report(f"done   {e['id']} ({e['seconds']:.0f} s)")
            if done is not None:
                done(e["id"])
        elif e["event"] == "step-failed":
            report(f"FAIL   {e['id']}: {e['error']}")

    return event


def records(work: Path) -> list[dict[str, Any]]:
    """The results of the `call` steps recorded in `work`, oldest first."""
    import json

    found = []
    for path in sorted(Path(work).glob(f"*/{STEP_JSON}"), key=lambda p: p.stat().st_mtime):
        try:
            record = json.loads(path.read_text())
        except (OSError, ValueError):
            continue
        if record.get("verb") == "call" and isinstance(record.get("result"), dict):
            found.append(record["result"])
    return found


def _experiment(steps: list[CallStep]) -> Experiment:
    return Experiment(name="bench", title="a benchmark's jobs", paper="",
                      steps=order(steps))
