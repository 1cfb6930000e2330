"""Quality benchmark: the paper's experiments at fixed epoch budgets, against naive baselines.

Each case trains one model with `mpnode train` (the CLI's defaults, plus only the options the
case is about), then measures it with `mpnode evaluate` / `mpnode zeroshot`, and reports
every MSE (normalized, t₀ excluded) beside two naive predictors on the same trajectories:
hold x(0) and the train split's time mean (`mpnode_cli.training.evaluate.baseline_mse`).

Cases (Gupta et al. 2022; paper numbers from Table 1):
- gene-ba-{mean,sum,pna}: MP-NODE on gene-ba-4x4 with each aggregation; BA validation and
  test MSE, zero-shot on gene-er-4x4 and gene-ws-4x4 (all their trajectories).
- gene-ba-l2s, gene-ba-gnode: the baselines on the same data at equal wall time: each trains
  for `GENE_EQUAL_SECONDS`, and is compared with the best validation MSE the MP-NODE run
  with the CLI's default aggregation reached within its first `GENE_EQUAL_SECONDS` of
  training (read from its `metrics.jsonl`; every gene-ba-* case reports that row). `mpnode
  train` has no time limit, so a baseline first trains a few epochs, and is then resumed
  (`--resume`, which continues exactly) in stages towards the budget, each stage sized by
  the seconds per epoch of the latest epochs (`epochs_to_budget`).
  L2S is CI-sized as in `bench/baselines.sh`: latent and hidden 32, 5 message-passing steps.
- pendulum-messages, pendulum-no-messages: the §4.1 ablation; the messages-on model is also
  evaluated with its messages zeroed at test time (Fig. 3b). The CLI has no switch for
  that, so it is done through the library: the checkpoint's model config gets
  `messages=False` (same weights) and `evaluate_checkpoint` runs it.
- kuramoto-m{1,3,7,13}: message dimensions on kuramoto10-ba (Fig. 8).
- lorenz3: trained on lorenz3, zero-shot on lorenz7 and lorenz10 (Fig. 11).
- quad3-mpnode, quad3-l2s: the 3-quadrotor swarm, L2S (CI-sized) at MP-NODE's wall time.

Verdict targets: gene BA test ≤ 0.0045 and ER/WS zero-shot ≤ 0.0051; MP-NODE's BA
validation MSE below L2S's at equal wall time; pendulum test ≤ 0.05 with messages and ≥ 3×
worse without; every MP-NODE test or zero-shot MSE ≥ 20× below hold x(0) and ≥ 5× below
the time mean.

Cases run as subprocesses on the experiments' engine (`mpnode_cli.experiments.jobs`),
`--workers` (2) at a time, each on one thread (OMP_NUM_THREADS=1): each dataset and each
case is a job in its folder under `--runs`, its result in the folder's `step.json`. A case
that ran with the same options is not run again, so `--only` refreshes some rows, and the
table is rebuilt from every recorded case.

Usage:
    .venv/bin/python bench/quality.py                       # all cases (see --plan for time)
    .venv/bin/python bench/quality.py --plan                # the time estimate only
    .venv/bin/python bench/quality.py --only lorenz3,pendulum-messages
    .venv/bin/python bench/quality.py --scale 0.003 --out /tmp/quality.md   # smoke
Writes `bench/results/quality.md`.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))  # this checkout's package, before an installed one

from mpnode_cli.experiments import jobs  # noqa: E402 (the engine the cases run on)
from mpnode_cli.experiments.spec import CallStep  # noqa: E402

RESULTS = HERE / "results" / "quality.md"
L2S_CI = ("--model", "l2s", "--latent", "32", "--hidden", "32", "--steps", "5")
GENE_AGGREGATES = ("mean", "sum", "pna")
TIMING_EPOCHS = 3  # epochs an equal-time case trains to measure its seconds per epoch
BUDGET_STAGES = 16  # at most this many resumes to fill an equal-time budget
BUDGET_STAGE_SHARE = 0.6  # share of the budget left that one resume aims at
GENE_EQUAL_SECONDS = 300.0  # the gene baselines' training budget (× --scale)


@dataclass(frozen=True)
class Case:
    """One training run and the measurements made on it.

    Attributes:
        preset: the training dataset (`mpnode generate --preset`).
        epochs: the epoch budget at `--scale 1` (an equal-time case: its estimate only).
        options: `mpnode train` options beyond the CLI's defaults: what the case is about.
        val: also report the validation MSE of the best checkpoint.
        zeroshot: presets to run the trained model on, without training.
        equal_time: a case's wall time is this case's budget; "gene-default" means the
            gene-ba case with the CLI's default aggregation.
        budget: a fixed wall-time budget in seconds (× --scale) instead; `equal_time` then
            only names the case it is compared with.
        zeroed: also evaluate with messages zeroed at test time.
        paper: measure → the paper's number.
        s_per_epoch: planning estimate: seconds per epoch (validation included) alone on
            one core of the 2-core machine the results were taken on, from the first epochs
            of each case (CPU time, as the machine was busy) and, where the learned dynamics
            stiffen during training (pendulum, kuramoto, lorenz), the growth of solver
            steps seen in longer runs.
        note: said in the table's notes.
    """

    name: str
    preset: str
    epochs: int
    options: tuple[str, ...] = ()
    val: bool = False
    zeroshot: tuple[str, ...] = ()
    equal_time: str | None = None
    budget: float | None = None
    zeroed: bool = False
    paper: dict[str, float] = field(default_factory=dict)
    s_per_epoch: float = 1.0
    note: str = ""


GENE_PAPER = {"val": 0.0051, "test": 0.0045, "gene-er-4x4": 0.0026, "gene-ws-4x4": 0.0023}
CASES = {c.name: c for c in [
    *(Case(f"gene-ba-{agg}", "gene-ba-4x4", 500, ("--aggregate", agg), val=True,
           zeroshot=("gene-er-4x4", "gene-ws-4x4"), paper=GENE_PAPER,
           s_per_epoch={"mean": 0.91, "sum": 0.75, "pna": 0.71}[agg])
      for agg in GENE_AGGREGATES),
    Case("gene-ba-l2s", "gene-ba-4x4", 26, L2S_CI, val=True, equal_time="gene-default",
         budget=GENE_EQUAL_SECONDS, paper={"val": 0.0106}, s_per_epoch=11.8,
         note="L2S CI-sized (latent/hidden 32, 5 steps), trained for the same wall time as "
              "the default-aggregation MP-NODE gene run's 'val within' row; the paper's L2S "
              "is full size."),
    Case("gene-ba-gnode", "gene-ba-4x4", 1300, ("--model", "gnode"), val=True,
         equal_time="gene-default", budget=GENE_EQUAL_SECONDS, s_per_epoch=1.0,
         note="GNN-ODE, trained for the same wall time as the default-aggregation MP-NODE "
              "gene run's 'val within' row."),
    Case("pendulum-messages", "pendulum", 150, zeroed=True, s_per_epoch=3.6,
         note="'messages zeroed at test': the same checkpoint with messages=False (library)."),
    Case("pendulum-no-messages", "pendulum", 150, ("--no-messages",), s_per_epoch=3.7),
    *(Case(f"kuramoto-m{m}", "kuramoto10-ba", 150, ("--message-dim", str(m)),
           s_per_epoch={1: 1.5, 3: 1.1, 7: 1.4, 13: 1.4}[m]) for m in (1, 3, 7, 13)),
    Case("lorenz3", "lorenz3", 200, zeroshot=("lorenz7", "lorenz10"), s_per_epoch=5.8),
    Case("quad3-mpnode", "quad3", 100, s_per_epoch=6.5),
    Case("quad3-l2s", "quad3", 320, L2S_CI, equal_time="quad3-mpnode", s_per_epoch=2.06,
         note="L2S CI-sized (latent/hidden 32, 5 steps), at MP-NODE's quad3 wall time."),
]}
# Seconds to generate each preset (one thread), for the plan.
GENERATE_SECONDS = {"quad3": 30.0, "lorenz10": 8.0, "kuramoto10-ba": 6.0, "pendulum": 6.0}
EVAL_SECONDS = 20.0  # a case's evaluations, zero-shot runs and process starts, for the plan


# ---------------------------------------------------------------------------- running cases


def env() -> dict[str, str]:
    """One thread per worker: the cases share 2 cores two at a time."""
    return {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
            "COLUMNS": "150", "PYTHONPATH": str(ROOT)}


def command(cmd: list[str], log: Path, clock: dict[str, float] | None = None) -> str:
    """Run `cmd` on one thread, appending its output to `log`; return its stdout.

    Args:
        clock: if given, its "cpu" and "wall" seconds grow by this process's. Their ratio
            is the share of a core the process got: on a busy machine wall times stretch,
            CPU times much less, so the report can say how loaded the run was.

    Raises:
        RuntimeError: a non-zero exit, with the last line it printed (the log has the rest).
    """
    start = time.perf_counter()
    with tempfile.TemporaryFile("w+") as out, open(log, "a") as err:
        err.write(f"$ {' '.join(cmd)}\n")
        err.flush()
        proc = subprocess.Popen(cmd, stdout=out, stderr=err, text=True, env=env(), cwd=ROOT)
        # wait4 rather than wait: it also returns the child's own CPU time.
        _, status, usage = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)
        out.seek(0)
        stdout = out.read()
        wall = time.perf_counter() - start
        err.write(f"{stdout}# exit {proc.returncode}, {wall:.1f} s wall, "
                  f"{usage.ru_utime + usage.ru_stime:.1f} s CPU\n\n")
    if clock is not None:
        clock["cpu"] = clock.get("cpu", 0.0) + usage.ru_utime + usage.ru_stime
        clock["wall"] = clock.get("wall", 0.0) + wall
    if proc.returncode != 0:
        tail = log.read_text().strip().splitlines()[-2:-1] or [""]
        raise RuntimeError(f"{' '.join(cmd[2:4])} exited {proc.returncode}: {tail[0]}")
    return stdout


def mpnode(*args: Any, log: Path, clock: dict[str, float] | None = None) -> str:
    """`mpnode ARGS` with this interpreter (see `command`)."""
    return command([sys.executable, "-m", "mpnode_cli.cli.app", *map(str, args)], log, clock)


def gen_id(preset: str) -> str:
    return f"gen-{preset}"


def dataset(inputs: dict[str, Any], preset: str) -> Path:
    """A preset's dataset, in the folder of the job that generated it."""
    return Path(inputs[gen_id(preset)].folder) / "data.h5"


