"""An experiment as data: the pydantic models of `mpnode_cli/experiments/<name>.toml`.

An experiment is a list of steps, each a verb of the CLI (generate, train, finetune,
zeroshot, evaluate, compare) with its options, and the paper's claims it measures. A step
names the steps it uses by id (`data = "lorenz3"`, `checkpoint = "pretrain"`), which must
come before it. Its options are those of the paper's scale; a `small` table overrides some
of them at the small scale:

    [[steps]]
    id = "pretrain"
    verb = "train"
    data = "lorenz3"
    epochs = 4000          # the paper's
    small.epochs = 300     # what --scale small trains

`tiny` is a third scale, derived from `small` by `shrink`: a smoke test of every step.

A claim compares two numbers of the results (`holds = "a.min_train_loss < b.min_train_loss"`,
each side `[FACTOR *] STEP.PATH` or a number); the paper's figure for it is text, with the
place in the paper it comes from; `mpnode_cli.experiments.claims` judges claims on results.
"""

from __future__ import annotations

import tomllib
from importlib import resources
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from mpnode_cli.experiments import members
from mpnode_cli.experiments.claim_grammar import parse_claim
from mpnode_cli.experiments.resolving import (  # noqa: F401 (spec.resolve, spec.DRAW_STRIDE)
    DRAW_STRIDE,
    TRAINING,
    resolve,
)
from mpnode_cli.textfiles import read_text

SCALES = ("tiny", "small", "paper")
Scale = Literal["tiny", "small", "paper"]
_ID = r"^[a-z0-9][a-z0-9-]*$"


class _Step(BaseModel):
    """What every step has.

    Attributes:
        id: the step's name; later steps and claims refer to it.
        small: options that differ at the small scale (merged over the step's own, tables
            key by key).
        reported: the paper's numbers for this step's rows, by row (`test`, `val`, a
            zero-shot data id, ...), shown beside ours.
        reported_in: where in the paper `reported` comes from.
        label: a short name for tables and figures (default: the id).
    """

    model_config = ConfigDict(extra="forbid")

    id: str = Field(pattern=_ID)
    small: dict[str, Any] = Field(default_factory=dict)
    reported: dict[str, float] = Field(default_factory=dict)
    reported_in: str | None = None
    label: str | None = None

    def inputs(self) -> list[str]:
        """Ids of the steps this one reads."""
        return []

    def options(self, scale: Scale) -> dict[str, Any]:
        """The step's verb options at `scale` (before `shrink` for tiny)."""
        # model_dump holds the verb's declared fields and the extra (config) fields.
        base = self.model_dump(exclude=set(_Step.model_fields) | {"verb"})
        return base if scale == "paper" else deep_merge(base, self.small)


class GenerateStep(_Step):
    """`mpnode generate`: a preset and generate config fields over it (`trajectories`,
    `t_end`, `params.coupling`, ...), checked against `GenerateConfig`."""

    model_config = ConfigDict(extra="allow")
    verb: Literal["generate"]
    preset: str | None = None


class TrainStep(_Step):
    """`mpnode train` on a generated dataset; train config fields (`epochs`, `model`,
    `model_options`, `trajectories`, `seed`, ...) as in `TrainConfig`."""

    model_config = ConfigDict(extra="allow")
    verb: Literal["train"]
    data: str

    def inputs(self) -> list[str]:
        return [self.data]


class FinetuneStep(TrainStep):
    """`mpnode finetune`: train from the best checkpoint of the step `checkpoint`."""

    verb: Literal["finetune"]  # type: ignore[assignment]
    checkpoint: str

    def inputs(self) -> list[str]:
        return [self.checkpoint, self.data]


class ZeroshotStep(_Step):
    """`mpnode zeroshot`: a trained model on other datasets, without training."""

    verb: Literal["zeroshot"]
    checkpoint: str
    data: list[str] = Field(min_length=1)
    split: Literal["train", "validation", "test", "all"] = "all"
    plot: bool = True

    def inputs(self) -> list[str]:
        return [self.checkpoint, *self.data]


