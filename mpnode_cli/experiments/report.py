"""`reports/<name>/report.md` and the index `reports/README.md`, from runs' records.

Each run leaves `reports/<name>/<scale>-<recipe>/results.json` (the `RunRecord`, the claims
judged) and its figures beside it; `report.md` is rebuilt from every such folder present,
one section per scale and recipe, and the index from every experiment's latest results. So
reports can be regenerated without running anything, and a second recipe or scale adds to
what is there instead of replacing it.

Every MSE is in the training normalization with t₀ excluded (the paper's "test error";
`mpnode_cli.training.evaluate`), beside the two naive predictors of `baseline_mse`. A run
with `--seeds S` (S > 1) shows every number of a trained model as the mean ± std
(population) over the members of its ensemble, and each claim as holds, fails or undecided
from the members (`mpnode_cli.experiments.members`); a run of one seed, and every record
written before seeds, shows its numbers as they are.
"""

from __future__ import annotations

import json
import math
import os
import shutil
from pathlib import Path
from typing import Any

from mpnode_cli.data.atomic import atomic_text
from mpnode_cli.experiments import members, spec
from mpnode_cli.experiments.runner import RunRecord
from mpnode_cli.jsonable import jsonable

RESULTS = "results.json"
REPORT = "report.md"
FINDINGS = "findings.md"  # a hand-written analysis beside a report (why a claim fails, ...)
INDEX = "README.md"
INDEX_TITLE = "# Reproducing the paper: the index"  # how an index mpnode wrote begins
_SCALE_ORDER = {"paper": 0, "small": 1, "tiny": 2}
# The seeds a row should rest on; a cell of a run with fewer also shows a smaller scale's run
# with more, where there is one (`rebuild_index`).
SEEDS_WANTED = 3
_RECIPE_ORDER = {"mpnode": 0, "paper": 1}