def job_generate(folder: Path, inputs, resumed: bool, preset: str) -> dict[str, Any]:
    tmp = folder / "partial.h5"
    mpnode("generate", "--preset", preset, "--out", tmp, "-y", log=folder / "log.txt")
    tmp.replace(folder / "data.h5")
    return {"preset": preset}


def epochs_for(case: Case, scale: float) -> int:
    return max(1, round(case.epochs * scale))


def default_aggregate(data: Path, probe: Path) -> str:
    """The aggregation `mpnode train` picks for gene-ba-4x4 (`data`) when none is given (a
    1-epoch run in `probe` resolves the CLI's defaults)."""
    shutil.rmtree(probe, ignore_errors=True)
    probe.mkdir(parents=True)
    mpnode("train", data, "--epochs", 1, "--no-plots", "--run-dir",
           probe / "run", log=probe / "log")
    summary = json.loads((probe / "run" / "summary.json").read_text())
    shutil.rmtree(probe, ignore_errors=True)
    return summary["model_config"]["aggregate"]


def reference(case: Case, aggregate: str) -> str | None:
    """The case whose wall time is `case`'s budget."""
    if case.equal_time == "gene-default":
        return f"gene-ba-{aggregate}"
    return case.equal_time


def job_case(folder: Path, inputs, resumed: bool, case: str, scale: float,
             extra: list[str], ref: str | None) -> dict[str, Any]:
    """Train and measure one case in its job's folder, and return its result: at the wall
    time of `ref` (the case whose job it needs) where it takes its budget from one, else at
    its own budget or epochs."""
    case_ = CASES[case]
    args = argparse.Namespace(scale=scale, extra=extra)
    log, run = folder / "log.txt", folder / "run"
    shutil.rmtree(run, ignore_errors=True)
    budget = case_.budget * scale if case_.budget is not None else (
        inputs[step_id(ref)].result["wall_seconds"] if ref else None)
    if case_.equal_time == "gene-default":  # named for the report: the CLI's default's
        ref = reference(case_, default_aggregate(dataset(inputs, case_.preset),
                                                 folder / "probe"))
    result = run_case(args, case_, ref, budget, inputs, folder, log, run)
    return result


