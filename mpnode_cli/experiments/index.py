"""The index `reports/README.md`: one row per claim of every shipped experiment, judged on
the saved runs (`saved.saved_runs`), and a table of what has run.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from mpnode_cli.data.atomic import atomic_text
from mpnode_cli.experiments import claims, members, spec
from mpnode_cli.experiments.saved import INDEX, INDEX_TITLE, REPORT, saved_runs, step_results

# The seeds a row should rest on; a cell of a run with fewer also shows a smaller scale's run
# with more, where there is one (`rebuild_index`).
SEEDS_WANTED = 3
# The index's head: its title, how to read it, and its table's header.
_INTRO = [
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
    "the verdict says which, and the report gives each member's numbers. A claim is "
    "not tested where no training run it compares beat the time-mean predictor, or "
    "where it holds against a run none of whose members did. After a "
    "verdict, in brackets: the training runs (members) it compares whose "
    "test error is not below the time-mean predictor's (they have not learned) or less "
    f"than {claims.BARELY_LEARNED:g}× below it (they barely have), so the comparison says "
    "little; and an MP-NODE that is not the paper's model: an aggregation other than "
    "the paper's mean (§3.2), as mpnode's recipe uses for some systems. Each experiment's "
    "report has its tables, figures, commands and machine; run one with `mpnode "
    "experiment run NAME --scale small`.", "",
    "| experiment | claim | the paper | where | ours, `--recipe paper` | ours, `--recipe "
    "mpnode` | holds |", "|---|---|---|---|---|---|---|"]


def rebuild_index(out: Path) -> Path:
    """`out/README.md`: one row per claim of every shipped experiment, with ours under each
    recipe from the largest scale run (tiny runs are smoke tests and are left out), and
    the verdicts that rest on runs that did not learn or barely learned."""
    lines = [*_INTRO]
    weak: list[str] = []
    for name in spec.names():
        experiment = spec.load(name)
        runs = [r for r in saved_runs(out, name) if r["scale"] != "tiny"]
        main = [r for r in runs if not r.get("draw")]  # draw 0: the experiment's own data
        shown_runs = {recipe: _shown_runs([r for r in main if r["recipe"] == recipe])
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
                    results = step_results(run)
                    _, shown, said = claims.verdict(claim.holds, results, experiment)
                    size = members.count(results)
                    where = f"{run['scale']}, {size} seed{'s' if size > 1 else ''}"
                    cell.append(f"{shown} ({where}){_over_draws(claim.holds, runs, run)}")
                    said_all.append(said if len(shown_runs[recipe]) == 1
                                    else f"{run['scale']}: {said}")
                    weak += _weak(name, claim, recipe, results, run["scale"])
                cells.append("<br>".join(cell))
                verdicts.append("; ".join(said_all))
            lines.append(f"| {link if i == 0 else ''} | {claim.claim} | {claim.paper} | "
                         f"{claim.where} | {cells[0]} | {cells[1]} | {' / '.join(verdicts)} |")
    lines += ["", *_coverage(out)]
    if weak:
        lines += ["", "## Verdicts that rest on runs that did not learn, barely learned, or "
                  "ran out of budget", "",
                  f"Runs not below the time-mean predictor, or less than "
                  f"{claims.BARELY_LEARNED:g}× below it, that a claim compares; and Table-2 "
                  "figures whose best epoch is 0 (the figure is 0 whatever the loss) or the "
                  "budget's last (the run was still improving):", "", *weak]
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
        every = saved_runs(out, name)
        runs = {(r["scale"], r["recipe"]): r for r in every if not r.get("draw")}
        draws = {kind: sum((r["scale"], r["recipe"]) == kind for r in every) for kind in kinds}
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
            if draws[kind] > 1:
                cell += f" × {draws[kind]} data draws"
            if run.get("started"):
                cell += f", {str(run['started'])[:10]}"
            if missing:
                cell += f"; not run: {', '.join(missing)}"
            cells.append(cell)
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return lines


def _over_draws(text: str, runs: list[dict[str, Any]], run: dict[str, Any]) -> str:
    """`run`'s claim margin over its scale's and recipe's data draws and seeds, with the
    95% bootstrap interval (`claims.interval`), where it ran on more than one draw."""
    group = [r for r in runs if (r["scale"], r["recipe"]) == (run["scale"], run["recipe"])]
    if len(group) < 2:
        return ""
    counted, found = claims.over_draws(text, [step_results(r) for r in group])
    if found is None:
        return f"; over {len(group)} data draws: —"
    low, high = (claims.format_bound(v) for v in found[1:])
    return (f"; over {counted} data draws, margin {claims.format_bound(found[0])} (95%: "
            f"{low}–{high})")


def _shown_runs(runs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The runs of one recipe that the index shows, largest scale first (`runs` in
    `_runs`' order): the largest scale's; and where that one has fewer than
    `SEEDS_WANTED` seeds, also the run of a smaller scale with the most seeds, if it has
    more, so that a row gives a mean ± std where one was measured."""
    if not runs:
        return []
    first = runs[0]
    size = members.count(step_results(first))
    if size >= SEEDS_WANTED:
        return [first]
    counted = [(members.count(step_results(r)), r)
               for r in runs[1:]]
    more = [(n, r) for n, r in counted if n > size]
    if not more:
        return [first]
    return [first, max(more, key=lambda pair: pair[0])[1]]


def _weak(name: str, claim: spec.Claim, recipe: str, results: dict[str, Any],
          scale: str) -> list[str]:
    """A line for the index if `claim`'s verdict under `recipe` at `scale` rests on runs
    that did not learn or barely learned; none for a claim with a number missing (a step not
    run), which compared nothing."""
    if claims.decide_claim(claim.holds, results).outcome is None:
        return []
    notes = claims.run_notes(claim.holds, results)
    if not notes:
        return []
    runs = ", ".join(f"{step} ({note})" for step, note in notes.items())
    return [f"- {name}, `--scale {scale} --recipe {recipe}`: {claim.claim}: {runs}."]
