"""What an experiment costs at the paper's scale, from the seconds per epoch its runs measured.

A training step's epoch rolls out each training trajectory once (and validates on a split
of the same dataset), so its time grows with the training trajectories. At the paper's
scale a training step costs

    the paper's epochs × (seconds per epoch ÷ training trajectories, as measured) × the
    paper's training trajectories × the torch threads it ran on,

in core-seconds. The measurement is the same step's in a committed run of the experiment
(`reports/<name>/<scale>-<recipe>/results.json`): the paper-scale run where there is one,
else the small one, the paper's recipe first (its epochs roll out the whole horizon; the
horizon curriculum of mpnode's recipe makes early epochs cheaper). Generate, evaluate and
compare steps are left out (seconds to minutes), a step with a wall-time budget
(`time_limit`) costs its budget, and a step shared with other experiments
counts in each. The measurements come from shared 2-core machines, so this is a rough guide.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mpnode_cli.experiments import spec

# Records of a run, most telling first for the paper's scale.
_PREFERENCE = ("paper-paper", "paper-mpnode", "small-paper", "small-mpnode")
HOW = ("Σ over the training steps of the paper's epochs × the seconds per epoch per training "
       "trajectory measured in the experiment's committed runs (reports/NAME/*/results.json, "
       "the paper-scale run where there is one) × the paper's training trajectories × torch "
       "threads; generate and evaluate steps left out, shared steps counted in each "
       "experiment; measured on shared 2-core machines, so a rough guide")


@dataclass
class CoreHourEstimate:
    """An experiment's training at the paper's scale.

    Attributes:
        core_hours: the measured training steps' estimate (0 when none is measured).
        steps: training steps in all; missing: those without a measurement (the estimate
            leaves them out, so it is a lower bound).
        resized: steps measured with other model options than the paper's (L2S runs
            CI-sized at the small scale), so they cost more than estimated.
        sources: the run records the measurements come from (e.g. `small-paper`).
    """

    core_hours: float = 0.0
    steps: int = 0
    missing: list[str] = field(default_factory=list)
    resized: list[str] = field(default_factory=list)
    sources: list[str] = field(default_factory=list)

    def shown(self) -> str:
        """`~12`, `≥ 3` (steps unmeasured), with `*` when a step was measured resized; `—`
        when nothing is measured."""
        if len(self.missing) == self.steps:
            return "—"
        text = f"{'≥ ' if self.missing else '~'}{self.core_hours:.2g}"
        return text + ("*" if self.resized else "")


def paper_cost(experiment: spec.Experiment, reports: Path) -> CoreHourEstimate:
    """The estimate for `experiment` from its runs' records under `reports`."""
    records = _records(Path(reports) / experiment.name)
    by_id = {step.id: step for step in experiment.steps}
    out = CoreHourEstimate()
    for step in experiment.steps:
        if step.verb not in spec.TRAINING:
            continue
        out.steps += 1
        paper = spec.resolve(step, "paper", "paper")["config"]
        if paper.get("time_limit"):  # a budget of wall time, on one thread
            out.core_hours += paper["time_limit"] / 3600
            continue
        found = _measured(step.id, records)
        if found is None:
            out.missing.append(step.id)
            continue
        name, measured, threads = found
        per_trajectory = measured["seconds_per_epoch"] / measured["trajectories"]
        seconds = paper.get("epochs", 4000) * per_trajectory * _train_trajectories(
            step, paper, by_id) * threads
        out.core_hours += seconds / 3600
        scale = name.split("-")[0]  # the scale it was measured at
        if spec.resolve(step, scale, "paper")["config"].get("model_options") != paper.get(
                "model_options"):
            out.resized.append(step.id)
        if name not in out.sources:
            out.sources.append(name)
    return out


def _records(folder: Path) -> list[tuple[str, dict[str, Any]]]:
    """The experiment's run records, most telling first."""
    found = []
    for name in _PREFERENCE:
        path = folder / name / "results.json"
        if path.is_file():
            found.append((name, json.loads(path.read_text())))
    return found


def _measured(step_id: str, records) -> tuple[str, dict[str, Any], int] | None:
    """The first record's results of `step_id` with seconds per epoch and trajectories,
    and the torch threads it ran on."""
    for name, record in records:
        for step in record["steps"]:
            result = step.get("result") or {}
            if (step["id"] == step_id and result.get("seconds_per_epoch")
                    and result.get("trajectories")):
                return name, result, int(record.get("machine", {}).get("threads", 1))
    return None


def _train_trajectories(step, config: dict[str, Any], by_id: dict[str, Any]) -> int:
    """The step's training trajectories at the paper's scale: its own `trajectories`, else
    its dataset's train split."""
    if config.get("trajectories"):
        return int(config["trajectories"])
    from mpnode_cli.data.splits import split_counts

    data = spec.resolve(by_id[step.data], "paper", "paper")["config"]
    return split_counts(int(data["trajectories"]), tuple(data["split"]))[0]

