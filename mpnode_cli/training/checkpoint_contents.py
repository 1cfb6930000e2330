"""The one checkpoint check: `checkpoint_problems(ckpt)`, everything wrong with a
checkpoint's contents, one line each.

`mpnode_cli.training.checkpoint.load_checkpoint` runs it for every reader (evaluate,
zeroshot, simulate, finetune, train --resume, experiments) and stops at the first problem;
`mpnode check` (`mpnode_cli.training.checkpoint_check`) lists them all.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import torch

from mpnode_cli.config.upgrade import upgrade_train_fields

if TYPE_CHECKING:
    from mpnode_cli.models.base import NeuralModel
    from mpnode_cli.training.checkpoint import Checkpoint


# Facts about the training dataset that evaluate, zeroshot and finetune rely on.
_DATASET_FACTS = ("fingerprint", "system", "num_nodes", "node_dim", "state_names")


def checkpoint_problems(ckpt: Checkpoint) -> list[str]:
    """Everything wrong with a checkpoint's contents, one line each (empty: usable).

    The one checkpoint check (`load_checkpoint` for every reader, `mpnode check` for a
    user): its model must build from its kind and config; its weights must fit that model
    (names and shapes) and be finite; its normalization must match the model's state and
    control sizes with finite means and positive standard deviations (as float32, the
    dtype it is applied in); an optimizer state, what `train --resume` continues, must be
    Adam's over the model's parameters with moments of their shapes, beside the RNG states
    and loop counters; its train config must validate; and it must say which dataset it was
    trained on (and, if it records its train split's range, a readable one).

    The model is built on torch's meta device: shapes without memory, so the check costs
    little next to reading the file, whatever sizes the config claims.
    """
    problems = []
    if not isinstance(ckpt.epoch, int) or isinstance(ckpt.epoch, bool) or ckpt.epoch < 0:
        problems.append(f"epoch must be a non-negative integer, got {ckpt.epoch!r}")
    model = _meta_model(ckpt, problems)
    if model is not None:
        problems += _weights(model.state_dict(), ckpt.state_dict)
        sizes = (int(model.config.get("node_dim", 0)), int(model.config.get("control_dim", 0)))
        problems += _normalizer(ckpt.normalizer, *sizes)
        problems += _dataset_facts(ckpt.dataset, sizes[0])
        if ckpt.optimizer is not None:
            problems += _resume_state(ckpt, [p for p in model.parameters() if p.requires_grad])
    problems += _train_config(ckpt.train_config)
    return problems


def _meta_model(ckpt: Checkpoint, problems: list[str]) -> NeuralModel | None:
    """The checkpoint's model with weights on the meta device (None: a problem added)."""
    from mpnode_cli.models.registry import OPTIONS, build_model

    if not isinstance(ckpt.model_kind, str) or ckpt.model_kind not in OPTIONS:
        problems.append(f"unknown model kind {ckpt.model_kind!r:.40} (this mpnode knows: "
                        f"{', '.join(OPTIONS)})")
        return None
    if not isinstance(ckpt.model_config, dict):
        problems.append("model_config must be a dictionary of the model's options")
        return None
    try:
        with torch.device("meta"):
            return build_model(ckpt.model_kind, ckpt.model_config)
    except (TypeError, ValueError, RuntimeError, OverflowError) as exc:
        problems.append(f"model_config does not build a '{ckpt.model_kind}' model: "
                        f"{(str(exc).splitlines() or [type(exc).__name__])[0]}")
        return None


def _weights(want: dict[str, torch.Tensor], have: Any) -> list[str]:
    """The stored weights against the built model's: names, shapes, finite values."""
    if not isinstance(have, dict):
        return ["state_dict must be a dictionary of tensors"]
    problems = []
    for what, names in (("lacks weights the model has", [n for n in want if n not in have]),
                        ("has weights the model does not", [n for n in have if n not in want])):
        if names:
            problems.append(f"state_dict {what}: {', '.join(map(str, names[:5]))}"
                            + (" ..." if len(names) > 5 else ""))
    for name, tensor in have.items():
        if name not in want:
            continue
        if not isinstance(tensor, torch.Tensor) or tensor.layout != torch.strided or (
                tensor.is_complex()):
            problems.append(f"weight {name} is not a dense real tensor")
        elif tensor.shape != want[name].shape:
            problems.append(f"weight {name} has shape {list(tensor.shape)}, the model "
                            f"expects {list(want[name].shape)}")
        elif tensor.is_floating_point() and not bool(torch.isfinite(tensor).all()):
            bad = int((~torch.isfinite(tensor)).sum())
            problems.append(f"weight {name} holds {bad} non-finite values")
    return problems


def _normalizer(normalizer: Any, d: int, u: int) -> list[str]:
    """Means and stds of the states (`[D]`) and controls (`[U]`): finite, stds positive,
    as the float32 `Normalizer.from_dict` makes of them."""
    if not isinstance(normalizer, dict):
        return ["normalizer must be a dictionary of x_mean, x_std, u_mean, u_std"]
    problems = []
    named = [("x_mean", d), ("x_std", d), ("u_mean", u), ("u_std", u)]
    for name, size in named:
        values = normalizer.get(name)
        if not isinstance(values, list | tuple) or len(values) != size:
            shown = len(values) if isinstance(values, list | tuple) else values
            problems.append(f"normalizer {name} must hold {size} numbers, got {shown!r:.40}")
            continue
        if not all(isinstance(v, int | float) and not isinstance(v, bool) for v in values):
            problems.append(f"normalizer {name} must hold numbers")
            continue
        as_used = torch.tensor(values, dtype=torch.float32)
        if not bool(torch.isfinite(as_used).all()):
            problems.append(f"normalizer {name} holds non-finite values (as float32)")
        elif name.endswith("std") and not bool((as_used > 0).all()):
            problems.append(f"normalizer {name} must be positive (as float32)")
    return problems


def _dataset_facts(facts: Any, d: int) -> list[str]:
    """What the checkpoint says of its training dataset, as readers use it."""
    if not isinstance(facts, dict):
        return ["the training dataset's facts must be a dictionary"]
    missing = [key for key in _DATASET_FACTS if key not in facts]
    if missing:
        return [f"the training dataset's facts lack {', '.join(missing)}"]
    problems = []
    n, names = facts["num_nodes"], facts["state_names"]
    if not isinstance(n, int) or isinstance(n, bool) or n < 1:
        problems.append(f"the training dataset's num_nodes must be a positive integer, "
                        f"got {n!r:.40}")
    if not isinstance(names, list | tuple) or len(names) != d or not all(
            isinstance(name, str) for name in names):
        problems.append(f"the training dataset's state_names must be {d} names (the "
                        f"model's node_dim), got {names!r:.60}")
    periodic = facts.get("periodic_states", [])
    if not isinstance(periodic, list | tuple) or not all(
            isinstance(name, str) and isinstance(names, list | tuple) and name in names
            for name in periodic):
        problems.append(f"the training dataset's periodic_states must be names among its "
                        f"state_names, got {periodic!r:.60}")
    if facts.get("train_range") is not None:  # absent in checkpoints older than the record
        from mpnode_cli.training.train_range import TrainRange

        try:
            spans = TrainRange.from_dict(facts["train_range"])
        except ValueError as exc:
            problems.append(str(exc))
        else:
            if len(spans.states) != d:
                problems.append(f"train_range holds {len(spans.states)} state ranges, the "
                                f"model's node_dim is {d}")
    return problems


def _resume_state(ckpt: Checkpoint, params: list[torch.Tensor]) -> list[str]:
    """What `train --resume` restores besides the weights: the optimizer (`Adam.state_dict`,
    parameters by index, as `torch.optim.Adam`), both RNG states and the loop's counters."""
    state = ckpt.optimizer
    try:
        groups = list(state["param_groups"])  # one, or one per ensemble member
        indices = [int(i) for group in groups for i in group["params"]]
        # Which parameter each moment belongs to; lr, eps and betas must be numbers.
        moments = {indices.index(int(i)): s for i, s in state["state"].items()}
        _ = [[float(g["lr"]), float(g["eps"]), *map(float, g["betas"])] for g in groups]
        if not groups:
            raise ValueError
    except (KeyError, TypeError, ValueError):
        return ["the optimizer state is not Adam's (param_groups, state by parameter)"]
    if len(indices) != len(params):
        return [f"the optimizer state holds {len(indices)} parameters, the model has "
                f"{len(params)}"]
    problems = []
    for i, moment in moments.items():
        for key, shape in (("step", ()), ("exp_avg", params[i].shape),
                           ("exp_avg_sq", params[i].shape)):
            value = moment.get(key) if isinstance(moment, dict) else None
            if not isinstance(value, torch.Tensor) or value.shape != shape:
                shown = list(value.shape) if isinstance(value, torch.Tensor) else value
                problems.append(f"optimizer {key} of parameter {i} is {shown!r:.40}, "
                                f"expected shape {list(shape)}")
            elif not bool(torch.isfinite(value).all()):
                problems.append(f"optimizer {key} of parameter {i} holds non-finite values")
    size = torch.get_rng_state().shape  # one CPU generator's state, global or not
    for name in ("torch", "shuffle"):
        value = ckpt.rng.get(name) if isinstance(ckpt.rng, dict) else None
        if not isinstance(value, torch.Tensor) or value.dtype != torch.uint8 or (
                value.shape != size):
            problems.append(f"the RNG state '{name}' must be a CPU generator's (uint8 "
                            f"{list(size)})")
    if not _numbers(ckpt.loop, members=True):
        problems.append("the loop state must be a dictionary of numbers (an ensemble's: "
                        "with a list of them, one per member)")
    return problems


def _numbers(loop: Any, members: bool = False) -> bool:
    """Whether `loop` is a dict of numbers; `members`: it may hold a list of such dicts."""
    if not isinstance(loop, dict):
        return False
    for key, value in loop.items():
        if members and key == "members":
            if not isinstance(value, list) or not all(_numbers(m) for m in value):
                return False
        elif not isinstance(value, int | float):
            return False
    return True


def _train_config(train_config: Any) -> list[str]:
    from pydantic import ValidationError

    from mpnode_cli.config.file import error_line
    from mpnode_cli.config.train import TrainConfig

    try:
        TrainConfig(**upgrade_train_fields(dict(train_config)))
    except ValidationError as exc:
        return [f"train_config does not validate: {error_line(exc)}"]
    except (TypeError, ValueError) as exc:
        return [f"train_config does not validate: {exc}"]
    return []
