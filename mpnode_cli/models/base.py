"""What every model shares: the declared contract (`NeuralModel`), its results, the MLP.

Training and evaluation call only what `NeuralModel` declares, so a model is used the same
way whatever it is: built from the data's sizes and its typed options, statistics fitted
on the train split, a batch's training loss, and a rollout from the data's first states.
The neural ODEs (MP-NODE, GNN-ODE, NODE) share one rollout, `mpnode_cli.models.ode`.
"""

from __future__ import annotations

import abc
import itertools
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, Self

import torch
from torch import nn

from mpnode_cli.models.options import ModelOptions
from mpnode_cli.models.stacked import Linear
from mpnode_cli.solver.options import SolverOptions

ACTIVATIONS: dict[str, type[nn.Module]] = {
    "tanh": nn.Tanh,
    "relu": nn.ReLU,
    "elu": nn.ELU,
    "silu": nn.SiLU,
    "softplus": nn.Softplus,
}


@dataclass
class Rollout:
    """Predicted trajectories.

    Attributes:
        states: `[B, T, N, D]` predicted (normalized) node states; index 0 is x0.
        messages: `[B, T, N, M]` message states, when asked for and the model has them.
        status: `[B]` int64 `mpnode_cli.solver.Status` per trajectory (all 0 for models
            that do not use the ODE solver).
        n_f_evals: vector-field evaluations (max over the batch; 0 without a solver).
    """

    states: torch.Tensor
    messages: torch.Tensor | None
    status: torch.Tensor
    n_f_evals: int

    # A model is an ensemble of one: its one member's trajectories are `states` (an
    # ensemble's rollout, `mpnode_cli.models.ensemble.EnsembleRollout`, holds S of them).
    @property
    def members(self) -> torch.Tensor:
        """`[S, B, T, N, D]` each member's predicted states (S = 1: `states`)."""
        return self.states.unsqueeze(0)

    @property
    def member_status(self) -> torch.Tensor:
        """`[S, B]` each member's solver status (S = 1: `status`)."""
        return self.status.unsqueeze(0)

    @property
    def spread(self) -> torch.Tensor:
        """`[B, T, N, D]` the members' standard deviation (population, over S)."""
        return self.members.std(dim=0, correction=0)


@dataclass
class BatchLoss:
    """The training loss of one batch.

    Attributes:
        loss: scalar to minimize, or None when a rollout failed (nothing to learn from).
        status: `[B]` int64 `mpnode_cli.solver.Status` per trajectory (all 0 without a solver).
        n_f_evals: vector-field evaluations (max over the batch; 0 without a solver).
    """

    loss: torch.Tensor | None
    status: torch.Tensor
    n_f_evals: int


