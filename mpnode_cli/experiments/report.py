"""`reports/<name>/report.md`, and the index `reports/README.md`, from runs' records.

Each run leaves `reports/<name>/<scale>-<recipe>/results.json` (the `RunRecord`, the claims
judged) and its figures beside it (`mpnode_cli.experiments.saved`); `report.md` is rebuilt
from every such folder present, one section per scale and recipe
(`mpnode_cli.experiments.markdown`), and the index from every experiment's latest results
(`mpnode_cli.experiments.index`). So reports can be regenerated without running anything,
and a second recipe or scale adds to what is there instead of replacing it.

Every MSE is in the training normalization with t₀ excluded (the paper's "test error";
`mpnode_cli.training.evaluate`), beside the two naive predictors of `baseline_mse`. A run
with `--seeds S` (S > 1) shows every number of a trained model as the mean ± std
(population) over the members of its ensemble, and each claim as holds, fails or undecided
from the members (`mpnode_cli.experiments.members`); a run of one seed, and every record
written before seeds, shows its numbers as they are.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path
from typing import Any

from mpnode_cli.data.atomic import atomic_text
from mpnode_cli.experiments import claims, spec
from mpnode_cli.experiments.index import rebuild_index
from mpnode_cli.experiments.markdown import draws_sections, run_section
from mpnode_cli.experiments.runner import RunRecord
from mpnode_cli.experiments.saved import (
    FINDINGS,
    REPORT,
    RESULTS,
    kept_facts,
    portable,
    run_folder,
    saved_runs,
    step_results,
)
from mpnode_cli.jsonable import jsonable
from mpnode_cli.paths import OutputError


def write_report(record: RunRecord, experiment: spec.Experiment, out: Path) -> Path:
    """Save a run's results and figures under `out/<name>/`, rebuild its `report.md` and
    the index `out/README.md`. Returns the report's path.

    Reports are committed, so they hold no folder of the machine that ran them: step
    folders are named relative to the work folder, commands are as run from it, and the
    work folder itself is shown relative to the current folder, or as `<work>`."""
    folder = Path(out) / experiment.name / run_folder(record.scale, record.recipe, record.draw)
    data = kept_facts(portable(record.to_dict(), Path(record.work)), folder / RESULTS)
    results = {r["id"]: r["result"] for r in data["steps"]}
    data["claims"] = [_claim(claim, results, experiment) for claim in experiment.claims]
    tmp = folder.with_name(folder.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    try:  # the folder whole beside the old one, then in its place
        tmp.mkdir(parents=True)
        for step in data["steps"]:
            names = []
            for figure in step["figures"]:
                name = Path(figure).name
                shutil.copyfile(figure, tmp / name)
                names.append(name)
            step["figures"] = names
        atomic_text(tmp / RESULTS, json.dumps(jsonable(data), indent=2, default=str) + "\n")
    except (OSError, OutputError) as exc:  # a full disk, most likely: nothing half-written
        shutil.rmtree(tmp, ignore_errors=True)
        said = exc.strerror if isinstance(exc, OSError) and exc.strerror else exc
        raise OutputError(f"cannot write {folder}: {said} (the record there is as it "
                          "was)") from None
    shutil.rmtree(folder, ignore_errors=True)
    os.replace(tmp, folder)
    path = rebuild_report(experiment, Path(out))
    rebuild_index(Path(out))
    return path


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
        "runs whose normalizations differ (a finetune keeps its parent's). Beside it, from "
        "each run's kept per-epoch curve (`results.json`): the epochs and seconds to 3× "
        "below the time-mean predictor, and the mean over epochs of the validation MSE ÷ "
        "the time mean's. Figures, tables and commands "
        "are regenerated by `mpnode experiment run`; a section per scale and recipe run.", ""]
    findings = out / experiment.name / FINDINGS
    if findings.is_file():  # written by hand; kept as it is when the report is rebuilt
        lines += ["## Findings", "", findings.read_text().strip(), ""]
    runs = saved_runs(out, experiment.name)
    for run in runs:
        # Claims judged anew from the spec, so a claim added later is judged on old results.
        try:
            results = step_results(run)
            run["claims"] = [_claim(claim, results, experiment) for claim in experiment.claims]
            lines += run_section(run)
        except (KeyError, TypeError, AttributeError, IndexError) as exc:  # a record edited
            record = out / experiment.name / run_folder(run["scale"], run["recipe"],
                                                        run.get("draw", 0)) / RESULTS
            raise ValueError(f"{record} is not a run record mpnode wrote (it lacks or "
                             f"mistypes {exc}): restore it from a copy, or move its "
                             "folder away") from None
    lines += draws_sections(runs, [(c.claim, c.holds) for c in experiment.claims])
    path = out / experiment.name / REPORT
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_text(path, "\n".join(lines).rstrip() + "\n")
    return path


def _claim(claim: spec.Claim, results: dict[str, Any],
           experiment: spec.Experiment) -> dict[str, Any]:
    holds, shown, said = claims.verdict(claim.holds, results, experiment)
    decision = claims.decide_claim(claim.holds, results)
    out = {**claim.model_dump(), "holds_now": holds, "ours": shown, "verdict": said}
    if decision.members > 1:
        out |= {"outcome": decision.outcome, "held": decision.held,
                "seeds": decision.members, "by_member": decision.by_member()}
    return out
