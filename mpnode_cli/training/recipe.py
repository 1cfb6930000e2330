"""Training recipes: the defaults a run starts from, beneath a config file and options.

A run's config is resolved in this order (later wins):
1. `TrainConfig`'s own field defaults;
2. the recipe named by `config.recipe`:
   - `mpnode` (the default): the choices measured in `bench/results/quality.md` and
     explained in `docs/training-recipe.md`, plus what the dataset's system recommends (a
     dataset carries it as its `recipe` attribute; files without one fall back to the
     system's declaration by name, then to nothing);
   - `paper`: the paper's and its authors' exact choices (MPNODE.jl,
     configs/empode_sys_32_3.toml and src/learn.jl:117-129): the paper's loss for the system,
     batches of 128 with the last partial batch kept, constant lr 1e-3 halved after 500
     epochs without improvement, mean aggregation, no curriculum, 4000 epochs;
3. a `--config` file; 4. command-line options.
Fields given at steps 3–4 are those in `TrainConfig.model_fields_set`; the resolved config
(every field explicit) is what a run folder's `config.json` keeps, so a resume never
re-applies a recipe. `resolve_train_config` applies the recipe and checks the model's
options.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from mpnode_cli.config.train import TrainConfig
from mpnode_cli.models.registry import OPTIONS, resolve_options

if TYPE_CHECKING:
    from mpnode_cli.data.dataset import TrajectoryData

RECIPES = ("mpnode", "paper")

# Trajectories with more samples than this are learned through the horizon curriculum by
# default: single shooting from x(t₀) over the pendulum's 101 samples learns nothing without
# it (docs/training-recipe.md).
CURRICULUM_MIN_SAMPLES = 61

_MPNODE: dict[str, Any] = {
    "loss": "mse",
    "batch_size": 32,
    "even_batches": True,
    "schedule": "plateau",
    "patience": 50,
    # Four halvings of the lr without a better validation loss: a long budget then spends
    # only the epochs it needs (each ensemble member stops on its own).
    "stop_patience": 200,
    "val_batch_size": 1024,
    # A node update affine in the sum of what the neighbours send, and message states that
    # start from the node's state: the choice that carries a node model to larger graphs
    # with higher degrees (bench/results/transfer.md). A system whose coupling is not a
    # neighbour sum says so in its own recommendation (Lorenz, the quadrotor swarm).
    # The node networks see (sin θ, cos θ) of the states a dataset declares angles, where
    # it declares any: unwrapped phases drift out of any training range (docs/transfer.md).
    "model_options": {"aggregate": "sum", "update": "affine", "message_init": "learned",
                      "periodic": "auto"},
}

_PAPER: dict[str, Any] = {
    "loss": "huber",  # replaced by the system's paper loss where it has one
    "batch_size": 128,
    "even_batches": False,
    "schedule": "plateau",
    "patience": 500,
    "val_batch_size": None,  # the training batch size, as the authors' loader
    "horizon_curriculum": False,
    "epochs": 4000,
    "model_options": {"aggregate": "mean"},
}


# The transfer recipe, over mpnode's for a `--for-graphs` run (fields given still win): the
# lr annealed to min_lr over the epochs (Loshchilov & Hutter 2017), the gradients' global
# norm clipped at 5, and no early stop, so that the annealing runs its course: with the
# recipe's patience of 200 epochs, gene's runs stopped at 1147-1330 of 4000 epochs, their
# lr still above 80% of its start (docs/transfer.md).
TRANSFER: dict[str, Any] = {"schedule": "cosine", "clip": 5.0, "stop_patience": None}


def system_recipe(system: str, stored: dict[str, Any] | None) -> dict[str, dict[str, Any]]:
    """What a dataset's system recommends: its stored attribute, else its declaration."""
    if stored:
        return stored
    from mpnode_cli.systems.registry import system_class

    try:  # built in, or a plug-in this process knows
        return system_class(system).recipe()
    except ValueError:
        return {}


def recipe_values(name: str, system: dict[str, dict[str, Any]], samples: int) -> dict[str, Any]:
    """The train-config fields recipe `name` sets for data of `samples` samples per
    trajectory whose system recommends `system` (`{"paper": ..., "mpnode": ...}`)."""
    if name not in RECIPES:
        raise ValueError(f"unknown recipe '{name}' (choose from: {', '.join(RECIPES)})")
    if name == "paper":
        values = {**_PAPER, **system.get("paper", {})}
    else:
        values = {**_MPNODE, "horizon_curriculum": samples >= CURRICULUM_MIN_SAMPLES,
                  **system.get("mpnode", {})}
    values["model_options"] = dict(values.get("model_options", {}))
    return values


