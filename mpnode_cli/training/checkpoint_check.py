"""Check a checkpoint completely: `check_checkpoint(path) -> Report`.

The file must be an mpnode checkpoint of a version this mpnode reads (see
`mpnode_cli.training.checkpoint`), and its contents must pass
`mpnode_cli.training.checkpoint_contents.checkpoint_problems`, the one checkpoint check, which
`load_checkpoint` runs for every other reader: the model builds from its kind and config,
its weights fit that model and are finite, its normalization fits the model's sizes with
finite means and positive standard deviations, an optimizer state fits the model's
parameters, its train config validates, and it says which dataset it was trained on.
`mpnode check` lists every problem, where a reader stops at the first.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from mpnode_cli.data.validate import Report
from mpnode_cli.report.members import shown


def check_checkpoint(path: str | Path) -> Report:
    """Every problem `checkpoint_problems` finds, and a summary; a run folder means its
    `checkpoints/best.pt`."""
    from mpnode_cli.training.checkpoint import FORMAT, FORMAT_VERSION, read_checkpoint
    from mpnode_cli.training.checkpoint_contents import checkpoint_problems

    report = Report(Path(path), "checkpoint")
    try:
        ckpt = read_checkpoint(path)
    except (FileNotFoundError, ValueError) as exc:
        report.problems.append(str(exc))
        return report
    report.path = ckpt.path or report.path
    version = f"{FORMAT} v{FORMAT_VERSION}"
    if ckpt.format_version != FORMAT_VERSION:  # read as stored, then upgraded
        version += f" (upgraded from v{ckpt.format_version} on reading)"
    report.summary.update({"format": version, "model": ckpt.model_kind,
                           "epoch": ckpt.epoch, "trained_on": _trained_on(ckpt.dataset),
                           "checksum": "sha256 of the contents, verified" if ckpt.digest else
                           "none (saved before mpnode recorded one)"})
    report.problems += checkpoint_problems(ckpt)
    if report.ok:
        report.summary["parameters"] = sum(p.numel() for p in ckpt.build_model().parameters())
        seed, s = int(ckpt.train_config.get("seed", 0)), ckpt.members
        # The K that `--member K` takes, for an ensemble.
        report.summary |= shown(s, {"members": f"{s} (members 0–{s - 1}, seeds "
                                               f"{seed}–{seed + s - 1})"}) or {}
    return report


def _trained_on(facts: Any) -> dict[str, Any] | None:
    if not isinstance(facts, dict):
        return None
    trained_on = {key: facts.get(key) for key in ("system", "num_nodes", "topology", "path")}
    if isinstance(facts.get("datasets"), list):  # several at once: the first's above
        trained_on["datasets"] = [d.get("path") for d in facts["datasets"]
                                  if isinstance(d, dict)]
    return trained_on
