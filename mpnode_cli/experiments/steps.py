"""The step verbs: each runs one step of an experiment through the library, in its folder.

A verb takes `(step, options, folder, inputs, status, emit)`: the spec's step, its resolved
options, the empty (or, for a resumed training, the interrupted) folder it writes in, the
records of the steps it reads by id, "ran" or "resumed", and the run's progress callback.
It returns `(result, outputs, commands, figures)`: the numbers the report needs, the files
(relative to the folder) whose presence says the step is done, the equivalent `mpnode`
command lines, and the figures' paths. A verb raises ValueError or FileNotFoundError for
what a user can fix; `scheduler.run_step` turns them into `StepFailed`.

A training step's options may ask for an ensemble (`seeds` S > 1, from `--seeds`); the
result of every step that reads a trained model then holds, under `members`, each member's
result with the keys of a single model's (`mpnode_cli.experiments.members`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mpnode_cli.experiments import commands, curves, members
from mpnode_cli.experiments.call_verb import call
from mpnode_cli.experiments.spec import TRAINING
from mpnode_cli.jsonable import jsonable

OnEvent = Callable[[dict[str, Any]], None]
DATA_FILE, RUN_DIR = "data.h5", "run"
FIGURE_DPI = 80


class StepFailed(RuntimeError):
    """A step could not run (bad data, a refused option, a diverged training)."""


@dataclass
class StepRecord:
    """One step of a run: what it did (or found done) and its results."""

    id: str
    verb: str
    label: str
    status: str  # "ran", "resumed" or "skipped" (done by an earlier run)
    folder: str
    fingerprint: str
    options: dict[str, Any]
    seconds: float
    commands: list[str]
    result: dict[str, Any]
    figures: list[str] = field(default_factory=list)
    reported: dict[str, float] = field(default_factory=dict)
    reported_in: str | None = None


def _generate(step, options, folder: Path, inputs, status, emit):
    from mpnode_cli.config.generate import GenerateConfig
    from mpnode_cli.data.generate import generate

    config = GenerateConfig(**{**options["config"], "out": folder / DATA_FILE})
    summary = generate(config, overwrite=True,
                       progress=lambda done, total: emit({"event": "generate", "done": done,
                                                          "total": total}))
    train, val, test = summary.split_counts
    result = {"system": config.system, "nodes": config.nodes, "topology": config.topology,
              "trajectories": summary.trajectories, "split": [train, val, test],
              "samples": config.num_steps + 1, "dt": config.dt, "t_end": config.t_end,
              "seed": config.seed, "graph_seed": config.graph_seed,
              "seconds": summary.seconds}
    return result, [DATA_FILE], [commands.generate_line(step, options, folder / DATA_FILE)], []


def _train(step, options, folder: Path, inputs, status, emit):
    from mpnode_cli.config.train import TrainConfig
    from mpnode_cli.training.loop import TrainingDiverged, train
    from mpnode_cli.training.run import read_config

    run_dir = folder / RUN_DIR
    data = Path(inputs[step.data].folder) / DATA_FILE
    fields = {"plots": False, **options["config"], "dataset": data, "run_dir": run_dir,
              "recipe": options["recipe"]}
    if step.verb == "finetune":
        fields["init_checkpoint"] = _best(inputs[step.checkpoint])
    try:
        if status == "resumed":
            # A training that finished before its step record was written trains no more
            # epochs and writes its summary again.
            train(read_config(run_dir), resume=True, progress=_forward(emit),
                  finished_ok=True)
        else:
            train(TrainConfig(**fields), progress=_forward(emit))
    except TrainingDiverged as exc:
        raise ValueError(f"training diverged: {exc}") from None
    result = training_result(run_dir, data)
    return (result, [f"{RUN_DIR}/summary.json", f"{RUN_DIR}/checkpoints/best.pt"],
            [commands.train_line(step, options, data, run_dir, fields.get("init_checkpoint"))], [])


def _forward(emit: OnEvent) -> Callable[[dict[str, Any]], None]:
    return lambda event: emit({"event": "train", "event_data": event})


def _best(record: StepRecord) -> Path:
    return Path(record.folder) / RUN_DIR / "checkpoints" / "best.pt"


def training_result(run_dir: Path, data: Path) -> dict[str, Any]:
    """What the report needs of a finished run: its summary's numbers, the lowest training
    loss, and the best checkpoint's validation MSE beside the naive predictors."""
    from mpnode_cli.data.dataset import TrajectoryData
    from mpnode_cli.training.baselines import baseline_mse
    from mpnode_cli.training.checkpoint import load_checkpoint
    from mpnode_cli.training.checkpoint_report import checkpoint_angles, train_reference
    from mpnode_cli.training.run import read_config, read_metrics, read_summary

    summary = read_summary(run_dir)
    config = read_config(run_dir)
    metrics = read_metrics(run_dir)
    train_losses = [r["train_loss"] for r in metrics if r.get("train_loss") is not None]
    best = load_checkpoint(Path(run_dir) / "checkpoints" / "best.pt")
    dataset = TrajectoryData.load(data)
    reference, _ = train_reference(best, dataset)
    normalizer = best.build_normalizer()
    val = baseline_mse(reference, dataset.subset("validation"), normalizer,
                       checkpoint_angles(best, normalizer))
    test = summary.get("test") or {}
    result = {
        "model": summary["model"], "loss": summary["loss"], "epochs": summary["epochs"],
        "best_epoch": summary["best_epoch"], "min_val_loss": summary["min_val_loss"],
        "table2": summary["table2"], "min_train_loss": min(train_losses, default=None),
        "val": {"mse": summary.get("min_val_mse"), **jsonable(val)},
        "test": {"mse": test.get("mse"), "failed": test.get("failed"),
                 **(summary.get("baselines") or {})},
        "wall_seconds": summary["wall_seconds"],
        "seconds_per_epoch": summary["seconds_per_epoch"],
        "parameters": summary["parameters"], "seed": config.seed,
        "trajectories": len(reference), "recipe": config.recipe,
        "model_options": config.model_options, "curve": curves.curve(metrics),
    }  # fmt: skip
    if summary.get("members"):
        result[members.MEMBERS] = [_member_training(result, member, metrics)
                                   for member in summary["members"]]
    return result


