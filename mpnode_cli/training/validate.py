"""Check a checkpoint completely: `check_checkpoint(path) -> Report`.

The file must be an mpnode checkpoint of a version this mpnode reads (see
`mpnode_cli.training.checkpoint`), its model must build from its kind and config, its
weights must fit that model and be finite, its normalization must match the model's state
and control sizes with finite means and positive standard deviations, its train config must
validate, and it must say which dataset it was trained on (and, if it records its train
split's range, `dataset["train_range"]`, a readable one).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import torch

from mpnode_cli.data.validate import Report

# Facts about the training dataset that evaluate, zeroshot and finetune rely on.
_DATASET_FACTS = ("fingerprint", "system", "num_nodes", "node_dim", "state_names")


def check_checkpoint(path: str | Path) -> Report:
    """Every check of the module docstring; a run folder means its `checkpoints/best.pt`."""
    from pydantic import ValidationError

    from mpnode_cli.config import TrainConfig, error_line, upgrade_train_fields
    from mpnode_cli.models.registry import OPTIONS, build_model
    from mpnode_cli.training.checkpoint import FORMAT, FORMAT_VERSION, load_checkpoint
    from mpnode_cli.training.extrapolation import TrainRange

    report = Report(Path(path), "checkpoint")
    problems, summary = report.problems, report.summary
    try:
        ckpt = load_checkpoint(path)
    except (FileNotFoundError, ValueError) as exc:
        problems.append(str(exc))
        return report
    report.path = ckpt.path or report.path
    summary.update({"format": f"{FORMAT} v{FORMAT_VERSION}", "model": ckpt.model_kind,
                    "epoch": ckpt.epoch, "trained_on": _trained_on(ckpt.dataset)})
    if not isinstance(ckpt.epoch, int) or ckpt.epoch < 0:
        problems.append(f"epoch must be a non-negative integer, got {ckpt.epoch!r}")
    if ckpt.model_kind not in OPTIONS:
        problems.append(f"unknown model kind '{ckpt.model_kind}' (this mpnode knows: "
                        f"{', '.join(OPTIONS)})")
    elif not isinstance(ckpt.model_config, dict):
        problems.append("model_config must be a dictionary of the model's options")
    else:
        try:
            model = build_model(ckpt.model_kind, ckpt.model_config)
        except (TypeError, ValueError, RuntimeError) as exc:
            problems.append(f"model_config does not build a '{ckpt.model_kind}' model: "
                            f"{str(exc).splitlines()[0]}")
        else:
            summary["parameters"] = sum(p.numel() for p in model.parameters())
            problems += _weights(model.state_dict(), ckpt.state_dict)
            problems += _normalizer(ckpt.normalizer, int(ckpt.model_config.get("node_dim", 0)),
                                    int(ckpt.model_config.get("control_dim", 0)))
    missing = [key for key in _DATASET_FACTS
               if not isinstance(ckpt.dataset, dict) or key not in ckpt.dataset]
    if missing:
        problems.append(f"the training dataset's facts lack {', '.join(missing)}")
    if isinstance(ckpt.dataset, dict) and ckpt.dataset.get("train_range") is not None:
        try:  # absent in checkpoints older than the record, which is fine
            TrainRange.from_dict(ckpt.dataset["train_range"])
        except ValueError as exc:
            problems.append(str(exc))
    try:
        TrainConfig(**upgrade_train_fields(dict(ckpt.train_config)))
    except ValidationError as exc:
        problems.append(f"train_config does not validate: {error_line(exc)}")
    except (TypeError, ValueError) as exc:
        problems.append(f"train_config does not validate: {exc}")
    return report


def _trained_on(facts: Any) -> dict[str, Any] | None:
    if not isinstance(facts, dict):
        return None
    trained_on = {key: facts.get(key) for key in ("system", "num_nodes", "topology", "path")}
    if isinstance(facts.get("datasets"), list):  # several at once: the first's above
        trained_on["datasets"] = [d.get("path") for d in facts["datasets"]
                                  if isinstance(d, dict)]
    return trained_on


def _weights(want: dict[str, torch.Tensor], have: Any) -> list[str]:
    """The stored weights against the built model's: names, shapes, finite values."""
    if not isinstance(have, dict):
        return ["state_dict must be a dictionary of tensors"]
    problems = []
    missing = [name for name in want if name not in have]
    extra = [name for name in have if name not in want]
    if missing:
        problems.append(f"state_dict lacks weights the model has: {', '.join(missing[:5])}"
                        + (" ..." if len(missing) > 5 else ""))
    if extra:
        problems.append(f"state_dict has weights the model does not: {', '.join(extra[:5])}"
                        + (" ..." if len(extra) > 5 else ""))
    for name, tensor in have.items():
        if name not in want or not isinstance(tensor, torch.Tensor):
            continue
        if tensor.shape != want[name].shape:
            problems.append(f"weight {name} has shape {list(tensor.shape)}, the model "
                            f"expects {list(want[name].shape)}")
        elif tensor.is_floating_point() and not bool(torch.isfinite(tensor).all()):
            bad = int((~torch.isfinite(tensor)).sum())
            problems.append(f"weight {name} holds {bad} non-finite values")
    return problems


def _normalizer(normalizer: Any, d: int, u: int) -> list[str]:
    """Means and stds of the states (`[D]`) and controls (`[U]`), finite, stds positive."""
    if not isinstance(normalizer, dict):
        return ["normalizer must be a dictionary of x_mean, x_std, u_mean, u_std"]
    problems = []
    for name, size in (("x_mean", d), ("x_std", d), ("u_mean", u), ("u_std", u)):
        values = normalizer.get(name)
        if not isinstance(values, list | tuple) or len(values) != size:
            shown = len(values) if isinstance(values, list | tuple) else values
            problems.append(f"normalizer {name} must hold {size} numbers, got {shown!r:.40}")
            continue
        if not all(isinstance(v, int | float) and math.isfinite(v) for v in values):
            problems.append(f"normalizer {name} holds non-finite values")
        elif name.endswith("std") and not all(v > 0 for v in values):
            problems.append(f"normalizer {name} must be positive")
    return problems
