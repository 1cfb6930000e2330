"""Checkpoint files, format "mpnode-checkpoint" version 5: everything to rebuild a model.

A checkpoint is one `torch.save` of a plain dict — tensors, numbers, strings, lists and
dicts only — so `torch.load(path, weights_only=True)` reads it without unpickling code.
It carries what made the weights (model kind and config, normalization, the resolved train
config, the dataset's fingerprint) and what training needs to continue exactly (epoch,
optimizer state, RNG states, the loop's counters), unlike the authors' weights-only JLD2
files (MPNODE.jl `src/learn.jl:110-115`; docs/authors-code.md).

Fields of the dict:
    format, format_version, mpnode_version: what this file is.
    model_kind, model_config: `build_model(model_kind, model_config)` rebuilds the model.
    state_dict: the model's weights.
    normalizer: `Normalizer.to_dict()` of the training normalization.
    train_config: the resolved `TrainConfig` (JSON form).
    dataset: fingerprint, path, system, num_nodes, node_dim, control_dim, state_names,
        control_names, topology of the training dataset, and train_range, what its train
        split spans (`mpnode_cli.training.extrapolation.TrainRange.to_dict`: in-degree,
        node count, each state's range), which `evaluate`, `zeroshot` and `simulate`
        compare their graphs and states with.
    epoch: epochs completed.
    optimizer: `optimizer.state_dict()`.
    rng: `torch` (the global CPU RNG state) and `shuffle` (the loop's generator), uint8.
    loop: the loop's own state (best validation loss, epoch counters, lr history).
    parent_sha256: sha256 of the checkpoint a finetune started from, else None.
    metrics: the best epoch's validation metrics (and test metrics once known).

Version 2 renamed MP-NODE's `aggregation` option (dense/scatter, how the mean is computed)
to `backend`, added the `aggregate` choice (mean/sum/pna) and the PNA degree statistic
`degree_delta` to MP-NODE's and GNN-ODE's weights; version 1 files are upgraded on reading
(they aggregated with the mean, or GNN-ODE's sum, which the upgrade keeps).
Version 3 moved the model options of `train_config` into its `model_options`, and L2S's
training input noise `step_noise` from there into its `model_config` (an L2S option);
version 2 files are upgraded on reading.
Version 4 moved the solver fields `rtol`, `atol` and `fixed_dt` of `train_config` into its
`solver` table (`SolverOptions`, which adds the method); version 3 files are upgraded on
reading. The version changed because an older mpnode would read a version 4 file without
complaint but evaluate it with its default solver, not the one it was trained with.
Version 5 added the step-size `controller` to the `solver` table; a version 4 file's table
gets "pi", the controller every solve used then (`config.pin_stored_solver`). An older
mpnode would ignore the new key and integrate differently, hence the new version.
`dataset["train_range"]` came later without a new version: a file without it only goes
without the extrapolation warning, and an older mpnode that ignores it computes the same.

Writes are atomic (temporary file beside the target, then rename), so Ctrl-C during a save
leaves the previous checkpoint intact.
"""

from __future__ import annotations

import os
import uuid
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch

from mpnode_cli import __version__
from mpnode_cli.config import pin_stored_solver, upgrade_solver_fields, upgrade_train_fields
from mpnode_cli.paths import file_sha256  # noqa: F401  (a checkpoint's identity)
from mpnode_cli.signals import deferred_signals

if TYPE_CHECKING:
    from mpnode_cli.models.base import NeuralModel

FORMAT = "mpnode-checkpoint"
FORMAT_VERSION = 5


class CheckpointFormatError(ValueError):
    """A file that is not an mpnode checkpoint this version of mpnode can read."""


@dataclass
class Checkpoint:
    """One checkpoint in memory; field meanings as in the module docstring."""

    model_kind: str
    model_config: dict[str, Any]
    state_dict: dict[str, torch.Tensor]
    normalizer: dict[str, list[float]]
    train_config: dict[str, Any]
    dataset: dict[str, Any]
    epoch: int
    optimizer: dict[str, Any] | None = None
    rng: dict[str, torch.Tensor] = field(default_factory=dict)
    loop: dict[str, Any] = field(default_factory=dict)
    parent_sha256: str | None = None
    metrics: dict[str, Any] = field(default_factory=dict)
    mpnode_version: str = __version__
    path: Path | None = None

    def build_model(self) -> NeuralModel:
        """The model with these weights (on the CPU)."""
        from mpnode_cli.models.registry import build_model

        model = build_model(self.model_kind, self.model_config)
        model.load_state_dict(self.state_dict)
        return model

    def build_normalizer(self):
        """The training normalization as a `Normalizer`."""
        from mpnode_cli.data.dataset import Normalizer

        return Normalizer.from_dict(self.normalizer)


