"""`mpnode experiment run --seeds S`: every training an ensemble, every number per member,
claims decided from the members (`mpnode_cli.experiments.members`).

One tiny experiment runs with two seeds end to end; the verdict rule is checked on
hand-made results, and old single-seed records still render without ±.
"""

from __future__ import annotations

import copy
import json
import math
from pathlib import Path

import pytest
from conftest import lorenz_experiment
from typer.testing import CliRunner

from mpnode_cli.cli.app import app
from mpnode_cli.experiments import claims, members, spec
from mpnode_cli.experiments.index import rebuild_index
from mpnode_cli.experiments.report import rebuild_report, write_report
from mpnode_cli.experiments.runner import plan_steps, run_experiment

runner = CliRunner()

TWO = lorenz_experiment("two seeds", 0.3, """\
[[steps]]
id = "tuned"
verb = "finetune"
checkpoint = "run"
data = "data"
epochs = 1
[[steps]]
id = "test"
verb = "evaluate"
checkpoint = "tuned"
data = "data"
[[steps]]
id = "zero"
verb = "zeroshot"
checkpoint = "run"
data = ["data"]
plot = false
[[steps]]
id = "curves"
verb = "compare"
runs = ["tuned", "run"]
groups.all = ["tuned", "run"]
[[claims]]
claim = "finetuning helps"
paper = "p"
where = "w"
holds = "tuned.test.mse < run.test.mse"
""", run_epochs=2)


def _load(tmp_path: Path, text: str = TWO) -> spec.Experiment:
    path = tmp_path / "two.toml"
    path.write_text(text)
    return spec.load(path)


def test_seeds_are_in_the_fingerprint_of_every_step_that_reads_a_model(tmp_path):
    """S is a training's option (`seeds`), so its folder and every later step's differ
    between runs of different S; the data is shared; one seed keeps the options (and
    folders) it had before seeds."""
    experiment = _load(tmp_path)
    one = {e.step.id: e for e in plan_steps(experiment, "small", "mpnode", tmp_path)}
    two = {e.step.id: e for e in plan_steps(experiment, "small", "mpnode", tmp_path, seeds=2)}
    assert one["data"].folder == two["data"].folder
    assert all(one[i].folder != two[i].folder for i in one if i != "data")
    assert "seeds" not in one["run"].options["config"]
    assert two["run"].options["config"]["seeds"] == two["tuned"].options["config"]["seeds"] == 2
    refused = TWO.replace("epochs = 2", "epochs = 2\nseeds = 4")
    with pytest.raises(ValueError, match="'seeds' is set by the runner"):
        _load(tmp_path, refused)
    named = TWO.replace('id = "zero"', 'id = "members"')
    with pytest.raises(ValueError, match="'members' is the name of an ensemble's results"):
        _load(tmp_path, named)


