"""Reading older checkpoints: each format version's upgrade to the next, applied in order
on reading (`upgrade_payload`), and the check of the stored version (`version_problem`).

What each version changed is told in `mpnode_cli.training.checkpoint`'s docstring. A file
is read as the version it says it is: one that says 1 goes through every upgrade from 1
(each leaves what it does not find as it is), and `mpnode check` says so ("upgraded from
v1"); a version that is not a whole number from 1 to this mpnode's is refused.
Whatever its version, a file's retired options go where they hold their "off" value
(`drop_retired`); a file that used one is refused.
"""

from __future__ import annotations

from typing import Any

from mpnode_cli.config.upgrade import (
    RetiredOptionError,
    pin_stored_solver,
    upgrade_solver_fields,
    upgrade_train_fields,
    without_retired,
    without_retired_options,
)


def version_problem(version: Any, newest: int) -> str | None:
    """What is wrong with a stored `format_version` (None: a version this mpnode reads,
    a whole number from 1 to `newest`); the line follows the file's path."""
    if type(version) is not int:  # bool, str ('6') and float are no version numbers
        return (f"has format_version {version!r}, not a whole number from 1 to {newest}: "
                "not a checkpoint mpnode wrote")
    if version > newest:
        return (f"is checkpoint format v{version}, newer than this mpnode reads "
                f"(v{newest}); upgrade mpnode")
    if version < 1:
        return f"has format_version {version}, below the first (1): not a checkpoint mpnode wrote"
    return None


def upgrade_payload(payload: dict[str, Any], version: int) -> None:
    """Upgrade a checkpoint's dict, stored as format `version`, to the newest, in place."""
    if version < 2:
        _upgrade_v1(payload)
    if version < 3:
        _upgrade_v2(payload)
    if version < 4 and isinstance(payload.get("train_config"), dict):
        payload["train_config"] = upgrade_solver_fields(payload["train_config"])
    if version < 5 and isinstance(payload.get("train_config"), dict):
        payload["train_config"] = pin_stored_solver(payload["train_config"])
    if version < 7:
        _upgrade_v6(payload)
    if version < 8:
        _upgrade_v7(payload)


def drop_retired(payload: dict[str, Any]) -> None:
    """The retired options (`mpnode_cli.config.upgrade.RETIRED`) out of an upgraded
    checkpoint's model config and train config, in place; an asinh scale in its
    normalizer is the retired `normalize = "asinh"`.

    Raises:
        RetiredOptionError: one of them at another value than "off".
    """
    if isinstance(payload.get("model_config"), dict):
        payload["model_config"] = without_retired_options(payload["model_config"])
    if isinstance(payload.get("train_config"), dict):
        payload["train_config"] = without_retired(payload["train_config"])
    if isinstance(payload.get("normalizer"), dict) and "x_scale" in payload["normalizer"]:
        raise RetiredOptionError("normalize", "asinh")


def _upgrade_v1(payload: dict[str, Any]) -> None:
    """Version 1 → 2 in place: the renamed MP-NODE option (version 2's PNA buffer is gone
    again since version 8, so it is not added)."""
    kind, config = payload.get("model_kind"), payload.get("model_config")
    if isinstance(config, dict) and kind == "mpnode" and "aggregation" in config:
        config["backend"] = config.pop("aggregation")


def _upgrade_v2(payload: dict[str, Any]) -> None:
    """Version 2 → 3 in place: model options out of the train config, and L2S's
    `step_noise` (then a train config field) into its model config."""
    train_config, config = payload.get("train_config"), payload.get("model_config")
    if not isinstance(train_config, dict):
        return
    if payload.get("model_kind") == "l2s" and isinstance(config, dict) and (
            "step_noise" in train_config):
        config.setdefault("step_noise", train_config["step_noise"])
    payload["train_config"] = upgrade_train_fields(train_config)


def _upgrade_v6(payload: dict[str, Any]) -> None:
    """Version 6 → 7 in place: datasets of then had no periodic states."""
    facts = payload.get("dataset")
    if isinstance(facts, dict):
        facts.setdefault("periodic_states", [])
        for each in facts.get("datasets") or []:
            if isinstance(each, dict):
                each.setdefault("periodic_states", [])


def _upgrade_v7(payload: dict[str, Any]) -> None:
    """Version 7 → 8 in place: PNA's δ belongs to its aggregation module
    (`aggregation.delta`); the other aggregations read no statistic, so their models' δ,
    fitted but unused, goes."""
    kind, config, state = (payload.get(k) for k in ("model_kind", "model_config", "state_dict"))
    if kind not in ("mpnode", "gnode") or not isinstance(state, dict):
        return
    pna = isinstance(config, dict) and config.get("aggregate") == "pna"
    for key in [k for k in state if k == "degree_delta" or k.endswith(".degree_delta")]:
        delta = state.pop(key)
        if pna:
            state[key.removesuffix("degree_delta") + "aggregation.delta"] = delta