def _member_training(result: dict[str, Any], member: dict[str, Any],
                     metrics: list[dict[str, Any]]) -> dict[str, Any]:
    """Member k's `training_result` from the ensemble's (`result`), its entry of
    `summary.json`'s `members` and its rows of `metrics.jsonl`: its best epoch, validation
    loss and MSE there, Table-2 figure, lowest training loss, test MSE and seed. The naive
    predictors, the model and the timings are the ensemble's."""
    k = member["member"]
    # Member k's rows, with the epoch and its seconds (the ensemble's) for its curve.
    rows = {row["epoch"]: {**row["members"][k], "epoch": row["epoch"],
                           "seconds": row["seconds"]}
            for row in metrics if row.get("members")}
    best = rows.get(member["best_epoch"]) or {}
    train_losses = [row["train_loss"] for row in rows.values()
                    if row.get("train_loss") is not None]
    test = member.get("test") or {}
    return {**result,
            "best_epoch": member["best_epoch"], "min_val_loss": member["min_val_loss"],
            "table2": member["best_epoch"] * member["min_val_loss"],
            "min_train_loss": min(train_losses, default=None),
            "val": {**result["val"], "mse": best.get("val_mse")},
            "test": {**result["test"], "mse": test.get("mse"), "failed": test.get("failed")},
            "seed": member["seed"], "stopped_early": member.get("stopped") or None,
            "curve": curves.curve(list(rows.values()))}


def _zeroshot(step, options, folder: Path, inputs, status, emit):
    from mpnode_cli.data.dataset import TrajectoryData
    from mpnode_cli.training.checkpoint import load_checkpoint
    from mpnode_cli.training.checkpoint_report import evaluate_checkpoint

    ckpt = load_checkpoint(_best(inputs[step.checkpoint]))
    result: dict[str, Any] = {}
    by_member: list[dict[str, Any]] = [{} for _ in range(ckpt.members if ckpt.members > 1
                                                         else 0)]
    figures, paths = [], []
    for data_id in step.data:
        path = Path(inputs[data_id].folder) / DATA_FILE
        paths.append(path)
        data = TrajectoryData.load(path)
        row = evaluate_checkpoint(ckpt, data, split=step.split, verb="zeroshot")
        result[data_id] = _row(row)
        for member, member_row in zip(by_member, _member_rows(row), strict=True):
            member[data_id] = member_row
        if step.plot:
            figures.append(_rollout_figure(ckpt, data, step.split,
                                           folder / f"{step.id}-{data_id}-rollout.png"))
    if by_member:
        result[members.MEMBERS] = by_member
    return (result, [Path(f).name for f in figures],
            [commands.zeroshot_line(_best(inputs[step.checkpoint]), paths, step.split)], figures)


