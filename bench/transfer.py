"""Transfer benchmark: node models trained on small graphs, run zero-shot on larger ones, and
scored against an oracle trained on the target's own distribution.

Protocols (docs/transfer.md has the whole of it):
- size: each system's small training graphs → graphs 2× and 4× larger (and another
  topology for gene and kuramoto); the BB systems from BA 16 → 32, 64.
- s1: Laber, Eliassi-Rad & Klein (2026): the five Barzel–Barabási systems (sis, mak, mm,
  bd, nd) trained on 64-node S¹ graphs, zero-shot on 1024 and 4096 nodes (8192 with
  `--n8192`), for γ = 2.1, 2.5, 3.5.

Jobs: a source model per (bench, seed); for each target an oracle (the same recipe trained
on a dataset of the target's kind with as many node-trajectories as the source's, until its
validation stops improving for `--oracle-patience` epochs and for at least the source's wall
time) and a zero-shot scoring; both are scored on the target's test split in physical units
(`transfer_score.score`). Each job writes its record JSON under `--runs`; a rerun skips
finished jobs; the table (`bench/results/transfer.md`) and the committed copy of the
records (`bench/results/transfer.json`) are rebuilt from the records alone.

Usage:
    .venv/bin/python bench/transfer.py --plan                     # core-hours, nothing runs
    .venv/bin/python bench/transfer.py --set selection --jobs 2
    .venv/bin/python bench/transfer.py --systems sis,mm --only-protocol s1 --gammas 2.1,2.5
    .venv/bin/python bench/transfer.py --table-only               # rebuild from the records
    .venv/bin/python bench/transfer.py --scale smoke --systems gene,sis --seeds 0 --gammas 2.5
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import sys
import threading
import time
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait
from dataclasses import dataclass, replace
from datetime import datetime
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from quality import ROOT, command, git_commit, mpnode, priorities, schedule  # noqa: E402
from transfer_specs import (  # noqa: E402
    BB,
    EVAL_SECONDS,
    FOR_GRAPHS_VARIANTS,
    GAMMAS,
    PROCESS_SECONDS,
    SETS,
    SYSTEMS,
    VARIANTS,
    Bench,
    Data,
    curriculum_share,
    epoch_seconds,
    generate_seconds,
    s1_bench,
    set_of,
    size_bench,
)
from transfer_table import rebuild, write_json  # noqa: E402

PLUGINS = {"fhn": ROOT / "examples" / "fitzhugh_nagumo.py",  # systems of a plug-in file
           "mutualistic": ROOT / "examples" / "mutualistic.py"}
NEVER = 10**9  # `--stop-patience` of an oracle run: the bench applies the patience itself
MAX_STAGES = 400  # resumes of one oracle at most
ORACLE_EPOCHS = {"full": 4000, "smoke": 40}  # an oracle's epoch cap (the recipe's epochs)


@dataclass
class Job:
    """One unit of work: a dataset to generate, or a training or scoring with a record.

    Attributes:
        name: the record's path under `--runs` without `.json` (a dataset: "gen:<name>").
        seconds: planning estimate (one core); cap: its upper bound.
        deps: jobs it waits for. work: does it. done: whether its output exists.
    """

    name: str
    system: str
    seconds: float
    deps: tuple[str, ...]
    work: Callable[[], Any]
    done: Callable[[], bool]
    cap: float | None = None


# ------------------------------------------------------------------------------ data


def data_path(args, d: Data) -> Path:
    return args.data / f"{d.name}.h5"


_GENERATING: dict[str, threading.Lock] = {}  # one lock per dataset: jobs are threads
_GENERATING_LOCK = threading.Lock()


def generate(args, d: Data) -> None:
    """Write dataset `d` (to a temporary name, renamed when complete), once even when
    several jobs ask for it at the same time (a source's coverage data)."""
    with _GENERATING_LOCK:
        lock = _GENERATING.setdefault(d.name, threading.Lock())
    with lock:
        _generate(args, d)


def _generate(args, d: Data) -> None:
    path = data_path(args, d)
    if path.is_file():
        return
    args.data.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f"{d.name}.partial.h5")
    tmp.unlink(missing_ok=True)
    if d.system == "grid":
        from power_grid import make_dataset

        make_dataset(tmp, nodes=d.nodes, trajectories=d.k, seed=d.seed,
                     graph_seed=d.graph_seed, graphs=d.graphs, split=d.fractions())
    else:
        head = (("--system-file", PLUGINS[d.system]) if d.system in PLUGINS
                else (d.system,))
        extra = [x for key, v in d.params for x in ("-p", f"{key}={v:g}")]
        split = ("--split", d.fractions()) if d.counts else ()
        hubs = ("--hubs", d.hubs, "--hub-multiplicity", d.multiplicity) if d.hubs else ()
        mpnode("generate", *head, "--nodes", d.nodes, "--topology", d.topology,
               "--trajectories", d.k, "--graphs", d.graphs, "--graph-seed", d.graph_seed,
               "--seed", d.seed, *extra, *split, *hubs, "--threads", 1, "--out", tmp, "-y",
               log=args.data / f"{d.name}.log")
    tmp.replace(path)