def test_a_two_seed_run_trains_ensembles_and_reports_mean_and_std(tmp_path):
    experiment = _load(tmp_path)
    work, out = tmp_path / "work", tmp_path / "out"
    record = run_experiment(experiment, scale="small", recipe="mpnode", work=work, seeds=2)
    steps = {s.id: s for s in record.steps}
    assert record.seeds == 2 and "--seeds 2" in record.command
    for run_id in ("run", "tuned"):
        summary = json.loads((Path(steps[run_id].folder) / "run" / "summary.json").read_text())
        assert [m["seed"] for m in summary["members"]] == [0, 1]
        result = steps[run_id].result
        assert len(result["members"]) == 2 and "--seeds 2" in steps[run_id].commands[0]
        for k, member in enumerate(result["members"]):
            # A member's result has a single model's keys, its own numbers.
            assert set(result) - {"members"} <= set(member)
            assert member["seed"] == k and member["model"] == result["model"]
            assert member["min_val_loss"] == summary["members"][k]["min_val_loss"]
            assert member["table2"] == pytest.approx(member["best_epoch"]
                                                     * member["min_val_loss"])
            assert member["test"]["mse"] == summary["members"][k]["test"]["mse"]
            assert member["val"]["mse"] is not None and member["min_train_loss"] is not None
    from mpnode_cli.experiments.curves import unpack
    from mpnode_cli.training.run import read_metrics

    # Each member keeps its per-epoch curve, the run's metrics.jsonl column (float32).
    rows = read_metrics(Path(steps["run"].folder) / "run")
    for k, member in enumerate(steps["run"].result["members"]):
        assert unpack(member["curve"]["val_mse"]) == pytest.approx(
            [r["members"][k]["val_mse"] for r in rows], rel=1e-6)
        assert unpack(member["curve"]["seconds"]) == pytest.approx(
            [r["seconds"] for r in rows], rel=1e-6)
    # The finetune's member k starts from its parent's: its epoch 0 validates the parent's
    # member k at its best (the same data, the parent's normalization).
    start = read_metrics(Path(steps["tuned"].folder) / "run")[0]["members"]
    assert [m["val_loss"] for m in start] == pytest.approx(
        [m["min_val_loss"] for m in steps["run"].result["members"]], rel=1e-5)
    test, zero, curves = steps["test"].result, steps["zero"].result, steps["curves"].result
    assert [m["mse"] for m in test["members"]] == [
        m["test"]["mse"] for m in steps["tuned"].result["members"]]
    assert len(zero["members"]) == 2 and set(zero["members"][0]) == {"data"}
    assert [m["runs"]["run"]["table2"] for m in curves["members"]] == [
        m["table2"] for m in steps["run"].result["members"]]

    write_report(record, experiment, out)
    report = (out / "two" / "report.md").read_text()
    assert "## `--scale small --recipe mpnode --seeds 2`" in report
    assert "ensemble of 2 members" in report
    tuned = members.values(steps["tuned"].result, "test.mse")
    mean, std = members.mean_and_std(tuned)
    assert f"| tuned | test | {mean:.4g} ± {std:.2g} |" in report
    row = next(line for line in report.splitlines() if line.startswith("| finetuning helps"))
    assert "; members: " in row and row.count(" < ") == 4
    assert any(word in row for word in ("| yes (holds for", "| **no** (holds for",
                                        "| undecided (holds for 1 of 2"))
    assert "run seeds 0–1" in report
    assert "| epochs to 3× | seconds to it | area ÷ time mean |" in report
    assert "curves not kept" not in report
    saved_path = out / "two" / "small-mpnode" / "results.json"
    saved = json.loads(saved_path.read_text())
    # A report saved before curves were kept: its cost columns read — and say why.
    old = copy.deepcopy(saved)
    for step in old["steps"]:
        for member in (step.get("result") or {}).get("members") or []:
            member.pop("curve", None)
    saved_path.write_text(json.dumps(old))
    rebuild_report(experiment, out)
    stale = (out / "two" / "report.md").read_text()
    assert "curves not kept" in stale and "| — | — | — |" in stale
    saved_path.write_text(json.dumps(saved))
    assert saved["seeds"] == 2 and saved["claims"][0]["seeds"] == 2
    assert saved["claims"][0]["outcome"] in ("holds", "fails", "undecided")

    again = run_experiment(experiment, scale="small", recipe="mpnode", work=work, seeds=2)
    assert {s.status for s in again.steps} == {"skipped"}


def _run(mse_a: list[float], mse_b: list[float], mean: float = 10.0) -> dict:
    """Two training runs' results with members' test MSEs (and a time mean of `mean`)."""
    def result(mses):
        rows = [{"best_epoch": 5, "test": {"mse": m, "time_mean": mean}} for m in mses]
        return {"best_epoch": 5, "test": {"mse": sum(mses) / len(mses), "time_mean": mean},
                "members": rows}

    return {"a": result(mse_a), "b": result(mse_b)}


CLAIM = "a.test.mse < b.test.mse"