def _evaluate(step, options, folder: Path, inputs, status, emit):
    from mpnode_cli.data.dataset import TrajectoryData
    from mpnode_cli.training.checkpoint import load_checkpoint
    from mpnode_cli.training.checkpoint_members import member_checkpoint
    from mpnode_cli.training.checkpoint_report import evaluate_checkpoint

    best = _best(inputs[step.checkpoint])
    ckpt = load_checkpoint(best)
    if step.zero_messages:
        if "messages" not in ckpt.model_config:
            raise ValueError(f"model '{ckpt.model_kind}' has no messages to zero")
        # messages=False clamps incoming messages to zero and changes no weight, so the
        # trained weights load unchanged (MP-NODE's `messages` option).
        ckpt.model_config = {**ckpt.model_config, "messages": False}
    path = Path(inputs[step.data].folder) / DATA_FILE
    data = TrajectoryData.load(path)
    row = evaluate_checkpoint(ckpt, data, split=step.split)
    result = {**_row(row), "zero_messages": step.zero_messages}
    by_member = [{**member_row, "zero_messages": step.zero_messages}
                 for member_row in _member_rows(row)]
    figures = []
    if step.plot:
        figures.append(_rollout_figure(ckpt, data, step.split, folder / f"{step.id}-rollout.png"))
    if step.pca:
        # An ensemble's messages are each member's own (their mean is no model's): each
        # member gets its PCA, and the figure and the step's own `pca` are member 0's.
        pca = folder / f"{step.id}-pca.png"
        if by_member:
            for k, member in enumerate(by_member):
                member["pca"] = _pca(member_checkpoint(ckpt, k), data, step,
                                     pca if k == 0 else None)
            result["pca"] = by_member[0]["pca"]
        else:
            result["pca"] = _pca(ckpt, data, step, pca)
        figures.append(str(pca))
    if by_member:
        result[members.MEMBERS] = by_member
    return (result, [Path(f).name for f in figures],
            [commands.evaluate_line(best, path, step)], figures)


def _pca(ckpt, data, step, path: Path | None) -> dict[str, Any]:
    """An evaluate step's message PCA (`mpnode_cli.training.message_pca`), drawn at `path`."""
    from mpnode_cli.training.message_pca import message_pca

    return message_pca(ckpt, data, split=step.split, components=step.pca,
                       trajectories=step.trajectories, untrained=step.pca_untrained,
                       path=path, dpi=FIGURE_DPI)


def _compare(step, options, folder: Path, inputs, status, emit):
    from mpnode_cli.training.run import read_metrics

    labels = {i: inputs[i].label for i in step.runs}
    metrics = {i: read_metrics(Path(inputs[i].folder) / RUN_DIR) for i in step.runs}
    curves = folder / f"{step.id}-loss.png"
    plot_losses(labels, metrics, {i: inputs[i].result for i in step.runs}, curves,
                per_mean=step.curves == "time-mean")
    figures = [str(curves)]
    results = {i: inputs[i].result for i in step.runs}
    result: dict[str, Any] = _compared(results)
    size = members.count(results)
    if size > 1:
        result[members.MEMBERS] = [_compared(members.view(results, k)) for k in range(size)]
    if step.groups:
        bars = folder / f"{step.id}-bars.png"
        plot_table2(step, labels, {i: members.values(results[i], "table2") for i in step.runs},
                    bars)
        figures.append(str(bars))
        result["groups"] = step.groups
    runs = [Path(inputs[i].folder) / RUN_DIR for i in step.runs]
    return result, [Path(f).name for f in figures], [commands.compare_line(runs)], figures