# ------------------------------------------------------------------------------ jobs


def job_name(args, bench: Bench, seed: int, what: str) -> str:
    return f"{bench.key}/{args.variant}/s{seed}/{what}"


def record_path(args, name: str) -> Path:
    return args.runs / f"{name}.json"


def read_record(args, name: str) -> dict[str, Any]:
    return json.loads(record_path(args, name).read_text())


def base_record(args, bench: Bench, seed: int, kind: str, label: str,
                d: Data) -> dict[str, Any]:
    what = kind if kind == "source" else f"{kind}-{label}"
    return {"job": job_name(args, bench, seed, what), "kind": kind,
            "protocol": bench.protocol, "system": bench.system, "set": set_of(bench.system),
            "gamma": bench.gamma, "variant": args.variant, "seed": seed, "label": label,
            "dataset": d.name, "nodes": d.nodes, "trajectories": d.split(),
            "scale": args.scale, "date": datetime.now().isoformat(timespec="seconds"),
            "commit": git_commit()}


def run_state(run: Path) -> tuple[int, int, float]:
    """(epochs done, best epoch, training seconds) of a run, from its `metrics.jsonl`:
    the best epoch is the first of the lowest validation loss, as `mpnode train` keeps."""
    rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    best, best_loss = 0, math.inf
    for row in rows:
        loss = row.get("val_loss")
        if loss is not None and math.isfinite(loss) and loss < best_loss:
            best, best_loss = row["epoch"], loss
    return rows[-1]["epoch"], best, sum(r.get("seconds") or 0.0 for r in rows)


def stop_reason(epochs: int, best: int, seconds: float, floor: float, patience: int,
                cap_seconds: float, cap_epochs: int) -> str | None:
    """Why an oracle stops now: "patience" (no better validation for `patience` epochs,
    after at least `floor` seconds, the source's wall time), "time cap", "epoch cap";
    None: train on."""
    if seconds >= floor and epochs - best >= patience:
        return "patience"
    if seconds >= cap_seconds:
        return "time cap"
    if epochs >= cap_epochs:
        return "epoch cap"
    return None


def oracle_chunk(patience: int) -> int:
    """Epochs an oracle trains per resume once past the source's wall time."""
    return max(2, math.ceil(patience / 4))


