"""A run's section of `reports/<name>/report.md`, in Markdown, from its saved record.

Every function takes the plain dicts of a saved record (`saved.saved_runs`). A run with
`--seeds S` (S > 1) shows every number of a trained model as the mean ± std (population)
over the members of its ensemble (`mpnode_cli.experiments.members`); a run of one seed, and
every record written before seeds, shows its numbers as they are.
"""

from __future__ import annotations

import math
from typing import Any

from mpnode_cli.experiments import curves, members
from mpnode_cli.experiments.claims import format_bound, margin, over_draws
from mpnode_cli.experiments.saved import run_folder, step_results
from mpnode_cli.experiments.spec import TRAINING


def _in_processes(jobs: int) -> str:
    return f" in each of {jobs} processes running steps side by side" if jobs > 1 else ""


def run_section(run: dict[str, Any]) -> list[str]:
    """The Markdown lines of one saved run (a `results.json`, its claims judged): its
    command and machine, the claims, the errors, training runs, Table-2 figures, figures,
    steps and the commands that do the same."""
    m = run["machine"]
    draw = run.get("draw", 0)
    sub = run_folder(run["scale"], run["recipe"], draw)
    ran = [s["id"] for s in run["steps"] if s["status"] != "skipped"]
    size = _size(run)
    lines = [
        f"## `--scale {run['scale']} --recipe {run['recipe']}"
        f"{f' --seeds {size}' if size > 1 else ''}"
        f"{f' --draw {draw}' if draw else ''}`", "",
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
    return members.count(step_results(run))


def _reused(ran: int, total: int) -> str:
    if ran == total:
        return ""
    return (f" ({ran} of {total} steps ran; the others were reused from earlier runs, and "
            "the steps table gives the seconds each took when it ran)")


def _errors(steps: list[dict[str, Any]]) -> list[str]:
    rows = []
    for s in steps:
        r, paper = s["result"], s.get("reported") or {}
        if s["verb"] in TRAINING:
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
    runs = [s for s in steps if s["verb"] in TRAINING]
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
                  f"Beside the paper's figure, what reaching "
                  f"{curves.TARGET_FACTOR:g}× below the time-mean predictor cost (epochs and "
                  "seconds, validation included), and the mean over epochs of the validation "
                  "MSE ÷ the time mean's (lower: learned sooner). ⚑ marks a best epoch of 0 "
                  "or the budget's last: the figure is then degenerate or capped.", "",
                  "| group | run | best epoch | min val loss | Table-2 figure | × the best "
                  f"of the group | the paper | epochs to {curves.TARGET_FACTOR:g}× | "
                  "seconds to it | area ÷ time mean |",
                  "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
        unkept = False
        for group, runs in groups.items():
            # An ensemble's bar is its members' mean; "× the best" is of the means.
            values = [members.values(by_id[m]["result"], "table2") for m in runs]
            means = [None if stats is None else stats[0]
                     for stats in map(members.mean_and_std, values)]
            best = min((v for v in means if v is not None), default=None)
            for m, value, mean in zip(runs, values, means, strict=True):
                r, cost = by_id[m]["result"], curves.cost(by_id[m]["result"])
                lines.append(f"| {group} | {m} | {_best_epochs(r)} | "
                             f"{_pm(members.values(r, 'min_val_loss'))} | {_pm(value)} | "
                             f"{_ratio(mean, best)} | {_f(paper.get(m))} | "
                             f"{_reached(cost['epochs'], cost['kept'])} | "
                             f"{_reached(cost['seconds'], cost['kept'])} | "
                             f"{_pm(cost['area'], 3)} |")
                unkept = unkept or not all(cost["kept"])
        if unkept:
            lines += ["", "— in the last three columns: curves not kept. These runs predate "
                      "the per-epoch curves that reports keep, so their cost cannot be "
                      "rebuilt; the same command run again fills them."]
        if s.get("reported_in"):
            lines += ["", f"The paper's numbers: {s['reported_in']}."]
        lines.append("")
    return lines


def _best_epochs(result: dict[str, Any]) -> str:
    """The best epoch (members: mean ± std), ⚑ where any member's is 0 or its last."""
    best = members.values(result, "best_epoch")
    last = members.values(result, "epochs")
    flag = any(b == 0 or b == e for b, e in zip(best, last, strict=True))
    return _pm(best) + (" ⚑" if flag else "")


def _reached(values: list[Any], kept: list[bool]) -> str:
    """Epochs or seconds to the target: as `_pm` where every member got there; else how
    many did ("1 of 3"), or "not reached"; — for a report that kept no curve."""
    if not all(kept):
        return "—"
    got = [v for v in values if v is not None]
    if len(got) == len(values):
        return _pm(got, 3)
    return f"{len(got)} of {len(values)}" if got else "not reached"


def _seeds(steps: list[dict[str, Any]]) -> str:
    parts = []
    for s in steps:
        r = s["result"]
        if s["verb"] == "generate":
            parts.append(f"{s['id']} data seed {r['seed']}, graph seed {r['graph_seed']}")
        elif s["verb"] in TRAINING:
            many = "s" if r.get(members.MEMBERS) else ""
            parts.append(f"{s['id']} seed{many} {_seed(r)}")
    return "; ".join(parts)


def _seed(result: dict[str, Any]) -> str:
    """A training's seed, or its members' (`0–2`)."""
    seeds = members.values(result, "seed")
    return str(seeds[0]) if len(seeds) == 1 else f"{min(seeds)}–{max(seeds)}"



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
    stats = members.mean_and_std([None if b is None or v is None or not v > 0 else b / v
                                  for b, v in zip(bases, values, strict=True)])
    return "—" if stats is None else f"{stats[0]:.3g} ± {stats[1]:.2g}"


def _pm(values: list[Any], digits: int = 4) -> str:
    """One member's value as `_f` shows it; several as mean ± std (population); — when
    one is missing."""
    if len(values) == 1:
        return _f(values[0], digits)
    stats = members.mean_and_std(values)
    if stats is None:
        return "—"
    return f"{_f(stats[0], digits)} ± {_f(stats[1], 2)}"


def draws_sections(runs: list[dict[str, Any]], claims: list[tuple[str, str]]) -> list[str]:
    """For each scale and recipe run on more than one data draw (`--draw`), each claim's
    margin per draw and over the draws and seeds with its 95% bootstrap interval
    (`claims.interval`); `claims` are the experiment's, as (what it says, `LEFT OP
    RIGHT`)."""
    groups: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for run in runs:
        groups.setdefault((run["scale"], run["recipe"]), []).append(run)
    lines: list[str] = []
    for (scale, recipe), group in groups.items():
        if len(group) < 2:
            continue
        draws = [step_results(run) for run in group]
        numbers = ", ".join(str(run.get("draw", 0)) for run in group)
        lines += [f"## Over data draws: `--scale {scale} --recipe {recipe}`", "",
                  f"Draws {numbers} (each its own graphs, initial states and split; "
                  "`--draw`). The margin is the ratio of a claim's two sides' means, the "
                  "claimed way (above 1 holds); the interval is a 95% bootstrap over the "
                  "draws that have the claim's numbers and, within each, the seeds. — on a "
                  "draw: no margin there (the claim's steps did not run on it, or a side's "
                  "mean is 0, as a Table-2 figure of best epoch 0 is); ∞: the resamples "
                  "that take only such zeros leave the margin unbounded.", "",
                  "| claim | margin per draw | margin over draws and seeds | 95% interval |",
                  "|---|---|---|---|"]
        for claim, text in claims:
            each = [margin(text, [d]) for d in draws]
            whole = over_draws(text, draws)[1]
            per = ", ".join("—" if e is None else format_bound(e) for e in each)
            shown = ("—", "—") if whole is None else (
                format_bound(whole[0]), f"{format_bound(whole[1])}–{format_bound(whole[2])}")
            lines.append(f"| {claim} | {per} | {shown[0]} | {shown[1]} |")
        lines.append("")
    return lines