class EvaluateStep(_Step):
    """`mpnode evaluate`, and what the CLI cannot do: messages zeroed at test time (the
    same weights with `messages=False`, the paper's Fig. 3b) and the PCA of the messages
    over time (Fig. 12).

    Attributes:
        plot: draw the first trajectory with its message norms (Fig. 2).
        pca: principal components of all nodes' messages to draw (0: none).
        pca_untrained: also take the PCA's spread statistics of an untrained model (the
            same architecture, fresh weights, the same trajectories): messages start at
            zero, so they spread out over time in any model, and a trained model's growth
            means something only beside an untrained one's. Only a PCA step has it.
        trajectories: how many trajectories of the split the PCA uses (the paper: 100).
    """

    verb: Literal["evaluate"]
    checkpoint: str
    data: str
    split: Literal["train", "validation", "test", "all"] = "test"
    zero_messages: bool = False
    plot: bool = True
    pca: int = Field(0, ge=0)
    pca_untrained: bool = True
    trajectories: int = Field(100, ge=1)

    def inputs(self) -> list[str]:
        return [self.checkpoint, self.data]


class CompareStep(_Step):
    """`mpnode compare`: runs side by side, their loss curves, and (with `groups`) the
    paper's Table-2 figure, epochs to the best validation loss × that loss, per group.

    Attributes:
        runs: train or finetune steps.
        groups: label → the runs compared in it, e.g. `"ds=50" = ["finetune-50",
            "scratch-50"]`.
        series: what the runs at each position of a group are, e.g. `["finetuned",
            "scratch"]` (default: the labels of the first group's runs).
        curves: the loss curves' units: `time-mean` (each run's training loss and
            validation MSE ÷ its time-mean predictor's validation MSE, so a finetune, which
            keeps its parent's normalization, and a scratch run share an axis) or `raw`.
    """

    verb: Literal["compare"]
    runs: list[str] = Field(min_length=1)
    groups: dict[str, list[str]] = Field(default_factory=dict)
    series: list[str] = Field(default_factory=list)
    curves: Literal["time-mean", "raw"] = "time-mean"

    def inputs(self) -> list[str]:
        return list(self.runs)


class CallStep(_Step):
    """A benchmark's job (`mpnode_cli.experiments.jobs`): `target(folder, inputs, **args)`,
    a function `module:name` importable where the run started, that writes in its folder
    and returns its record. What the benches run through this engine.

    Attributes:
        needs: the steps it reads. seconds: its planned seconds on one core; cap: their
            bound where they may run longer. group: its line in the plan (a system).
    """

    verb: Literal["call"]
    target: str = Field(pattern=r"^[A-Za-z_][\w.]*:[A-Za-z_]\w*$")
    args: dict[str, Any] = Field(default_factory=dict)
    needs: list[str] = Field(default_factory=list)
    seconds: float = Field(0.0, ge=0)
    cap: float | None = Field(None, ge=0)
    group: str = ""

    def inputs(self) -> list[str]:
        return list(self.needs)


Step = Annotated[GenerateStep | TrainStep | FinetuneStep | ZeroshotStep | EvaluateStep
                 | CompareStep | CallStep, Field(discriminator="verb")]


class Claim(BaseModel):
    """One claim of the paper and how our results test its direction.

    Attributes:
        claim: what the paper says, in a sentence.
        paper: the paper's number or figure for it, as text.
        where: where in the paper.
        holds: `LEFT OP RIGHT`, OP one of < > <= >=, each side a number or `[FACTOR *]
            STEP.PATH` (a value in the step's results, e.g. `finetune-50.table2`).
    """

    model_config = ConfigDict(extra="forbid")

    claim: str
    paper: str
    where: str
    holds: str


