"""The tiny scale of an experiment: every step shrunk to a smoke test (`--scale tiny`, derived
from the small scale's options)."""

from __future__ import annotations

from typing import Any

TINY_TRAJECTORIES = 24  # per generated dataset at the tiny scale
TINY_SAMPLES = 5  # sample times per trajectory at the tiny scale
TINY_EPOCHS = 2


def shrink_generate(fields: dict[str, Any]) -> dict[str, Any]:
    """The tiny scale of a generate step: a few trajectories of a few samples (a quadrotor
    flight keeps the horizon it needs to pass the doorway)."""
    from mpnode_cli.systems.quadrotor_flight import MIN_HORIZON
    from mpnode_cli.systems.registry import system_class

    defaults = system_class(fields["system"]).data_defaults
    dt = fields.get("dt", defaults.get("dt", 0.1))
    t_end = fields.get("t_end", defaults.get("t_end", 1.0))
    shortest = MIN_HORIZON if fields["system"] == "quadrotor" else 0.0
    trajectories = fields.get("trajectories", defaults.get("trajectories", 100))
    return {**fields, "t_end": min(t_end, max((TINY_SAMPLES - 1) * dt, shortest)),
            "trajectories": max(fields.get("graphs", 1), min(trajectories, TINY_TRAJECTORIES))}


def shrink_train(options: dict[str, Any]) -> dict[str, Any]:
    """The tiny scale of a train or finetune step: two epochs on a few trajectories, and
    the smallest L2S (it is the slowest model per epoch)."""
    out = {**options, "epochs": min(options.get("epochs", TINY_EPOCHS), TINY_EPOCHS),
           "batch_size": 8}
    if "trajectories" in out:
        out["trajectories"] = max(2, min(out["trajectories"] // 50, 8))
    if out.get("model") == "l2s":
        out["model_options"] = {**out.get("model_options", {}), "latent": 8, "hidden": 8,
                                "steps": 1}
    return out
