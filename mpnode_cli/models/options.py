"""Each model's declared options: typed, defaulted, documented, and free of torch.

A model class (`mpnode_cli.models.<name>`) names its options class as `Options`; the
registry maps model names to them. They live here, apart from the models, because the CLI
builds `mpnode train`'s options and their help from these declarations at import time, and
`mpnode --help` must not import torch. Each field's `description` is its CLI help (the CLI
adds a `Literal` field's choices and the models that take the option).

The choices shared with the torch side are declared once, here, as `Literal` types:
`mpnode_cli.models.aggregate` takes its `AGGREGATES` and `mpnode_cli.models.backend` its
`BACKENDS` from them (each registry is tested to match), and
`mpnode_cli.models.base.ACTIVATIONS` is tested to cover `Activation`.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Literal, Self

from pydantic import BaseModel, ConfigDict, Field, ValidationError

Activation = Literal["tanh", "relu", "elu", "silu", "softplus"]
Aggregate = Literal["mean", "sum", "pna"]
Backend = Literal["auto", "dense", "scatter"]
GraphMode = Literal["sys", "full"]
Update = Literal["mlp", "affine"]
MessageInit = Literal["zero", "learned"]
Periodic = Literal["off", "embed", "auto"]

# Upper bounds on sizes: far beyond what the paper's systems need (widths of 32 to 128),
# and small enough that a typo (`--hidden 10000000`) is refused rather than exhausting memory.
WIDTH_MAX = 8192
DEPTH_MAX = 64

_GRAPH = "Graph messages pass over: sys is the dataset's, full is complete with self-loops."
_AGGREGATE = "Neighbour aggregation: mean is the paper's; sum and pna sense the in-degree."


class ModelOptions(BaseModel):
    """Base of every model's options: unknown names are refused, and a built model's
    options cannot change under it (they are its `config`)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    @classmethod
    def parse(cls, given: Mapping[str, Any], model: str) -> Self:
        """Validate options given for `model`; those left out take their defaults.

        Raises:
            ValueError: an option this model does not declare, or a bad value — one line
                that names the model and the option.
        """
        foreign = [name for name in given if name not in cls.model_fields]
        if foreign:
            raise ValueError(f"model '{model}' has no option '{foreign[0]}' (its options: "
                             f"{', '.join(cls.model_fields)})")
        try:
            return cls(**given)
        except ValidationError as exc:
            err = exc.errors()[0]
            loc = ".".join(str(p) for p in err["loc"])
            raise ValueError(f"model '{model}' option {loc}: {err['msg']} "
                             f"(got {err['input']!r})") from None


class MPNODEOptions(ModelOptions):
    """MP-NODE (Gupta, Vemprala & Kapoor 2022, §3.2); defaults are the authors' shipped
    widths (MPNODE.jl, exps/models.jl:92-95)."""

    message_dim: int = Field(3, ge=1, le=WIDTH_MAX, description=(
        "Message states per node (M); --no-messages turns message passing off."))
    hidden: int = Field(32, ge=1, le=WIDTH_MAX, description="Width of the hidden layers.")
    layers: int = Field(2, ge=1, le=DEPTH_MAX, description="Hidden layers of the MLP.")
    activation: Activation = Field("tanh", description="Nonlinearity of the hidden layers.")
    graph: GraphMode = Field("sys", description=_GRAPH)
    messages: bool = Field(True, description=(
        "Pass messages between nodes; off clamps incoming messages to zero (the paper's "
        "§4.1 ablation)."))
    aggregate: Aggregate = Field("mean", description=_AGGREGATE)
    update: Update = Field("mlp", description=(
        "Node update: mlp is the paper's MLP of x, u and the aggregated messages; affine is "
        "F(x, u) + G(x, u)·(aggregated messages), linear in the neighbours' messages, so "
        "a sum over more neighbours than in training stays in range."))
    message_init: MessageInit = Field("zero", description=(
        "Message states at t₀: zero (the paper's) or learned, a function of the node's "
        "x(t₀), u(t₀), for coupling that acts from the start."))
    periodic: Periodic = Field("off", description=(
        "States the dataset declares periodic (angles, its periodic_states): embed feeds "
        "the node networks (sin θ, cos θ) in place of θ (the ODE state stays θ, in radians: "
        "the normalizer leaves those components unscaled); off feeds θ as every other "
        "state; auto embeds where the training data declare periodic states and is off "
        "elsewhere (mpnode's recipe; the paper's model is off)."))
    backend: Backend = Field(
        "auto", description="How aggregation is computed (auto picks by graph size).")


class L2SOptions(ModelOptions):
    """Learning to Simulate (Sanchez-Gonzalez et al. 2020) without edge features."""

    latent: int = Field(128, ge=1, le=WIDTH_MAX, description="Node and edge latent size.")
    hidden: int = Field(128, ge=1, le=WIDTH_MAX, description="Width of the hidden layers.")
    layers: int = Field(2, ge=1, le=DEPTH_MAX, description="Hidden layers of the MLP.")
    steps: int = Field(
        10, ge=1, le=DEPTH_MAX, description="Message-passing steps (unshared weights).")
    history: int = Field(
        1, ge=1, le=DEPTH_MAX,
        description="Input states C (C > 1 starts rollouts from C data states).")
    graph: GraphMode = Field("sys", description=_GRAPH)
    step_noise: float = Field(
        3e-3, ge=0,
        description="Std of the random-walk noise on one-step training inputs (normalized).")
    unroll: int = Field(
        1, ge=1, le=DEPTH_MAX,
        description="Steps each training rollout takes from a noisy data state: 1 is L2S's "
                    "one step ahead; more backpropagates through the model's own predictions.")
    windows: int = Field(
        0, ge=0, le=1_000_000,
        description="Training windows drawn at random from each trajectory of a batch (0: "
                    "every one, each step of the horizon); fewer makes an epoch cheaper.")


class GNODEOptions(ModelOptions):
    """The authors' GNN-ODE baseline (`gnnsc_de0`); defaults as they shipped it."""

    hidden: int = Field(32, ge=1, le=WIDTH_MAX, description="Width of the hidden layers.")
    depth: int = Field(
        1, ge=1, le=DEPTH_MAX,
        description="Message-passing steps per evaluation (shared weights).")
    graph: GraphMode = Field("sys", description=_GRAPH)
    aggregate: Aggregate = Field("sum", description=_AGGREGATE)


class NODEOptions(ModelOptions):
    """The authors' monolithic neural ODE (`ndeln4`)."""

    hidden: int = Field(32, ge=1, le=WIDTH_MAX, description="Width of the hidden layers.")
    layers: int = Field(2, ge=1, le=DEPTH_MAX, description="Hidden layers of the MLP.")
    activation: Activation = Field("tanh", description="Nonlinearity of the hidden layers.")