def train_source(args, bench: Bench, seed: int) -> dict[str, Any]:
    """Train the source model and write its record. A run cut off before its record was
    written (it has a last checkpoint) resumes to its epochs, which continues it exactly
    (one that reached them is only recorded); any other leftover folder starts afresh."""
    name = job_name(args, bench, seed, "source")
    run = args.runs / name
    resume = (run / "checkpoints" / "last.pt").is_file() and (run / "metrics.jsonl").is_file()
    if not resume:
        shutil.rmtree(run, ignore_errors=True)
    run.parent.mkdir(parents=True, exist_ok=True)
    clock: dict[str, float] = {}
    extra: dict[str, Any] = {}
    options: tuple[Any, ...] = VARIANTS[args.variant]
    if args.variant in FOR_GRAPHS_VARIANTS:  # the CLI makes the coverage data itself
        options = tuple(x for d in bench.targets.values()
                        for x in ("--for-graphs", data_path(args, d)))
    budget: tuple[Any, ...] = ("--epochs", source_epochs(args, bench))
    if resume:
        if run_state(run)[0] < budget[1]:
            mpnode("train", "--resume", run, *budget[:2], "--no-plots",
                   log=run.parent / "log.txt", clock=clock)
    else:
        mpnode("train", data_path(args, bench.source), *budget, "--seed", seed,
               "--run-dir", run, "--no-plots", "--threads", 1, *options,
               log=run.parent / "log.txt", clock=clock)
    summary = json.loads((run / "summary.json").read_text())
    if args.variant in FOR_GRAPHS_VARIANTS:
        made = json.loads((run / "config.json").read_text())["coverage"]
        extra = {"coverage": made["dataset"], "coverage_multiplicity": made["multiplicity"],
                 "targets_max_in_degree": made["max_in_degree"]}
    epochs, best, seconds = run_state(run)
    record = {**base_record(args, bench, seed, "source", "own", bench.source),
              "epochs": epochs, "best_epoch": best, "train_seconds": seconds,
              "cpu_seconds": clock.get("cpu"), "process_seconds": clock.get("wall"),
              "model": summary["model"], "options": list(VARIANTS[args.variant]), **extra}
    write_json(record_path(args, name), record)
    return record


def source_epochs(args, bench: Bench) -> int:
    """The epochs a source trains for (at most, for a variant that stops early): the
    system's, or for `--for-graphs` the recipe's, its patience kept."""
    return ORACLE_EPOCHS[args.scale] if args.variant in FOR_GRAPHS_VARIANTS else bench.epochs


def train_oracle(args, bench: Bench, seed: int, label: str) -> dict[str, Any]:
    """Train the oracle of one target (resuming a run cut off before), score it on the
    target's test split, and write its record.

    It trains for at least the source's wall time, then in chunks of a quarter of the
    patience, until its best validation is `--oracle-patience` epochs old or a cap is hit
    (`stop_reason`); `mpnode train --stop-patience` cannot say "not before", so the run
    itself gets a patience it never reaches. The oracle of a cosine schedule trains in one
    run, to its epoch cap or its time cap: resuming it with fewer epochs would shorten the
    schedule."""
    d, name = bench.targets[label], job_name(args, bench, seed, f"oracle-{label}")
    floor = read_record(args, job_name(args, bench, seed, "source"))["train_seconds"]
    run, log = args.runs / name, args.runs / name.rsplit("/", 1)[0] / "log.txt"
    cap_s, cap_e = args.oracle_cap * floor, ORACLE_EPOCHS[args.scale]
    chunk, clock = oracle_chunk(args.oracle_patience), {}
    whole = "cosine" in VARIANTS[args.variant]
    first_limit = cap_s if whole else floor
    if not (run / "checkpoints" / "last.pt").is_file():
        shutil.rmtree(run, ignore_errors=True)
        mpnode("train", data_path(args, d), "--epochs", cap_e, "--time-limit", first_limit,
               "--stop-patience", NEVER, "--seed", seed, "--run-dir", run, "--no-plots",
               "--threads", 1, *VARIANTS[args.variant], log=log, clock=clock)
    reason = None
    for _ in range(MAX_STAGES):
        epochs, best, seconds = run_state(run)
        reason = stop_reason(epochs, best, seconds, floor, args.oracle_patience, cap_s, cap_e)
        if reason:
            break
        target = cap_e if seconds < floor or whole else min(epochs + chunk, cap_e)
        mpnode("train", "--resume", run, "--epochs", target, "--time-limit",
               floor if seconds < floor and not whole else cap_s, "--no-plots", log=log,
               clock=clock)
        if run_state(run)[0] == epochs:
            reason = "stalled"
            break
    epochs, best, seconds = run_state(run)
    result = score_in_worker(run / "checkpoints" / "best.pt", data_path(args, d), None, log)
    record = {**base_record(args, bench, seed, "oracle", label, d), "epochs": epochs,
              "best_epoch": best, "train_seconds": seconds, "source_seconds": floor,
              "stopped_by": reason or "stages", "patience": args.oracle_patience,
              "cap_seconds": cap_s, "cap_epochs": cap_e, "cpu_seconds": clock.get("cpu"),
              "process_seconds": clock.get("wall"), "score": result}
    write_json(record_path(args, name), record)
    return record


