"""A run's saved results: the files under `reports/<name>/<scale>-<recipe>/`, and reading
them back.

Each run of an experiment leaves its `RunRecord` (`results.json`, with the claims judged)
and its figures in its own folder, so reports and the index can be rebuilt from what is
saved, without running anything. Reports are committed, so a saved record holds no folder
of the machine that ran it (`portable`).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

RESULTS = "results.json"
REPORT = "report.md"
FINDINGS = "findings.md"  # a hand-written analysis beside a report (why a claim fails, ...)
INDEX = "README.md"
INDEX_TITLE = "# Reproducing the paper: the index"  # how an index mpnode wrote begins
_SCALE_ORDER = {"paper": 0, "small": 1, "tiny": 2}
_RECIPE_ORDER = {"mpnode": 0, "paper": 1}


def kept_facts(data: dict[str, Any], previous: Path) -> dict[str, Any]:
    """A rerun that ran no step (every one reused) keeps the saved run's facts: its command,
    start, wall time, machine and which steps ran then; results and claims are the new."""
    if any(step["status"] != "skipped" for step in data["steps"]) or not previous.is_file():
        return data
    old = read_record(previous)
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
    from mpnode_cli.file_records import shown_path

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


def step_results(run: dict[str, Any]) -> dict[str, Any]:
    """A saved run's results by step id."""
    return {step["id"]: step["result"] for step in run["steps"]}


def run_folder(scale: str, recipe: str, draw: int = 0) -> str:
    """The folder of a run under `reports/<name>/`: `<scale>-<recipe>`, and `-draw<d>` for
    data draw d > 0."""
    return f"{scale}-{recipe}" + (f"-draw{draw}" if draw else "")


def saved_runs(out: Path, name: str) -> list[dict[str, Any]]:
    """Every saved run of an experiment, paper scale and mpnode recipe first, each
    scale's and recipe's data draws in order (a record without one is draw 0)."""
    runs = []
    for path in sorted((out / name).glob(f"*/{RESULTS}")):
        if path.parent.name.endswith(".tmp"):
            continue
        runs.append(read_record(path))
    return sorted(runs, key=lambda r: (_SCALE_ORDER.get(r["scale"], 9),
                                       _RECIPE_ORDER.get(r["recipe"], 9), r.get("draw", 0)))


def read_record(path: Path) -> dict[str, Any]:
    """The run record at `path` (`<scale>-<recipe>[-draw<d>]/results.json`), checked to be
    one mpnode wrote for its folder: a JSON object whose scale, recipe and draw name that
    folder, with its steps.

    Raises:
        ValueError: one line naming the file (not JSON, or not such a record).
        OSError: the file cannot be read.
    """
    try:
        data = json.loads(path.read_bytes())
    except ValueError as exc:  # JSONDecodeError and UnicodeDecodeError
        problem: str | None = f"not JSON: {exc}"
    else:
        problem = _record_problem(data, path.parent.name)
    if problem:
        raise ValueError(f"{path} is not a run record mpnode wrote ({problem}): restore it "
                         "from a copy, or move its folder away")
    return data


def _record_problem(data: Any, folder: str) -> str | None:
    """What makes `data` no record of the run folder named `folder`; None if nothing."""
    if not isinstance(data, dict):
        return "not a JSON object"
    scale, recipe, draw = data.get("scale"), data.get("recipe"), data.get("draw", 0)
    if scale not in _SCALE_ORDER:
        return f"scale {scale!r} is none of {', '.join(_SCALE_ORDER)}"
    if recipe not in _RECIPE_ORDER:
        return f"recipe {recipe!r} is none of {', '.join(_RECIPE_ORDER)}"
    if not isinstance(draw, int) or isinstance(draw, bool) or draw < 0:
        return f"draw {draw!r} is not a count"
    if folder != run_folder(scale, recipe, draw):
        return f"it is the record of {run_folder(scale, recipe, draw)}/, not of {folder}/"
    steps = data.get("steps")
    if not isinstance(steps, list) or not all(
            isinstance(s, dict) and isinstance(s.get("id"), str)
            and isinstance(s.get("result"), dict) for s in steps):
        return "its steps are not a list of steps, each with an id and a result"
    return None