def run_case(args, case: Case, ref: str | None, budget: float | None, inputs,
             folder: Path, log: Path, run: Path) -> dict[str, Any]:
    """Train and measure one case (at `ref`'s wall time `budget`, if given) in `run`."""
    data = dataset(inputs, case.preset)
    started = time.perf_counter()
    common = ("--seed", 0, "--run-dir", run)
    options = [*case.options, *args.extra]
    clock: dict[str, float] = {}
    if budget is None:
        mpnode("train", data, "--epochs", epochs_for(case, args.scale), *common, *options,
               log=log, clock=clock)
    else:
        # Equal wall time: time a few epochs, then resume towards the budget in stages.
        timing = TIMING_EPOCHS if args.scale >= 1 else 1
        mpnode("train", data, "--epochs", timing, *common, *options, log=log, clock=clock)
        for _ in range(BUDGET_STAGES):
            more = epochs_to_budget(run, budget)
            if more < 1:
                break
            done = json.loads((run / "summary.json").read_text())["epochs"]
            mpnode("train", "--resume", run, "--epochs", done + more, log=log, clock=clock)
    summary = json.loads((run / "summary.json").read_text())
    best = run / "checkpoints" / "best.pt"
    rows = []
    if case.val:
        val = json.loads(mpnode("evaluate", best, data, "--split", "validation", "--json",
                                log=log))
        rows.append(_row("val", case.preset, "validation", val))
    if case.name.startswith("gene-ba-") and case.budget is None:
        rows.append(val_within(run, GENE_EQUAL_SECONDS * args.scale, case.preset))
    rows.append({"measure": "test", "dataset": case.preset, "split": "test",
                 "mse": (summary["test"] or {}).get("mse"),
                 "failed": (summary["test"] or {}).get("failed"),
                 **(summary.get("baselines") or {})})
    if case.zeroshot:
        paths = [dataset(inputs, p) for p in case.zeroshot]
        report = json.loads(mpnode("zeroshot", best, *paths, "--json", log=log))
        for preset, row in zip(case.zeroshot, report["datasets"], strict=True):
            rows.append(_row(preset, preset, row["split"], row))
    if case.zeroed:
        zeroed = command([sys.executable, __file__, "--zeroed-eval", str(best), str(data)], log)
        rows.append(_row("test, messages zeroed", case.preset, "test", json.loads(zeroed)))
    result = {
        "case": case.name, "options": options, "scale": args.scale,
        "epochs": summary["epochs"], "best_epoch": summary["best_epoch"],
        "wall_seconds": summary["wall_seconds"], "process_seconds":
            time.perf_counter() - started,
        "seconds_per_epoch": summary["seconds_per_epoch"], "budget_seconds": budget,
        "train_cpu_seconds": clock["cpu"], "train_process_seconds": clock["wall"],
        "reference": ref,
        "model": summary["model"], "parameters": summary["parameters"],
        "date": datetime.now().isoformat(timespec="seconds"), "commit": git_commit(),
        "rows": rows,
    }  # fmt: skip
    return result


