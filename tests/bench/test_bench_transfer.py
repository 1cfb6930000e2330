"""The pure parts of bench/transfer.py: oracle sizing, skill and per-degree binning, the
oracle's stopping rule, and the table rebuilt from records."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import synthetic

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench"))

import transfer
import transfer_score as ts
import transfer_specs as spec
import transfer_table as tt


@pytest.mark.parametrize("k", [1, 2, 5, 6, 7, 24, 77, 100, 300, 501])
def test_split_counts_is_generates(k):
    from mpnode_cli.data.splits import split_counts

    assert spec.split_counts(k, spec.SPLIT) == split_counts(k, spec.SPLIT)


def test_oracle_counts_match_node_trajectories():
    # gene: 300 trajectories of 9 nodes (210/45/45) → 36 nodes
    assert spec.oracle_counts((210, 45, 45), 9, 36) == (53, 12, 12)
    # S¹: 100 of 64 nodes (70/15/15) → 4096 nodes: at least 1 validation, 2 test
    assert spec.oracle_counts((70, 15, 15), 64, 4096) == (2, 1, 2)
    for source, n_s, n_t in [((350, 75, 75), 10, 40), ((17, 4, 3), 64, 512)]:
        counts = spec.oracle_counts(source, n_s, n_t)
        assert all(c * n_t >= s * n_s for c, s in zip(counts, source, strict=True))


@pytest.mark.parametrize("system", ["gene", "kuramoto", "pendulum", "fhn", "grid", "sis"])
def test_target_split_is_reproduced_by_fractions(system):
    """The `--split` a target is generated with gives exactly its counts."""
    from mpnode_cli.data.splits import split_counts

    for smoke in (False, True):
        bench = spec.size_bench(system, smoke)
        for d in bench.targets.values():
            fractions = tuple(float(x) for x in d.fractions().split(","))
            assert math.isclose(sum(fractions), 1.0, abs_tol=1e-6)
            assert split_counts(d.k, fractions) == d.counts
            assert d.graphs <= d.k and d.system == bench.source.system


def test_s1_bench_protocol():
    bench = spec.s1_bench("mm", 2.1, seed=1, smoke=False, largest=True)
    assert bench.source.nodes == 64 and dict(bench.source.params) == {"gamma": 2.1}
    assert list(bench.targets) == ["n1024", "n4096", "n8192"]
    assert all(d.graphs == d.k and d.topology == "s1" for d in bench.targets.values())
    other = spec.s1_bench("mm", 2.1, seed=2, smoke=False, largest=False)
    assert other.source.graph_seed != bench.source.graph_seed  # data vary with the seed
    assert spec.per_degree("n1024") and spec.per_degree("x4") and not spec.per_degree("x2")
    assert spec.set_of("mm") == "selection" and spec.set_of("grid") == "confirmation"


def test_curriculum_share():
    assert spec.curriculum_share("gene", 100) == 1.0
    short = spec.curriculum_share("sis", 100)
    assert 0.5 < short < 0.6 and short < spec.curriculum_share("sis", 1000) < 1.0


def test_degree_bins_and_by_degree():
    degree = np.array([0, 1, 2, 3, 4, 7, 8, 40])
    assert ts.degree_bins(degree) == [(0, 1), (1, 2), (2, 4), (4, 8), (8, 16), (16, 32),
                                      (32, 64)]
    mse = np.array([1.0, 2.0, 3.0, np.nan, 5.0, 7.0, 8.0, 40.0])
    rows = ts.by_degree({"degree": degree, "mse": mse, "outside": np.zeros(8)})
    assert [(r["lo"], r["nodes"]) for r in rows] == [(0, 1), (1, 1), (2, 2), (4, 2),
                                                      (8, 1), (32, 1)]
    assert rows[2]["mse"] == 3.0  # the failed node-trajectory (NaN) is left out
    assert rows[3]["mse"] == 6.0


def test_pack_round_trip():
    values = np.random.default_rng(0).normal(size=1000).astype(np.float32)
    assert np.array_equal(ts.unpack(ts.pack(values, "float32"), "float32"), values)


def test_time_mean_per_node_is_baseline_mse():
    """Skill's denominator is mpnode's own time-mean predictor, in physical units."""
    from mpnode_cli.training.evaluate import baseline_mse

    train, test = synthetic(6, 8, seed=1), synthetic(4, 8, seed=2)
    per_node = ts.time_mean_per_node(train.states.double().numpy(),
                                     test.states.double().numpy())
    expected = baseline_mse(train, test, ts._identity(2))["time_mean"]
    assert per_node.shape == (4, 3)
    assert per_node.mean() == pytest.approx(expected, rel=1e-9)


def test_wrapped_errors_are_mod_2pi_and_match_baseline_mse():
    """An angle and the same angle a turn on are 0 apart; the wrapped time-mean predictor's
    error per node is mpnode's `baseline_mse` with the same component wrapped."""
    from mpnode_cli.training.evaluate import baseline_mse
    from mpnode_cli.training.losses import Angles

    theta = np.random.default_rng(3).uniform(-3, 3, size=(2, 5, 3, 2))
    turned = theta.copy()
    turned[..., 0] += 2 * np.pi * np.array([1, -3, 7])[None, None, :]
    assert np.abs(ts.node_mse(turned, theta, (0,))).max() < 1e-24
    assert ts.node_mse(turned, theta).min() > 1.0  # plain differences see the turns
    train, test = synthetic(6, 8, seed=1), synthetic(4, 8, seed=2)
    test.states[..., 0] *= 10.0  # angles far beyond one turn
    per_node = ts.time_mean_per_node(train.states.double().numpy(),
                                     test.states.double().numpy(), (0,))
    expected = baseline_mse(train, test, ts._identity(2), Angles((0,)))["time_mean"]
    assert per_node.mean() == pytest.approx(expected, rel=1e-9)
    plain = ts.time_mean_per_node(train.states.double().numpy(), test.states.double().numpy())
    assert per_node.mean() < plain.mean() / 2  # the turns are not counted


