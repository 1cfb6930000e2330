"""The paper's experiments as data (`mpnode_cli/experiments/*.toml`) and their runner.

Every shipped experiment parses and validates at every scale; one runs end to end at the
tiny scale, then resumes (every step skipped), reruns exactly the steps downstream of a
changed one, and reruns a step whose folder an interruption left unfinished.
"""

from __future__ import annotations

import json
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
import tomllib
from pathlib import Path

import pytest
from conftest import child_env, lorenz_experiment
from typer.testing import CliRunner

from mpnode_cli.cli.app import app
from mpnode_cli.data.presets import PRESETS
from mpnode_cli.experiments import claims, scheduler, spec
from mpnode_cli.experiments import runner as experiment_runner
from mpnode_cli.experiments.report import write_report
from mpnode_cli.experiments.runner import PENDING_JSON, STEP_JSON, run_experiment

runner = CliRunner()
ROOT = Path(__file__).resolve().parents[2]
# An absolute path of the machine that wrote a file: a root folder right after a space,
# quote, backtick or bracket (not inside a URL, a relative path or a word).
ABSOLUTE_PATH = re.compile(
    r"(?<![\w.:/~-])/(?:work|tmp|home|root|Users|private|var|mnt|opt|srv|scratch)/")
# The issue's experiments (the paper's §4 and App. B), each one command.
PAPER_EXPERIMENTS = {
    "messages-pendulum", "messages-kuramoto", "finetune-lorenz", "finetune-lorenz-high",
    "finetune-lorenz-long", "finetune-gene", "finetune-kuramoto", "zeroshot-gene",
    "zeroshot-lorenz", "message-size", "finetune-quad", "message-pca",
}
# And mpnode's own: the paper's model against its recipe.
EXPERIMENTS = PAPER_EXPERIMENTS | {"ablation-model-recipe"}


def test_every_paper_experiment_is_shipped():
    assert set(spec.names()) == EXPERIMENTS


@pytest.mark.parametrize("name", sorted(EXPERIMENTS))
def test_shipped_experiment_validates(name):
    """Parses, names existing presets, options and steps at every scale (`spec.check`),
    and says where the paper's numbers come from."""
    experiment = spec.load(name)
    assert experiment.name == name and experiment.claims
    for step in experiment.steps:
        if step.verb == "generate" and step.preset:
            assert step.preset in PRESETS
        if step.reported:
            assert step.reported_in, f"{name}: step {step.id} gives no source for its numbers"
        for scale in spec.SCALES:
            options = spec.resolve(step, scale, "paper")
            if step.verb in spec.TRAINING and scale == "paper":
                assert options["config"]["epochs"] == 4000  # the authors' config