def zeroshot(args, bench: Bench, seed: int, label: str) -> dict[str, Any]:
    """Score the source model on a target's test split ("own": its own) and write it."""
    d = bench.source if label == "own" else bench.targets[label]
    name = job_name(args, bench, seed, f"zeroshot-{label}")
    source = args.runs / job_name(args, bench, seed, "source")
    result = score_in_worker(source / "checkpoints" / "best.pt", data_path(args, d), None,
                             source.parent / "log.txt")
    record = {**base_record(args, bench, seed, "zeroshot", label, d), "score": result}
    write_json(record_path(args, name), record)
    return record


def score_in_worker(checkpoint: Path, dataset: Path, range_from: Path | None,
                    log: Path) -> dict[str, Any]:
    """`transfer_score.score` in a process of its own, on one thread."""
    out = command([sys.executable, str(Path(__file__).resolve()), "--score", str(checkpoint),
                   str(dataset), str(range_from or "-")], log)
    return json.loads(out.strip().splitlines()[-1])


# ------------------------------------------------------------------------------ planning


def bench_jobs(args, bench: Bench, seed: int) -> list[Job]:
    """The jobs of one bench and seed: its datasets, source, oracles and scorings."""
    src = bench.source
    per_epoch, epochs = epoch_seconds(bench.system, src, src), source_epochs(args, bench)
    train_s = epochs * per_epoch * curriculum_share(bench.system, epochs)
    source = job_name(args, bench, seed, "source")
    jobs = [Job(f"gen:{d.name}", bench.system, generate_seconds(d), (),
                lambda d=d: generate(args, d), lambda d=d: data_path(args, d).is_file())
            for d in (src, *bench.targets.values())]

    def recorded(name: str) -> Callable[[], bool]:
        return lambda: record_path(args, name).is_file()

    needs = (f"gen:{src.name}",) + (tuple(f"gen:{d.name}" for d in bench.targets.values())
                                     if args.variant in FOR_GRAPHS_VARIANTS else ())
    jobs.append(Job(source, bench.system, train_s + PROCESS_SECONDS, needs,
                    lambda: train_source(args, bench, seed), recorded(source)))
    for label, d in {"own": src, **bench.targets}.items():
        name = job_name(args, bench, seed, f"zeroshot-{label}")
        jobs.append(Job(name, bench.system, EVAL_SECONDS, (source, f"gen:{d.name}"),
                        lambda label=label: zeroshot(args, bench, seed, label),
                        recorded(name)))
        if label == "own" or args.no_oracles:
            continue
        name = job_name(args, bench, seed, f"oracle-{label}")
        oracle_epoch = epoch_seconds(bench.system, d, src)
        expected = max(train_s, (bench.epochs + args.oracle_patience) * oracle_epoch)
        chunk = oracle_chunk(args.oracle_patience)
        stages = math.ceil(max(0.0, expected - train_s) / oracle_epoch / chunk)
        seconds = expected + (1 + stages) * PROCESS_SECONDS + EVAL_SECONDS
        jobs.append(Job(name, bench.system, seconds, (source, f"gen:{d.name}"),
                        lambda label=label: train_oracle(args, bench, seed, label),
                        recorded(name), cap=max(seconds, args.oracle_cap * train_s
                                                + (2 + stages) * PROCESS_SECONDS)))
    return jobs


def all_jobs(args) -> dict[str, Job]:
    """Every job the filters select, datasets shared between benches once."""
    smoke = args.scale == "smoke"
    jobs: dict[str, Job] = {}
    for seed in args.seeds:
        for system in args.systems:
            benches = []
            if args.only_protocol in (None, "size"):
                benches.append(size_bench(system, smoke))
            if system in BB and args.only_protocol in (None, "s1"):
                benches += [s1_bench(system, g, seed, smoke, args.n8192) for g in args.gammas]
            for bench in benches:
                if args.targets:  # the "own" scoring stays; only the chosen targets
                    bench = replace(bench, targets={label: d for label, d in
                                                    bench.targets.items()
                                                    if label in args.targets})
                for job in bench_jobs(args, bench, seed):
                    jobs.setdefault(job.name, job)
    return jobs


