"""Models by name: what `--model` accepts, each model's declared options, and the classes
that checkpoints' `model_kind` rebuilds.

Importing this module does not import torch: `OPTIONS` (name → options class) feeds the
CLI's options and help, and `model_class` imports a model's module only when asked.
Adding a model is its module, its options class in `mpnode_cli.models.options`, and one
line in each table below.
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from mpnode_cli.models.options import (
    GNODEOptions,
    L2SOptions,
    ModelOptions,
    MPNODEOptions,
    NODEOptions,
)

if TYPE_CHECKING:
    from mpnode_cli.models.base import NeuralModel

OPTIONS: dict[str, type[ModelOptions]] = {
    "mpnode": MPNODEOptions, "l2s": L2SOptions, "gnode": GNODEOptions, "node": NODEOptions,
}
_CLASSES = {"mpnode": "mpnode_cli.models.mpnode:MPNODE", "l2s": "mpnode_cli.models.l2s:L2S",
            "gnode": "mpnode_cli.models.gnode:GNODE", "node": "mpnode_cli.models.node:NODE"}


def _check_kind(kind: str) -> None:
    if kind not in OPTIONS:
        raise ValueError(f"unknown model '{kind}' (choose from: {', '.join(OPTIONS)})")


def model_class(kind: str) -> type[NeuralModel]:
    """The model class registered as `kind` (imports its module, and so torch).

    Raises:
        ValueError: unknown kind.
    """
    _check_kind(kind)
    module, name = _CLASSES[kind].split(":")
    return getattr(importlib.import_module(module), name)


def resolve_options(kind: str, given: Mapping[str, Any]) -> ModelOptions:
    """Validate options given for model `kind`; those left out take the model's defaults.

    Returns:
        The model's options (`.model_dump()` holds every option, defaults filled in).

    Raises:
        ValueError: unknown kind, an option the model does not declare, or a bad value —
            one line that names the model and the option.
    """
    _check_kind(kind)
    return OPTIONS[kind].parse(given, kind)


def build_model(kind: str, config: Mapping[str, Any]) -> NeuralModel:
    """Build a model from its kind and `model.config` (data sizes and options, one flat dict).

    A config with `members` S (an ensemble's, `mpnode_cli.models.ensemble`; 1 if left out)
    builds S members of that config; their weights come from the checkpoint that holds them.

    Raises:
        ValueError: unknown kind, missing sizes, or an option the model refuses.
    """
    members = int(config.get("members", 1))
    config = {k: v for k, v in config.items() if k != "members"}
    if members < 1:
        raise ValueError(f"an ensemble has at least one member, not {members}")
    from mpnode_cli.models.ensemble import ensemble_of

    return ensemble_of([model_class(kind).from_config(config) for _ in range(members)])
