"""A checkpoint's errors on a dataset's split, as `evaluate` and `zeroshot` report them:
`evaluate_checkpoint` (one dataset) and `evaluate_datasets` (several, and pooled).

The rollout errors are `mpnode_cli.training.evaluate.evaluate`'s, with the checkpoint's
training normalization and solver; beside them the two naive predictors of `baseline_mse`
(hold x(0), the train split's time mean, from `train_reference`), the split against the
checkpoint's training range (`mpnode_cli.training.extrapolation`), and on request plots,
errors by in-degree and the predictions written as a dataset file.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from mpnode_cli.data.dataset import Normalizer, TrajectoryData
from mpnode_cli.jsonable import jsonable
from mpnode_cli.progress import Progress, pass_of
from mpnode_cli.training.baselines import baseline_mse_vs_time, mean_of_curves
from mpnode_cli.training.by_degree import degree_sums
from mpnode_cli.training.compat import check_compatible
from mpnode_cli.training.eval_result import EvalResult, pooled, pooled_baselines
from mpnode_cli.training.evaluate import evaluate, predict
from mpnode_cli.training.extrapolation import data_extrapolation
from mpnode_cli.training.losses import Angles, run_angles
from mpnode_cli.training.predict import roll_out, rollout_solver, write_predictions


def checkpoint_angles(ckpt, normalizer: Normalizer) -> Angles | None:
    """The components a checkpoint's errors take mod 2π: its training dataset's periodic
    states when it was trained with `wrap_angles` (`run_angles`), else None."""
    return run_angles(bool(ckpt.train_config.get("wrap_angles", False)), ckpt.dataset,
                      normalizer.x_std)


def train_reference(ckpt, data: TrajectoryData) -> tuple[TrajectoryData | list[TrajectoryData],
                                                          str]:
    """The train split a checkpoint was fitted on, for `baseline_mse`'s time mean.

    It is the checkpoint's own training dataset (the same file by fingerprint, or the file at
    its recorded path if that still has the recorded fingerprint), limited to the first
    `trajectories` as in training. When that file is gone or changed, the train split of
    `data` stands in, and the returned note says so. A checkpoint trained on several
    datasets: `data`'s own train split if it is one of them, else all of theirs (pooled).

    Returns:
        (train trajectories (a list for several datasets), where they came from: "the train
        split of NAME", and why when it is not the training dataset).
    """
    records = ckpt.dataset.get("datasets") or [ckpt.dataset]
    wanted = [r.get("fingerprint") for r in records]
    sources: list[TrajectoryData] = []
    if data.fingerprint in wanted:
        sources = [data]
    else:
        for record, want in zip(records, wanted, strict=True):
            path = Path(record.get("path") or "")
            try:
                candidate = TrajectoryData.load(path) if path.is_file() else None
            except (OSError, ValueError):
                candidate = None
            if candidate is None or candidate.fingerprint != want:
                sources = []
                break
            sources.append(candidate)
    limit = ckpt.train_config.get("trajectories")
    note = ""
    if not sources:
        which = "the training dataset" if len(records) == 1 else "a training dataset of"
        gone = ", ".join(str(r.get("path")) for r in records)
        note = f" ({which} {gone} is missing or changed, so {data.path.name} stands in)"
        sources, limit = [data], None
    train = [source.subset("train") for source in sources]
    if limit is not None:
        train = [t.select(torch.arange(min(int(limit), len(t)))) for t in train]
    names = ", ".join(source.path.name for source in sources)
    splits = "split" if len(sources) == 1 else "splits"
    return (train[0] if len(train) == 1 else train), f"the train {splits} of {names}{note}"


def plot_paths(plot_dir: Path, dataset: Path, split: str) -> tuple[Path, Path]:
    """The rollout and error plots `evaluate_checkpoint` draws of a dataset's split."""
    stem = f"{Path(dataset).stem}-{split}"
    return Path(plot_dir) / f"{stem}-rollout.png", Path(plot_dir) / f"{stem}-error.png"


def evaluate_checkpoint(ckpt, data: TrajectoryData, *, split: str = "all",
                        verb: str = "evaluate", batch_size: int = 128,
                        device: str | torch.device = "cpu",
                        plot_dir: Path | None = None,
                        allow_other_system: bool = False,
                        save_predictions: Path | None = None,
                        overwrite: bool = False, by_degree: bool = False,
                        progress: Progress | None = None) -> dict[str, Any]:
    """A checkpoint's errors on one split of a dataset (evaluate, zeroshot).

    The model rolls out with the checkpoint's training normalization and solver options.

    Args:
        ckpt: a `Checkpoint`. data: the dataset. split: "train", "validation", "test", "all".
        verb: the command asking, for the compatibility message.
        plot_dir: if given, draw the split's first trajectory (Fig. 2 style; its titles say
            which trajectory and nodes) and the error vs time there as
            `<dataset>-<split>-rollout.png` and `-error.png`.
        allow_other_system: accept a dataset of another system than the checkpoint's.
        save_predictions: if given, write the split's predictions there as an
            `mpnode-dataset` file (`mpnode_cli.training.predict.write_predictions`).
        overwrite: replace an existing regular file at `save_predictions`.
        by_degree: also the errors by in-degree bin, as "by_degree"
            (`mpnode_cli.training.by_degree`); refused for a dataset of predictions.
        progress: called as the split's trajectories are rolled out (twice over with
            `save_predictions`: `progress(done, total)` counts both passes).

    Returns:
        JSON-able: dataset, system, num_nodes, topology, split, result (`EvalResult`),
        baselines (`baseline_mse`, with the train split from `train_reference`),
        baselines_note (where the time mean came from), plots, predictions (the file
        written, or None), data_note (when the dataset itself holds a model's
        predictions rather than ground truth), and extrapolation (the split against the
        checkpoint's training range, as a whole and node by node by the true states,
        `Extrapolation.to_dict`, its worst nodes' `trajectory` their row in the file;
        None for a checkpoint without one).

    Raises:
        ValueError: incompatible per-node sizes, or an empty split.
        PredictionFailed: `save_predictions` with rollouts that did not finish.
    """
    check_compatible(ckpt.model_kind, ckpt.model_config, ckpt.dataset["num_nodes"], data, verb,
                     ckpt.dataset.get("system"), allow_other_system=allow_other_system)
    subset = data.subset(split)
    if len(subset) == 0:
        raise ValueError(f"{data.path.name} has no trajectories in its {split} split")
    beyond = data_extrapolation(ckpt, subset, trajectory=np.asarray(_file_indices(data, split)))
    model, normalizer = ckpt.build_model().to(device), ckpt.build_normalizer()
    options = {"solver": rollout_solver(ckpt), "device": device}
    passes = 1 if save_predictions is None else 2
    angles = checkpoint_angles(ckpt, normalizer)
    train, note = train_reference(ckpt, data)
    degrees = degree_sums(data, subset, normalizer, train, angles) if by_degree else None
    result = evaluate(model, subset, normalizer, batch_size=batch_size,
                      progress=pass_of(progress, 0, passes), angles=angles,
                      per_batch=degrees and degrees.add, **options)
    curves = baseline_mse_vs_time(train, subset, normalizer, angles)  # each [T]
    baselines = jsonable(mean_of_curves(curves))
    plots: list[str] = []
    if plot_dir is not None:
        from mpnode_cli.report.plots import BASELINE_LABELS, plot_error_vs_time, plot_rollout

        rollout_png, error_png = plot_paths(plot_dir, data.path, split)
        pred = predict(model, subset, normalizer, torch.arange(1), **options)
        messages = None if pred.messages is None else pred.messages[0]
        index = _file_index(data, split, 0)
        # A prediction file holds a model's predictions: never call them the truth.
        labels = (("prediction (file)", "predicted (this checkpoint)")
                  if data.attrs.get("prediction") else ("true", "predicted"))
        plots = [
            str(plot_rollout(pred.time, pred.true[0], pred.pred[0], messages, data.state_names,
                             rollout_png,
                             title=f"{data.path.name}: trajectory {index} (the first of the "
                                   f"{split} split)", labels=labels,
                             spread=None if pred.spread is None else pred.spread[0])),
            str(plot_error_vs_time(data.time, [np.asarray(result.mse_vs_time, dtype=float),
                                               curves["hold_x0"],
                                               curves["time_mean"]],
                                   error_png,
                                   labels=("model", *BASELINE_LABELS),
                                   title=f"{data.path.name} ({split}): error vs time")),
        ]
    written = None
    if save_predictions is not None:
        written = str(_save_predictions(ckpt, data, subset, split, batch_size, device,
                                        save_predictions, overwrite, pass_of(progress, 1, 2)))
    data_note = None
    if data.attrs.get("prediction"):
        data_note = (f"{data.path.name} holds a model's predictions, not ground truth: these "
                     "errors compare the model with those predictions")
    return {"dataset": str(data.path), "system": data.system, "num_nodes": data.num_nodes,
            "topology": data.attrs.get("topology"), "split": split,
            "result": result.to_dict(), "baselines": baselines, "baselines_note": note,
            "plots": plots, "predictions": written, "data_note": data_note,
            "extrapolation": None if beyond is None else beyond.to_dict(),
            **({} if degrees is None else {"by_degree": degrees.rows(beyond and beyond.nodes)})}


def evaluate_datasets(ckpt, datasets: Sequence[TrajectoryData], names: Sequence[str], *,
                      split: str, **options: Any) -> dict[str, Any]:
    """A checkpoint's errors on one split of each of several datasets, and pooled.

    Each dataset with trajectories in `split` is evaluated as `evaluate_checkpoint` does
    (its baselines' time mean from its own train split when it is one of the checkpoint's
    training datasets); the pooled result and baselines weight each dataset's by its
    predicted values (`pooled`, `pooled_baselines`): the MSE is that of all values of all
    the datasets' splits. With one dataset this is `evaluate_checkpoint`'s report.

    Args:
        ckpt: a `Checkpoint`. datasets: the datasets; names: the name each goes under.
        split: "train", "validation", "test" or "all".
        **options: `evaluate_checkpoint`'s (verb, batch_size, device, plot_dir, ...).

    Returns:
        `evaluate_checkpoint`'s report of the pooled numbers ("result", "baselines"), plus
        "by_dataset" (each dataset's report by name) when there are several.
    """
    if len(datasets) == 1:
        return evaluate_checkpoint(ckpt, datasets[0], split=split, **options)
    from mpnode_cli.data.pooled import element_weights

    reports, subsets = {}, []
    for data, name in zip(datasets, names, strict=True):
        subset = data.subset(split)
        if len(subset):
            reports[name] = evaluate_checkpoint(ckpt, data, split=split, **options)
            subsets.append(subset)
    if not reports:
        raise ValueError(f"none of the datasets has trajectories in its {split} split")
    results = [EvalResult(**_nan(r["result"])) for r in reports.values()]
    result = pooled(results, [d.num_nodes for d in subsets])
    baselines = pooled_baselines([r["baselines"] for r in reports.values()],
                                 element_weights(subsets))
    first = next(iter(reports.values()))
    return {"dataset": [r["dataset"] for r in reports.values()], "system": first["system"],
            "num_nodes": [r["num_nodes"] for r in reports.values()], "split": split,
            "result": result.to_dict(), "baselines": baselines,
            "plots": [p for r in reports.values() for p in r["plots"]], "by_dataset": reports}


def _save_predictions(ckpt, data: TrajectoryData, subset: TrajectoryData, split: str,
                      batch_size: int, device, path: Path, overwrite: bool,
                      progress: Progress | None = None) -> Path:
    """Roll out a split from its first states and write the predictions beside the facts
    of the data they were made for."""
    pred = roll_out(ckpt, subset.states[:, 0].numpy(), subset.time.numpy(),
                    subset.graphs, subset.graph_index.numpy(),
                    None if subset.controls is None else subset.controls.numpy(),
                    batch_size=batch_size, device=device, progress=progress)
    source = {"dataset": str(Path(data.path).resolve()), "fingerprint": data.fingerprint,
              "split": split, "trajectories": _file_indices(data, split)}
    config = {"verb": "evaluate", "checkpoint": str(ckpt.path), "dataset": str(data.path),
              "split": split, "batch_size": batch_size, "topology": data.attrs.get("topology")}
    return write_predictions(path, ckpt, pred, time=subset.time.numpy(),
                             graphs=subset.graphs, graph_index=subset.graph_index.numpy(),
                             controls=None if subset.controls is None else
                             subset.controls.numpy(),
                             split=subset.split.numpy(), config=config, source=source,
                             overwrite=overwrite)


def _file_indices(data: TrajectoryData, split: str) -> list[int]:
    """The indices in the file of a split's trajectories."""
    if split == "all":
        return list(range(len(data)))
    from mpnode_cli.data.dataset import SPLITS

    return torch.nonzero(data.split == SPLITS[split]).flatten().tolist()


def _file_index(data: TrajectoryData, split: str, i: int) -> int:
    """The index in the file of the i-th trajectory of a split."""
    return _file_indices(data, split)[i]


def _nan(value: Any) -> Any:
    """`jsonable` undone: None back to NaN (in dicts and lists too)."""
    if value is None:
        return math.nan
    if isinstance(value, dict):
        return {k: _nan(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_nan(v) for v in value]
    return value
