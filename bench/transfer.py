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
(`transfer_score.score`). The jobs run on the experiments' engine
(`mpnode_cli.experiments.jobs`): each in its folder under `--runs`, its record in the
folder's `step.json`; a rerun skips finished jobs and resumes cut-off trainings; a failed
job skips those that need it, not the others. The table (`bench/results/transfer.md`) and
the committed copy of the records (`bench/results/transfer.json`) are rebuilt from the
records alone.

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
import re
import shutil
import sys
import time
from dataclasses import asdict, replace
from datetime import datetime
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(HERE), str(HERE.parent)]  # the benches, then this checkout's package

from quality import ROOT, command, git_commit, mpnode  # noqa: E402
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
from transfer_table import rebuild  # noqa: E402

from mpnode_cli.experiments import jobs  # noqa: E402
from mpnode_cli.experiments.spec import CallStep  # noqa: E402

PLUGINS = {"fhn": ROOT / "examples" / "fitzhugh_nagumo.py",  # systems of a plug-in file
           "mutualistic": ROOT / "examples" / "mutualistic.py"}
NEVER = 10**9  # `--stop-patience` of an oracle run: the bench applies the patience itself
MAX_STAGES = 400  # resumes of one oracle at most
ORACLE_EPOCHS = {"full": 4000, "smoke": 40}  # an oracle's epoch cap (the recipe's epochs)


DATA = "data.h5"  # a dataset step's file in its folder


# ------------------------------------------------------------------------------ jobs
# Each job is a `CallStep` of the experiments' engine (`mpnode_cli.experiments.jobs`): a
# function below with JSON arguments, run in its own folder under `--runs`, recorded in its
# `step.json`. A job rebuilds its bench from `bench_spec` and reads its datasets from the
# folders of the dataset steps it needs.


def step_id(name: str) -> str:
    """A job's name as a step id (lower case letters, digits and dashes)."""
    return re.sub(r"[^a-z0-9]+", "-", name.lower()).strip("-")


def bench_spec(args, bench: Bench, seed: int) -> dict[str, Any]:
    return {"system": bench.system, "protocol": bench.protocol, "gamma": bench.gamma,
            "seed": seed, "smoke": args.scale == "smoke", "largest": args.n8192,
            "targets": sorted(bench.targets)}


def bench_of(spec: dict[str, Any]) -> Bench:
    if spec["protocol"] == "size":
        bench = size_bench(spec["system"], spec["smoke"])
    else:
        bench = s1_bench(spec["system"], spec["gamma"], spec["seed"], spec["smoke"],
                         spec["largest"])
    return replace(bench, targets={k: v for k, v in bench.targets.items()
                                   if k in spec["targets"]})


def settings(args) -> dict[str, Any]:
    """What a job reads of the command line (and its fingerprint hashes)."""
    return {"variant": args.variant, "scale": args.scale,
            "oracle_patience": args.oracle_patience, "oracle_cap": args.oracle_cap}


def data_of(value: dict[str, Any]) -> Data:
    params = tuple((k, float(v)) for k, v in value["params"])
    counts = tuple(value["counts"]) if value["counts"] else None
    return Data(**{**value, "params": params, "counts": counts})


def data_path(inputs: dict[str, Any], d: Data) -> Path:
    return Path(inputs[gen_id(d)].folder) / DATA


def gen_id(d: Data) -> str:
    return "gen-" + step_id(d.name)


def job_generate(folder: Path, inputs, resumed: bool, data: dict[str, Any]) -> dict[str, Any]:
    """Write a dataset into the job's folder (to a temporary name, renamed when complete)."""
    d = data_of(data)
    path, tmp, log = folder / DATA, folder / "partial.h5", folder / "log.txt"
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
               log=log)
    tmp.replace(path)
    return {"dataset": d.name}


def job_name(args, bench: Bench, seed: int, what: str) -> str:
    return f"{bench.key}/{args.variant}/s{seed}/{what}"


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