def plan(args, jobs: dict[str, Job]) -> str:
    """Core-hours per system, per set and in all (expected; the oracles' caps in
    brackets), what is left of them, and the wall time on `--jobs` workers."""
    def hours(selected: list[Job], left: bool = False) -> tuple[float, float]:
        chosen = [j for j in selected if not (left and j.done())]
        return (sum(j.seconds for j in chosen) / 3600,
                sum(j.cap or j.seconds for j in chosen) / 3600)

    lines = [f"{'core-hours':18s} {'jobs':>5s} {'expected':>9s} {'(cap)':>8s} {'left':>8s}"]

    def line(label: str, selected: list[Job]) -> None:
        exp, cap = hours(selected)
        lines.append(f"{label:18s} {len(selected):5d} {exp:9.2f} {cap:8.2f} "
                     f"{hours(selected, left=True)[0]:8.2f}")

    for system in args.systems:
        line(system, [j for j in jobs.values() if j.system == system])
    for name, members in SETS.items():
        line(f"set {name}", [j for j in jobs.values() if j.system in members])
    line("total", list(jobs.values()))
    left = {n: (j.seconds, tuple(d for d in j.deps if d in jobs and not jobs[d].done()))
            for n, j in jobs.items() if not j.done()}
    lines.append(f"wall time left on {args.jobs} workers (one thread each): about "
                 f"{schedule(left, args.jobs) / 3600:.2f} h (expected; oracles may run up to "
                 f"their caps, {args.oracle_cap:g}× their source's wall time)")
    return "\n".join(lines)


# ------------------------------------------------------------------------------ running


def run_jobs(args, jobs: dict[str, Job], report: Callable[[str], None]) -> list[str]:
    """Run the jobs not done yet, `--jobs` at a time, each when its dependencies are done
    (highest `priorities` first); a failed job's dependents are skipped. Returns the
    failures."""
    done = {n for n, j in jobs.items() if j.done()}
    rank = priorities({n: (j.seconds, j.deps) for n, j in jobs.items()})
    pending = sorted((n for n in jobs if n not in done), key=lambda n: -rank[n])
    failed: list[str] = []
    broken: set[str] = set()
    running: dict[Any, str] = {}
    with ThreadPoolExecutor(args.jobs) as pool:
        while pending or running:
            for name in list(pending):
                deps = jobs[name].deps
                if any(d in broken for d in deps):
                    pending.remove(name)
                    broken.add(name)
                    failed.append(f"{name}: skipped (a dependency failed)")
                elif len(running) < args.jobs and all(d in done for d in deps):
                    pending.remove(name)
                    running[pool.submit(jobs[name].work)] = name
                    report(f"start {name}")
            if not running:
                break
            finished, _ = wait(running, return_when=FIRST_COMPLETED)
            for future in finished:
                name = running.pop(future)
                try:
                    future.result()
                    done.add(name)
                    report(f"done  {name}")
                except Exception as exc:  # one broken job must not stop the others
                    broken.add(name)
                    failed.append(f"{name}: {exc}")
                    report(f"FAIL  {name}: {exc}")
                if not name.startswith("gen:"):
                    report(write_table(args))
    return failed


def write_table(args) -> str:
    return rebuild(args.runs, args.records, args.out, args.note)


# ------------------------------------------------------------------------------ main


