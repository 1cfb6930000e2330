"""The `mpnode` command line equivalent to each step, for the report.

A step runs through the library; these are the commands that would do the same from a
shell, run from the work folder (`from_work`: its paths relative to it, so a committed
report holds no folder of the machine that ran it). What the CLI has no switch for
(messages zeroed at test time, the PCA of the messages) is said in a comment after the
command.
"""

from __future__ import annotations

import re
import shlex
from pathlib import Path
from typing import Any

from mpnode_cli import flags


def _options(fields: dict[str, Any], skip: tuple[str, ...] = ()) -> list[str]:
    """The words of each field (`mpnode_cli.flags.words`); `solver` and `model_options`
    tables as their own options; `params` as `-p NAME=VALUE`."""
    out: list[str] = []
    for name, value in fields.items():
        if name in skip or value is None:
            continue
        if name in ("solver", "model_options"):
            out += _options(value)
        elif name == "params":
            for key, item in value.items():
                out += ["-p", f"{key}={item}"]
        else:
            out += flags.words(name, value)
    return out


def _line(args: list[Any]) -> str:
    return shlex.join(str(a) for a in args)


def from_work(line: str, work: Path) -> str:
    """`line` as run from the folder `work`: each argument under it (as given or resolved)
    relative to it. Only whole arguments' starts are matched, so `../x` stays."""
    for prefix in dict.fromkeys((str(Path(work)), str(Path(work).resolve()))):
        if prefix not in (".", ""):
            line = re.sub(r"(?<![^\s'\"=])" + re.escape(prefix.rstrip("/") + "/"), "", line)
    return line


def generate_line(step, options: dict[str, Any], out: Path) -> str:
    """`mpnode generate --preset P` and the fields where the resolved config differs from
    the preset's (the scale's sizes included)."""
    from mpnode_cli.config.generate import GenerateConfig
    from mpnode_cli.data.generate import resolve_generate_config
    from mpnode_cli.data.presets import get_preset

    config = options["config"]
    start: dict[str, Any] = {}
    args: list[Any] = ["mpnode", "generate"]
    if step.preset:
        args += ["--preset", step.preset]
        start = resolve_generate_config(GenerateConfig(**get_preset(step.preset))).model_dump(
            mode="json", exclude={"out"})
    else:
        args.append(config["system"])
    changed = {k: v for k, v in config.items() if start.get(k) != v and k != "system"}
    if "params" in changed:
        changed["params"] = {k: v for k, v in config["params"].items()
                             if start.get("params", {}).get(k) != v}
    if "solver" in changed:
        changed["solver"] = {k: v for k, v in config["solver"].items()
                             if start.get("solver", {}).get(k) != v}
    return _line([*args, *_options(changed), "--out", out])


def train_line(step, options: dict[str, Any], data: Path, run_dir: Path,
               checkpoint: Path | None) -> str:
    """`mpnode train DATA` (or `mpnode finetune CKPT DATA`) with the step's options."""
    head = (["mpnode", "finetune", checkpoint, data] if checkpoint is not None
            else ["mpnode", "train", data])
    fields = {"plots": False, **options["config"], "recipe": options["recipe"]}
    return _line([*head, *_options(fields), "--run-dir", run_dir])


def zeroshot_line(checkpoint: Path, datasets: list[Path], split: str) -> str:
    return _line(["mpnode", "zeroshot", checkpoint, *datasets, "--split", split])


def evaluate_line(checkpoint: Path, data: Path, step) -> str:
    line = _line(["mpnode", "evaluate", checkpoint, data, "--split", step.split])
    notes = []
    if step.zero_messages:
        notes.append("with messages zeroed: no CLI switch; the library evaluates the "
                     "checkpoint's weights in a model built with messages=False")
    if step.pca:
        notes.append(f"PCA of the messages of {step.trajectories} trajectories: library only "
                     "(mpnode_cli.experiments.steps)")
    return line + "".join(f"  # {n}" for n in notes)


def compare_line(runs: list[Path]) -> str:
    return _line(["mpnode", "compare", *runs])