def _compared(results: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """A compare step's numbers of its runs (run id → its training result)."""
    return {"runs": {i: {key: result.get(key) for key in
                         ("best_epoch", "min_val_loss", "table2", "min_train_loss")}
                     for i, result in results.items()}}


def plot_losses(labels: dict[str, str], metrics: dict[str, list[dict[str, Any]]],
                results: dict[str, dict[str, Any]], path: Path, per_mean: bool = True) -> Path:
    """Training runs' loss curves (run id → label, `metrics.jsonl` rows, results). With
    `per_mean`, each run's training loss and validation MSE are divided by its own
    time-mean predictor's validation MSE: a finetune keeps its parent's normalization, so
    its raw losses are in other units than a scratch run's on the same data. Raw when a
    run has no time-mean MSE to divide by."""
    from mpnode_cli.report.plots import plot_curves

    means = {i: (results[i].get("val") or {}).get("time_mean") for i in labels}
    if per_mean and all(isinstance(m, int | float) and m > 0 for m in means.values()):
        runs = {labels[i]: [{**row, **{key: row[key] / means[i] for key in
                                       ("train_loss", "val_mse") if row.get(key) is not None}}
                            for row in metrics[i]] for i in labels}
        return plot_curves(runs, path, dpi=FIGURE_DPI, titles=(
            "training loss ÷ time-mean predictor's val MSE",
            "validation MSE ÷ time-mean predictor's"))
    return plot_curves({labels[i]: metrics[i] for i in labels}, path, dpi=FIGURE_DPI)


def plot_table2(step, labels: dict[str, str], table2: dict[str, list[float | None]],
                path: Path) -> Path:
    """The paper's Table-2 figure of a compare step's groups, a bar per run (run id →
    label, its members' Table-2 figures: one for a single model), an ensemble's the
    members' mean with their std as an error bar."""
    from mpnode_cli.report.plots import plot_bars

    first = next(iter(step.groups.values()))
    series = step.series or [labels[i] for i in first]
    stats = {i: members.mean_and_std(values) for i, values in table2.items()}

    def bars(pick: int) -> dict[str, dict[str, float | None]]:
        return {group: {series[j] if j < len(series) else labels[i]:
                        None if stats[i] is None else stats[i][pick]
                        for j, i in enumerate(runs)}
                for group, runs in step.groups.items()}

    spread = any(len(values) > 1 for values in table2.values())
    return plot_bars(bars(0), path, dpi=FIGURE_DPI, errors=bars(1) if spread else None,
                     ylabel="best epoch × min validation loss",
                     title="Table-2 figure (lower is better)")


VERBS = {"generate": _generate, "train": _train, "finetune": _train, "zeroshot": _zeroshot,
         "evaluate": _evaluate, "compare": _compare, "call": call}


def _member_rows(row: dict[str, Any]) -> list[dict[str, Any]]:
    """Each member's `_row` of an ensemble's `evaluate_checkpoint` row (none for a single
    model's): its own errors beside the same naive predictors."""
    return [_row({**row, "result": member})
            for member in row["result"].get(members.MEMBERS) or []]


def _row(row: dict[str, Any]) -> dict[str, Any]:
    """The numbers of an `evaluate_checkpoint` row."""
    result, base = row["result"], row.get("baselines") or {}
    return {"dataset": Path(row["dataset"]).parent.name, "split": row["split"],
            "num_nodes": row["num_nodes"], "topology": row["topology"],
            "mse": result["mse"], "failed": result["failed"], "huber": result["huber"],
            "trajectories": result["trajectories"],
            "hold_x0": base.get("hold_x0"), "time_mean": base.get("time_mean")}


def _rollout_figure(ckpt, data, split: str, path: Path) -> str:
    """The first trajectory of `split`, predicted against true, message norms beneath (the
    paper's Fig. 2, 3b and 11)."""
    import torch

    from mpnode_cli.config.fields import train_solver
    from mpnode_cli.config.upgrade import stored_solver
    from mpnode_cli.report.plots import plot_rollout
    from mpnode_cli.training.evaluate import predict

    subset = data.subset(split)
    pred = predict(ckpt.build_model(), subset, ckpt.build_normalizer(), torch.arange(1),
                   solver=stored_solver(ckpt.train_config, train_solver))
    messages = None if pred.messages is None else pred.messages[0]
    title = f"{data.system}, N={data.num_nodes} ({split}), trajectory 0"
    return str(plot_rollout(pred.time, pred.true[0], pred.pred[0], messages, data.state_names,
                            path, title=title, dpi=FIGURE_DPI,
                            spread=None if pred.spread is None else pred.spread[0]))


def line(record: StepRecord) -> str:
    """One line of a finished step's main number (an ensemble's as mean ± std over its
    members)."""
    r = record.result

    def g(path: str) -> str:
        return members.shown(members.values(r, path))

    if record.verb in TRAINING:
        return (f"best epoch {g('best_epoch')}/{r['epochs']}, min val loss "
                f"{g('min_val_loss')}, test MSE {g('test.mse')}" + _of_members(r))
    if record.verb == "generate":
        return f"{r['trajectories']} trajectories × {r['samples']} samples"
    if record.verb == "evaluate":
        return f"{r['split']} MSE {g('mse')} (hold x(0) {_g(r['hold_x0'])})" + _of_members(r)
    if record.verb == "zeroshot":
        return ", ".join(f"{k} MSE {g(k + '.mse')}" for k in r
                         if k != members.MEMBERS) + _of_members(r)
    return f"{len(record.figures)} figures"


def _of_members(result: dict[str, Any]) -> str:
    size = len(result.get(members.MEMBERS) or [])
    return f" (mean ± std of {size} members)" if size else ""


def _g(value: Any) -> str:
    return "—" if value is None else f"{value:.4g}"