def parse(argv) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--set", choices=(*SETS, "all"), default="all")
    p.add_argument("--systems", help=f"comma-separated, of {','.join(SYSTEMS)} "
                   "(default: the set's)")
    p.add_argument("--seeds", default="0,1,2", help="training seeds, comma-separated")
    p.add_argument("--gammas", default=",".join(map(str, GAMMAS)), help="S¹ γ values")
    p.add_argument("--only-protocol", choices=("size", "s1"))
    p.add_argument("--n8192", action="store_true", help="S¹: also zero-shot on 8192 nodes")
    p.add_argument("--targets", type=lambda s: set(s.split(",")), default=None,
                   help="only these targets, comma-separated labels (x2, x4, other, n1024, "
                   "n4096, n8192; default: all)")
    p.add_argument("--variant", choices=VARIANTS, default="default")
    p.add_argument("--no-oracles", action="store_true", help="train no oracles: a variant's "
                   "zero-shot rows are then set against the default variant's oracles")
    p.add_argument("--jobs", type=int, default=2, help="parallel workers, one thread each")
    p.add_argument("--scale", choices=("full", "smoke"), default="full")
    p.add_argument("--smoke", action="store_const", const="smoke", dest="scale")
    p.add_argument("--oracle-patience", type=int, help="epochs without a better validation "
                   "that stop an oracle (default 200, the recipe's --stop-patience; smoke 2)")
    p.add_argument("--oracle-cap", type=float, help="an oracle stops at this many times "
                   "its source's wall time (default 8; smoke 3)")
    p.add_argument("--data", type=Path)
    p.add_argument("--runs", type=Path)
    p.add_argument("--out", type=Path, help="the table (default bench/results/transfer.md)")
    p.add_argument("--records", type=Path, help="the committed copy of the records")
    p.add_argument("--plan", action="store_true", help="print the estimate and stop")
    p.add_argument("--allow-dirty", action="store_true", help="run from a tree with "
                   "uncommitted changes (its records say +dirty; refused by default)")
    p.add_argument("--table-only", action="store_true", help="rebuild the table and stop")
    p.add_argument("--note", default="", help="a sentence for the table's header")
    p.add_argument("--in-range", nargs=2, type=Path, metavar=("CHECKPOINT", "DATASET"),
                   help="print a zero-shot error split by nodes in and out of the training "
                   "range (JSON; transfer_score.in_range_report), and stop")
    p.add_argument("--score", nargs=3, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    smoke = args.scale == "smoke"
    tail = "transfer-smoke" if smoke else "transfer"
    args.data = (args.data or HERE / ".data" / tail).resolve()
    args.runs = (args.runs or HERE / ".runs" / tail).resolve()
    results = args.runs if smoke else HERE / "results"  # a smoke run's never replace these
    args.out = args.out or results / "transfer.md"
    args.records = args.records or results / "transfer.json"
    if args.oracle_patience is None:
        args.oracle_patience = 2 if smoke else 200
    if args.oracle_cap is None:
        args.oracle_cap = 3.0 if smoke else 8.0
    members = SYSTEMS if args.set == "all" else SETS[args.set]
    args.systems = args.systems.split(",") if args.systems else list(members)
    if unknown := [s for s in args.systems if s not in SYSTEMS]:
        p.error(f"unknown system {', '.join(unknown)} (of {', '.join(SYSTEMS)})")
    args.seeds = [int(s) for s in args.seeds.split(",")]
    args.gammas = [float(g) for g in args.gammas.split(",")]
    return args


def main(argv=None) -> int:
    args = parse(argv)
    if args.score:
        from transfer_score import score

        ckpt, data, range_from = args.score
        print(json.dumps(score(Path(ckpt), Path(data),
                               None if range_from == "-" else Path(range_from))))
        return 0
    if args.in_range:
        from transfer_score import in_range_report

        print(json.dumps(in_range_report(*args.in_range)))
        return 0
    if args.table_only:
        print(write_table(args))
        return 0
    jobs = all_jobs(args)
    print(plan(args, jobs), flush=True)
    if args.plan:
        return 0
    if git_commit().endswith("+dirty") and not args.allow_dirty and args.scale == "full":
        print("the working tree has uncommitted changes: records must come from committed "
              "code (commit, or run from a clean worktree; --allow-dirty marks its records "
              "and keeps them out of the README)", file=sys.stderr)
        return 2

    def report(line: str) -> None:
        print(f"[{time.strftime('%H:%M:%S')}] {line}", flush=True)

    failed = run_jobs(args, jobs, report)
    report(write_table(args))
    for line in failed:
        report(f"not done: {line}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