def save_checkpoint(path: str | Path, ckpt: Checkpoint) -> Path:
    """Write `ckpt` to `path` atomically (its folder is created if missing)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "mpnode_version": ckpt.mpnode_version,
        "model_kind": ckpt.model_kind,
        "model_config": ckpt.model_config,
        "state_dict": {k: v.detach().cpu() for k, v in ckpt.state_dict.items()},
        "normalizer": ckpt.normalizer,
        "train_config": ckpt.train_config,
        "dataset": ckpt.dataset,
        "epoch": int(ckpt.epoch),
        "optimizer": ckpt.optimizer,
        "rng": ckpt.rng,
        "loop": ckpt.loop,
        "parent_sha256": ckpt.parent_sha256,
        "metrics": ckpt.metrics,
    }
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp")
    try:
        with deferred_signals():  # an interrupt waits for the save, then propagates
            torch.save(payload, tmp)
            os.replace(tmp, path)
    except BaseException:  # an interrupt too: never leave a half-written temp behind
        tmp.unlink(missing_ok=True)
        raise
    return path


def resolve_path(path: str | Path) -> Path:
    """The checkpoint file a user means: the file itself, or a run folder's (or its
    `checkpoints/` folder's) `best.pt`.

    Raises:
        FileNotFoundError: nothing there, or a folder without `checkpoints/best.pt`.
    """
    path = Path(path)
    if path.is_dir():
        for candidate in (path / "checkpoints" / "best.pt", path / "best.pt"):
            if candidate.is_file():
                return candidate
        raise FileNotFoundError(f"{path} is a folder without a checkpoint: give a .pt file, "
                                "e.g. runs/<name>/checkpoints/best.pt")
    if not path.exists():
        raise FileNotFoundError(f"no checkpoint at {path}")
    return path


def load_checkpoint(path: str | Path) -> Checkpoint:
    """Read a checkpoint (tensors on the CPU); a run folder means its `checkpoints/best.pt`.

    Raises:
        FileNotFoundError: no such file (or a folder without a checkpoint).
        CheckpointFormatError: not an mpnode checkpoint, or a newer format version.
    """
    path = resolve_path(path)
    if not path.is_file():
        raise CheckpointFormatError(f"{path} is not a regular file")
    try:
        with warnings.catch_warnings():
            # torch warns of pickles it is about to refuse (another protocol, a legacy
            # file); the refusal below says it, in one line.
            warnings.simplefilter("ignore")
            payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception:  # pickle, zip and weights_only errors all mean "not ours"
        raise CheckpointFormatError(
            f"{path} is not an mpnode checkpoint (torch cannot read it as a saved "
            "dictionary of tensors; is it a dataset or another file?)") from None
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise CheckpointFormatError(f"{path} is not an mpnode checkpoint (no format '{FORMAT}')")
    version = payload.get("format_version")
    if not isinstance(version, int) or version > FORMAT_VERSION:
        raise CheckpointFormatError(
            f"{path} is checkpoint format v{version}, newer than this mpnode reads "
            f"(v{FORMAT_VERSION}); upgrade mpnode")
    if version < 2:
        _upgrade_v1(payload)
    if version < 3:
        _upgrade_v2(payload)
    if version < 4 and isinstance(payload.get("train_config"), dict):
        payload["train_config"] = upgrade_solver_fields(payload["train_config"])
    if version < 5 and isinstance(payload.get("train_config"), dict):
        payload["train_config"] = pin_stored_solver(payload["train_config"])
    try:
        return Checkpoint(
            model_kind=payload["model_kind"], model_config=payload["model_config"],
            state_dict=payload["state_dict"], normalizer=payload["normalizer"],
            train_config=payload["train_config"], dataset=payload["dataset"],
            epoch=payload["epoch"], optimizer=payload.get("optimizer"),
            rng=payload.get("rng") or {}, loop=payload.get("loop") or {},
            parent_sha256=payload.get("parent_sha256"), metrics=payload.get("metrics") or {},
            mpnode_version=payload.get("mpnode_version", "?"), path=path,
        )  # fmt: skip
    except KeyError as exc:
        raise CheckpointFormatError(f"{path} lacks the checkpoint field {exc.args[0]!r}") from None


def _upgrade_v1(payload: dict[str, Any]) -> None:
    """Version 1 → 2 in place: the renamed MP-NODE option and the new PNA buffer."""
    kind, config = payload.get("model_kind"), payload.get("model_config")
    if isinstance(config, dict) and kind == "mpnode" and "aggregation" in config:
        config["backend"] = config.pop("aggregation")
    state = payload.get("state_dict")
    if kind in ("mpnode", "gnode") and isinstance(state, dict):
        state.setdefault("degree_delta", torch.zeros((), dtype=torch.float64))


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
