"""Checkpoint files, format "mpnode-checkpoint" version 7: everything to rebuild a model.

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
        control_names, periodic_states, topology of the training dataset, and
        train_range, what its train split spans
        (`mpnode_cli.training.train_range.TrainRange.to_dict`: in-degree, node count,
        each state's range), which `evaluate`, `zeroshot` and `simulate`
        compare their graphs and states with.
    epoch: epochs completed.
    optimizer: `optimizer.state_dict()`.
    rng: `torch` (the global CPU RNG state) and `shuffle` (the loop's generator), uint8.
    loop: the loop's own state (best validation loss, epoch counters, lr history); an
        ensemble's holds each member's under `members`.
    parent_sha256: sha256 of the checkpoint a finetune started from, else None.
    metrics: its epoch's metrics row (best.pt's: the best epoch's validation metrics).
    payload_sha256: sha256 of all the other fields, which every reader verifies
        (`mpnode_cli.training.checkpoint_digest`); none in a file saved before it.

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
Version 6 added ensembles (`mpnode train --seeds S`, `mpnode_cli.models.ensemble`): their
`model_config` holds `members` S, their `state_dict` each member's weights under
`members.k.`, their optimizer one parameter group per member and their `loop` a `members`
list of each member's counters. A version 5 file is a model of one member and reads as it
is; an older mpnode would refuse the ensemble's `members` option, hence the new version.
Version 7 added the training dataset's `periodic_states` to `dataset` (and to each of
`dataset["datasets"]`), and MP-NODE's `periodic` option, whose `embed` puts the periodic
states' indices in `model_config` as `periodic_dims`; a version 6 file reads with no
periodic states (`_upgrade_v6`). An older mpnode would refuse the option, and would measure
the errors of a run trained with `wrap_angles` without wrapping, hence the new version.
Version 8 made each aggregation a module of the model (`mpnode_cli.models.aggregate`): PNA's
δ is its buffer `aggregation.delta`, and a model that aggregates otherwise keeps no δ; a
version 7 file's `degree_delta` moves or goes (`_upgrade_v7`). An older mpnode would miss
`degree_delta` in the weights, hence the new version.
`dataset["train_range"]` came later without a new version: a file without it only goes
without the extrapolation warning, and an older mpnode that ignores it computes the same.
Options retired later without a new version (`mpnode_cli.config.upgrade.RETIRED`) go on
reading where they are off, and a file trained with one on is refused, naming it
(`checkpoint_upgrade.drop_retired`): a file without them reads as off in an older mpnode.

Writes are atomic (temporary file beside the target, then rename), so Ctrl-C during a save
leaves the previous checkpoint intact; torch serializes in memory and Python writes the
bytes, so that a full disk is one line (`mpnode_cli.data.atomic.atomic_bytes`).
"""

from __future__ import annotations

import io
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch

from mpnode_cli import __version__
from mpnode_cli.config.upgrade import RetiredOptionError, retired_note
from mpnode_cli.data.atomic import atomic_bytes
from mpnode_cli.file_records import file_sha256  # noqa: F401  (a checkpoint's identity)
from mpnode_cli.terminal import suggested
from mpnode_cli.training.checkpoint_contents import checkpoint_problems
from mpnode_cli.training.checkpoint_digest import DIGEST, payload_sha256
from mpnode_cli.training.checkpoint_upgrade import drop_retired, upgrade_payload, version_problem

if TYPE_CHECKING:
    from mpnode_cli.models.base import NeuralModel