class Experiment(BaseModel):
    """One of the paper's experiments.

    Attributes:
        name: the file's stem (set by `load`).
        title: one line. paper: the sections and figures it reproduces.
        small_minutes: the small scale's expected wall time on one core of a 2-core
            machine, from seconds per epoch measured on this repository's runs
            (bench/results/quality.md and the first epochs of each training).
        summary: what it does and what to look for (Markdown).
        steps: in order; a step reads only steps before it.
        claims: what the index (`reports/README.md`) checks.
    """

    model_config = ConfigDict(extra="forbid")

    name: str = Field("", pattern=r"^$|" + _ID)
    title: str
    paper: str
    small_minutes: float | None = Field(None, gt=0)
    summary: str = ""
    steps: list[Step] = Field(min_length=1)
    claims: list[Claim] = Field(default_factory=list)


# ------------------------------------------------------------------------------ loading


def names() -> list[str]:
    """The shipped experiments, sorted."""
    return sorted(p.name.removesuffix(".toml") for p in _folder().iterdir()
                  if p.name.endswith(".toml"))


def load(name_or_path: str | Path) -> Experiment:
    """A shipped experiment by name, or a TOML file by path, parsed and checked.

    Raises:
        ValueError: unknown name, a file that does not parse, or a spec that does not
            validate (one line).
    """
    path = Path(name_or_path)
    if not str(name_or_path).endswith(".toml"):
        if str(name_or_path) not in names():
            raise ValueError(f"unknown experiment '{name_or_path}' (choose from: "
                             f"{', '.join(names())})")
        path = shipped(str(name_or_path))
    try:
        fields = tomllib.loads(read_text(path, ""))
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{path.name} does not parse: {exc}") from None
    fields.setdefault("name", path.stem)
    try:
        experiment = Experiment(**fields)
    except ValidationError as exc:
        from mpnode_cli.config.file import error_line

        raise ValueError(f"{path.name}: {error_line(exc)}") from None
    check(experiment)
    return experiment


def _folder():
    return resources.files("mpnode_cli.experiments")


def shipped(name: str) -> Path:
    """The TOML file of a shipped experiment."""
    return Path(str(_folder() / f"{name}.toml"))


def check(experiment: Experiment) -> None:
    """Check what the models cannot: ids, references, presets, options at every scale,
    and the claims' references.

    Raises:
        ValueError: one line naming the experiment and the step.
    """
    seen: dict[str, str] = {}
    for step in experiment.steps:
        where = f"{experiment.name}: step '{step.id}'"
        if step.id in seen:
            raise ValueError(f"{where} is defined twice")
        if step.id == members.MEMBERS:  # a zero-shot step's results hold a row per data id
            raise ValueError(f"{where}: '{members.MEMBERS}' is the name of an ensemble's "
                             "results per member, not a step's")
        for ref in step.inputs():
            want = _wanted(step, ref)
            if ref not in seen:
                raise ValueError(f"{where} reads '{ref}', which is no earlier step")
            if seen[ref] not in want:
                raise ValueError(f"{where} reads '{ref}' ({seen[ref]}), not a "
                                 f"{' or '.join(want)} step")
        for group, runs in getattr(step, "groups", {}).items():
            missing = [m for m in runs if m not in step.runs]
            if missing:
                raise ValueError(f"{where}: group '{group}' names {missing[0]}, not in runs")
        seen[step.id] = step.verb
        for scale in SCALES:
            try:
                resolve(step, scale, "mpnode")
            except ValueError as exc:
                raise ValueError(f"{where} at scale {scale}: {exc}") from None
    for claim in experiment.claims:
        for side in parse_claim(claim.holds)[::2]:
            ref = side[1]
            if ref is not None and ref.split(".", 1)[0] not in seen:
                raise ValueError(f"{experiment.name}: claim '{claim.holds}' names an unknown "
                                 f"step '{ref.split('.', 1)[0]}'")


def _wanted(step: Any, ref: str) -> tuple[str, ...]:
    """The verbs a step's reference `ref` may name."""
    data = getattr(step, "data", None)
    if step.verb == "call":  # a job reads any step
        return ("generate", *TRAINING, "zeroshot", "evaluate", "compare", "call")
    if ref == data or (isinstance(data, list) and ref in data):
        return ("generate",)
    return TRAINING


def deep_merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    """`over` on `base`; tables merge key by key."""
    out = dict(base)
    for key, value in over.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = deep_merge(out[key], value)
        else:
            out[key] = value
    return out