def test_a_wrapped_variant_borrows_no_plain_oracle(tmp_path):
    degree = np.array([1, 2, 3, 9, 20])
    oracle = _record("oracle", 0, epochs=400, best_epoch=200, train_seconds=300.0,
                     stopped_by="patience", score=_score(0.1, 2.0, degree))
    variant = {**_record("zeroshot", 0, score={**_score(0.3, 2.0, degree), "wrapped": [0]}),
               "variant": "periodic-wrapped", "job": "size/gene/periodic-wrapped/s0/zeroshot-x4"}
    text = tt.page({r["job"]: r for r in (oracle, variant)})
    row = next(line for line in text.splitlines() if "| periodic-wrapped | x4 |" in line)
    assert "†" not in row


def test_node_mse_and_outside_share():
    true = np.zeros((2, 3, 4, 1))
    pred = true.copy()
    pred[0, 1:, 2] = 2.0
    pred[1, 0] = 9.0  # t₀ is excluded
    mse = ts.node_mse(pred, true)
    assert mse[0, 2] == 4.0 and mse.sum() == 4.0
    states = np.linspace(-1, 2, 24).reshape(2, 3, 4, 1)
    share = ts.outside_share(states, [[0.0, 1.0]])
    assert share.shape == (2, 4) and share.mean() == pytest.approx(
        ((states < 0) | (states > 1)).mean())


def test_stop_reason():
    args = dict(floor=100.0, patience=10, cap_seconds=800.0, cap_epochs=4000)
    assert transfer.stop_reason(50, 30, 90.0, **args) is None  # before the source's time
    assert transfer.stop_reason(50, 40, 120.0, **args) == "patience"
    assert transfer.stop_reason(50, 45, 120.0, **args) is None
    assert transfer.stop_reason(500, 499, 800.0, **args) == "time cap"
    assert transfer.stop_reason(4000, 3999, 500.0, **args) == "epoch cap"


