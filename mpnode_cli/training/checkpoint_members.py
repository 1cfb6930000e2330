"""An ensemble checkpoint's members as checkpoints of one model: `--member k` of evaluate,
zeroshot and simulate, and `mpnode check --member k --out` (docs/ensembles.md).
"""

from __future__ import annotations

from pathlib import Path

from mpnode_cli.training.checkpoint import Checkpoint, load_checkpoint, save_checkpoint


def member_checkpoint(ckpt: Checkpoint, k: int) -> Checkpoint:
    """Member k of an ensemble checkpoint as a checkpoint of one model.

    The result is what `mpnode train --seed <seed + k>` would have saved, less what only
    resuming needs: `model_config` without `members`, the weights under `members.k.` with
    that prefix taken off, `train_config` with `seeds` 1 and `seed` + k, no optimizer, RNG
    or loop state, and the ensemble's normalization, dataset facts, epoch and parent. Its
    `metrics` say only where it came from (`member_of`): the ensemble's are the members'
    mean's, and its row of a member may be of another epoch than the member's best weights.
    Its `path` stays the ensemble's, with `member` k, until it is saved.

    Raises:
        ValueError: a checkpoint of one model, or k not one of its members (one line).
    """
    where = ckpt.path or "the checkpoint"
    if ckpt.members == 1:
        raise ValueError(f"--member: {where} holds one model, not an ensemble (members come "
                         "from mpnode train --seeds S)")
    if not 0 <= k < ckpt.members:
        raise ValueError(f"--member: {where} holds members 0 to {ckpt.members - 1}, not {k}")
    prefix = f"members.{k}."
    metrics = {"member_of": {"checkpoint": None if ckpt.path is None else str(ckpt.path),
                             "member": k, "members": ckpt.members}}
    seed = int(ckpt.train_config.get("seed", 0)) + k
    return Checkpoint(
        model_kind=ckpt.model_kind,
        model_config={key: v for key, v in ckpt.model_config.items() if key != "members"},
        state_dict={name.removeprefix(prefix): value for name, value in ckpt.state_dict.items()
                    if name.startswith(prefix)},
        normalizer=ckpt.normalizer, train_config={**ckpt.train_config, "seeds": 1, "seed": seed},
        dataset=ckpt.dataset, epoch=ckpt.epoch, parent_sha256=ckpt.parent_sha256,
        metrics=metrics, mpnode_version=ckpt.mpnode_version, path=ckpt.path, member=k,
    )  # fmt: skip


def export_member(path: str | Path, k: int, out: str | Path, *,
                  overwrite: bool = False) -> Checkpoint:
    """Write member k of the ensemble checkpoint at `path` to `out` as a checkpoint of one
    model (`member_checkpoint`), atomically; `out` is checked and reserved first
    (`mpnode_cli.paths.reserve_output`: never the input, an existing file only with
    `overwrite`).

    Returns:
        The member's checkpoint, as written.

    Raises:
        FileNotFoundError, CheckpointFormatError: as `load_checkpoint`.
        ValueError: not an ensemble, or k not one of its members; an unusable `out`.
        FileExistsError: `out` exists and `overwrite` is False.
    """
    from mpnode_cli.paths import reserve_output

    ckpt = load_checkpoint(path)
    member = member_checkpoint(ckpt, k)
    with reserve_output(out, overwrite=overwrite, inputs=(ckpt.path,)):
        save_checkpoint(out, member)
    return member