def epochs_to_budget(run: Path, budget: float) -> int:
    """How many more epochs to train towards `budget` seconds of training (the epochs'
    seconds in `metrics.jsonl`, as `val_within` counts them).

    Epochs slow down as training goes on: a GNN-ODE's learned dynamics stiffen (its first
    three epochs took 0.44 s each, later ones 0.65–0.81 s), and the horizon curriculum
    lengthens the trajectories (a quad3 L2S epoch: 0.57 s at first, 1.7–1.8 s once the
    horizon is whole). So the rate is the latest epochs', and a stage covers only part of
    what is left, at most as many epochs as are done (the curriculum's growth shows), unless
    little is left; the next stage measures again.
    """
    rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    rows = [r for r in rows if r.get("epoch", 0) > 0] or rows
    spent = sum(r["seconds"] for r in rows)
    recent = rows[-10:]
    per_epoch = max(sum(r["seconds"] for r in recent) / len(recent), 1e-6)
    left = (budget - spent) / per_epoch
    if left <= 10:
        return math.floor(left)
    return math.floor(min(BUDGET_STAGE_SHARE * left, max(len(rows), TIMING_EPOCHS)))


def val_within(run: Path, seconds: float, preset: str) -> dict[str, Any]:
    """The best validation MSE a run reached within its first `seconds` of training."""
    rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    spent, best = 0.0, math.inf
    for row in rows:
        spent += row["seconds"]
        if spent > seconds:
            break
        if row["val_mse"] is not None:
            best = min(best, row["val_mse"])
    return {"measure": within_label(seconds), "dataset": preset, "split": "validation",
            "mse": best if math.isfinite(best) else None, "failed": 0}