def job_source(folder: Path, inputs, resumed: bool, bench: dict[str, Any], seed: int,
               run: dict[str, Any]) -> dict[str, Any]:
    """Train the source model in `folder/run` and return its record. A run cut off before
    its record was written (it has a last checkpoint) resumes to its epochs, which continues
    it exactly (one that reached them is only recorded)."""
    args, bench_ = argparse.Namespace(**run), bench_of(bench)
    train_dir, log = folder / "run", folder / "log.txt"
    resume = (train_dir / "checkpoints" / "last.pt").is_file() and \
        (train_dir / "metrics.jsonl").is_file()
    if not resume:
        shutil.rmtree(train_dir, ignore_errors=True)
    clock: dict[str, float] = {}
    extra: dict[str, Any] = {}
    options: tuple[Any, ...] = VARIANTS[args.variant]
    if args.variant in FOR_GRAPHS_VARIANTS:  # the CLI makes the coverage data itself
        options = tuple(x for d in bench_.targets.values()
                        for x in ("--for-graphs", data_path(inputs, d)))
    budget: tuple[Any, ...] = ("--epochs", source_epochs(args, bench_))
    if resume:
        if run_state(train_dir)[0] < budget[1]:
            mpnode("train", "--resume", train_dir, *budget[:2], "--no-plots", log=log,
                   clock=clock)
    else:
        mpnode("train", data_path(inputs, bench_.source), *budget, "--seed", seed,
               "--run-dir", train_dir, "--no-plots", "--threads", 1, *options, log=log,
               clock=clock)
    summary = json.loads((train_dir / "summary.json").read_text())
    if args.variant in FOR_GRAPHS_VARIANTS:
        made = json.loads((train_dir / "config.json").read_text())["coverage"]
        extra = {"coverage": made["dataset"], "coverage_multiplicity": made["multiplicity"],
                 "targets_max_in_degree": made["max_in_degree"]}
    epochs, best, seconds = run_state(train_dir)
    return {**base_record(args, bench_, seed, "source", "own", bench_.source),
            "epochs": epochs, "best_epoch": best, "train_seconds": seconds,
            "cpu_seconds": clock.get("cpu"), "process_seconds": clock.get("wall"),
            "model": summary["model"], "options": list(VARIANTS[args.variant]), **extra}


def source_epochs(args, bench: Bench) -> int:
    """The epochs a source trains for (at most, for a variant that stops early): the
    system's, or for `--for-graphs` the recipe's, its patience kept."""
    return ORACLE_EPOCHS[args.scale] if args.variant in FOR_GRAPHS_VARIANTS else bench.epochs


def job_oracle(folder: Path, inputs, resumed: bool, bench: dict[str, Any], seed: int,
               run: dict[str, Any], label: str, source: str) -> dict[str, Any]:
    """Train the oracle of one target in `folder/run` (resuming a run cut off before),
    score it on the target's test split, and return its record.

    It trains for at least the source's wall time (`source`: the source job's step), then
    in chunks of a quarter of the patience, until its best validation is
    `--oracle-patience` epochs old or a cap is hit (`stop_reason`); `mpnode train
    --stop-patience` cannot say "not before", so the run itself gets a patience it never
    reaches. The oracle of a cosine schedule trains in one run, to its epoch cap or its
    time cap: resuming it with fewer epochs would shorten the schedule."""
    args, bench_ = argparse.Namespace(**run), bench_of(bench)
    d = bench_.targets[label]
    floor = inputs[source].result["train_seconds"]
    train_dir, log = folder / "run", folder / "log.txt"
    cap_s, cap_e = args.oracle_cap * floor, ORACLE_EPOCHS[args.scale]
    chunk, clock = oracle_chunk(args.oracle_patience), {}
    whole = "cosine" in VARIANTS[args.variant]
    first_limit = cap_s if whole else floor
    if not (train_dir / "checkpoints" / "last.pt").is_file():
        shutil.rmtree(train_dir, ignore_errors=True)
        mpnode("train", data_path(inputs, d), "--epochs", cap_e, "--time-limit", first_limit,
               "--stop-patience", NEVER, "--seed", seed, "--run-dir", train_dir,
               "--no-plots", "--threads", 1, *VARIANTS[args.variant], log=log, clock=clock)
    reason = None
    for _ in range(MAX_STAGES):
        epochs, best, seconds = run_state(train_dir)
        reason = stop_reason(epochs, best, seconds, floor, args.oracle_patience, cap_s, cap_e)
        if reason:
            break
        target = cap_e if seconds < floor or whole else min(epochs + chunk, cap_e)
        mpnode("train", "--resume", train_dir, "--epochs", target, "--time-limit",
               floor if seconds < floor and not whole else cap_s, "--no-plots", log=log,
               clock=clock)
        if run_state(train_dir)[0] == epochs:
            reason = "stalled"
            break
    epochs, best, seconds = run_state(train_dir)
    result = score_in_worker(train_dir / "checkpoints" / "best.pt", data_path(inputs, d),
                             None, log)
    return {**base_record(args, bench_, seed, "oracle", label, d), "epochs": epochs,
            "best_epoch": best, "train_seconds": seconds, "source_seconds": floor,
            "stopped_by": reason or "stages", "patience": args.oracle_patience,
            "cap_seconds": cap_s, "cap_epochs": cap_e, "cpu_seconds": clock.get("cpu"),
            "process_seconds": clock.get("wall"), "score": result}