def _experiment(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "bad.toml"
    path.write_text(text)
    return path


GOOD = """
title = "t"
paper = "p"
[[steps]]
id = "data"
verb = "generate"
preset = "lorenz3"
[[steps]]
id = "run"
verb = "train"
data = "data"
epochs = 3
[[claims]]
claim = "c"
paper = "p"
where = "w"
holds = "run.test.mse < 1"
"""


@pytest.mark.parametrize(("change", "message"), [
    (('preset = "lorenz3"', 'preset = "lorenz4"'), "unknown preset 'lorenz4'"),
    (("epochs = 3", "epoch = 3"), "unknown config field 'epoch'"),
    (("epochs = 3", "model_options.message_size = 3"), "has no option 'message_size'"),
    (('data = "data"', 'data = "nothing"'), "reads 'nothing', which is no earlier step"),
    (("epochs = 3", "run_dir = 'x'"), "'run_dir' is set by the runner"),
    (("epochs = 3", "recipe = 'theirs'"), "recipe"),
    (("run.test.mse < 1", "other.test.mse < 1"), "unknown step 'other'"),
    (("run.test.mse < 1", "run.test.mse about 1"), "is not LEFT OP RIGHT"),
    (('verb = "train"', 'verb = "fly"'), "steps.1"),
])
def test_bad_spec_is_one_line(tmp_path, change, message):
    spec.load(_experiment(tmp_path, GOOD))  # the good one loads
    with pytest.raises(ValueError, match=message) as err:
        spec.load(_experiment(tmp_path, GOOD.replace(*change)))
    assert "\n" not in str(err.value)


def test_a_step_that_names_its_recipe_keeps_it_whatever_recipe_runs(tmp_path):
    """An ablation of recipes pins each step's; other steps take `--recipe`'s."""
    text = GOOD.replace("epochs = 3", "epochs = 3\nrecipe = 'paper'")
    pinned = spec.load(_experiment(tmp_path, text))
    plain = spec.load(_experiment(tmp_path, GOOD))
    for recipe in ("paper", "mpnode"):
        assert spec.resolve(pinned.steps[1], "small", recipe)["recipe"] == "paper"
        assert spec.resolve(plain.steps[1], "small", recipe)["recipe"] == recipe
    ablation = spec.load("ablation-model-recipe")
    trained = [s for s in ablation.steps if s.verb == "train"]
    assert sorted(spec.resolve(s, "paper", "mpnode")["recipe"] for s in trained) == \
        ["mpnode"] * 4 + ["paper"] * 4
    assert {spec.resolve(s, "small", "paper")["config"]["time_limit"] for s in trained} == {480}


def test_claims_are_judged_on_results():
    results = {"a": {"test": {"mse": 0.1}}, "b-c": {"test": {"mse": 0.3}}}
    assert claims.judge("a.test.mse < b-c.test.mse", results) == (True, "0.1 < 0.3")
    assert claims.judge("a.test.mse > 0.5 * b-c.test.mse", results) == (False, "0.1 > 0.15")
    assert claims.judge("a.val.mse < 1", results) == (None, "— < 1")


@pytest.mark.parametrize(("args", "message"), [
    (["nope"], "unknown experiment 'nope'"),
    (["messages-pendulum", "--scale", "huge"], "unknown scale 'huge'"),
    (["messages-pendulum", "--recipe", "theirs"], "unknown recipe 'theirs'"),
    (["messages-pendulum", "--jobs", "0"], "jobs: Input should be greater than or equal to 1"),
])
def test_cli_refuses_bad_input_in_one_line(args, message, tmp_path):
    result = runner.invoke(app, ["experiment", "run", *args, "--work", str(tmp_path)])
    assert result.exit_code == 2, result.output
    errors = [line for line in result.output.splitlines() if line.startswith("Error:")]
    assert len(errors) == 1 and message in errors[0]


def test_cli_lists_the_experiments():
    result = runner.invoke(app, ["experiment", "list"])
    assert result.exit_code == 0, result.output
    assert all(name in result.output for name in PAPER_EXPERIMENTS)


def _measured_run(out: Path, name: str, folder: str, steps: dict[str, dict]) -> None:
    (out / name / folder).mkdir(parents=True)
    (out / name / folder / "results.json").write_text(json.dumps({
        "machine": {"threads": 1},
        "steps": [{"id": step, "result": result} for step, result in steps.items()]}))


def test_paper_scale_cost_is_estimated_from_measured_seconds_per_epoch(tmp_path):
    """A training step at the paper's scale: its epochs × the measured seconds per epoch
    per training trajectory × its training trajectories (the pendulum's 500 × 0.7)."""
    from mpnode_cli.experiments.estimate import paper_cost

    _measured_run(tmp_path, "messages-pendulum", "small-paper",
                  {"messages": {"seconds_per_epoch": 2.0, "trajectories": 140}})
    cost = paper_cost(spec.load("messages-pendulum"), tmp_path)
    assert cost.core_hours == pytest.approx(4000 * 2.0 / 140 * 350 / 3600)
    assert cost.missing == ["no-messages"] and cost.sources == ["small-paper"]
    assert cost.shown() == "≥ 5.6"
    # L2S trains CI-sized at the small scale: it costs more at the paper's (marked *).
    _measured_run(tmp_path, "zeroshot-gene", "small-mpnode", {
        "train-gene-ba-4x4": {"seconds_per_epoch": 0.7, "trajectories": 140},
        "l2s": {"seconds_per_epoch": 12.0, "trajectories": 140}})
    gene = paper_cost(spec.load("zeroshot-gene"), tmp_path)
    assert gene.resized == ["l2s"] and gene.shown().endswith("*") and not gene.missing
    # A step with a wall-time budget (l2s-full: 3600 s at the paper's scale) costs its
    # budget, measured or not.
    trained = 4000 * (0.7 + 12.0) / 140 * 140 / 3600  # the pairs' 140 training trajectories
    assert gene.core_hours == pytest.approx(trained + 3600 / 3600)
    assert paper_cost(spec.load("message-pca"), tmp_path).shown() == "—"

    result = runner.invoke(app, ["experiment", "list", "--scale", "paper", "--out",
                                 str(tmp_path)], env={"COLUMNS": "200"})
    assert result.exit_code == 0, result.output
    assert "paper, core-h" in result.output and "≥ 5.6" in result.output
    assert "seconds per epoch per training trajectory measured" in result.output
    assert "costs more than shown" in result.output
    refused = runner.invoke(app, ["experiment", "list", "--scale", "tiny"])
    assert refused.exit_code == 2 and "unknown scale 'tiny'" in refused.output


def _statuses(record) -> dict[str, str]:
    return {step.id: step.status for step in record.steps}


def test_tiny_run_reports_resumes_and_reruns_what_changed(tmp_path):
    work, out = tmp_path / "work", tmp_path / "reports"
    experiment = spec.load("messages-pendulum")

    def run(exp):
        record = run_experiment(exp, scale="tiny", recipe="mpnode", work=work)
        write_report(record, exp, out)
        return record

    first = run(experiment)
    assert set(_statuses(first).values()) == {"ran"}
    report = (out / "messages-pendulum" / "report.md").read_text()
    assert "| MSE | hold x(0) | time mean | hold ÷ ours | mean ÷ ours |" in report
    assert "messages zeroed" in report and "mpnode train " in report
    figures = list((out / "messages-pendulum" / "tiny-mpnode").glob("*.png"))
    assert figures and all(f.stat().st_size < 200_000 for f in figures)
    index = (out / "README.md").read_text()
    assert "not run" in index  # tiny runs measure nothing and stay out of the index

    saved = out / "messages-pendulum" / "tiny-mpnode" / "results.json"
    facts = {k: json.loads(saved.read_text())[k] for k in ("started", "wall_seconds")}
    second = run(experiment)
    assert set(_statuses(second).values()) == {"skipped"}
    assert [s.result for s in second.steps] == [s.result for s in first.steps]
    # A rerun that ran nothing keeps the saved run's facts (when it ran, and which steps).
    kept = json.loads(saved.read_text())
    assert {k: kept[k] for k in facts} == facts
    assert {step["status"] for step in kept["steps"]} == {"ran"}

    # A changed step reruns, with every step after it that reads it; the rest is reused.
    fields = tomllib.loads(spec.shipped("messages-pendulum").read_text())
    next(s for s in fields["steps"] if s["id"] == "no-messages")["seed"] = 1
    changed = run(spec.Experiment(**{**fields, "name": "messages-pendulum"}))
    assert _statuses(changed) == {
        "pendulum": "skipped", "messages": "skipped", "no-messages": "ran", "test": "skipped",
        "zeroed": "skipped", "no-messages-test": "ran", "curves": "ran"}

    # A step an interruption left without its step.json runs again, alone.
    zeroed = next(s for s in changed.steps if s.id == "zeroed")
    (Path(zeroed.folder) / STEP_JSON).unlink()
    again = run(experiment)
    assert [k for k, v in _statuses(again).items() if v != "skipped"] == ["zeroed"]
    # A training interrupted after some epochs (its last.pt saved) continues from there.
    messages = next(s for s in again.steps if s.id == "messages")
    folder = Path(messages.folder)
    (folder / STEP_JSON).unlink()
    (folder / "run" / "summary.json").unlink()
    (folder / PENDING_JSON).write_text(json.dumps({"fingerprint": messages.fingerprint}))
    resumed = run(experiment)
    assert [k for k, v in _statuses(resumed).items() if v != "skipped"] == ["messages"]
    assert _statuses(resumed)["messages"] == "resumed"
    assert resumed.steps[1].result["best_epoch"] == messages.result["best_epoch"]
    # The index shows a non-tiny run's comparisons (here the same records, relabelled).
    resumed.scale = "small"
    write_report(resumed, experiment, tmp_path / "index")
    rows = [line for line in (tmp_path / "index" / "README.md").read_text().splitlines()
            if "(small, 1 seed)" in line]
    assert len(rows) == len(experiment.claims)
    assert all(" < " in row or " > " in row for row in rows)
    saved = json.loads((out / "messages-pendulum" / "tiny-mpnode" / "results.json").read_text())
    assert saved["scale"] == "tiny" and len(saved["claims"]) == len(experiment.claims)
    # The work folder (under /tmp here) is nowhere in what a report commits.
    assert saved["work"] == "<work>" and "--work <work>" in saved["command"]
    assert saved["steps"][0]["folder"] == Path(first.steps[0].folder).name
    for written in (out / "messages-pendulum").rglob("*"):
        if written.suffix in (".md", ".json"):
            assert not ABSOLUTE_PATH.search(written.read_text()), written


def test_table2_per_mean_does_not_depend_on_the_normalization():
    # One run's validation errors in two normalizations: the same predictions, scaled by
    # the square of a std ratio, as a finetune (parent's normalization) and a scratch run.
    run = {"best_epoch": 40, "table2": 40 * 0.02, "val": {"mse": 0.02, "time_mean": 0.5},
           "test": {"mse": 0.03, "time_mean": 0.6}}
    scaled = {**run, "table2": 40 * 0.02 * 9.0, "val": {"mse": 0.02 * 9.0,
                                                         "time_mean": 0.5 * 9.0},
              "test": {"mse": 0.03 * 9.0, "time_mean": 0.6 * 9.0}}
    assert claims.with_derived(run)["test_per_mean"] == pytest.approx(0.05)
    assert claims.judge("a.test.mse < b.test.mse", {"a": scaled, "b": run})[0] is False
    assert claims.with_derived(scaled)["test_per_mean"] == pytest.approx(0.05)
    results = {"a": run, "b": scaled}
    assert claims.with_derived(run)["table2_per_mean"] == pytest.approx(40 * 0.02 / 0.5)
    assert claims.judge("a.table2 < b.table2", results)[0] is True  # units differ
    holds, shown = claims.judge("a.table2_per_mean < b.table2_per_mean", results)
    assert holds is False and shown == "1.6 < 1.6"
    assert claims.with_derived({"best_epoch": 3, "val": {"mse": None}}) == {
        "best_epoch": 3, "val": {"mse": None}}  # nothing to derive from


def test_a_verdict_names_the_runs_that_did_not_beat_the_time_mean():
    # Two training runs below and at the time-mean predictor, and an evaluation that is
    # meant to be worse (messages zeroed): only the unlearned training run is named.
    learned = {"best_epoch": 9, "test": {"mse": 0.1, "time_mean": 1.0}}
    flat = {"best_epoch": 9, "test": {"mse": 1.08, "time_mean": 1.06}}
    zeroed = {"mse": 2.0, "time_mean": 1.0}
    results = {"on": learned, "off": flat, "zeroed": zeroed}
    assert claims.not_learned("on.test.mse < off.test.mse", results) == ["off"]
    assert claims.not_learned("zeroed.mse > on.test.mse", results) == []
    assert claims.not_learned("2 * off.test.mse > off.min_val_loss", results) == ["off"]
    # Holding against a run that never learned tests nothing; failing against it does.
    assert claims.verdict("on.test.mse < off.test.mse", results)[2] == (
        "not tested (off, the side it beats, did not learn) (off: not below the time mean)")
    assert claims.verdict("off.test.mse > on.test.mse", results)[2].startswith(
        "not tested (off, the side it beats")
    assert claims.verdict("off.test.mse < on.test.mse", results)[2] == (
        "**no** (off: not below the time mean)")
    assert claims.verdict("zeroed.mse > on.test.mse", results)[2] == "yes"
    assert claims.verdict("on.val.mse < 1", results)[2] == "—"
    # 1.006× below the time mean "beats" it but has barely learned, as has 2.9×; 10× has.
    results["near"] = {"best_epoch": 9, "test": {"mse": 1.0, "time_mean": 1.006}}
    results["weak"] = {"best_epoch": 9, "test": {"mse": 1.0, "time_mean": 2.9}}
    assert claims.barely_learned("near.test.mse < weak.test.mse", results) == ["near", "weak"]
    assert claims.barely_learned("on.test.mse < off.test.mse", results) == []
    assert claims.verdict("near.test.mse < on.test.mse", results)[2] == (
        "**no** (near: barely learned, 1.01× below the time mean)")
    # Neither side learned: the claim is not tested, whichever way the numbers fall.
    results["flat2"] = {"best_epoch": 9, "test": {"mse": 1.2, "time_mean": 1.0}}
    holds, _, said = claims.verdict("off.test.mse < flat2.test.mse", results)
    assert holds is None and said == ("not tested (no run it compares learned) (off: not "
                                      "below the time mean; flat2: not below the time mean)")
    assert claims.verdict("off.test.mse < 2 * off.test.mse", results)[2].startswith("not tested")
    # A member of an ensemble learned: tested, with the notes.
    mixed = {"best_epoch": 9, "test": {"mse": 1.2, "time_mean": 1.0},
             "members": [{"best_epoch": 9, "test": {"mse": 1.2, "time_mean": 1.0}},
                         {"best_epoch": 9, "test": {"mse": 0.1, "time_mean": 1.0}}]}
    assert not claims.nothing_learned("m.test.mse < 2", {"m": mixed})
    assert claims.beaten_unlearned("0.01 < m.test.mse", {"m": mixed}) == []
    assert claims.beaten_unlearned("0.01 < off.test.mse", results) == ["off"]


def test_a_verdict_says_when_the_model_is_not_the_papers():
    """An MP-NODE run with PNA (mpnode's recipe for gene) is not the paper's mean-aggregating
    model; a claim on an evaluation of it says so too, through its checkpoint."""
    experiment = spec.Experiment(**{**tomllib.loads(GOOD), "name": "good"})
    experiment.steps.append(spec.EvaluateStep(id="test", verb="evaluate", checkpoint="run",
                                              data="data"))
    run = {"best_epoch": 3, "model": "mpnode", "model_options": {"aggregate": "pna"},
           "test": {"mse": 0.001, "time_mean": 0.5}}
    results = {"run": run, "test": {"mse": 0.002}}
    assert claims.verdict("run.test.mse < 1", results, experiment)[2] == (
        "yes (PNA aggregation, not the paper's mean)")
    assert claims.verdict("test.mse < 1", results, experiment)[2] == (
        "yes (PNA aggregation, not the paper's mean)")
    mean = {**run, "model_options": {"aggregate": "mean"}}
    assert claims.verdict("run.test.mse < 1", {"run": mean}, experiment)[2] == "yes"


def _index_of(reports: Path, name: str, results: dict) -> str:
    """The index `rebuild_index` writes for one shipped experiment `name` whose small-scale
    mpnode-recipe records hold `results` (step id → result)."""
    from mpnode_cli.experiments.index import rebuild_index

    folder = reports / name / "small-mpnode"
    folder.mkdir(parents=True)
    (folder / "results.json").write_text(json.dumps({
        "scale": "small", "recipe": "mpnode",
        "steps": [{"id": step, "result": result} for step, result in results.items()]}))
    return rebuild_index(reports).read_text()


def test_the_index_lists_the_verdicts_that_rest_on_unlearned_runs(tmp_path):
    """From stored results alone: a claim comparing a run 1.01× below the time mean is
    listed under the table, and a PNA model is named in its verdict."""
    results = {"train-gene-ba-4x4": {"best_epoch": 5, "model": "mpnode",
                                     "model_options": {"aggregate": "pna"},
                                     "val": {"mse": 0.001},
                                     "test": {"mse": 0.001, "time_mean": 0.5}},
               "l2s": {"best_epoch": 5, "model": "l2s", "model_options": {},
                       "val": {"mse": 0.5}, "test": {"mse": 0.5, "time_mean": 0.505}},
               "zeroshot": {"gene-er-4x4": {"mse": 0.002}, "gene-ws-4x4": {"mse": 0.003}}}
    index = _index_of(tmp_path, "zeroshot-gene", results)
    row = next(line for line in index.splitlines() if "BA test error at or below" in line)
    assert row.endswith("| — / yes (PNA aggregation, not the paper's mean) |")
    weak = index.split("## Verdicts that rest on runs that did not learn")[1]
    assert ("- zeroshot-gene, `--scale small --recipe mpnode`: MP-NODE's validation error on "
            "BA is below L2S's: l2s (barely learned, 1.01× below the time mean).") in weak


def test_the_index_flags_table2_figures_of_best_epoch_0_or_the_budgets_end(tmp_path):
    """A Table-2 claim whose scratch member had its best epoch at 0, and whose finetune ran
    to the last epoch of its budget, is listed with both; a claim on test errors is not."""
    def run(best, mse):
        return {"best_epoch": best, "epochs": 50, "table2": best * mse, "model": "mpnode",
                "val": {"mse": mse, "time_mean": 1.0}, "test": {"mse": mse, "time_mean": 1.0}}

    scratch = {**run(10, 0.1), "members": [run(10, 0.1), run(0, 0.2)]}
    results = {"finetune-50": {**run(50, 0.05), "members": [run(50, 0.05), run(40, 0.06)]},
               "scratch-50": scratch}
    index = _index_of(tmp_path, "finetune-lorenz", results)
    first = next(line for line in index.splitlines() if line.startswith("| [finetune-lorenz]"))
    assert "finetune-50: member 0's best epoch is the budget's last (50): not converged" in first
    weak = index.split("## Verdicts that rest on runs")[1]
    flagged = [line for line in weak.splitlines() if line.startswith("- finetune-lorenz")]
    assert flagged and all("scratch-50 (member 1's best epoch is 0 (figure 0))" in line
                           for line in flagged)
    assert any("finetune-50 (member 0's best epoch is the budget's last (50): not "
               "converged)" in line for line in flagged)
    assert all("table2" in next(c.holds for c in spec.load("finetune-lorenz").claims
                                if c.claim in line) for line in flagged)


def test_a_claim_on_a_step_not_run_is_not_listed_as_resting_on_unlearned_runs(tmp_path):
    """finetune-gene's record without its L2S step: the L2S claims compared nothing, so
    they read — alone and are not listed under the table, though the finetune they name
    barely learned; its claim against scratch, which was judged, is listed."""
    def run(mse):
        return {"best_epoch": 100, "epochs": 250, "table2": 100 * mse, "model": "mpnode",
                "val": {"mse": mse, "time_mean": 1.0}, "test": {"mse": mse, "time_mean": 1.0},
                "table2_per_mean": 100 * mse}

    results = {"finetune-8x8": run(0.9), "scratch-8x8": run(0.01),
               "finetune-8x8-renorm": run(0.01)}
    index = _index_of(tmp_path, "finetune-gene", results)
    rows = [line for line in index.splitlines() if "beats L2S" in line and "46.64" in line]
    assert len(rows) == 3 and all(row.endswith("| — / — |") for row in rows)
    weak = index.split("## Verdicts that rest on runs")[1]
    assert "L2S" not in weak
    assert ("Finetuned beats scratch on the Table-2 figure, gene 4×4 → 8×8: finetune-8x8 "
            "(barely learned, 1.11× below the time mean)") in weak
    assert claims.verdict("finetune-8x8.table2 < l2s-8x8.table2", results)[2] == "—"


def test_the_absolute_path_check_tells_paths_from_urls():
    for text in ("--work /work/x/y", "`/tmp/qruns`", '"/home/me/a"', "(/Users/me/b)"):
        assert ABSOLUTE_PATH.search(text), text
    for text in ("https://example.org/home/x", "reports/work/x", "~/tmp/x", "a.b/var/x",
                 "file:///tmp/x", "<work>/gene", "/workshop/"):
        assert not ABSOLUTE_PATH.search(text), text


def test_recorded_paths_are_relative_or_placeholders(tmp_path, monkeypatch):
    """What the runner and the benchmarks record of a path: relative as given, relative to
    the current folder when under it, else a placeholder; commands as run from --work."""
    from mpnode_cli.experiments.commands import from_work
    from mpnode_cli.file_records import shown_argv, shown_path

    monkeypatch.chdir(tmp_path)
    assert shown_path(tmp_path / "runs" / "x", "<work>") == "runs/x"
    assert shown_path("runs/x", "<work>") == "runs/x"
    assert shown_path("/elsewhere/x", "<work>") == "<work>"
    assert shown_argv(["--runs", "/elsewhere/q", "--data", str(tmp_path / "d"), "--only",
                       "a"]) == ["--runs", "<runs>", "--data", "d", "--only", "a"]
    line = "mpnode train /w/a/data.h5 --run-dir '/w/b c/run' --x ../w/y --out=/w/z"
    assert from_work(line, Path("/w")) == (
        "mpnode train a/data.h5 --run-dir 'b c/run' --x ../w/y --out=z")

def test_committed_reports_hold_no_absolute_paths():
    """Reports and benchmark results are committed: the folders of the machine that ran
    them (step folders, --work, --out, data and run folders) are written relative to a
    folder the report names, or as placeholders (`<work>`)."""
    files = [path for folder in ("reports", "bench/results") for path in (ROOT / folder).rglob("*")
             if path.suffix in (".md", ".json", ".csv", ".txt", ".toml")]
    assert files
    found = {str(path.relative_to(ROOT)): match.group(0) for path in files
             for match in [ABSOLUTE_PATH.search(path.read_text(errors="replace"))] if match}
    assert not found, f"absolute paths in committed files: {found}"



def test_loss_curves_are_drawn_in_time_mean_units(tmp_path, monkeypatch):
    """A finetune's losses are in its parent's normalization: each run's curves are divided
    by its own time-mean predictor's validation MSE (raw when one has none)."""
    from mpnode_cli.experiments.steps import plot_losses
    from mpnode_cli.report import plots

    drawn = {}
    monkeypatch.setattr(plots, "plot_curves",
                        lambda runs, path, **kw: drawn.update(runs=runs, **kw) or path)
    metrics = {"f": [{"epoch": 1, "train_loss": 2.0, "val_mse": 4.0}],
               "s": [{"epoch": 1, "train_loss": 0.5, "val_mse": None}]}
    results = {"f": {"val": {"time_mean": 4.0}}, "s": {"val": {"time_mean": 0.5}}}
    labels = {"f": "finetuned", "s": "scratch"}
    plot_losses(labels, metrics, results, tmp_path / "loss.png")
    assert drawn["runs"] == {"finetuned": [{"epoch": 1, "train_loss": 0.5, "val_mse": 1.0}],
                             "scratch": [{"epoch": 1, "train_loss": 1.0, "val_mse": None}]}
    assert all("time-mean" in title for title in drawn["titles"])
    drawn.clear()
    plot_losses(labels, metrics, {**results, "s": {"val": {}}}, tmp_path / "loss.png")
    assert drawn["runs"] == {"finetuned": metrics["f"], "scratch": metrics["s"]}
    assert "titles" not in drawn


def test_a_one_group_bar_chart_is_wide_enough_for_its_title(tmp_path):
    from matplotlib.image import imread

    from mpnode_cli.report.plots import plot_bars

    title = "Table-2 figure (lower is better)"
    path = plot_bars({"gene 8×8": {"finetuned": 700.0, "scratch": 200.0}}, tmp_path / "b.png",
                     ylabel="best epoch × min validation loss", title=title, dpi=50)
    assert imread(path).shape[1] >= (1.0 + 0.085 * len(title)) * 50 - 1


PCA = lorenz_experiment("t", 0.5, """\
[[steps]]
id = "pca"
verb = "evaluate"
checkpoint = "run"
data = "data"
split = "all"
plot = false
pca = 2
trajectories = 4
[[claims]]
claim = "c"
paper = "p"
where = "w"
holds = "pca.pca.growth > pca.pca.untrained.growth"
""", run_epochs=2)


def test_the_message_pca_is_judged_against_an_untrained_model(tmp_path):
    """Messages start at zero, so they spread out in any model: the PCA step takes the same
    statistic of the same architecture with its initial weights, and the claim compares
    the trained model's growth with that one's. A step without a PCA keeps its options."""
    experiment = spec.load(_experiment(tmp_path, PCA))
    record = run_experiment(experiment, scale="small", recipe="mpnode", work=tmp_path / "w")
    pca = record.steps[-1].result["pca"]
    for stats in (pca, pca["untrained"]):
        assert stats["growth"] == pytest.approx(stats["spread_last"] / stats["spread_first"])
    assert pca["untrained"]["spread_last"] != pytest.approx(pca["spread_last"])
    holds, shown = claims.judge(experiment.claims[0].holds,
                              {s.id: s.result for s in record.steps})
    assert holds is not None and " > " in shown
    plain = spec.EvaluateStep(id="e", verb="evaluate", checkpoint="run", data="data")
    assert "pca_untrained" not in spec.resolve(plain, "small", "mpnode")
    assert spec.resolve(experiment.steps[-1], "small", "mpnode")["pca_untrained"] is True

HOLD_LOCK = """
import fcntl, sys
with open(sys.argv[1], "a") as handle:
    fcntl.flock(handle, fcntl.LOCK_EX)
    print("held", flush=True)
    sys.stdin.readline()
"""


def test_a_step_another_process_holds_is_left_to_it_and_the_rest_goes_on(tmp_path):
    """Two runs sharing a work folder: a step the other process holds (its `flock` on
    WORK/<step folder>.lock) is left to it; the run goes on with the steps that do not read
    it, says it waits, and takes the step itself once the other process lets go of it
    unfinished (it simply exits)."""
    experiment = spec.load("messages-pendulum")
    work = tmp_path / "work"
    work.mkdir()
    held = next(entry for entry in experiment_runner.plan_steps(experiment, "tiny", "mpnode", work)
                if entry.step.id == "messages")
    other = subprocess.Popen([sys.executable, "-c", HOLD_LOCK, f"{held.folder}.lock"],
                             text=True, stdin=subprocess.PIPE, stdout=subprocess.PIPE)
    events, records, finished = [], [], threading.Event()

    def run():
        records.append(run_experiment(experiment, scale="tiny", recipe="mpnode", work=work,
                                      progress=events.append))
        finished.set()

    try:
        assert other.stdout.readline().strip() == "held"
        threading.Thread(target=run, daemon=True).start()
        deadline = time.monotonic() + 120
        while not any(e["event"] == "waiting" for e in events) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert [e["id"] for e in events if e["event"] == "waiting"] == ["messages"]
        started = [e["id"] for e in events if e["event"] == "step"]
        assert started == ["pendulum", "no-messages", "no-messages-test"]
        assert not finished.is_set()
        other.stdin.write("\n")
        other.stdin.flush()
        other.wait(timeout=30)
        assert finished.wait(120), "still waiting after the other process let go"
    finally:
        other.kill()
    assert set(_statuses(records[0]).values()) == {"ran"}


def _timeless(value):
    """`value` without its wall-clock entries, which differ between any two runs."""
    if isinstance(value, dict):
        return {key: _timeless(item) for key, item in value.items()
                if "second" not in key and "wall" not in key}
    if isinstance(value, list):
        return [_timeless(item) for item in value]
    return value


@pytest.fixture(scope="module")
def pendulum_alone(tmp_path_factory):
    """messages-pendulum at the tiny scale, run in one process (the reference of the
    `--jobs` tests)."""
    return run_experiment(spec.load("messages-pendulum"), scale="tiny", recipe="mpnode",
                          work=tmp_path_factory.mktemp("alone") / "one")


def test_a_worker_process_runs_steps_as_the_run_does(tmp_path, pendulum_alone):
    """What `--jobs` adds: a spawned worker takes steps as they become ready. Here the
    worker runs a whole experiment alone; its results equal a run in one process, the run
    that started it (the same token) counts its steps as run, any other run as done earlier."""
    experiment, alone = spec.load("messages-pendulum"), pendulum_alone
    steps = experiment_runner.plan_steps(experiment, "tiny", "mpnode", tmp_path / "two")
    workers = scheduler.start_workers(steps, "this-run", 1)
    for worker in workers:
        worker.join(timeout=300)
    assert [worker.exitcode for worker in workers] == [0]

    events = []
    collected = scheduler.take_steps(steps, "this-run", events.append)
    assert {record.status for record in collected.values()} == {"ran"}
    assert all(event.get("worker") for event in events if event["event"] == "step")
    assert ([_timeless(collected[step.id].result) for step in alone.steps]
            == [_timeless(step.result) for step in alone.steps])
    later = scheduler.take_steps(steps, "another-run", lambda event: None)
    assert {record.status for record in later.values()} == {"skipped"}


def test_jobs_run_every_step_once_with_the_same_results(tmp_path, pendulum_alone):
    """`run_experiment(jobs=2)`: every step ran in this run (by the run or its worker),
    each once, and the results are a one-process run's."""
    experiment, alone = spec.load("messages-pendulum"), pendulum_alone
    events = []
    both = run_experiment(experiment, scale="tiny", recipe="mpnode", work=tmp_path / "two",
                          jobs=2, progress=events.append)
    assert set(_statuses(both).values()) == {"ran"}
    started = [event["id"] for event in events if event["event"] == "step"]
    assert sorted(started) == sorted(step.id for step in experiment.steps)
    assert [_timeless(s.result) for s in both.steps] == [_timeless(s.result) for s in alone.steps]
    assert both.machine["jobs"] == 2


SLOW_PAIR = lorenz_experiment("two long trainings side by side", 0.2, """\
[[steps]]
id = "first"
verb = "train"
data = "data"
epochs = 100000
solver.compile = false  # compiling (~30 s) is not what is stopped here

[[steps]]
id = "second"
verb = "train"
data = "data"
epochs = 100000
solver.compile = false
seed = 1
""")


def _children(pid: int) -> list[int]:
    tasks = Path(f"/proc/{pid}/task")
    return [int(child) for task in tasks.iterdir()
            for child in (task / "children").read_text().split()]


def _cmdline(pid: int) -> str:
    """A live process's command line ('' once it has gone, or is a zombie)."""
    try:
        if "zombie" in Path(f"/proc/{pid}/status").read_text():
            return ""
        return Path(f"/proc/{pid}/cmdline").read_text().replace("\0", " ").strip()
    except FileNotFoundError:
        return ""


@pytest.mark.skipif(not Path("/proc/self/task").exists(), reason="reads /proc (Linux)")
@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGKILL], ids=["SIGTERM", "SIGKILL"])
def test_a_stopped_run_leaves_no_worker_and_both_trainings_can_resume(tmp_path, signum):
    """`experiment run --jobs 2` stopped while the run and its worker each train. SIGTERM:
    exit 143 with one line. SIGKILL (the run cannot stop its workers): the worker notices
    and stops itself. Either way no worker is left behind, and each training keeps a last
    epoch that the next run resumes from (its step is planned as 'resumed')."""
    (tmp_path / "pair.toml").write_text(SLOW_PAIR)
    work = tmp_path / "work"
    proc = subprocess.Popen(
        [sys.executable, "-m", "mpnode_cli", "experiment", "run", str(tmp_path / "pair.toml"),
         "--jobs", "2", "--threads", "1", "--seeds", "1", "--work", str(work), "--out",
         str(tmp_path / "out")],
        env=child_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    steps = experiment_runner.plan_steps(spec.load(tmp_path / "pair.toml"), "small", "mpnode", work)
    trainings = [entry for entry in steps if entry.step.verb == "train"]
    deadline = time.monotonic() + 180
    try:
        while not all((e.folder / "run" / "checkpoints" / "last.pt").is_file()
                      for e in trainings):
            assert proc.poll() is None, proc.communicate()[1]
            assert time.monotonic() < deadline, "the two trainings did not both start"
            time.sleep(0.2)
        workers = _children(proc.pid)
        assert workers, "no worker process"
        proc.send_signal(signum)
        _, err = proc.communicate(timeout=90)
    finally:
        proc.kill()
    if signum == signal.SIGTERM:
        assert proc.returncode == 128 + signum, err
        assert "Interrupted (SIGTERM)" in err and "Traceback" not in err
    deadline = time.monotonic() + 60
    while any(_cmdline(pid) for pid in workers) and time.monotonic() < deadline:
        time.sleep(0.2)
    left = {pid: _cmdline(pid) for pid in workers if _cmdline(pid)}
    assert not left, left
    for entry in trainings:
        assert scheduler.resumable(entry.folder, entry.fingerprint), entry.step.id
        assert not (entry.folder / STEP_JSON).exists()
    assert list(tmp_path.glob("out/*")) == []  # no report from a run that did not finish


def test_an_option_added_later_leaves_fingerprints_alone_at_its_default():
    """Finished steps stay finished when the solver table gains `compact` (on by default):
    the fingerprint leaves it out at its default, and counts it when it is turned off."""
    from mpnode_cli.experiments.scheduler import step_fingerprint

    before = {"config": {"system": "gene", "solver": {"method": "tsit5", "rtol": 1e-8}}}
    now = {"config": {"system": "gene", "solver": {"method": "tsit5", "rtol": 1e-8,
                                                   "compact": True}}}
    off = {"config": {"system": "gene", "solver": {"method": "tsit5", "rtol": 1e-8,
                                                   "compact": False}}}
    assert step_fingerprint("generate", now, ["a"]) == step_fingerprint("generate", before, ["a"])
    assert step_fingerprint("generate", off, ["a"]) != step_fingerprint("generate", before, ["a"])



def test_experiment_report_rebuilds_the_committed_reports_from_their_records(tmp_path):
    """`mpnode experiment report` runs nothing: from a copy of the committed records it
    writes every committed report and the index again, byte for byte; a folder's README.md
    that mpnode did not write is refused in one line."""
    shutil.copytree(ROOT / "reports", tmp_path / "reports")
    for report in (tmp_path / "reports").glob("*/report.md"):
        report.unlink()
    (tmp_path / "reports" / "README.md").unlink()
    result = runner.invoke(app, ["experiment", "report", "--out", str(tmp_path / "reports")])
    assert result.exit_code == 0, result.output
    for path in [ROOT / "reports" / "README.md", *(ROOT / "reports").glob("*/report.md")]:
        rebuilt = tmp_path / "reports" / path.relative_to(ROOT / "reports")
        assert rebuilt.read_text() == path.read_text(), path
    (tmp_path / "own").mkdir()
    (tmp_path / "own" / "README.md").write_text("# my notes\n")
    result = runner.invoke(app, ["experiment", "report", "--out", str(tmp_path / "own")])
    assert result.exit_code == 2 and "README.md" in result.output
