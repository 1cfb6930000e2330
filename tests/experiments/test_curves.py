"""A report's kept training curves and the cost-aware figures read from them
(`mpnode_cli.experiments.curves`), against sums done by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mpnode_cli.experiments import curves

ROWS = [{"epoch": e, "val_mse": v, "train_loss": t, "seconds": s}
        for e, v, t, s in [(0, 10.0, None, 0.5), (1, 5.0, 6.0, 2.0), (2, 2.5, 3.0, 2.0),
                           (3, 1.0, 1.5, 2.0), (4, 0.5, 0.7, 2.0)]]


def test_a_column_round_trips_as_float32_with_nan_for_none():
    got = curves.unpack(curves.pack([1.0, None, 1 / 3, 1e-30]))
    assert got[0] == 1.0 and math.isnan(got[1])
    assert got[2] == pytest.approx(1 / 3, rel=2 ** -23) and got[3] == pytest.approx(1e-30,
                                                                                  rel=1e-6)


def test_epochs_and_seconds_to_a_target_and_the_area():
    packed = curves.curve(ROWS)
    # 1.0 is first reached at epoch 3, after 0.5 + 2 + 2 + 2 seconds.
    assert curves.to_target(packed, 1.0) == {"epochs": 3, "seconds": pytest.approx(6.5)}
    assert curves.to_target(packed, 0.1) == {"epochs": None, "seconds": None}
    # Epochs 1-4 over a time mean of 4: (5 + 2.5 + 1 + 0.5) / 4 / 4.
    assert curves.area(packed, 4.0) == pytest.approx(9.0 / 16)
    assert curves.area(packed, 0.0) is None


def test_an_ensembles_cost_is_each_members_and_an_old_report_has_none():
    slow = [{**r, "val_mse": 2 * r["val_mse"]} for r in ROWS]
    result = {"members": [{"curve": curves.curve(rows), "val": {"time_mean": 3.0}}
                          for rows in (ROWS, slow)]}
    cost = curves.cost(result)  # target: 3 / 3 = 1.0
    assert cost["epochs"] == [3, 4] and cost["kept"] == [True, True]
    assert cost["seconds"] == pytest.approx([6.5, 8.5])
    assert cost["area"] == pytest.approx([9.0 / 12, 18.0 / 12])
    old = curves.cost({"val": {"time_mean": 3.0}, "best_epoch": 4})
    assert old == {"epochs": [None], "seconds": [None], "area": [None], "kept": [False]}
    assert np.isfinite(curves.unpack(curves.curve(ROWS)["epochs"])).all()