def resolve_recipe(config: TrainConfig, system: str, stored: dict[str, Any] | None,
                   samples: int, accepts: Callable[[str], bool]) -> TrainConfig:
    """`config` with every field it was not given taken from its recipe.

    Args:
        config: as built from a config file and options.
        system, stored: the training dataset's system name and `recipe` attribute.
        samples: T, samples per trajectory.
        accepts: whether the model being trained declares a model option of this name
            (a recipe's model options apply only to models that have them).
    """
    values = recipe_values(config.recipe, system_recipe(system, stored), samples)
    if config.coverage is not None:
        values |= TRANSFER
    model_options = values.pop("model_options")
    given = config.model_fields_set
    update = {k: v for k, v in values.items() if k not in given}
    if "val_batch_size" in update and update["val_batch_size"] is None:
        update["val_batch_size"] = config.batch_size if "batch_size" in given else values[
            "batch_size"]
    chosen = dict(config.model_options)  # the options given win, key by key
    for k, v in model_options.items():
        if accepts(k):
            chosen.setdefault(k, v)
    update["model_options"] = chosen
    return config.model_copy(update=update)


def resolve_train_config(config: TrainConfig, data: TrajectoryData) -> TrainConfig:
    """Fill what `config` was not given from its recipe (for `data`), then check the model
    and its options and fill in the options' defaults.

    A finetune's model comes from its checkpoint, so its model options are left as they are.

    Raises:
        ValueError: unknown model, or an option the model does not declare or refuses
            (one line naming the model and the option); a min_lr above the lr.
    """
    finetune = config.init_checkpoint is not None
    declared = () if finetune or config.model not in OPTIONS else OPTIONS[config.model].model_fields
    config = resolve_recipe(config, data.system, data.attrs.get("recipe"), data.time.numel(),
                            lambda name: name in declared)
    if config.min_lr > config.lr:  # checked here, where a system's recipe has set the lr
        raise ValueError(f"min_lr ({config.min_lr:g}) is above lr ({config.lr:g}): the lr "
                         "would start below its floor; lower --min-lr or raise --lr")
    if finetune:
        return config
    options = resolve_options(config.model, config.model_options)
    return config.model_copy(update={"model_options": options.model_dump()})


# Compile the solver's step when a run takes at least this many optimizer steps. Compiling
# costs 10–60 s on 2 CPU cores (less from inductor's on-disk cache) and saves about 30% of
# each training step (bench/results/train.md), so it pays from a few thousand steps on.
COMPILE_MIN_STEPS = 3000
# The least --time-limit a compiled run is worth: its first epochs compile for tens of
# seconds on a CPU (18 s for a 3-node Lorenz run), which a shorter budget would overrun.
COMPILE_MIN_SECONDS = 300


def resolve_compile(config: TrainConfig, n_train: int) -> TrainConfig:
    """Settle `solver.compile = "auto"` for a run over `n_train` trajectories.

    Compile when the run is long (≥ `COMPILE_MIN_STEPS` optimizer steps, and no
    `--time-limit` under `COMPILE_MIN_SECONDS`, which compiling would overrun), its steps are
    adaptive (compiling does not apply to `fixed_dt`), it trains one model (not an
    ensemble), backpropagates without checkpoints and a C++ compiler is there for
    inductor on CPU. Shapes that change (a smaller last batch, the horizon curriculum's
    growing horizon) cost one more compile, after which torch.compile treats that size as
    dynamic (`solve`'s automatic dynamic shapes).
    """
    if config.solver.compile != "auto":
        return config
    steps = config.epochs * -(-n_train // config.batch_size)
    # An ensemble runs eager: its members' stacked weights are swapped in for each rollout
    # (`mpnode_cli.models.ensemble`), which the compiled step is not traced for.
    # A checkpointed solve runs its steps uncompiled (`solve` ignores compile there).
    decide = (steps >= COMPILE_MIN_STEPS and config.solver.fixed_dt is None
              and (config.time_limit is None or config.time_limit >= COMPILE_MIN_SECONDS)
              and config.seeds == 1 and config.solver.checkpoints is None
              and (config.device != "cpu" or have_cxx()))
    return config.model_copy(update={"solver": config.solver.model_copy(
        update={"compile": decide})})


def describe_solver(config: TrainConfig) -> str:
    """One line for the run's header: the method, tolerances, controller and compile."""
    o = config.solver
    steps = f"fixed dt {o.fixed_dt:g}" if o.fixed_dt is not None else (
        f"rtol {o.rtol:g}, atol {o.atol:g}, {o.controller.upper()} controller")
    compiled = "compiled (the first epochs compile)" if o.compile is True else "not compiled"
    if o.checkpoints is not None:  # `solve` ignores compile then
        compiled = f"not compiled, checkpointed backprop ({o.checkpoints} stored states)"
    return f"{o.method}, {steps}, {compiled}"


def have_cxx() -> bool:
    return shutil.which(os.environ.get("CXX", "g++")) is not None