def test_run_state(tmp_path):
    rows = [{"epoch": 0, "val_loss": 3.0, "seconds": 0.1},
            {"epoch": 1, "val_loss": 1.0, "seconds": 1.0},
            {"epoch": 2, "val_loss": 1.0, "seconds": 1.0},
            {"epoch": 3, "val_loss": float("nan"), "seconds": 1.5}]
    (tmp_path / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    assert transfer.run_state(tmp_path) == (3, 1, pytest.approx(3.6))


def _score(mse: float, tm: float, degree: np.ndarray) -> dict:
    per_node = {"degree": degree, "mse": np.full(degree.shape, mse),
                "time_mean": np.full(degree.shape, tm),
                "outside": np.full(degree.shape, 0.9187654)}  # not a float16: 0.91895 there
    return {"dataset": "t.h5", "trajectories": 1, "nodes": degree.size, "failed": 0,
            "mse": mse, "time_mean": tm, "hold_x0": 2 * tm, "skill": mse / tm,
            "states_outside": 0.0, "in_degree": [int(degree.min()), int(degree.max())],
            "train_in_degree": [1, 4], "by_degree": ts.by_degree(per_node),
            "per_node": {k: ts.pack(v, ts.PER_NODE[k]) for k, v in per_node.items()}}


def _record(kind: str, seed: int, label: str = "x4", **extra) -> dict:
    what = kind if kind == "source" else f"{kind}-{label}"
    return {"job": f"size/gene/default/s{seed}/{what}", "kind": kind, "protocol": "size",
            "system": "gene", "set": "selection", "gamma": None, "variant": "default",
            "seed": seed, "label": label, "dataset": "gene-ba36", "nodes": 36,
            "scale": "full", "date": "2026-11-28T00:00:00", **extra}


def test_table_from_records(tmp_path):
    degree = np.array([1, 2, 3, 9, 20])
    records = []
    for seed in (0, 1):
        records.append(_record("source", seed, "own", epochs=100, best_epoch=90,
                               train_seconds=60.0))
        records.append(_record("zeroshot", seed, score=_score(0.4 + 0.2 * seed, 2.0, degree)))
        records.append(_record("oracle", seed, epochs=400, best_epoch=200,
                               train_seconds=300.0, stopped_by="patience",
                               score=_score(0.1, 2.0, degree)))
    runs = tmp_path / "runs"
    for r in records:
        tt.write_json(runs / f"{r['job']}.json", r)
    committed = tmp_path / "transfer.json"
    tt.save_committed({r["job"]: r for r in records}, committed)
    saved = json.loads(committed.read_text())
    assert all("per_node" not in r.get("score", {}) for r in saved)
    out = tmp_path / "transfer.md"
    tt.rebuild(tmp_path / "elsewhere", committed, out)  # a fresh clone: the copy alone
    fresh = out.read_text()
    tt.rebuild(runs, committed, out)
    text = out.read_text()
    assert text == fresh  # a fresh clone's table is the one the bench wrote
    assert "91.88%" in text  # the stored bins' full precision, not the packed float16's
    assert "**5**" in text  # (0.4 + 0.6) / 2 ÷ 0.1
    assert "2/2 converged" in text and "### gene (size, default): x4" in text
    assert "| 8–15 | 1 | 0.5 ± 0.14 | 0.1 ± 0 | 5 |" in text


def test_a_variant_without_oracles_is_set_against_the_defaults(tmp_path):
    degree = np.array([1, 2, 3, 9, 20])
    oracle = _record("oracle", 0, epochs=400, best_epoch=200, train_seconds=300.0,
                     stopped_by="patience", score=_score(0.1, 2.0, degree))
    variant = {**_record("zeroshot", 0, score=_score(0.3, 2.0, degree)),
               "variant": "relu", "job": "size/gene/relu/s0/zeroshot-x4"}
    text = tt.page({r["job"]: r for r in (oracle, variant)})
    row = next(line for line in text.splitlines() if "| relu | x4 |" in line)
    assert "**3**†" in row  # 0.3 ÷ the default's 0.1
    assert "default variant's oracles" in text


def test_merged_records_prefer_local(tmp_path):
    old = _record("zeroshot", 0, score=_score(1.0, 2.0, np.array([1, 2])))
    new = {**old, "score": _score(0.5, 2.0, np.array([1, 2]))}
    committed = tmp_path / "transfer.json"
    tt.save_committed({old["job"]: old}, committed)
    tt.write_json(tmp_path / "runs" / "a-0123456789ab" / "step.json",  # the engine's record
                  {"verb": "call", "result": new})
    merged = tt.merged_records(tmp_path / "runs", committed)
    assert merged[old["job"]]["score"]["mse"] == 0.5


def test_identity_normalizer_is_physical():
    norm = ts._identity(3)
    x = torch.randn(2, 4, 5, 3, dtype=torch.float64)
    assert torch.equal(norm.norm_x(x), x)


def test_a_row_resting_on_a_dirty_record_is_marked(tmp_path):
    degree = np.array([1, 2, 3, 9, 20])
    clean = _record("oracle", 0, epochs=400, best_epoch=200, train_seconds=300.0,
                    stopped_by="patience", score=_score(0.1, 2.0, degree))
    dirty = {**_record("zeroshot", 0, score=_score(0.3, 2.0, degree)), "commit": "abc+dirty"}
    text = tt.page({r["job"]: {**r, "commit": r.get("commit", "abc")} for r in (clean, dirty)})
    assert "| default‡ | x4 |" in text and "(1 of the 2 records)" in text
    assert "‡" not in tt.page({clean["job"]: {**clean, "commit": "abc"}})


def test_a_dirty_tree_is_refused_unless_allowed(monkeypatch, tmp_path, capsys):
    monkeypatch.setattr(transfer, "git_commit", lambda: "abc+dirty")
    monkeypatch.setattr(transfer.jobs, "run_jobs", lambda *a: pytest.fail("jobs ran"))
    argv = ["--systems", "gene", "--seeds", "0", "--only-protocol", "size",
            "--runs", str(tmp_path / "runs")]
    assert transfer.main(argv) == 2
    assert "uncommitted changes" in capsys.readouterr().err
    monkeypatch.setattr(transfer.jobs, "run_jobs", lambda *a: {})
    monkeypatch.setattr(transfer, "write_table", lambda args: "table")
    assert transfer.main([*argv, "--allow-dirty"]) == 0
