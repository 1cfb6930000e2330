"""The config of `mpnode train` and `mpnode finetune`."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from mpnode_cli.config.fields import SEED_MAX, over_defaults, train_solver
from mpnode_cli.limits import within_float32
from mpnode_cli.memory import MemorySize
from mpnode_cli.solver.options import SolverOptions


class TrainConfig(BaseModel):
    """What `mpnode train` (and `mpnode finetune`) does: one model, its datasets, one run folder.

    Fields not given are filled from the run's recipe (`mpnode_cli.training.recipe`); the
    defaults below equal mpnode's recipe without a system's recommendation. Each field's
    `description` documents it, and is the help of its option in `mpnode train` and
    `mpnode finetune`, which are built from these fields.
    """

    # No inf or NaN in any number (`--t-end inf` would never end).
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    dataset: Path | list[Path] = Field(description=(
        "The training dataset (an mpnode .h5 file): its train split is fitted, its "
        "validation split selects the best epoch, its test split is reported. Or a list of "
        "datasets of one system and per-node sizes (N, graphs and the number of samples "
        "may differ), trained on at once: their splits are pooled (mpnode_cli.data.pooled). "
        "A list of one is stored as that one path, so a one-file config reads as it always "
        "has; `datasets` gives the list either way."))
    model: str = Field("mpnode", description="The model, by its registry name.")
    model_options: dict[str, Any] = Field(default_factory=dict, description=(
        "Options of that model, by name (a [model_options] table in a TOML file); each "
        "model declares its own, with their defaults, in mpnode_cli.models.options. Options "
        "left out take the model's defaults; the training layer validates them against the "
        "model (mpnode_cli.training.recipe.resolve_train_config), and the resolved config written "
        "to a run holds every option of the model that was built."))
    recipe: Literal["mpnode", "paper"] = Field("mpnode", description=(
        "Where the fields left out come from: mpnode (measured choices and the dataset "
        "system's recommendation) or paper (the paper's exact choices)."))
    loss: Literal["huber", "mse", "node-mse"] = Field("mse", description=(
        "Training loss: mse; huber (δ = 1, summed over time and features, mean over "
        "trajectories × nodes: the authors' Huber along time); or node-mse, each node's "
        "squared error over its own variance in the window, for graphs whose hubs' states "
        "dwarf a typical node's."))
    lr: float = Field(1e-3, gt=0, description="Adam learning rate.")
    min_lr: float = Field(1e-6, ge=0, description=(
        "Lowest lr: schedules stop there, and a rollback below it ends the run as "
        "diverged."))
    schedule: Literal["plateau", "cosine", "constant"] = Field("plateau", description=(
        "lr schedule: plateau (halve it after `patience` epochs without validation gain), "
        "cosine (down to min_lr over the epochs) or constant."))
    batch_size: int = Field(32, ge=1, description="Trajectories per step.")
    even_batches: bool = Field(True, description=(
        "Batches of nearly equal size each epoch (no tiny last one), or full ones and a "
        "partial last one."))
    val_batch_size: int = Field(1024, ge=1, description=(
        "Trajectories per validation rollout."))
    clip: float = Field(500.0, gt=0, description="Global gradient-norm clip.")
    patience: int = Field(50, ge=1, description=(
        "Plateau schedule: epochs without validation gain before the lr halves."))
    wrap_angles: bool = Field(False, description=(
        "Take the training loss and every error (validation, evaluate, zeroshot, the "
        "baselines) of the states the dataset declares periodic mod 2π, as the wrapped "
        "difference atan2(sin Δ, cos Δ): for angles defined only mod 2π, such as "
        "Kuramoto's phases, where a whole turn is no error. Off: plain differences, as "
        "runs made without this option report."))
    balance_datasets: bool = Field(False, description=(
        "Several datasets: weigh each one's loss (training, and the validation that picks "
        "the best epoch) by 1 / its normalized states' variance; off: all values alike."))
    noise: float = Field(1e-4, ge=0, description=(
        "Std of Gaussian noise on the normalized training states (inputs and targets "
        "alike), fresh every batch."))
    epochs: int = Field(4000, ge=1, description=(
        "The last epoch to train (on resume the total, not the extra)."))
    seed: int = Field(0, ge=0, le=SEED_MAX, description=(
        "Seed of initialization, shuffling and noise."))
    seeds: int = Field(1, ge=1, le=64, description=(
        "Members of an ensemble, trained at once as one batched model: member k has seed "
        "seed + k (its own initialization, batch order and noise), its own lr schedule, "
        "clipping, best epoch and early stop, and all of them are integrated in one solve. "
        "The checkpoints hold every member; evaluate, zeroshot and compare report mean ± std "
        "over them, and simulate writes their spread."))
    time_limit: float | None = Field(None, gt=0, description=(
        "Stop after the epoch in which the run's time (the sum of its epochs, validation "
        "included; a resumed run's earlier epochs count) reaches this many seconds: a "
        "budget of wall time rather than epochs (none: train every epoch)."))
    stop_patience: int | None = Field(None, ge=1, description=(
        "Early stop: a member stops training after this many epochs without a better "
        "validation loss, and the run stops when all have (none: train every epoch)."))
    device: Literal["cpu", "cuda"] = Field("cpu", description="Where to train.")
    dtype: Literal["float32", "float64"] = Field("float32", description=(
        "Precision of the weights and the training rollouts; float64 is slower, for "
        "checks that compare runs to round-off and for stiff systems."))
    memory_budget: MemorySize | None = Field(None, description=(
        "Memory the run may take, e.g. 4GiB or 500MiB (default: what is free): past it, "
        "steps backpropagate through checkpointed solves (docs/training-recipe.md)."))
    run_dir: Path | None = Field(None, description=(
        "The run folder (default runs/<dataset>-<model>-<time>)."))
    solver: SolverOptions = Field(default_factory=train_solver, description=(
        "How the rollouts are integrated, in training and in every evaluation of the "
        "checkpoints; default adaptive Tsit5 at rtol = atol = 1e-4 (train_solver). A table "
        "that names only some options takes the others from that default."))
    horizon_curriculum: bool = Field(False, description=(
        "Train on prefixes of the trajectories growing from curriculum_start samples to "
        "the whole horizon over curriculum_epochs epochs (validation takes it whole)."))
    curriculum_start: int = Field(5, ge=2, description=(
        "Curriculum: samples per trajectory in the first epoch."))
    curriculum_epochs: int = Field(100, ge=1, description=(
        "Curriculum: epochs to reach the whole horizon."))
    max_bad_steps: int = Field(5, ge=1, description=(
        "Skipped batches in a row (non-finite loss or gradient, failed solves) before the "
        "last epoch's state is restored at half the lr."))
    plots: bool = Field(True, description=(
        "Draw the test-split plots into the run folder at the end."))
    init_checkpoint: Path | None = Field(None, description=(
        "Finetune: start from this checkpoint's weights and architecture (model and "
        "model_options are then ignored), with a fresh optimizer."))
    trajectories: int | None = Field(None, ge=1, description=(
        "Use only the first K train trajectories of each dataset (all of them, with a "
        "warning, where a dataset has fewer)."))
    renormalize: bool = Field(False, description=(
        "Finetune: fit the normalization on the new train split instead of reusing the "
        "checkpoint's; better when the new graphs' states have another scale "
        "(docs/cli.md)."))
    allow_other_system: bool = Field(False, description=(
        "Finetune: accept a dataset whose system differs from the checkpoint's (refused "
        "by default: the model learned another system)."))
    allow_predictions: bool = Field(False, description=(
        "Accept a model's predictions (evaluate --save-predictions, simulate) as training "
        "data; refused by default, as a model would learn another model's errors."))
    stream: bool = Field(False, description=(
        "Read the batches from the dataset file as they are needed (a thread reads two "
        "ahead), for data larger than memory; the losses are those of the data in "
        "memory."))
    for_graphs: list[Path] = Field(default_factory=list, description=(
        "Train for deployment to these graphs (mpnode datasets, adjacency .npy or edge "
        "lists; only their graphs are read): degree-coverage data reaching their largest "
        "in-degree are simulated into the run folder and trained on beside the datasets, "
        "with the transfer recipe (docs/transfer.md)."))
    for_in_degree: int | None = Field(None, ge=1, description=(
        "As --for-graphs, for nodes of in-degree up to this."))
    system_file: Path | None = Field(None, description=(
        "With --for-graphs: the plug-in system's file, where the dataset's has moved."))
    coverage: dict[str, Any] | None = Field(None, description=(
        "Set by the run: the coverage data --for-graphs made (file, W, seeds, reach)."))

    # They meet float32 tensors (the optimizer's, the gradients', the states').
    _in_float32 = field_validator("lr", "min_lr", "clip", "noise")(within_float32)

    @field_validator("solver", mode="before")
    @classmethod
    def _fill_solver(cls, value: Any) -> Any:
        return over_defaults(train_solver, value)

    @field_validator("dataset")
    @classmethod
    def _one_or_several(cls, value: Path | list[Path]) -> Path | list[Path]:
        if isinstance(value, list) and not value:
            raise ValueError("give at least one dataset")
        return value[0] if isinstance(value, list) and len(value) == 1 else value

    @model_validator(mode="after")
    def _check_members(self) -> TrainConfig:
        if self.seeds > 1 and self.seed + self.seeds - 1 > SEED_MAX:
            raise ValueError(f"seeds: the members' seeds seed … seed + {self.seeds - 1} "
                             f"pass {SEED_MAX}; give a smaller seed")
        if self.seeds > 1 and isinstance(self.dataset, list):
            # Each member draws its own batch order, and with several datasets a step
            # would hold batches of different graph sizes, which one solve cannot stack.
            raise ValueError("seeds: an ensemble trains on one dataset; train one run per "
                             "seed on several datasets, or give one dataset")
        self.solver.check_precision(self.dtype)
        return self

    @property
    def datasets(self) -> list[Path]:
        """The training datasets, in the order given (one or several)."""
        return list(self.dataset) if isinstance(self.dataset, list) else [self.dataset]