def write_report(record: RunRecord, experiment: spec.Experiment, out: Path) -> Path:
    """Save a run's results and figures under `out/<name>/`, rebuild its `report.md` and
    the index `out/README.md`. Returns the report's path.

    Reports are committed, so they hold no folder of the machine that ran them: step
    folders are named relative to the work folder, commands are as run from it, and the
    work folder itself is shown relative to the current folder, or as `<work>`."""
    folder = Path(out) / experiment.name / f"{record.scale}-{record.recipe}"
    tmp = folder.with_name(folder.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    data = _kept_facts(portable(record.to_dict(), Path(record.work)), folder / RESULTS)
    for step in data["steps"]:
        names = []
        for figure in step["figures"]:
            name = Path(figure).name
            shutil.copyfile(figure, tmp / name)
            names.append(name)
        step["figures"] = names
    results = {r["id"]: r["result"] for r in data["steps"]}
    data["claims"] = [_claim(claim, results, experiment) for claim in experiment.claims]
    (tmp / RESULTS).write_text(json.dumps(jsonable(data), indent=2, default=str) + "\n")
    shutil.rmtree(folder, ignore_errors=True)
    os.replace(tmp, folder)
    path = rebuild_report(experiment, Path(out))
    rebuild_index(Path(out))
    return path


def _kept_facts(data: dict[str, Any], previous: Path) -> dict[str, Any]:
    """A rerun that ran no step (every one reused) keeps the saved run's facts: its command,
    start, wall time, machine and which steps ran then; results and claims are the new."""
    if any(step["status"] != "skipped" for step in data["steps"]) or not previous.is_file():
        return data
    old = json.loads(previous.read_text())
    before = {step["id"]: step["status"] for step in old.get("steps", [])}
    if old.get("seeds", 1) != data.get("seeds", 1) or not set(before) >= {
            step["id"] for step in data["steps"]}:
        return data
    steps = [{**step, "status": before[step["id"]]} for step in data["steps"]]
    return {**data, **{key: old[key] for key in ("command", "started", "wall_seconds",
                                                  "machine") if key in old},
            "steps": steps}


def portable(data: dict[str, Any], work: Path) -> dict[str, Any]:
    """A run's record (`RunRecord.to_dict()`) with its paths relative to the work folder
    `work`: each step's folder by its path in it, its commands as run from it, and `work`
    as `shown_path` shows it."""
    from mpnode_cli.experiments.commands import from_work
    from mpnode_cli.paths import shown_path

    steps = []
    for step in data["steps"]:
        folder = Path(step["folder"])
        for base in (work, work.resolve()):
            if folder.is_relative_to(base):
                folder = folder.relative_to(base)
                break
        steps.append({**step, "folder": str(folder),
                      "commands": [from_work(c, work) for c in step["commands"]]})
    return {**data, "work": shown_path(work, "<work>"), "steps": steps}


def _runs(out: Path, name: str) -> list[dict[str, Any]]:
    """Every saved run of an experiment, paper scale and mpnode recipe first."""
    runs = []
    for path in sorted((out / name).glob(f"*/{RESULTS}")):
        if path.parent.name.endswith(".tmp"):
            continue
        runs.append(json.loads(path.read_text()))
    return sorted(runs, key=lambda r: (_SCALE_ORDER.get(r["scale"], 9),
                                       _RECIPE_ORDER.get(r["recipe"], 9)))


def rebuild_report(experiment: spec.Experiment, out: Path) -> Path:
    lines = [f"# {experiment.name}: {experiment.title}", "",
             f"The paper: {experiment.paper}.", ""]
    if experiment.small_minutes:
        lines += [f"Expected time at `--scale small`: about {experiment.small_minutes:g} "
                  "minutes on one core, without steps shared with experiments already run.",
                  ""]
    if experiment.summary:
        lines += [experiment.summary.strip(), ""]
    lines += [
        "Errors are MSEs in the training normalization, t₀ excluded, averaged over predicted "
        "samples, nodes and state components (the paper's \"test error\"). Beside each: "
        "*hold x(0)* predicts x(t) = x(t₀); *time mean* predicts the train split's mean "
        "state at each sample time; ÷ is that baseline's MSE over ours (higher is better). "
        "The Table-2 figure is the paper's: the epoch of the lowest validation loss × that "
        "loss (in the run's training loss; lower is better); `table2_per_mean` is the same "
        "with the validation MSE in units of the time-mean predictor's, comparable between "
        "runs whose normalizations differ (a finetune keeps its parent's). Figures, tables "
        "and commands "
        "are regenerated by `mpnode experiment run`; a section per scale and recipe run.", ""]
    findings = out / experiment.name / FINDINGS
    if findings.is_file():  # written by hand; kept as it is when the report is rebuilt
        lines += ["## Findings", "", findings.read_text().strip(), ""]
    for run in _runs(out, experiment.name):
        # Claims judged anew from the spec, so a claim added later is judged on old results.
        results = {s["id"]: s["result"] for s in run["steps"]}
        run["claims"] = [_claim(claim, results, experiment) for claim in experiment.claims]
        lines += _section(run)
    path = out / experiment.name / REPORT
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_text(path, "\n".join(lines).rstrip() + "\n")
    return path


def _in_processes(jobs: int) -> str:
    return f" in each of {jobs} processes running steps side by side" if jobs > 1 else ""


def _section(run: dict[str, Any]) -> list[str]:
    m = run["machine"]
    sub = f"{run['scale']}-{run['recipe']}"
    ran = [s["id"] for s in run["steps"] if s["status"] != "skipped"]
    size = _size(run)
    lines = [
        f"## `--scale {run['scale']} --recipe {run['recipe']}"
        f"{f' --seeds {size}' if size > 1 else ''}`", "",
        f"Run `{run['command']}` on {run['started']}: {run['wall_seconds'] / 60:.1f} min wall"
        f"{_reused(len(ran), len(run['steps']))}. Machine: "
        f"{m['cores']} cores, torch {m['torch']} on {m['threads']} thread(s)"
        f"{_in_processes(m.get('jobs', 1))}, Python "
        f"{m['python']}, {m['platform']}, mpnode {m['mpnode']} at git {m['commit']}; load "
        f"average (1/5/15 min) {m['load_before']} before, {m.get('load_after', '?')} after.",
        ""]
    if run["scale"] == "tiny":
        lines += ["*The tiny scale is a smoke test (a few trajectories and samples, two "
                  "epochs): its numbers measure nothing.*", ""]
    if size > 1:
        lines += [_ENSEMBLE.format(size=size), ""]
    if run.get("claims"):
        lines += ["### The paper's claims", "",
                  "| claim | the paper | where | ours | holds |", "|---|---|---|---|---|"]
        for c in run["claims"]:
            each = f"; members: {c['by_member']}" if c.get("by_member") else ""
            lines.append(f"| {c['claim']} | {c['paper']} | {c['where']} | `{c['holds']}`: "
                         f"{c['ours']}{each} | {c['verdict']} |")
        lines.append("")
    lines += _errors(run["steps"])
    lines += _training(run["steps"])
    lines += _table2(run["steps"])
    figures = [(s["id"], f) for s in run["steps"] for f in s["figures"]]
    if figures:
        lines += ["### Figures", ""]
        for step_id, name in figures:
            lines += [f"**{name.removesuffix('.png')}** (step `{step_id}`)", "",
                      f"![{name}]({sub}/{name})", ""]
    work = run.get("work", "<work>")
    lines += ["### Steps and the commands that do the same", "",
              f"Folders and paths are in the work folder (`--work`, here `{work}`).", "",
              "| step | verb | status | seconds | folder |", "|---|---|---|---:|---|"]
    for s in run["steps"]:
        lines.append(f"| {s['id']} | {s['verb']} | {s['status']} | {s['seconds']:.1f} | "
                     f"`{s['folder']}` |")
    lines += ["", "```bash", f"# from the work folder: cd {work}"]
    lines += [c for s in run["steps"] for c in s["commands"]]
    lines += ["```", ""]
    seeds = _seeds(run["steps"])
    if seeds:
        lines += [f"Seeds: {seeds}.", ""]
    return lines


_ENSEMBLE = (
    "*Every training here is an ensemble of {size} members (`--seeds {size}`: member k has "
    "the step's seed + k, and a finetune's member k starts from its parent's member k). "
    "Each number of a trained model is the mean ± std (population) over the {size} "
    "members; the naive predictors do not depend on the seed. A claim is judged on each "
    "member alone (member k of every step it names) and on the means: it holds when it "
    "holds for every member, or when the means differ by more than their combined std "
    "(√(std₁² + std₂²)) the claimed way; it fails when it fails for every member, or when "
    "the means differ by more than that the other way; otherwise it is undecided. Each "
    "member's comparison follows the means.*")


def _size(run: dict[str, Any]) -> int:
    """S, the members a run's numbers are over (1 for a record of one seed)."""
    return members.count({s["id"]: s["result"] for s in run["steps"]})


def _reused(ran: int, total: int) -> str:
    if ran == total:
        return ""
    return (f" ({ran} of {total} steps ran; the others were reused from earlier runs, and "
            "the steps table gives the seconds each took when it ran)")


def _errors(steps: list[dict[str, Any]]) -> list[str]:
    rows = []
    for s in steps:
        r, paper = s["result"], s.get("reported") or {}
        if s["verb"] in spec.TRAINING:
            rows.append((s["id"], "validation (best)", _each(r, "val"), paper.get("val")))
            rows.append((s["id"], "test", _each(r, "test"), paper.get("test")))
        elif s["verb"] == "evaluate":
            what = f"{r['split']}" + (", messages zeroed" if r.get("zero_messages") else "")
            rows.append((s["id"], what, _each(r), paper.get(s["id"]) or paper.get(r["split"])))
        elif s["verb"] == "zeroshot":
            for data_id, row in r.items():
                if data_id != members.MEMBERS:
                    rows.append((s["id"], f"zero-shot on {data_id} ({row['split']})",
                                 _each(r, data_id), paper.get(data_id)))
    if not rows:
        return []
    lines = ["### Errors beside the naive predictors", "",
             "| step | rows | MSE | hold x(0) | time mean | hold ÷ ours | mean ÷ ours | "
             "the paper |", "|---|---|---:|---:|---:|---:|---:|---:|"]
    for step_id, what, each, paper in rows:
        # The naive predictors are the same for every member: they do not depend on a seed.
        mse, hold, mean = ([row.get(key) for row in each] for key in ("mse", "hold_x0",
                                                                     "time_mean"))
        fails = [row.get("failed") or 0 for row in each]
        failed = f" ({'/'.join(map(str, fails))} failed)" if any(fails) else ""
        lines.append(f"| {step_id} | {what} | {_pm(mse)}{failed} | {_f(hold[0])} | "
                     f"{_f(mean[0])} | {_ratios(hold, mse)} | {_ratios(mean, mse)} | "
                     f"{_f(paper)} |")
    sources = sorted({s["reported_in"] for s in steps if s.get("reported_in")})
    if sources:
        lines += ["", f"The paper's numbers: {'; '.join(sources)}."]
    return [*lines, ""]


def _each(result: dict[str, Any], key: str | None = None) -> list[dict[str, Any]]:
    """Each member's `result[key]` (the result itself without `key`); one for a single
    model."""
    rows = result.get(members.MEMBERS) or [result]
    return [row if key is None else (row.get(key) or {}) for row in rows]


def _training(steps: list[dict[str, Any]]) -> list[str]:
    runs = [s for s in steps if s["verb"] in spec.TRAINING]
    if not runs:
        return []
    lines = ["### Training runs", "",
             "| run | verb | model | train trajectories | epochs | best epoch | min val loss "
             "| Table-2 figure | min train loss | s/epoch | wall s | seed |",
             "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for s in runs:
        r = s["result"]
        options = ", ".join(f"{k} {v}" for k, v in (s["options"]["config"].get(
            "model_options") or {}).items())
        model = r["model"] + (f" ({options})" if options else "")

        def each(key: str, result: dict[str, Any] = r) -> str:
            return _pm(members.values(result, key))

        lines.append(f"| {s['id']} | {s['verb']} | {model} | {r['trajectories']} | "
                     f"{r['epochs']} | {each('best_epoch')} | {each('min_val_loss')} "
                     f"({r['loss']}) | {each('table2')} | {each('min_train_loss')} | "
                     f"{_f(r['seconds_per_epoch'], 3)} | {_f(r['wall_seconds'], 4)} | "
                     f"{_seed(r)} |")
    return [*lines, ""]


def _table2(steps: list[dict[str, Any]]) -> list[str]:
    by_id = {s["id"]: s for s in steps}
    lines: list[str] = []
    for s in steps:
        groups = s["result"].get("groups") if s["verb"] == "compare" else None
        if not groups:
            continue
        paper = s.get("reported") or {}
        lines += ["### Table 2: epochs to the lowest validation loss × that loss", "",
                  "| group | run | best epoch | min val loss | Table-2 figure | × the best "
                  "of the group | the paper |", "|---|---|---:|---:|---:|---:|---:|"]
        for group, runs in groups.items():
            # An ensemble's bar is its members' mean; "× the best" is of the means.
            values = [members.values(by_id[m]["result"], "table2") for m in runs]
            means = [None if stats is None else stats[0]
                     for stats in map(members.mean_std, values)]
            best = min((v for v in means if v is not None), default=None)
            for m, value, mean in zip(runs, values, means, strict=True):
                r = by_id[m]["result"]
                lines.append(f"| {group} | {m} | {_pm(members.values(r, 'best_epoch'))} | "
                             f"{_pm(members.values(r, 'min_val_loss'))} | {_pm(value)} | "
                             f"{_ratio(mean, best)} | {_f(paper.get(m))} |")
        if s.get("reported_in"):
            lines += ["", f"The paper's numbers: {s['reported_in']}."]
        lines.append("")
    return lines


def _seeds(steps: list[dict[str, Any]]) -> str:
    parts = []
    for s in steps:
        r = s["result"]
        if s["verb"] == "generate":
            parts.append(f"{s['id']} data seed {r['seed']}, graph seed {r['graph_seed']}")
        elif s["verb"] in spec.TRAINING:
            many = "s" if r.get(members.MEMBERS) else ""
            parts.append(f"{s['id']} seed{many} {_seed(r)}")
    return "; ".join(parts)


def _seed(result: dict[str, Any]) -> str:
    """A training's seed, or its members' (`0–2`)."""
    seeds = members.values(result, "seed")
    return str(seeds[0]) if len(seeds) == 1 else f"{min(seeds)}–{max(seeds)}"


# --------------------------------------------------------------------------------- index


def rebuild_index(out: Path) -> Path:
    """`out/README.md`: one row per claim of every shipped experiment, with ours under each
    recipe from the largest scale run (tiny runs are smoke tests and are left out), and
    the verdicts that rest on runs that did not learn or barely learned."""
    lines = [
        INDEX_TITLE, "",
        "One row per claim of the paper (Gupta, Vemprala & Kapoor, \"Learning Modular "
        "Simulations for Homogeneous Systems\", NeurIPS 2022). *Ours* shows the claim's "
        "comparison on our results, from the largest scale run (`paper`, else `small`) with "
        "the paper's recipe (`--recipe paper`) and with mpnode's default (`--recipe "
        "mpnode`), with the scale and the seeds it ran with; where that run has fewer than "
        f"{SEEDS_WANTED} seeds and a smaller scale's has more, the cell gives that one too, "
        "on a second line. *Holds* says whether the "
        "paper's direction holds in each (paper recipe / mpnode recipe; each scale's "
        "verdict, where a cell has two). A run of one seed "
        "trained one model per step and shows its two numbers: yes or **no**. A run with "
        "`--seeds S` trained every model as an ensemble of S members and shows each side "
        "as mean ± std (population) over the members: the claim holds (yes) when it holds "
        "for every member or when the means differ by more than their combined std "
        "(√(std₁² + std₂²)) the claimed way, fails (**no**) when it fails for every member "
        "or the means differ by more than that the other way, and is otherwise undecided; "
        "the verdict says which, and the report gives each member's numbers. After a "
        "verdict, in brackets: the training runs (members) it compares whose "
        "test error is not below the time-mean predictor's (they have not learned) or less "
        f"than {spec.BARELY_LEARNED:g}× below it (they barely have), so the comparison says "
        "little; and an MP-NODE that is not the paper's model: an aggregation other than "
        "the paper's mean (§3.2), as mpnode's recipe uses for some systems. Each experiment's "
        "report has its tables, figures, commands and machine; run one with `mpnode "
        "experiment run NAME --scale small`.", "",
        "| experiment | claim | the paper | where | ours, `--recipe paper` | ours, `--recipe "
        "mpnode` | holds |", "|---|---|---|---|---|---|---|"]
    weak: list[str] = []
    for name in spec.names():
        experiment = spec.load(name)
        runs = [r for r in _runs(out, name) if r["scale"] != "tiny"]
        shown_runs = {recipe: _shown_runs([r for r in runs if r["recipe"] == recipe])
                      for recipe in ("paper", "mpnode")}
        link = f"[{name}]({name}/{REPORT})" if runs else name
        for i, claim in enumerate(experiment.claims):
            cells, verdicts = [], []
            for recipe in ("paper", "mpnode"):
                if not shown_runs[recipe]:
                    cells.append("not run")
                    verdicts.append("—")
                    continue
                cell, said_all = [], []
                for run in shown_runs[recipe]:
                    results = {s["id"]: s["result"] for s in run["steps"]}
                    _, shown, said = spec.verdict(claim.holds, results, experiment)
                    size = members.count(results)
                    where = f"{run['scale']}, {size} seed{'s' if size > 1 else ''}"
                    cell.append(f"{shown} ({where})")
                    said_all.append(said if len(shown_runs[recipe]) == 1
                                    else f"{run['scale']}: {said}")
                    weak += _weak(name, claim, recipe, results, run["scale"])
                cells.append("<br>".join(cell))
                verdicts.append("; ".join(said_all))
            lines.append(f"| {link if i == 0 else ''} | {claim.claim} | {claim.paper} | "
                         f"{claim.where} | {cells[0]} | {cells[1]} | {' / '.join(verdicts)} |")
    lines += ["", *_coverage(out)]
    if weak:
        lines += ["", "## Verdicts that rest on runs that did not learn, or barely", "",
                  f"Runs not below the time-mean predictor, or less than "
                  f"{spec.BARELY_LEARNED:g}× below it, that a claim compares:", "", *weak]
    path = out / INDEX
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_text(path, "\n".join(lines) + "\n")
    return path


def _coverage(out: Path) -> list[str]:
    """The index's table of what has run: per experiment, scale and recipe, the seeds and
    the date of the saved run, and the steps the experiment has that the run lacks (added
    since it ran: its claims on them show —)."""
    kinds = [("paper", "paper"), ("paper", "mpnode"), ("small", "paper"), ("small", "mpnode")]
    lines = ["## What has run", "",
             "Per experiment, the saved run at each scale and recipe (the rows above come "
             "from the largest scale): its seeds, the day it started, and the steps it has "
             "not run yet (added to the experiment since; rerunning it runs only those). — "
             "means no run.", "",
             "| experiment | " + " | ".join(f"{scale} scale, `--recipe {recipe}`"
                                         for scale, recipe in kinds) + " |",
             "|---|" + "---|" * len(kinds)]
    for name in spec.names():
        experiment = spec.load(name)
        runs = {(r["scale"], r["recipe"]): r for r in _runs(out, name)}
        cells = []
        for kind in kinds:
            run = runs.get(kind)
            if run is None:
                cells.append("—")
                continue
            results = {s["id"]: s["result"] for s in run["steps"] if s.get("result")}
            seeds = int(run.get("seeds") or members.count(results))
            missing = [step.id for step in experiment.steps if step.id not in results]
            cell = f"{seeds} seed{'s' if seeds > 1 else ''}"
            if run.get("started"):
                cell += f", {str(run['started'])[:10]}"
            if missing:
                cell += f"; not run: {', '.join(missing)}"
            cells.append(cell)
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return lines


def _shown_runs(runs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The runs of one recipe that the index shows, largest scale first (`runs` in
    `_runs`' order): the largest scale's; and where that one has fewer than
    `SEEDS_WANTED` seeds, also the run of a smaller scale with the most seeds, if it has
    more, so that a row gives a mean ± std where one was measured."""
    if not runs:
        return []
    first = runs[0]
    size = members.count({s["id"]: s["result"] for s in first["steps"]})
    if size >= SEEDS_WANTED:
        return [first]
    counted = [(members.count({s["id"]: s["result"] for s in r["steps"]}), r)
               for r in runs[1:]]
    more = [(n, r) for n, r in counted if n > size]
    if not more:
        return [first]
    return [first, max(more, key=lambda pair: pair[0])[1]]


def _weak(name: str, claim: spec.Claim, recipe: str, results: dict[str, Any],
          scale: str) -> list[str]:
    """A line for the index if `claim`'s verdict under `recipe` at `scale` rests on runs
    that did not learn or barely learned."""
    notes = spec.learning_notes(claim.holds, results)
    if not notes:
        return []
    runs = ", ".join(f"{step} ({note})" for step, note in notes.items())
    return [f"- {name}, `--scale {scale} --recipe {recipe}`: {claim.claim}: {runs}."]


def _claim(claim: spec.Claim, results: dict[str, Any],
           experiment: spec.Experiment) -> dict[str, Any]:
    holds, shown, said = spec.verdict(claim.holds, results, experiment)
    decision = spec.decide(claim.holds, results)
    out = {**claim.model_dump(), "holds_now": holds, "ours": shown, "verdict": said}
    if decision.members > 1:
        out |= {"outcome": decision.outcome, "held": decision.held,
                "seeds": decision.members, "by_member": decision.by_member()}
    return out


def _f(value: Any, digits: int = 4) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "—"
    if isinstance(value, int) and not isinstance(value, bool):
        return str(value)
    if 1e3 <= abs(value) < 1e7:  # Table-2 figures: 12800, not 1.28e+04
        return f"{value:.0f}"
    return f"{value:.{digits}g}"


def _ratio(base: Any, value: Any) -> str:
    if base is None or value is None or not value > 0:
        return "—"
    return f"{base / value:.3g}"


def _ratios(bases: list[Any], values: list[Any]) -> str:
    """Each member's `base ÷ value`, as mean ± std over the members (one: as `_ratio`)."""
    if len(values) == 1:
        return _ratio(bases[0], values[0])
    stats = members.mean_std([None if b is None or v is None or not v > 0 else b / v
                              for b, v in zip(bases, values, strict=True)])
    return "—" if stats is None else f"{stats[0]:.3g} ± {stats[1]:.2g}"


def _pm(values: list[Any], digits: int = 4) -> str:
    """One member's value as `_f` shows it; several as mean ± std (population); — when
    one is missing."""
    if len(values) == 1:
        return _f(values[0], digits)
    stats = members.mean_std(values)
    if stats is None:
        return "—"
    return f"{_f(stats[0], digits)} ± {_f(stats[1], 2)}"
