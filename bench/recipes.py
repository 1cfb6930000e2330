"""Recipes at equal wall time: mpnode's default recipe against the paper's, on every system.

For each system's training dataset (a preset) and seed, `mpnode train --recipe mpnode` and
`mpnode train --recipe paper` train side by side, one process each, one torch thread each,
so that both see the same machine load. Each stops at the budget:

- `time`: `--time-limit` seconds of its own training (default 600, ten minutes of one core;
  the epoch that crosses it finishes);
- `epochs`: the paper's 4000 epochs (mpnode's recipe then stops early where its
  `--stop-patience` says).

From each run's `metrics.jsonl`, the best validation MSE reached by each time (the curve
drawn per system in `bench/results/recipes-<system>.png`, both recipes, each seed); from its
`summary.json`, the test MSE of its best checkpoint beside the naive predictors (hold x(0),
the train split's time mean); and its zero-shot MSE on held-out graphs (`HELD_OUT`: a larger
graph or another topology, 200 trajectories), where a recipe that wins on its own graphs
must also hold. The table gives, per system and recipe, mean ± std over the
seeds of the validation MSE at the budget and the test MSE, and says which recipe is ahead.

Runs are jobs of the experiments' engine (`mpnode_cli.experiments.jobs`), two at a time in
order, so the two recipes of a system and seed run side by side: each in its folder under
`--runs`, its numbers in the folder's `step.json`; a run that was cut off resumes
(`mpnode train --resume`) where it stopped, a finished one is not run again. Each run's
numbers are also written beside the table (`recipes.json`, committed with it), and a table
rebuilt where the work folder lacks a run takes that run from there: seeds run on different
machines or days add up. A system known only from the table's own rows (run before the
records existed) keeps those rows.

Usage:
    .venv/bin/python bench/recipes.py --plan                 # what would run, and how long
    .venv/bin/python bench/recipes.py --systems lorenz3 gene --seeds 0
    .venv/bin/python bench/recipes.py --budget epochs --systems lorenz3     # hours
    .venv/bin/python bench/recipes.py --table-only           # rebuild the table from cache
Writes `bench/results/recipes.md` (and `recipes-epochs.md` for the epoch budget).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import statistics
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))  # this checkout's package, before an installed one

from mpnode_cli.experiments import jobs  # noqa: E402 (the engine the runs go on)
from mpnode_cli.experiments.spec import CallStep  # noqa: E402

RECIPES = ("mpnode", "paper")
# Each system's training set, as bench/quality.py trains it.
SYSTEMS = {"lorenz": "lorenz3", "gene": "gene-ba-4x4", "kuramoto": "kuramoto10-ba",
           "pendulum": "pendulum", "quadrotor": "quad3"}
# Held-out graphs for each system, where the recipe must also hold: a larger graph or another
# topology, 200 trajectories of the preset (the model is run on them zero-shot).
HELD_OUT = {"lorenz": "lorenz10", "gene": "gene-er-4x4", "kuramoto": "kuramoto10-er",
            "quadrotor": "quad6"}
HELD_OUT_TRAJECTORIES = 200
PAPER_EPOCHS = 4000
# Why a system keeps mpnode's recipe where the paper's is ahead on its own graphs here
# (docs/training-recipe.md, "The recipe against the paper's at equal wall time"). A system
# behind without an entry is reported as one whose default needs another look.
KEPT_BEHIND = {
    "lorenz": (
        "The paper's recipe (Huber loss along time, batches of 128, the whole horizon) fits "
        "lorenz3 better within the budget, but its models carry to lorenz10 worse and less "
        "evenly than the default's (the held-out column; lorenz10's time-mean predictor "
        "scores 0.75). A default that wins on its own graphs and breaks on larger ones is "
        "what mpnode avoids, so Lorenz keeps mpnode's recipe at this budget. At the paper's "
        "4000 epochs the one run of each points the other way on both: the paper's recipe "
        "reaches test 0.0525 on lorenz3 and 0.050 zero-shot on lorenz10 "
        "(reports/zeroshot-lorenz, the paper-scale run), where mpnode's levels off near 0.20 "
        "(bench/results/quality-long.md). Three seeds at that budget (about 6 core-hours for "
        "Lorenz, below) decide the default."),
}


def env() -> dict[str, str]:
    return {**os.environ, "OMP_NUM_THREADS": "1", "MPNODE_THREADS": "1",
            "PYTHONPATH": str(ROOT)}


def mpnode(*args: str, log: Path, out: Path | None = None) -> None:
    """`mpnode ARGS`, its output appended to `log` (its stdout to `out`, if given)."""
    log.parent.mkdir(parents=True, exist_ok=True)
    with log.open("a") as err, (out or log).open("a") as std:
        code = subprocess.run([sys.executable, "-m", "mpnode_cli", *args], cwd=ROOT,
                              env=env(), stdout=std, stderr=err).returncode
    if code:
        raise RuntimeError(f"mpnode {args[0]} exited {code}: see {log}")


def job_generate(folder: Path, inputs, resumed: bool, preset: str,
                 trajectories: int | None) -> dict:
    """A preset's dataset (`trajectories` of them, if given) in the job's folder."""
    more = ["--trajectories", str(trajectories)] if trajectories else []
    mpnode("generate", "--preset", preset, *more, "--out", str(folder / "partial.h5"), "-y",
           log=folder / "log.txt")
    (folder / "partial.h5").replace(folder / "data.h5")
    return {"preset": preset}


def job_train(folder: Path, inputs, resumed: bool, system: str, recipe: str, seed: int,
              budget: str, seconds: float, data: str, held_out: str | None) -> dict:
    """Train one recipe on one system in `folder/run` (a cut-off run resumes), run it
    zero-shot on the held-out graphs, and return its numbers."""
    run, log = folder / "run", folder / "log.txt"
    limit = (["--time-limit", str(seconds), "--epochs", str(PAPER_EPOCHS)]
             if budget == "time" else ["--epochs", str(PAPER_EPOCHS)])
    if (run / "checkpoints" / "last.pt").exists():
        mpnode("train", "--resume", str(run), *limit, "--no-plots", log=log)
    else:
        mpnode("train", str(Path(inputs[data].folder) / "data.h5"), "--recipe", recipe,
               "--seed", str(seed), "--run-dir", str(run), "--no-plots", *limit, log=log)
    s = json.loads((run / "summary.json").read_text())
    points = curve(run)
    zero = None
    if held_out:
        out = folder / "held-out.json"
        out.unlink(missing_ok=True)
        mpnode("zeroshot", str(run), str(Path(inputs[held_out].folder) / "data.h5"), "--json",
               log=log, out=out)
        (item,) = json.loads(out.read_text())["datasets"]
        zero = item["result"]["mse"]
    return {"system": system, "recipe": recipe, "seed": seed, "budget": budget,
            "seconds_limit": seconds, "val": points[-1][1] if points else math.nan,
            "seconds": points[-1][0] if points else 0.0, "epochs": s["epochs"],
            "test": (s.get("test") or {}).get("mse"), "held_out": zero,
            "baselines": s.get("baselines") or {}, "curve": points}


def steps_of(args) -> list[CallStep]:
    """The datasets, then both recipes of each (system, seed), side by side in order."""
    steps: dict[str, CallStep] = {}
    for system in args.systems:
        wanted = [(SYSTEMS[system], None)]
        if system in HELD_OUT:
            wanted.append((HELD_OUT[system], HELD_OUT_TRAJECTORIES))
        for preset, k in wanted:
            sid = f"gen-{preset}" + (f"-k{k}" if k else "")
            steps[sid] = CallStep(verb="call", id=sid, target="recipes:job_generate",
                                  args={"preset": preset, "trajectories": k}, seconds=10.0,
                                  group="data")
        ids = [s for s in steps if s.startswith(f"gen-{SYSTEMS[system]}")][:1] + (
            [f"gen-{HELD_OUT[system]}-k{HELD_OUT_TRAJECTORIES}"] if system in HELD_OUT else [])
        for seed in args.seeds:
            for recipe in RECIPES:
                sid = f"{args.budget}-{system}-{recipe}-s{seed}"
                steps[sid] = CallStep(
                    verb="call", id=sid, target="recipes:job_train", needs=ids,
                    args={"system": system, "recipe": recipe, "seed": seed,
                          "budget": args.budget, "seconds": args.seconds, "data": ids[0],
                          "held_out": ids[1] if len(ids) > 1 else None},
                    seconds=args.seconds if args.budget == "time" else 4 * 3600.0,
                    group=system)
    return list(steps.values())


def curve(folder: Path) -> list[tuple[float, float]]:
    """(training seconds so far, best validation MSE so far) after each epoch."""
    out, seconds, best = [], 0.0, math.inf
    metrics = folder / "metrics.jsonl"
    if not metrics.exists():
        return out
    for line in metrics.read_text().splitlines():
        row = json.loads(line)
        seconds += row.get("seconds") or 0.0
        if row.get("val_mse") is not None:
            best = min(best, row["val_mse"])
        out.append((seconds, best))
    return out


def result(args, system: str, recipe: str, seed: int) -> dict | None:
    """The latest recorded run of (system, recipe, seed) at this budget, if any."""
    found = [r for r in jobs.records(args.runs)
             if (r.get("system"), r.get("recipe"), r.get("seed"), r.get("budget"))
             == (system, recipe, seed, args.budget)]
    return found[-1] if found else None


def _pm(values: list[float], spec: str = ".3g") -> str:
    values = [v for v in values if v is not None and math.isfinite(v)]
    if not values:
        return "—"
    if len(values) == 1:
        return f"{values[0]:{spec}}"
    return f"{statistics.mean(values):{spec}} ± {statistics.pstdev(values):{spec}}"


def write_table(args) -> None:
    lines = [f"# Recipes at equal wall time: mpnode's against the paper's ({args.budget} "
             "budget)", "",
             f"Written by `bench/recipes.py` on {time.strftime('%Y-%m-%d')}. "
             + ("Budget: " + (f"{args.seconds:g} s of training per run (`--time-limit`)"
                              if args.budget == "time" else f"{PAPER_EPOCHS} epochs")
                + ", one torch thread; the two recipes of a system and seed trained at the "
                "same time, one core each, so both saw the same load. MSE in normalized "
                "units, t₀ excluded; validation: the best reached within the budget; test: "
                "the best checkpoint's. Mean ± std (population) over the seeds listed."),
             "",
             "| system (train set) | recipe | seeds | epochs | validation MSE | test MSE | "
             "test: time mean / hold x(0) | held out: zero-shot MSE | ahead on validation |",
             "|---|---|---|---|---|---|---|---|---|"]
    behind: dict[str, dict[str, float]] = {}
    cost: dict[tuple[str, str], float] = {}
    kept = _saved_rows(results_file(args))
    saved = _load_records(records_file(args))
    records = {}
    for system in args.all_systems:
        rows = {}
        for r in RECIPES:
            got = []
            for seed in sorted(set(args.all_seeds) | {k[2] for k in saved
                                                       if k[:2] == (system, r)}):
                x = result(args, system, r, seed) or saved.get((system, r, seed))
                if x:
                    got.append(x)
                    records[(system, r, seed)] = x
            rows[r] = got
        if not any(rows.values()) and system in kept:
            # No run of this system in the cache (a fresh checkout, or another machine's
            # runs): keep its rows as the table had them rather than drop them.
            lines += kept[system]["lines"]
            if kept[system]["behind"]:
                behind[system] = kept[system]["means"]
            cost.update(kept[system]["cost"])
            continue
        means = {r: statistics.mean(x["val"] for x in v) if v else math.nan
                 for r, v in rows.items()}
        ahead = "—"
        if all(rows.values()):
            ahead = min(means, key=means.get)
        if ahead == "paper":
            behind[system] = means
        for recipe, got in rows.items():
            if not got:
                continue
            cost[(system, recipe)] = statistics.mean(x["seconds"] / x["epochs"] for x in got)
            base = got[0]["baselines"]
            lines.append(
                f"| {system} ({SYSTEMS[system]}) | {recipe} | {len(got)} | "
                f"{_pm([x['epochs'] for x in got], '.0f')} | {_pm([x['val'] for x in got])} | "
                f"{_pm([x['test'] for x in got])} | {_fmt(base.get('time_mean'))} / "
                f"{_fmt(base.get('hold_x0'))} | {_held_out(system, got)} | "
                f"{'yes' if ahead == recipe else ''} |")
        plot(args, system, rows)
    lines += notes(behind)
    if args.budget == "time":
        lines += epoch_budget(cost, len(args.all_seeds))
    out = results_file(args)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(".md.tmp")
    tmp.write_text("\n".join(lines) + "\n")
    tmp.replace(out)
    _save_records(records_file(args), records)


def records_file(args) -> Path:
    """Each run's numbers beside the table (`<table>.json`), so that a table rebuilt where
    the run cache lacks some runs (a fresh checkout, another machine) keeps them."""
    return results_file(args).with_suffix(".json")


def _load_records(path: Path) -> dict[tuple[str, str, int], dict]:
    if not path.exists():
        return {}
    return {(r["system"], r["recipe"], r["seed"]): r["result"]
            for r in json.loads(path.read_text())}


def _save_records(path: Path, records: dict[tuple[str, str, int], dict]) -> None:
    rows = [{"system": system, "recipe": recipe, "seed": seed,
             "result": {**x, "curve": _thin(x["curve"])}}
            for (system, recipe, seed), x in sorted(records.items())]
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(rows, indent=1) + "\n")
    tmp.replace(path)


def _thin(points: list, keep: int = 200) -> list:
    """At most `keep` points of a curve, evenly spaced, its last point kept (the plot's)."""
    if len(points) <= keep:
        return [list(p) for p in points]
    step = len(points) / keep
    return [list(points[int(i * step)]) for i in range(keep - 1)] + [list(points[-1])]


def _saved_rows(path: Path) -> dict[str, dict]:
    """The rows of each system in an existing table (`write_table`'s format), with what
    the notes below the table need of them: each recipe's mean validation MSE, whether
    the paper's recipe was ahead, and the seconds per epoch of the budget's runs (the
    budget's seconds over the mean epochs; time budget only)."""
    if not path.exists():
        return {}
    text = path.read_text()
    budget = re.search(r"Budget: ([0-9.]+) s of training", text)
    saved: dict[str, dict] = {}
    for line in text.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) != 9 or cells[1] not in RECIPES:
            continue
        system = cells[0].split(" (")[0]
        if system not in SYSTEMS:
            continue
        entry = saved.setdefault(system, {"lines": [], "means": {}, "behind": False,
                                          "cost": {}})
        entry["lines"].append(line)
        try:
            entry["means"][cells[1]] = float(cells[4].split()[0])
            epochs = float(cells[3].split()[0])
        except ValueError:
            continue
        if budget and epochs > 0:
            entry["cost"][(system, cells[1])] = float(budget.group(1)) / epochs
        entry["behind"] |= cells[1] == "paper" and cells[8] == "yes"
    return saved