def within_label(seconds: float) -> str:
    return f"val within {seconds:.0f} s"


def _row(measure: str, preset: str, split: str, report: dict[str, Any]) -> dict[str, Any]:
    """A row from `evaluate --json` / one `zeroshot --json` dataset."""
    base = report.get("baselines") or {}
    return {"measure": measure, "dataset": preset, "split": split,
            "mse": report["result"]["mse"], "failed": report["result"]["failed"],
            "hold_x0": base.get("hold_x0"), "time_mean": base.get("time_mean")}


def zeroed_eval(checkpoint: str, data_path: str) -> None:
    """Print `evaluate_checkpoint` JSON of a checkpoint with its messages zeroed (Fig. 3b).

    MP-NODE's `messages=False` clamps every incoming message to zero and changes no weight,
    so the trained weights load unchanged into that model.
    """
    from mpnode_cli.data.dataset import TrajectoryData
    from mpnode_cli.training.checkpoint import load_checkpoint
    from mpnode_cli.training.checkpoint_report import evaluate_checkpoint

    ckpt = load_checkpoint(checkpoint)
    ckpt.model_config = {**ckpt.model_config, "messages": False}
    row = evaluate_checkpoint(ckpt, TrajectoryData.load(data_path), split="test")
    print(json.dumps(row))


# ------------------------------------------------------------------------------- scheduling


def step_id(case: str) -> str:
    return f"case-{case}"


def per_epoch(args, case: Case) -> tuple[float, str]:
    """Seconds per epoch for the plan, and where the number comes from.

    A recorded full-budget result of this case measured it: its seconds per epoch × the
    share of a core its training got (what it would take alone on a core). Otherwise the
    `Case` estimate (a smoke run's first epochs are faster than a whole run's).
    """
    cached = read_result(args, case.name)
    if cached and cached.get("train_cpu_seconds") and cached["scale"] >= 0.5:
        share = min(1.0, cached["train_cpu_seconds"] / cached["train_process_seconds"])
        return cached["seconds_per_epoch"] * share, f"measured {cached['date'][:10]}"
    return case.s_per_epoch, "estimate"


