"""Configs stored by earlier versions of mpnode, read as today's: datasets' `config`, run
folders' `config.json`, checkpoints' `train_config` and config files given to a verb.

Each upgrade maps old fields onto today's without changing what the stored run did; the
format versions that call them are in `mpnode_cli.data.hdf5` and
`mpnode_cli.training.checkpoint_upgrade`. Options that a bench measured and mpnode then
retired (`RETIRED`) read as today's where they hold the value that meant "off", and are
refused otherwise: no model of this mpnode computes what they did.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from typing import Any

from mpnode_cli.config.fields import over_defaults
from mpnode_cli.solver.options import SolverOptions

# TrainConfig fields that held model options before each model declared its own (written
# into run folders' config.json and checkpoints' train_config by earlier versions);
# `aggregation` is MP-NODE's `backend` under its first name.
_FLAT_MODEL_FIELDS = ("hidden", "layers", "activation", "message_dim", "graph", "messages",
                      "aggregate", "backend", "aggregation", "latent", "steps", "depth",
                      "history", "step_noise")


# Config fields that held solver options before `solver` (generate: rtol, atol; train: all
# three), written into datasets' config, run folders' config.json and checkpoints.
_FLAT_SOLVER_FIELDS = ("rtol", "atol", "fixed_dt")


def upgrade_solver_fields(fields: dict[str, Any]) -> dict[str, Any]:
    """Map a generate or train config written before `solver` onto today's fields.

    The flat `rtol`, `atol` and `fixed_dt` move into the `solver` table (where it names
    them too, the table wins); the options they did not have take the config's defaults,
    which are what the solver did then (Tsit5, `solve`'s `max_steps`, no compile). A
    config without flat solver fields is returned as it is.

    Args:
        fields: a config as JSON fields (a dataset's stored config, a run's `config.json`,
            a config file).

    Returns:
        New fields that the config accepts (if the rest is valid).
    """
    flat = {k: fields[k] for k in _FLAT_SOLVER_FIELDS if k in fields}
    if not flat:
        return fields
    fields = {k: v for k, v in fields.items() if k not in flat}
    nested = fields.get("solver")
    if nested is None or isinstance(nested, dict):
        fields["solver"] = {**flat, **(nested or {})}
    return fields


def stored_solver(fields: dict[str, Any], defaults: Callable[[], SolverOptions]) -> SolverOptions:
    """The solver options of a stored config, of today's form or an earlier one, without
    validating the rest of it.

    Args:
        fields: e.g. a checkpoint's `train_config` or a dataset's stored config.
        defaults: the verb's defaults, `train_solver` or `generate_solver`.
    """
    fields = pin_stored_solver(upgrade_solver_fields(fields))
    return SolverOptions(**over_defaults(defaults, fields.get("solver", {})))


def pin_stored_solver(fields: dict[str, Any]) -> dict[str, Any]:
    """A config that mpnode stored before `SolverOptions.controller` existed ran with the
    PI controller, and one stored without `compile` ran uncompiled: say so, so that a
    resumed or re-evaluated run integrates as it did (the train defaults are now "i" and
    "auto"). Only for stored configs (run folders, checkpoints, datasets): a user's config
    file that leaves them out gets the verb's defaults.

    Args:
        fields: a stored config as JSON fields, after `upgrade_solver_fields`.
    """
    solver = fields.get("solver")
    if solver is None or isinstance(solver, dict):
        pinned = {"controller": "pi", "compile": False} | (solver or {})
        if pinned != solver:
            fields = {**fields, "solver": pinned}
    return fields


def upgrade_train_fields(fields: dict[str, Any]) -> dict[str, Any]:
    """Map a train config written by an earlier version onto today's fields.

    The flat model fields set (not None) move into `model_options`, `aggregation`
    becoming `backend`; `step_noise`, then a field of every config, is kept for L2S
    only, the one model that used it. The flat solver fields move into `solver`
    (`upgrade_solver_fields`), and retired options at their "off" value go
    (`without_retired`). A config of today's form is returned as it is.

    Args:
        fields: a resolved train config as JSON fields (e.g. a run's `config.json`).

    Returns:
        New fields that `TrainConfig(**fields)` accepts (if the rest is valid).

    Raises:
        RetiredOptionError: a retired option at another value.
    """
    fields = without_retired(upgrade_solver_fields(fields))
    if "model_options" in fields or not any(k in fields for k in _FLAT_MODEL_FIELDS):
        return fields
    fields = dict(fields)
    options = {k: fields.pop(k) for k in _FLAT_MODEL_FIELDS if k in fields}
    if "aggregation" in options:
        options["backend"] = options.pop("aggregation")
    if fields.get("model", "mpnode") != "l2s":
        options.pop("step_noise", None)
    fields["model_options"] = {k: v for k, v in options.items() if v is not None}
    return fields


# Options that the transfer bench measured and mpnode retired, no better than the default
# (docs/transfer.md, "What was tried and retired"), each with the value that meant "off":
# MP-NODE's `linear_path`, `gain` and `input_scale`, and the train config's `normalize`.
RETIRED = {"model_options": {"linear_path": False, "gain": "mlp", "input_scale": "z"},
           "train": {"normalize": "z"}}
RETIRED_AFTER = "0.1.0"  # the last mpnode version that reads them


class RetiredOptionError(ValueError):
    """A stored config or config file that sets a retired option to another value than
    "off"; `setting` is it as `name = value` (JSON)."""

    def __init__(self, name: str, value: Any):
        self.setting = f"{name} = {json.dumps(value, default=str)}"
        super().__init__(f"the config sets {self.setting}, {retired_note()}")


def retired_note() -> str:
    """What a refusal of a retired option says after naming it."""
    return (f"an option retired after mpnode {RETIRED_AFTER} (the last version that reads "
            "it; docs/transfer.md)")


def without_retired_options(options: Mapping[str, Any]) -> dict[str, Any]:
    """A model config (or a train config's `model_options`) without the retired model
    options, which must hold their "off" value.

    Raises:
        RetiredOptionError: the first that does not.
    """
    return _without(options, RETIRED["model_options"])


def without_retired(fields: dict[str, Any]) -> dict[str, Any]:
    """A train config's JSON fields without the retired fields and model options, which
    must hold their "off" value; `fields` itself where it has none.

    Raises:
        RetiredOptionError: the first that does not.
    """
    options = fields.get("model_options")
    nested = isinstance(options, dict) and any(k in options for k in RETIRED["model_options"])
    if not nested and not any(k in fields for k in RETIRED["train"]):
        return fields
    fields = _without(fields, RETIRED["train"])
    if nested:
        fields["model_options"] = without_retired_options(options)
    return fields


def _without(fields: Mapping[str, Any], retired: Mapping[str, Any]) -> dict[str, Any]:
    for name, off in retired.items():
        if name in fields and fields[name] != off:
            raise RetiredOptionError(name, fields[name])
    return {k: v for k, v in fields.items() if k not in retired}