def notes(behind: dict[str, dict[str, float]]) -> list[str]:
    """The table's section on the systems where the paper's recipe is ahead on validation
    (`behind`: system → each recipe's mean validation MSE), each with why the default stays
    (`KEPT_BEHIND`) or a line saying that it needs another look."""
    if not behind:
        return ["", "mpnode's recipe is ahead on validation on every system in the table."]
    lines = ["", "## Where the default is not ahead", ""]
    for system, means in behind.items():
        why = KEPT_BEHIND.get(system, "No reason is recorded: this system's default needs "
                                      "another look.")
        lines.append(f"- **{system}**: validation MSE {means['mpnode']:.3g} with mpnode's "
                     f"recipe against {means['paper']:.3g} with the paper's. {why}")
    return lines


def epoch_budget(cost: dict[tuple[str, str], float], seeds: int) -> list[str]:
    """What the paper's budget (`--budget epochs`) would cost, from the seconds per epoch
    measured here (`cost`: (system, recipe) → seconds per epoch), where it has not run."""
    if (HERE / "results" / "recipes-epochs.md").exists() or not cost:
        return []
    hours = {key: PAPER_EPOCHS * seconds / 3600 for key, seconds in cost.items()}
    each = ", ".join(f"{system} {recipe} {h:.1f} h" for (system, recipe), h in hours.items())
    total = seeds * sum(hours.values())
    return ["", f"The paper's budget ({PAPER_EPOCHS} epochs, `--budget epochs`) has not run. "
            f"At the seconds per epoch measured here, one run costs, on one core: {each}; "
            f"{seeds} seeds of every system and recipe, about {total:.0f} core-hours "
            "(mpnode's recipe stops early where `--stop-patience` says, so its share may be "
            "smaller)."]


