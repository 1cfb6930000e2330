"""A training step's per-epoch curves, kept in the report's `results.json`, and the
cost-aware figures read from them.

A report keeps what it needs to be rebuilt from committed files. The run folders behind it
are not committed, so the per-epoch metrics a figure or a curve metric reads are kept with
the step's result: each column (`CURVE_COLUMNS`) as float32, zlib-compressed, in base64
(about 4 bytes an epoch before compression), with NaN where a row has no value (epoch 0 has
no training loss).

From a curve, beside the paper's Table-2 figure (best epoch × best validation loss, which
ignores what an epoch costs):
- `to_target`: the first epoch, and the training seconds spent up to it, at which the
  validation MSE reaches a target (k× below the time-mean predictor, or another run's
  final loss);
- `area`: the mean over epochs of the validation MSE over the time-mean predictor's (the
  area under the per-time-mean curve, per epoch): low when a run learns early and stays.
"""

from __future__ import annotations

import base64
import math
import zlib
from collections.abc import Sequence
from typing import Any

import numpy as np

from mpnode_cli.experiments import members

# metrics.jsonl key → the curve's name for it.
# `seconds` is the epoch's whole time: its training steps and its validation.
CURVE_COLUMNS = {"val_mse": "val_mse", "train_loss": "train_loss", "seconds": "seconds"}


def pack(values: Sequence[float | None]) -> str:
    """A column as compressed base64 text of float32 (None → NaN); `unpack` reads it."""
    raw = np.array([math.nan if v is None else v for v in values], dtype="<f4").tobytes()
    return base64.b64encode(zlib.compress(raw, 9)).decode("ascii")


def unpack(text: str) -> np.ndarray:
    """The float32 column `pack` wrote, as float64."""
    return np.frombuffer(zlib.decompress(base64.b64decode(text)), dtype="<f4").astype(float)


def curve(rows: Sequence[dict[str, Any]]) -> dict[str, str]:
    """The packed curves of a run's (or a member's) metrics rows, epoch 0 first."""
    return {"epochs": pack([r["epoch"] for r in rows]),
            **{name: pack([r.get(key) for r in rows]) for key, name in CURVE_COLUMNS.items()}}


def to_target(packed: dict[str, str], target: float) -> dict[str, float | None]:
    """The first epoch at which the validation MSE is at or below `target`, and the
    seconds spent up to and including it (training and validation, epoch 0's too); None
    for both where it never is."""
    val, epochs = unpack(packed["val_mse"]), unpack(packed["epochs"])
    seconds = np.nancumsum(unpack(packed["seconds"]))
    hit = np.flatnonzero(val <= target)
    if not hit.size:
        return {"epochs": None, "seconds": None}
    return {"epochs": int(epochs[hit[0]]), "seconds": float(seconds[hit[0]])}


def area(packed: dict[str, str], time_mean: float) -> float | None:
    """The mean over the epochs after epoch 0 of validation MSE ÷ `time_mean`, the
    time-mean predictor's MSE on the same split (None where that is not positive)."""
    if not time_mean or not math.isfinite(time_mean) or time_mean <= 0:
        return None
    val = unpack(packed["val_mse"])[1:]
    val = val[np.isfinite(val)]
    return float(val.mean() / time_mean) if val.size else None


# A run counts as at its target once its validation MSE is this many times below the
# time-mean predictor's (the reports' line for "has learned").
TARGET_FACTOR = 3.0


def cost(result: dict[str, Any]) -> dict[str, list[Any]]:
    """Each member's (a single model: its own) epochs and seconds to `TARGET_FACTOR`×
    below the time-mean predictor on the validation split, and its `area`; None where it
    never got there or the result keeps no curve (`kept` False: reports written before
    curves were kept)."""
    out: dict[str, list[Any]] = {"epochs": [], "seconds": [], "area": [], "kept": []}
    for k in range(members.count({"run": result})):
        member = members.of(result, k)
        packed, mean = member.get("curve"), (member.get("val") or {}).get("time_mean")
        usable = bool(packed) and isinstance(mean, int | float) and mean > 0
        hit = to_target(packed, mean / TARGET_FACTOR) if usable else {}
        out["epochs"].append(hit.get("epochs"))
        out["seconds"].append(hit.get("seconds"))
        out["area"].append(area(packed, mean) if usable else None)
        out["kept"].append(usable)
    return out