class NeuralModel(nn.Module, metaclass=abc.ABCMeta):
    """The contract every model implements (abstract: a model defines at least `rollout`).

    A model is built from the data's sizes and an instance of its `Options`; `config`
    (sizes and options in one flat dict) is what checkpoints store as `model_config`, and
    `build_model(kind, config)` rebuilds the same model from it. Its defaults train like
    the neural ODEs (MP-NODE, GNN-ODE, NODE): whole-horizon rollouts from x(t₀).

    Class attributes:
        kind: registry name (`--model`, checkpoints' `model_kind`).
        transferable: runs on graphs of any node count. A model that is not is built for
            one N, which its `config` then records as `num_nodes`.
        Options: its declared options (`mpnode_cli.models.options`).
        statistics_need_states: `fit_statistics` reads the train states (not only the
            graphs); streamed training then reads them into memory for it.

    Args:
        node_dim: D, per-node state size.
        control_dim: U, per-node control size (0 if none).
        num_nodes: N, needed only by a model that is not transferable.
        options: an instance of `Options` (default: every option at its default).
    """

    kind: ClassVar[str]
    transferable: ClassVar[bool] = True
    Options: ClassVar[type[ModelOptions]]
    statistics_need_states: ClassVar[bool] = False

    def __init__(self, node_dim: int, control_dim: int = 0, num_nodes: int | None = None,
                 options: ModelOptions | None = None):
        super().__init__()
        options = self.Options() if options is None else options
        if not isinstance(options, self.Options):
            raise TypeError(f"model '{self.kind}' takes {self.Options.__name__}, "
                            f"not {type(options).__name__}")
        if node_dim < 1 or control_dim < 0:
            raise ValueError("node_dim must be ≥ 1 and control_dim ≥ 0")
        if not self.transferable and (num_nodes is None or num_nodes < 1):
            raise ValueError(f"model '{self.kind}' is built for one node count: give num_nodes")
        self.node_dim, self.control_dim, self.options = node_dim, control_dim, options
        self.num_nodes = None if self.transferable else num_nodes

    @property
    def config(self) -> dict[str, Any]:
        """Sizes and options in one flat dict: what `from_config` takes back."""
        sizes = {"node_dim": self.node_dim, "control_dim": self.control_dim}
        if not self.transferable:
            sizes["num_nodes"] = self.num_nodes
        return sizes | self.options.model_dump()

    # The config keys that go to the constructor as they are; every other key is an option.
    constructor_keys: ClassVar[tuple[str, ...]] = ("node_dim", "control_dim", "num_nodes")

    @classmethod
    def from_config(cls, config: Mapping[str, Any]) -> Self:
        """The model of a `config` dict (sizes and options; options left out: defaults).

        Raises:
            ValueError: no `node_dim`, or an option this model refuses.
        """
        sizes = {k: config[k] for k in cls.constructor_keys if k in config}
        if "node_dim" not in sizes:
            raise ValueError(f"model '{cls.kind}' config lacks node_dim")
        given = {k: v for k, v in config.items() if k not in sizes}
        return cls(**sizes, options=cls.Options.parse(given, cls.kind))

    @property
    def initial_states(self) -> int:
        """C, the data states a rollout starts from (1: x(t₀) alone)."""
        return 1

    def fit_statistics(self, states: torch.Tensor | None, dt: float,
                       adjacency: torch.Tensor) -> None:
        """Fit statistics of the training data that are not learned by gradient (none here).

        Called once on a fresh model (and on a finetune that renormalizes), before training.

        Args:
            states: `[K, T, N, D]` normalized train-split states; None in a streamed run
                when `statistics_need_states` is False. Training on several datasets, a
                list of them, one per dataset (their N and T differ; a statistic is then
                fitted on all of them pooled).
            dt: sample spacing (one for all datasets).
            adjacency: `[K, N, N]` the train split's graphs (or an `EdgeBatch`); a list of
                them, one per dataset, when `states` is a list.
        """

    def check_states(self, x0: torch.Tensor) -> None:
        """Refuse initial states `x0: [B, N, D]` that the model was not built for.

        Raises:
            ValueError: D is not `node_dim`, or (a model that is not transferable) N is not
                its `num_nodes`.
        """
        if x0.shape[-1] != self.node_dim:
            raise ValueError(f"states have {x0.shape[-1]} features per node but the model "
                             f"expects {self.node_dim}")
        if not self.transferable and x0.shape[-2] != self.num_nodes:
            raise ValueError(f"model '{self.kind}' is built for {self.num_nodes} nodes and "
                             f"runs on no other node count, got {x0.shape[-2]}")

    @abc.abstractmethod
    def rollout(self, x0: torch.Tensor, ts: torch.Tensor, adjacency: torch.Tensor,
                controls: torch.Tensor | None = None, **options: Any) -> Rollout:
        """Predict trajectories from x(t₀).

        Args:
            x0: `[B, N, D]` normalized states at `ts[0]`.
            ts: `[T]` sample times.
            adjacency: `[B, N, N]`, `A[b, i, j] ≠ 0` iff node j sends to node i.
            controls: `[B, T, N, U]` normalized (zero-order hold), or None.
            **options: `solver` (a `SolverOptions`; None: `solve`'s defaults) and
                `return_messages` (models without a solver accept and ignore them); a model
                with `initial_states` C > 1 also takes `history: [B, C, N, D]`.
        """

    def rollout_from_data(self, x: torch.Tensor, ts: torch.Tensor, adjacency: torch.Tensor,
                          controls: torch.Tensor | None = None, **options: Any) -> Rollout:
        """Roll out from the start of the data trajectories `x: [B, T, N, D]`.

        Every model starts from x(t₀); one that needs C = `initial_states` > 1 states is
        given the data's first C.
        """
        c = self.initial_states
        extra = {"history": x[:, :c]} if c > 1 else {}
        return self.rollout(x[:, 0], ts, adjacency, controls, **options, **extra)

    @property
    def members(self) -> Sequence[NeuralModel]:
        """The models trained: a single model is an ensemble of one, itself (an ensemble's
        are its S members, `mpnode_cli.models.ensemble`)."""
        return (self,)

    def member_prefix(self, k: int) -> str:
        """Where member k's weights are in this model's `state_dict`: all of it here, the
        model being its one member (an ensemble's are under `members.k.`)."""
        return ""

    def member_state(self, state_dict: Mapping[str, torch.Tensor], k: int
                     ) -> dict[str, torch.Tensor]:
        """Member k's weights in a `state_dict` of this model, named as the member's own."""
        prefix = self.member_prefix(k)
        return {name.removeprefix(prefix): value for name, value in state_dict.items()
                if name.startswith(prefix)}

    def training_losses(self, xs: torch.Tensor, ts: torch.Tensor, graphs: Sequence,
                        controls: torch.Tensor | None,
                        loss_fn: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
                        active: Sequence[int] = (0,), solver: SolverOptions | None = None
                        ) -> list[BatchLoss]:
        """Each member's training loss on its own batch, the member axis first, as an
        ensemble's: here S = 1, so `xs: [1, B, H, N, D]`, one graph, `active` is `[0]`.

        Args:
            xs: `[1, B, H, N, D]`; ts: `[H]`; graphs: one batch's graphs, in a sequence;
                controls: `[1, B, H, N, U]` or None; loss_fn, solver: as `training_loss`.
        """
        return [self.training_loss(x, ts, graph, None if controls is None else controls[i],
                                   loss_fn, solver=solver)
                for i, (x, graph) in enumerate(zip(xs, graphs, strict=True))]

    def training_loss(self, x: torch.Tensor, ts: torch.Tensor, adjacency: torch.Tensor,
                      controls: torch.Tensor | None,
                      loss_fn: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
                      solver: SolverOptions | None = None) -> BatchLoss:
        """The loss of one training batch: `loss_fn` of the whole-horizon rollout.

        Args:
            x: `[B, H, N, D]` normalized (noisy) training states; ts: `[H]` their times.
            adjacency: `[B, N, N]`. controls: `[B, H, N, U]` or None.
            loss_fn: `loss_fn(pred, target)` on `[B, H, N, D]` states.
            solver: how the rollout is integrated (None: `solve`'s defaults).
        """
        out = self.rollout_from_data(x, ts, adjacency, controls, solver=solver)
        loss = loss_fn(out.states, x) if bool((out.status == 0).all()) else None
        return BatchLoss(loss, out.status, out.n_f_evals)