def case_steps(args, names: list[str]) -> tuple[list[CallStep], list[str]]:
    """The jobs of the cases `names` (and of the cases whose wall time one of them takes as
    its budget): their datasets, then each case; and the plan's line per case."""
    chosen = list(names)
    for name in names:  # a case measured at another's wall time needs that one
        ref = CASES[name].equal_time
        if CASES[name].budget is None and ref and ref not in chosen:
            chosen.append(ref)
    cases = [CASES[n] for n in chosen]
    presets = list(dict.fromkeys(p for c in cases for p in (c.preset, *c.zeroshot)))
    steps = [CallStep(verb="call", id=gen_id(p), target="quality:job_generate",
                      args={"preset": p}, seconds=GENERATE_SECONDS.get(p, 5.0), group="data")
             for p in presets]
    lines = [f"{'case':22s} {'epochs':>7s} {'s/epoch':>8s} {'est. s':>8s}  source; options"]
    for case in cases:
        ref = case.equal_time if case.budget is None else None
        speed, source = per_epoch(args, case)
        if case.budget is not None:
            seconds = case.budget * args.scale
            epochs = f"~{max(1, round(seconds / speed))}"
        elif ref is not None:
            seconds = epochs_for(CASES[ref], args.scale) * per_epoch(args, CASES[ref])[0]
            epochs = f"~{max(1, round(seconds / speed))}"
        else:
            seconds = epochs_for(case, args.scale) * speed
            epochs = str(epochs_for(case, args.scale))
        needs = [gen_id(p) for p in (case.preset, *case.zeroshot)] + (
            [step_id(ref)] if ref else [])
        steps.append(CallStep(verb="call", id=step_id(case.name), target="quality:job_case",
                              args={"case": case.name, "scale": args.scale,
                                    "extra": args.extra, "ref": ref},
                              needs=needs, seconds=seconds + EVAL_SECONDS, group="cases"))
        lines.append(f"{case.name:22s} {epochs:>7s} {speed:8.3f} {seconds:8.0f}  {source}; "
                     f"{' '.join([*case.options, *args.extra])}"
                     + (f" (= {ref}'s wall time)" if ref else ""))
    return steps, lines


def read_result(args, name: str) -> dict[str, Any] | None:
    """The latest recorded result of case `name` in the work folder."""
    found = [r for r in jobs.records(args.runs) if r.get("case") == name]
    return found[-1] if found else None


# ---------------------------------------------------------------------------------- verdicts


def verdicts(results: dict[str, dict[str, Any]]) -> dict[tuple[str, str], str]:
    """(case, measure) → "pass", "FAIL: why", or "—" (no target), from all cached results."""
    out: dict[tuple[str, str], str] = {}

    def mse_of(case: str, measure: str) -> float | None:
        rows = (results.get(case) or {}).get("rows", [])
        return next((r["mse"] for r in rows if r["measure"] == measure), None)

    for name, result in results.items():
        case = CASES[name]
        for row in result["rows"]:
            checks: list[tuple[bool, str]] = []
            mse, measure = row["mse"], row["measure"]
            if mse is None:
                out[name, measure] = "FAIL: no MSE (rollouts failed)"
                continue
            mpnode_row = result["model"] == "mpnode" and case.name != "pendulum-no-messages"
            if mpnode_row and measure != "val" and "zeroed" not in measure:
                for key, times in (("hold_x0", 20), ("time_mean", 5)):
                    base = row.get(key)
                    if base is not None:
                        label = key.replace("_x0", " x(0)").replace("_", "-")
                        checks.append((base >= times * mse, f"{label} ≥ {times}× this"))
            if name.startswith("gene-ba-") and result["model"] == "mpnode":
                if measure == "test":
                    checks.append((mse <= 0.0045, "≤ 0.0045"))
                elif measure in ("gene-er-4x4", "gene-ws-4x4"):
                    checks.append((mse <= 0.0051, "≤ 0.0051"))
            if name in ("gene-ba-l2s", "gene-ba-gnode") and measure == "val":
                ref = result.get("reference") or ""
                label = within_label(result.get("budget_seconds") or 0.0)
                ours = mse_of(ref, label)
                if ours is not None:
                    checks.append((ours < mse, f"{ref} {label} ({_fmt(ours)}) < this"))
            if name == "pendulum-messages" and measure == "test":
                checks.append((mse <= 0.05, "≤ 0.05"))
            if name == "pendulum-no-messages" and measure == "test":
                ours = mse_of("pendulum-messages", "test")
                if ours is not None:
                    checks.append((mse >= 3 * ours, f"≥ 3× messages-on ({_fmt(ours)})"))
            if row.get("failed"):
                checks.append((False, "no failed rollouts"))
            if not checks:
                out[name, measure] = "—"
                continue
            failed = [why for ok, why in checks if not ok]
            out[name, measure] = "pass" if not failed else "FAIL: want " + "; ".join(failed)
    return out


