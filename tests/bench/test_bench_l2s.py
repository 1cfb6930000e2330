"""bench/l2s_tuning.py reads what `mpnode train` writes: its records come from a real run's
summary.json, and its table's verdict is every member below the time mean."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from conftest import invoke

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench"))

import l2s_tuning


def test_a_records_numbers_are_the_runs_and_learns_means_every_member(gene_2x2, tmp_path):
    run = tmp_path / "run"
    result = invoke("train", gene_2x2, "--model", "l2s", "--epochs", "1", "--seeds", "2",
                    "--latent", "8", "--hidden", "8", "--steps", "1", "--unroll", "2",
                    "--batch-size", "8", "--no-plots", "--run-dir", run)
    assert result.exit_code == 0, result.output
    summary = json.loads((run / "summary.json").read_text())
    rec = l2s_tuning.record_of(summary, "quad6", "unroll-5", 12.0)
    members = [m["mse"] for m in summary["test"]["members"]]
    assert rec["member_mse"] == members and len(members) == 2
    assert rec["time_mean"] == summary["baselines"]["time_mean"] > 0
    assert rec["flags"] == l2s_tuning.CONFIGS["unroll-5"][1]

    def verdict(mses):
        row = l2s_tuning.table([rec | {"member_mse": mses}]).splitlines()[-1]
        return row.split(" | ")[7]

    tm = rec["time_mean"]
    assert verdict([0.5 * tm, 0.9 * tm]) == "**yes**"
    assert verdict([0.5 * tm, 1.0 * tm]) == "no (1 of 2 not below)"