def mlp(in_dim: int, hidden: int, layers: int, out_dim: int, activation: str) -> nn.Sequential:
    """`layers` hidden layers of width `hidden` with `activation`, then a linear output.

    Weights are Glorot-uniform and biases zero, as Flux's `Dense` (the authors' init).
    """
    if activation not in ACTIVATIONS:
        raise ValueError(f"unknown activation '{activation}' (choose from: "
                         f"{', '.join(ACTIVATIONS)})")
    if layers < 1 or hidden < 1:
        raise ValueError("an MLP needs at least one hidden layer of width ≥ 1")
    dims = [in_dim] + [hidden] * layers
    modules: list[nn.Module] = []
    for a, b in itertools.pairwise(dims):
        modules += [Linear(a, b), ACTIVATIONS[activation]()]
    modules.append(Linear(dims[-1], out_dim))
    for module in modules:
        if isinstance(module, nn.Linear):
            nn.init.xavier_uniform_(module.weight)
            nn.init.zeros_(module.bias)
    return nn.Sequential(*modules)


def model_dtype(model: nn.Module | None) -> torch.dtype:
    """The floating dtype of a model's weights (float32 for no model or no weights)."""
    for p in model.parameters() if model is not None else []:
        if p.is_floating_point():
            return p.dtype
    return torch.float32