FORMAT = "mpnode-checkpoint"
FORMAT_VERSION = 8


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
    # In memory only: the ensemble member of the file at `path` this is (`member_checkpoint`).
    member: int | None = None
    # In memory only: the format version the file was stored in (upgraded on reading).
    format_version: int = FORMAT_VERSION
    # In memory only: the digest the file carried and matched (None: saved before digests).
    digest: str | None = None

    @property
    def members(self) -> int:
        """S, the models this checkpoint holds: an ensemble's members, or 1."""
        return int(self.model_config.get("members", 1))

    def build_model(self) -> NeuralModel:
        """The model with these weights (on the CPU), in their precision."""
        from mpnode_cli.models.registry import build_model

        model = build_model(self.model_kind, self.model_config)
        floating = [v for v in self.state_dict.values()
                    if isinstance(v, torch.Tensor) and v.is_floating_point()]
        if floating and floating[0].dtype == torch.float64:  # trained in float64
            model.double()
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
    payload[DIGEST] = payload_sha256(payload)
    buffer = io.BytesIO()
    torch.save(payload, buffer)
    return atomic_bytes(path, buffer.getbuffer())  # an interrupt waits for the write


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
    """Read a checkpoint (tensors on the CPU) and check it completely
    (`checkpoint_problems`): what every reader of a checkpoint calls (evaluate, zeroshot,
    simulate, finetune, train --resume, experiments), so that a file `mpnode check`
    refuses never starts a rollout or a run. A run folder means its `checkpoints/best.pt`.

    Raises:
        FileNotFoundError: no such file (or a folder without a checkpoint).
        CheckpointFormatError: not an mpnode checkpoint, a newer format version, or one
            whose contents do not make a usable model: one line naming the file and the
            first problem (and how many more there are).
    """
    ckpt = read_checkpoint(path)
    problems = checkpoint_problems(ckpt)
    if problems:
        more = len(problems) - 1
        tail = f" (and {more} more: {suggested('check', Path(ckpt.path))})" if more else ""
        raise CheckpointFormatError(f"{ckpt.path} is not a valid checkpoint: {problems[0]}{tail}")
    return ckpt


def read_checkpoint(path: str | Path) -> Checkpoint:
    """A checkpoint's fields as stored (upgraded to this format version), unchecked:
    `mpnode check` reads with it to list every problem; everything else uses
    `load_checkpoint`.

    Raises:
        FileNotFoundError, CheckpointFormatError: as `load_checkpoint`, but only for a file
            that is not a checkpoint of a format this mpnode reads.
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
    except Exception as exc:  # pickle, zip and weights_only errors: "not ours"; EACCES: no
        raise CheckpointFormatError(f"cannot read {path}: {exc.strerror}" if getattr(
            exc, "errno", None) else f"{path} is not an mpnode checkpoint (torch cannot read "
            "it as a saved dictionary of tensors; is it a dataset or another file?)") from None
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise CheckpointFormatError(f"{path} is not an mpnode checkpoint (no format '{FORMAT}')")
    digest = payload.get(DIGEST)
    try:
        intact = digest is None or digest == payload_sha256(payload)
    except (RuntimeError, TypeError, ValueError):  # a tensor of a kind mpnode never saves
        intact = False
    if not intact:
        raise CheckpointFormatError(
            f"{path} is damaged: its contents are not those it was saved with (their sha256 "
            "differs from the one recorded in it); use another checkpoint (a run keeps "
            "best.pt and last.pt) or train again")
    version = payload.get("format_version")
    if problem := version_problem(version, FORMAT_VERSION):
        raise CheckpointFormatError(f"{path} {problem}")
    upgrade_payload(payload, version)
    try:
        drop_retired(payload)
    except RetiredOptionError as exc:
        raise CheckpointFormatError(f"{path}: this checkpoint was trained with {exc.setting}, "
                                    f"{retired_note()}") from None
    try:
        return Checkpoint(
            model_kind=payload["model_kind"], model_config=payload["model_config"],
            state_dict=payload["state_dict"], normalizer=payload["normalizer"],
            train_config=payload["train_config"], dataset=payload["dataset"],
            epoch=payload["epoch"], optimizer=payload.get("optimizer"),
            rng=payload.get("rng") or {}, loop=payload.get("loop") or {},
            parent_sha256=payload.get("parent_sha256"), metrics=payload.get("metrics") or {},
            mpnode_version=payload.get("mpnode_version", "?"), path=path,
            format_version=version, digest=digest,
        )  # fmt: skip
    except KeyError as exc:
        raise CheckpointFormatError(f"{path} lacks the checkpoint field {exc.args[0]!r}") from None
