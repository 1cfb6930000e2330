"""Data draws (`mpnode experiment run --draw D`): other data for every generated dataset,
and each claim's margin with a 95% bootstrap interval over the draws and seeds."""

from __future__ import annotations

import json

import pytest
from conftest import invoke

from mpnode_cli.experiments import claims, saved, spec
from mpnode_cli.experiments.index import rebuild_index
from mpnode_cli.experiments.markdown import draws_sections


def test_a_draw_offsets_every_generated_datasets_seeds_and_draw_0_is_the_data_as_before():
    experiment = spec.load("messages-kuramoto")
    step = next(s for s in experiment.steps if s.verb == "generate")
    base = spec.resolve(step, "small", "mpnode")["config"]
    assert spec.resolve(step, "small", "mpnode", draw=0)["config"] == base
    drawn = spec.resolve(step, "small", "mpnode", draw=2)["config"]
    assert drawn["seed"] == base["seed"] + 2 * spec.DRAW_STRIDE
    assert drawn["graph_seed"] == base["graph_seed"] + 2 * spec.DRAW_STRIDE
    assert {k: v for k, v in drawn.items() if k not in ("seed", "graph_seed")} == {
        k: v for k, v in base.items() if k not in ("seed", "graph_seed")}
    trained = next(s for s in experiment.steps if s.verb == "train")
    assert spec.resolve(trained, "small", "mpnode", draw=2) == spec.resolve(
        trained, "small", "mpnode")  # only data change; the trainings follow their inputs


def _results(on: float, off: float) -> dict:
    return {"on": {"test": {"mse": on}}, "off": {"test": {"mse": off}}}


def _members(pairs: list[tuple[float, float]]) -> dict:
    """Results of ensembles whose members have these (on, off) test errors."""
    return {step: {"test": {"mse": sum(p[i] for p in pairs) / len(pairs)},
                   "members": [{"test": {"mse": p[i]}} for p in pairs]}
            for i, step in enumerate(("on", "off"))}


def test_the_interval_of_identical_draws_is_their_margin_the_claimed_way():
    draws = [_results(0.1, 0.3)] * 3
    assert claims.interval("on.test.mse < off.test.mse", draws) == pytest.approx((3, 3, 3))
    assert claims.interval("off.test.mse > on.test.mse", draws) == pytest.approx((3, 3, 3))
    assert claims.interval("on.test.mse < 0.2", draws) == pytest.approx((2, 2, 2))
    assert claims.interval("on.test.mse < other.test.mse", draws) is None  # missing
    # A draw that lacks a step (added after it ran) is left out, not the whole claim.
    partial = [{"on": {"test": {"mse": 0.1}}}, *draws]
    assert claims.interval("on.test.mse < off.test.mse", partial) == pytest.approx((3, 3, 3))


def test_two_draws_of_one_model_each_bound_the_interval_by_their_own_margins():
    """With two draws, a resample takes draw 0 twice, draw 1 twice, or one of each, so the
    2.5 and 97.5 percentiles are the two draws' own margins (closed form: 1.5 and 4)."""
    draws = [_results(0.2, 0.3), _results(0.1, 0.4)]
    margin, lower, upper = claims.interval("on.test.mse < off.test.mse", draws)
    assert margin == pytest.approx(0.7 / 0.3)
    assert (lower, upper) == pytest.approx((1.5, 4.0))


def test_a_side_of_mean_zero_leaves_the_interval_unbounded_not_undefined():
    """A finetune whose best epoch is 0 has a Table-2 figure of 0: a resample of only such
    draws has an infinite ratio. Two draws: a quarter of the resamples take the zero draw
    twice (ratio ∞), a half one of each ((0.3 + 0.4) / 0.1 = 7), a quarter the other twice
    (4), so the 97.5th percentile lies between two infinite ratios: ∞, where
    interpolating gave NaN."""
    draws = [_results(0.0, 0.3), _results(0.1, 0.4)]
    margin, lower, upper = claims.interval("on.test.mse < off.test.mse", draws)
    assert margin == pytest.approx(7.0)
    assert lower == pytest.approx(4.0)
    assert upper == float("inf")
    lines = draws_sections([{"scale": "small", "recipe": "mpnode", "draw": d,
                             "steps": [{"id": k, "result": v} for k, v in r.items()]}
                            for d, r in enumerate(draws)],
                           [("on beats off", "on.test.mse < off.test.mse")])
    assert "| on beats off | —, 4 | 7 | 4–∞ |" in lines


def test_members_are_resampled_within_their_draw():
    """One draw of two members: the resamples take member 0 twice, member 1 twice or one of
    each, so the interval runs from one member's margin to the other's."""
    draws = [_members([(0.1, 0.2), (0.1, 0.5)])]
    margin, lower, upper = claims.interval("on.test.mse < off.test.mse", draws)
    assert margin == pytest.approx(3.5)
    assert (lower, upper) == pytest.approx((2.0, 5.0))


def test_the_report_and_the_index_give_the_margin_over_draws(tmp_path):
    """From stored results alone: two draws of messages-kuramoto at the small scale."""
    for draw, (on, off) in enumerate([(0.01, 0.02), (0.01, 0.03)]):
        folder = tmp_path / "messages-kuramoto" / saved.run_folder("small", "mpnode", draw)
        folder.mkdir(parents=True)
        results = {"train-kuramoto10-ba": {"best_epoch": 5, "min_train_loss": on,
                                           "test": {"mse": on, "time_mean": 1.0}},
                   "no-messages": {"best_epoch": 5, "min_train_loss": off,
                                   "test": {"mse": off, "time_mean": 1.0}}}
        (folder / "results.json").write_text(json.dumps({
            "scale": "small", "recipe": "mpnode", "draw": draw,
            "steps": [{"id": k, "result": v} for k, v in results.items()]}))
    index = rebuild_index(tmp_path).read_text()
    row = next(line for line in index.splitlines() if "lower test error than messages off" in line)
    assert "0.01 < 0.02 (small, 1 seed); over 2 data draws, margin 2.5 (95%: 2–3)" in row
    assert "| messages-kuramoto | — | — | — | 1 seed × 2 data draws; not run:" in index


def test_the_reports_section_gives_each_draws_margin_and_the_interval():
    runs = [{"scale": "small", "recipe": "paper", "draw": d,
             "steps": [{"id": k, "result": v} for k, v in _results(0.1, off).items()]}
            for d, off in enumerate((0.15, 0.4))]
    lines = draws_sections(runs, [("on below off", "on.test.mse < off.test.mse")])
    assert lines[0] == "## Over data draws: `--scale small --recipe paper`"
    assert "| on below off | 1.5, 4 | 2.75 | 1.5–4 |" in lines
    assert draws_sections(runs[:1], [("on below off", "on.test.mse < off.test.mse")]) == []


def test_a_negative_draw_is_one_line(tmp_path):
    result = invoke("experiment", "run", "messages-kuramoto", "--draw", "-1",
                    "--out", tmp_path / "o", "--work", tmp_path / "w")
    assert result.exit_code == 2 and "draw" in result.output
