"""Models by name: what `--model` accepts and checkpoints record."""

from __future__ import annotations

from typing import Any

from torch import nn

from mpnode_cli.models.gnode import GNODE
from mpnode_cli.models.l2s import L2S
from mpnode_cli.models.mpnode import MPNODE
from mpnode_cli.models.node import NODE

MODELS: dict[str, type[nn.Module]] = {"mpnode": MPNODE, "l2s": L2S, "gnode": GNODE, "node": NODE}


def build_model(kind: str, config: dict[str, Any]) -> nn.Module:
    """Rebuild a model from its kind and `model.config`.

    Raises:
        ValueError: unknown kind or configuration.
    """
    if kind not in MODELS:
        raise ValueError(f"unknown model '{kind}' (choose from: {', '.join(MODELS)})")
    try:
        return MODELS[kind](**config)
    except TypeError as exc:
        raise ValueError(f"bad configuration for model '{kind}': {exc}") from None