def job_zeroshot(folder: Path, inputs, resumed: bool, bench: dict[str, Any], seed: int,
                 run: dict[str, Any], label: str, source: str) -> dict[str, Any]:
    """Score the source model (`source`: its job's step) on a target's test split ("own":
    its own) and return the record."""
    args, bench_ = argparse.Namespace(**run), bench_of(bench)
    d = bench_.source if label == "own" else bench_.targets[label]
    best = Path(inputs[source].folder) / "run" / "checkpoints" / "best.pt"
    result = score_in_worker(best, data_path(inputs, d), None, folder / "log.txt")
    return {**base_record(args, bench_, seed, "zeroshot", label, d), "score": result}


def score_in_worker(checkpoint: Path, dataset: Path, range_from: Path | None,
                    log: Path) -> dict[str, Any]:
    """`transfer_score.score` in a process of its own, on one thread."""
    out = command([sys.executable, str(Path(__file__).resolve()), "--score", str(checkpoint),
                   str(dataset), str(range_from or "-")], log)
    return json.loads(out.strip().splitlines()[-1])


# ------------------------------------------------------------------------------ planning


def bench_steps(args, bench: Bench, seed: int) -> list[CallStep]:
    """The jobs of one bench and seed: its datasets, source, oracles and scorings."""
    src, spec, run = bench.source, bench_spec(args, bench, seed), settings(args)
    per_epoch, epochs = epoch_seconds(bench.system, src, src), source_epochs(args, bench)
    train_s = epochs * per_epoch * curriculum_share(bench.system, epochs)
    source = step_id(job_name(args, bench, seed, "source"))
    steps = [CallStep(verb="call", id=gen_id(d), target="transfer:job_generate",
                      args={"data": asdict(d)}, seconds=generate_seconds(d),
                      group=bench.system)
             for d in (src, *bench.targets.values())]
    needs = [gen_id(src)] + ([gen_id(d) for d in bench.targets.values()]
                             if args.variant in FOR_GRAPHS_VARIANTS else [])
    steps.append(CallStep(verb="call", id=source, target="transfer:job_source",
                          args={"bench": spec, "seed": seed, "run": run}, needs=needs,
                          seconds=train_s + PROCESS_SECONDS, group=bench.system))
    for label, d in {"own": src, **bench.targets}.items():
        job = {"bench": spec, "seed": seed, "run": run, "label": label, "source": source}
        steps.append(CallStep(
            verb="call", id=step_id(job_name(args, bench, seed, f"zeroshot-{label}")),
            target="transfer:job_zeroshot", args=job, needs=[source, gen_id(d)],
            seconds=EVAL_SECONDS, group=bench.system))
        if label == "own" or args.no_oracles:
            continue
        oracle_epoch = epoch_seconds(bench.system, d, src)
        expected = max(train_s, (bench.epochs + args.oracle_patience) * oracle_epoch)
        stages = math.ceil(max(0.0, expected - train_s) / oracle_epoch
                           / oracle_chunk(args.oracle_patience))
        seconds = expected + (1 + stages) * PROCESS_SECONDS + EVAL_SECONDS
        steps.append(CallStep(
            verb="call", id=step_id(job_name(args, bench, seed, f"oracle-{label}")),
            target="transfer:job_oracle", args=job, needs=[source, gen_id(d)],
            seconds=seconds, group=bench.system,
            cap=max(seconds, args.oracle_cap * train_s + (2 + stages) * PROCESS_SECONDS)))
    return steps


def all_steps(args) -> list[CallStep]:
    """Every job the filters select, datasets shared between benches once."""
    smoke = args.scale == "smoke"
    steps: dict[str, CallStep] = {}
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
                for step in bench_steps(args, bench, seed):
                    steps.setdefault(step.id, step)
    return list(steps.values())


def plan(args, steps: list[CallStep]) -> str:
    return (jobs.plan(steps, args.runs, args.jobs, SETS) + f" (oracles may run up to their "
            f"caps, {args.oracle_cap:g}× their source's wall time)")


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
    steps = all_steps(args)
    print(plan(args, steps), flush=True)
    if args.plan:
        return 0
    if git_commit().endswith("+dirty") and not args.allow_dirty and args.scale == "full":
        print("the working tree has uncommitted changes: records must come from committed "
              "code (commit, or run from a clean worktree; --allow-dirty marks its records "
              "and keeps them out of the README)", file=sys.stderr)
        return 2

    def report(line: str) -> None:
        print(f"[{time.strftime('%H:%M:%S')}] {line}", flush=True)

    def done(step: str) -> None:  # the table after every job but a dataset's
        if not step.startswith("gen-"):
            report(write_table(args))

    failed = jobs.run_jobs(steps, args.runs, args.jobs, jobs.reporter(report, done))
    report(write_table(args))
    for name, why in failed.items():
        report(f"not done: {name}: {why}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