def results_file(args) -> Path:
    """The table's file; the plots go beside it."""
    return args.out or HERE / "results" / ("recipes.md" if args.budget == "time"
                                           else "recipes-epochs.md")


def _held_out(system: str, got: list[dict]) -> str:
    if system not in HELD_OUT:
        return "—"
    values = [x["held_out"] for x in got]
    shown = ", ".join("—" if v is None else f"{v:.3g}" for v in values)
    return f"{HELD_OUT[system]}: {_pm(values)} (seeds: {shown})"


def _fmt(value) -> str:
    return "—" if value is None else f"{value:.3g}"


def plot(args, system: str, rows: dict[str, list[dict]]) -> None:
    """Best validation MSE against training seconds, each recipe and seed (runs known only
    from the saved records have no curve; with none, the figure is left as it is)."""
    if not any(x["curve"] for got in rows.values() for x in got):
        return
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.6))
    for recipe, colour in zip(RECIPES, ("tab:blue", "tab:orange"), strict=True):
        for i, got in enumerate(x for x in rows[recipe] if x["curve"]):
            xs, ys = zip(*got["curve"], strict=True)
            ax.plot(xs, ys, color=colour, alpha=0.8, label=recipe if i == 0 else None)
    ax.set_yscale("log")
    ax.set_xlabel("training seconds (one core)")
    ax.set_ylabel("best validation MSE")
    ax.set_title(f"{system} ({SYSTEMS[system]}): {args.budget} budget", fontsize=10)
    ax.legend()
    fig.tight_layout()
    suffix = "" if args.budget == "time" else "-epochs"
    fig.savefig(results_file(args).parent / f"recipes-{system}{suffix}.png", dpi=90)
    plt.close(fig)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--systems", nargs="+", default=list(SYSTEMS), choices=SYSTEMS)
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--budget", choices=("time", "epochs"), default="time")
    parser.add_argument("--seconds", type=float, default=600.0)
    parser.add_argument("--runs", type=Path, default=HERE / ".runs" / "recipes")
    parser.add_argument("--out", type=Path)
    parser.add_argument("--plan", action="store_true")
    parser.add_argument("--table-only", action="store_true")
    args = parser.parse_args(argv)
    args.all_systems, args.all_seeds = list(SYSTEMS), sorted(set(args.seeds) | {0, 1, 2})
    args.runs = args.runs.resolve()
    steps = steps_of(args)
    print(jobs.plan(steps, args.runs, 2), file=sys.stderr)
    if args.plan:
        return 0
    failed = {} if args.table_only else jobs.run_jobs(
        steps, args.runs, 2, jobs.reporter(lambda line: print(line, file=sys.stderr)))
    write_table(args)
    for name, why in failed.items():
        print(f"not run: {name}: {why}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