@pytest.mark.parametrize(("a", "b", "outcome", "said"), [
    # Every member holds: holds, though the means are within the spread.
    ([1.0, 2.0, 3.0], [1.1, 2.1, 3.1], "holds", "yes (holds for 3 of 3 members)"),
    ([2.0, 2.0, 2.0], [1.0, 1.5, 1.9], "fails", "**no** (holds for 0 of 3 members)"),
    # Split, and the spread covers the gap of the means: undecided.
    ([1.0, 2.0, 3.0], [2.5, 1.5, 2.6], "undecided", "undecided (holds for 1 of 3 members; "
     "the means differ by less than their combined std)"),
    # Split, but the means are apart by more than the combined std: the means decide.
    ([1.0, 1.0, 1.0, 3.0], [3.0, 3.0, 3.0, 2.9], "holds", "yes (holds for 3 of 4 members; "
     "the means differ by more than their combined std, the claimed way)"),
    ([3.0, 3.0, 3.0, 1.0], [1.0, 1.0, 1.0, 1.1], "fails", "**no** (holds for 1 of 4 members; "
     "the means differ by more than their combined std, the other way)"),
])
def test_a_claim_is_decided_from_its_members(a, b, outcome, said):
    results = _run(a, b)
    decision = claims.decide_claim(CLAIM, results)
    assert decision.outcome == outcome and decision.members == len(a)
    holds, shown, verdict = claims.verdict(CLAIM, results)
    assert verdict == said
    assert holds == {"holds": True, "fails": False, "undecided": None}[outcome]
    mean_a, std_a = members.mean_and_std(a)
    assert shown.startswith(f"{mean_a:.4g} ± {std_a:.2g} < ")


def test_the_mean_and_std_rule():
    """Population stds, combined as sqrt(std_a² + std_b²), against the gap of the means,
    in the claimed direction (`>` too); a number side has no spread."""
    assert members.mean_and_std([1.0, 3.0]) == (2.0, 1.0)
    # Means 2 ± 1 and 4 ± 1: gap 2 > √2, so a split holds for `<` and fails for `>`.
    pairs = [(1.0, 5.0), (3.0, 3.0)]
    assert members.decide_pairs(pairs, "<").outcome == "holds"
    assert members.decide_pairs(pairs, ">").outcome == "fails"
    # Gap 2 < √5 (stds 1 and 2): undecided.
    assert members.decide_pairs([(1.0, 6.0), (3.0, 2.0)], "<").outcome == "undecided"
    assert math.hypot(1.0, 2.0) > 2.0
    # Against a number: 0.5 ± 0.5 < 0.9 is split and the gap 0.4 is within 0.5.
    assert members.decide_pairs([(0.0, 0.9), (1.0, 0.9)], "<").outcome == "undecided"
    assert members.decide_pairs([(0.5, None), (0.1, 0.2)], "<").outcome is None
    assert claims.verdict("a.test.mse < 0.9", {"a": {"members": [
        {"test": {"mse": 0.0}}, {"test": {"mse": 1.0}}]}})[1] == "0.5 ± 0.5 < 0.9 ± 0"


def test_a_single_seed_verdict_reads_as_before():
    results = {"a": {"best_epoch": 5, "test": {"mse": 0.1, "time_mean": 1.0}},
               "b": {"best_epoch": 5, "test": {"mse": 0.3, "time_mean": 1.0}}}
    assert claims.verdict(CLAIM, results) == (True, "0.1 < 0.3", "yes")
    assert claims.decide_claim(CLAIM, results).members == 1


def test_a_verdict_names_each_member_that_did_not_learn():
    """Member 1 of `b` is not below the time mean, member 0 of `a` barely (1.25×)."""
    results = _run([8.0, 1.0], [2.0, 12.0])
    assert claims.verdict(CLAIM, results)[2] == (
        "undecided (holds for 1 of 2 members; the means differ by less than their combined "
        "std; a: member 0 barely learned (1.25× below the time mean); b: member 1 not below "
        "the time mean)")
    assert claims.not_learned(CLAIM, results) == ["b"]
    assert claims.barely_learned(CLAIM, results) == ["a"]


def _record(out: Path, name: str, results: dict, scale: str = "small") -> None:
    folder = out / name / f"{scale}-mpnode"
    folder.mkdir(parents=True)
    (folder / "results.json").write_text(json.dumps({
        "scale": scale, "recipe": "mpnode",
        "steps": [{"id": step, "result": result} for step, result in results.items()]}))


