"""A step's options at a scale, resolved and checked: what the step does and what its
fingerprint hashes (`spec.resolve`)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from pydantic import BaseModel, ValidationError

from mpnode_cli.experiments.tiny import shrink_generate, shrink_train

if TYPE_CHECKING:
    from mpnode_cli.experiments.spec import Scale

TRAINING = ("train", "finetune")
# Fields of a train config that the runner sets: the data, the run folder, the parent
# checkpoint, the ensemble's members (from the step's `data`, its folder, `checkpoint`,
# `--seeds`). The recipe is `--recipe`'s unless the step names its own (`recipe = "paper"`:
# an experiment that compares recipes pins each step's).
RUNNER_FIELDS = ("dataset", "run_dir", "init_checkpoint", "seeds")
# Data draw d (`mpnode experiment run --draw d`) offsets the seed and the graph seed of every
# generated dataset by d × this: other graphs, initial states, split, and parameters drawn
# per graph (Kuramoto's ω). Draw 0 is the experiment's own data.
DRAW_STRIDE = 1000


def resolve(step: Any, scale: Scale, recipe: str, seeds: int = 1,
            draw: int = 0) -> dict[str, Any]:
    """A step's verb options at `scale`, checked, as plain JSON: what the step does and what
    its fingerprint hashes (with its inputs' fingerprints).

    - generate: `{"config": GenerateConfig fields}`, the preset merged in (no `out`), its
      seeds offset by `draw` × `DRAW_STRIDE`.
    - train / finetune: `{"config": TrainConfig fields given, "recipe": recipe}` (the
      step's own `recipe` where it names one), with `seeds` when it is over 1 (an
      ensemble of that many members; left out at 1, so a single model's step keeps the
      fingerprint and folder it had before seeds).
    - others: their options.

    Raises:
        ValueError: an unknown preset, config field or model option, or a bad value.
    """
    if step.verb == "call":  # what it does: not its plan's estimates
        return {"target": step.target, "args": step.args}
    options = step.options("small" if scale == "tiny" else scale)
    if step.verb == "generate":
        from mpnode_cli.config.generate import GenerateConfig
        from mpnode_cli.data.generate import resolve_generate_config
        from mpnode_cli.data.presets import get_preset, merge_layers

        preset = options.pop("preset", None)
        layers = [(f"preset {preset}", get_preset(preset) if preset else {}),
                  (f"step {step.id}", options)]
        fields = merge_layers(layers)
        if "out" in fields:
            raise ValueError("'out' is the runner's (the step's folder)")
        if draw:
            fields = {**fields, **{key: int(fields.get(key, 0)) + draw * DRAW_STRIDE
                                   for key in ("seed", "graph_seed")}}
        if scale == "tiny":
            fields = shrink_generate(fields)
        config = resolve_generate_config(_validated(GenerateConfig, {**fields, "out": "data.h5"}))
        return {"config": config.model_dump(mode="json", exclude={"out"})}
    if step.verb in TRAINING:
        from mpnode_cli.config.train import TrainConfig
        from mpnode_cli.models.registry import OPTIONS, resolve_options

        for key in ("data", "checkpoint"):
            options.pop(key, None)
        taken = [k for k in RUNNER_FIELDS if k in options]
        if taken:
            raise ValueError(f"'{taken[0]}' is set by the runner, not the step")
        if scale == "tiny":
            options = shrink_train(options)
        if step.verb == "finetune" and ("model" in options or "model_options" in options):
            raise ValueError("a finetune keeps its checkpoint's model (no model options)")
        if seeds > 1:
            options["seeds"] = seeds
        recipe = options.pop("recipe", recipe)
        _validated(TrainConfig, {**options, "dataset": "data.h5", "recipe": recipe})
        model = options.get("model", "mpnode")
        if model in OPTIONS:
            resolve_options(model, options.get("model_options", {}))
        else:
            raise ValueError(f"unknown model '{model}' (choose from: {', '.join(OPTIONS)})")
        return {"config": options, "recipe": recipe}
    if step.verb == "evaluate" and not options["pca"]:
        # Without a PCA it means nothing; left out, so such a step's fingerprint stays.
        options.pop("pca_untrained")
    if scale == "tiny" and step.verb == "evaluate":
        options["trajectories"] = min(options["trajectories"], 4)
    return options


def _validated(model: type[BaseModel], fields: dict[str, Any]) -> Any:
    from mpnode_cli.config.file import error_line

    try:
        return model(**fields)
    except ValidationError as exc:
        raise ValueError(error_line(exc)) from None