# ------------------------------------------------------------------------------------ report


def _fmt(value: Any, digits: int = 4) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "—"
    return f"{value:.{digits}g}"


def _ratio(base: Any, mse: Any) -> str:
    if base is None or mse is None or not mse > 0:
        return "—"
    return f"{base / mse:.3g}"


def git_commit() -> str:
    def git(*a):
        return subprocess.run(["git", *a], capture_output=True, text=True, cwd=ROOT).stdout
    commit = git("rev-parse", "--short=10", "HEAD").strip() or "?"
    # The benches' own tables (bench/results) change as they run: not the code that ran.
    changed = git("status", "--porcelain", "--untracked-files=no", "--", ".",
                  ":(exclude)bench/results")
    return commit + ("+dirty" if changed else "")


def write_report(args, header: dict[str, Any]) -> None:
    """Rebuild the table from every cached case result, in `CASES` order."""
    results = {n: r for n in CASES if (r := read_result(args, n)) is not None}
    verdict = verdicts(results)
    lines = [
        "# Quality: the paper's experiments against naive baselines",
        "",
        f"Command: `{header['command']}`. Machine: {header['cores']} cores, "
        f"{args.workers} workers × 1 thread (OMP_NUM_THREADS=1; torch.get_num_threads() = "
        f"{header['threads']}), torch {header['torch']}, Python "
        f"{sys.version.split()[0]}, git {header['commit']}, {header['date']}. Load average "
        f"(1/5/15 min) before {header['load_before']}, after {header['load_after']}. "
        f"Epoch budgets × {args.scale:g}; estimated {header['estimate'] / 60:.0f} min, took "
        f"{header['took'] / 60:.1f} min (this invocation: {header['ran']}).",
        "",
        "MSE: normalized units (the training z-score), t₀ excluded, mean over predicted "
        "samples, nodes and features, best-validation checkpoint. Baselines on the same "
        "trajectories: hold x(0) predicts x(t) = x(t₀); time mean predicts the train split's "
        "mean state at each sample time (mean over train trajectories and nodes; a longer "
        "horizon holds the last train mean). Ratios: baseline MSE / ours (higher is "
        "better). val: validation split; test: test split; zero-shot rows: every "
        "trajectory of that dataset. Wall s: training time (validation included) from "
        "`summary.json`.",
        "",
        "| case | measure | MSE | hold x(0) | time mean | hold ÷ ours | mean ÷ ours | paper | "
        "epochs | wall s | verdict |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---|",
    ]
    for name, result in results.items():
        for i, row in enumerate(result["rows"]):
            paper = CASES[name].paper.get(row["measure"])
            first = i == 0
            failed = f" ({row['failed']} failed)" if row.get("failed") else ""
            lines.append(
                f"| {name if first else ''} | {row['measure']} | {_fmt(row['mse'])}{failed} | "
                f"{_fmt(row.get('hold_x0'))} | {_fmt(row.get('time_mean'))} | "
                f"{_ratio(row.get('hold_x0'), row['mse'])} | "
                f"{_ratio(row.get('time_mean'), row['mse'])} | {_fmt(paper)} | "
                f"{result['epochs'] if first else ''} | "
                f"{_fmt(result['wall_seconds'], 3) if first else ''} | "
                f"{verdict.get((name, row['measure']), '—')} |")
    lines += ["", "Cases:", ""]
    for name, result in results.items():
        case = CASES[name]
        extra = f" {case.note}" if case.note else ""
        if result.get("budget_seconds"):
            extra += (f" Budget {result['budget_seconds']:.0f} s ({result.get('reference')}); "
                      f"{result['seconds_per_epoch']:.3g} s/epoch.")
        options = " ".join(result["options"]) or "(CLI defaults)"
        cpu, wall = result["train_cpu_seconds"], result["train_process_seconds"]
        lines.append(f"- {name}: `mpnode train {case.preset}.h5 {options}`, "
                     f"{result['model']} ({result['parameters']:,} parameters), best epoch "
                     f"{result['best_epoch']}; training processes {wall:.0f} s wall, "
                     f"{cpu:.0f} s CPU ({cpu / wall:.0%} of a core).{extra}")
    runs: dict[tuple, list[str]] = {}
    for name, r in results.items():
        runs.setdefault((r["date"][:13], r["commit"], r["scale"]), []).append(name)
    if len(runs) > 1:
        lines += ["", "Rows come from more than one invocation (date and hour, commit, scale):"]
        lines += [f"- {', '.join(names)}: {when}, {commit}, × {scale:g}"
                  for (when, commit, scale), names in sorted(runs.items())]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(lines) + "\n")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", help=f"comma-separated cases (of: {', '.join(CASES)})")
    parser.add_argument("--scale", type=float, default=1.0,
                        help="multiply the epoch budgets (0.003 for a smoke run)")
    parser.add_argument("--workers", type=int, default=2, help="cases run at once")
    parser.add_argument("--runs", type=Path, default=HERE / ".runs" / "quality",
                        help="the jobs' folders (datasets and cases)")
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("--plan", action="store_true", help="print the estimate and stop")
    parser.add_argument("--extra", default="", help="options added to every case's `mpnode "
                        "train`, e.g. \"--clip 5\": the same cases under a variant of the "
                        "recipe (give it its own --runs and --out)")
    parser.add_argument("--zeroed-eval", nargs=2, metavar=("CKPT", "DATA"),
                        help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.zeroed_eval:
        zeroed_eval(*args.zeroed_eval)
        return 0
    args.runs = args.runs.resolve()
    args.extra = shlex.split(args.extra)
    names = args.only.split(",") if args.only else list(CASES)
    unknown = [n for n in names if n not in CASES]
    if unknown:
        parser.error(f"unknown case {', '.join(unknown)} (choose from: {', '.join(CASES)})")

    def report(line: str) -> None:
        print(f"[{time.strftime('%H:%M:%S')}] {line}", file=sys.stderr, flush=True)

    steps, lines = case_steps(args, names)
    print("\n".join(lines), file=sys.stderr)
    print(jobs.plan(steps, args.runs, args.workers), file=sys.stderr)
    estimate = jobs.schedule({s.id: (s.seconds, tuple(s.needs)) for s in steps}, args.workers)
    if args.plan:
        return 0
    threads = subprocess.run([sys.executable, "-c", "import torch; print(torch.get_num_threads(),"
                              " torch.__version__)"], capture_output=True, text=True,
                             env=env(), check=True).stdout.split()
    from mpnode_cli.file_records import shown_argv

    # Absolute paths are shown relative to the current folder, or as <option>: the
    # results are committed, and the folders of the machine that ran them mean nothing.
    shown = shown_argv(list(argv or sys.argv[1:]))
    header = {"command": " ".join(shlex.quote(a) if " " in a else a
                                  for a in ["bench/quality.py", *shown]),
              "cores": os.cpu_count(), "threads": threads[0], "torch": threads[1],
              "commit": git_commit(), "date": datetime.now().isoformat(timespec="minutes"),
              "load_before": "/".join(f"{x:.2f}" for x in os.getloadavg()),
              "estimate": estimate, "ran": ", ".join(names)}
    start = time.perf_counter()

    failed = jobs.run_jobs(steps, args.runs, args.workers, jobs.reporter(report))
    header["took"] = time.perf_counter() - start
    header["load_after"] = "/".join(f"{x:.2f}" for x in os.getloadavg())
    write_report(args, header)
    report(f"wrote {args.out} ({header['took'] / 60:.1f} min)")
    for name, why in failed.items():
        report(f"not run: {name}: {why}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