def test_the_index_says_how_many_seeds_and_shows_mean_and_std(tmp_path):
    """A record of one seed (every committed one) shows its numbers as before, with
    "1 seed"; a record of ensembles its means ± std and the members' verdict."""
    assert spec.load("messages-pendulum").claims[1].holds == (
        "messages.test.mse < no-messages.test.mse")
    first, second = "messages", "no-messages"

    def run(mse):
        return {"best_epoch": 5, "model": "mpnode", "test": {"mse": mse, "time_mean": 10.0}}

    _record(tmp_path, "messages-pendulum", {first: run(0.1), second: run(0.3)})
    single = rebuild_index(tmp_path).read_text()
    row = next(line for line in single.splitlines() if "0.1 < 0.3 (small, 1 seed)" in line)
    assert "±" not in row and row.endswith("| — / yes |")

    ensemble = {step: {**run(sum(m) / 2), "members": [run(x) for x in m]}
                for step, m in ((first, [0.1, 0.2]), (second, [0.3, 0.5]))}
    (tmp_path / "messages-pendulum" / "small-mpnode" / "results.json").unlink()
    (tmp_path / "messages-pendulum" / "small-mpnode").rmdir()
    _record(tmp_path, "messages-pendulum", ensemble)
    index = rebuild_index(tmp_path).read_text()
    row = next(line for line in index.splitlines() if "< 0.4 ± 0.1 (small, 2 seeds)" in line)
    assert "0.15 ± 0.05 < 0.4 ± 0.1 (small, 2 seeds)" in row
    assert row.endswith("yes (holds for 2 of 2 members) |")


def test_a_row_of_one_seed_at_the_paper_scale_also_shows_the_seeded_smaller_run(tmp_path):
    """The paper scale's run (one seed) leads the cell; the small scale's run with three
    seeds follows on a second line, and each scale has its own verdict; with no seeded
    smaller run, the cell is the paper scale's alone."""
    first, second = "messages", "no-messages"

    def run(mse):
        return {"best_epoch": 5, "model": "mpnode", "test": {"mse": mse, "time_mean": 10.0}}

    _record(tmp_path, "messages-pendulum", {first: run(0.3), second: run(0.1)}, "paper")
    alone = rebuild_index(tmp_path).read_text()
    row = next(line for line in alone.splitlines() if "0.3 < 0.1 (paper, 1 seed)" in line)
    assert "<br>" not in row and row.endswith("| — / **no** |")

    seeded = {step: {**run(sum(m) / 3), "members": [run(x) for x in m]}
              for step, m in ((first, [0.1, 0.2, 0.3]), (second, [0.4, 0.5, 0.6]))}
    _record(tmp_path, "messages-pendulum", seeded, "small")
    index = rebuild_index(tmp_path).read_text()
    row = next(line for line in index.splitlines() if "0.3 < 0.1 (paper, 1 seed)" in line)
    assert "0.3 < 0.1 (paper, 1 seed)<br>0.2 ± 0.082 < 0.5 ± 0.082 (small, 3 seeds)" in row
    assert row.endswith("| — / paper: **no**; small: yes (holds for 3 of 3 members) |")


def test_the_index_says_what_has_run_and_which_steps_a_run_lacks(tmp_path):
    """A record without some of the experiment's steps (added since it ran) is listed with
    those steps; scales and recipes without a record read —."""
    steps = [step.id for step in spec.load("messages-pendulum").steps]
    result = {"best_epoch": 5, "model": "mpnode", "test": {"mse": 0.1, "time_mean": 1.0}}
    _record(tmp_path, "messages-pendulum", {step: result for step in steps[:-1]})
    index = rebuild_index(tmp_path).read_text()
    table = index[index.index("## What has run"):].splitlines()
    row = next(line for line in table if line.startswith("| messages-pendulum |"))
    assert row == f"| messages-pendulum | — | — | — | 1 seed; not run: {steps[-1]} |"
    row = next(line for line in table if line.startswith("| zeroshot-lorenz |"))
    assert row == "| zeroshot-lorenz | — | — | — | — |"


def test_cli_refuses_zero_seeds(tmp_path):
    result = runner.invoke(app, ["experiment", "run", "messages-pendulum", "--seeds", "0",
                                 "--work", str(tmp_path)])
    assert result.exit_code == 2, result.output
    assert "seeds: Input should be greater than or equal to 1" in result.output
