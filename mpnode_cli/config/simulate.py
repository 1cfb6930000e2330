"""The config of `mpnode simulate`."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from mpnode_cli.config.fields import (
    ADJACENCY_HELP,
    DIRECTED_HELP,
    EDGE_LIST_HELP,
    check_graph_source,
    check_grid,
)


class SimulateConfig(BaseModel):
    """What `mpnode simulate` does: a trained node model rolled out on graphs of your own.

    Each field's description is its `mpnode simulate` option's help
    (`mpnode_cli.cli.simulate`); the graph is given as for `ImportConfig`.
    """

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    checkpoint: Path = Field(description=(
        "A checkpoint (.pt), or a run folder (its checkpoints/best.pt)."))
    x0: Path = Field(description=(
        "Initial states [K, N, D] (or [N, D]) in physical units, .npy."))
    adjacency: Path | None = Field(None, description=ADJACENCY_HELP)
    edge_list: Path | None = Field(None, description=EDGE_LIST_HELP)
    directed: bool = Field(False, description=DIRECTED_HELP)
    t_end: float = Field(gt=0, description="Last sample time (samples 0, dt, ..., t_end).")
    dt: float = Field(gt=0, description="Sample spacing.")
    controls: Path | None = Field(None, description=(
        "Controls [K, T, N, U] in physical units (zero-order hold), T = t_end / dt + 1, "
        ".npy."))
    batch_size: int = Field(128, ge=1, description="Trajectories per rollout.")
    device: Literal["cpu", "cuda"] = Field("cpu", description="Where the rollouts run.")
    dtype: Literal["float32", "float64"] = Field("float32", description=(
        "Storage dtype of the predictions."))
    out: Path | None = Field(None, description=(
        "Output file (default predictions/<x0 file name>.h5); a path ending in / is "
        "refused: name the file."))
    member: int | None = Field(None, description=(
        "An ensemble checkpoint's member to roll out alone (none: the members' mean, with "
        "their spread in hidden/ensemble_std)."))

    @model_validator(mode="after")
    def _check(self) -> SimulateConfig:
        check_graph_source(self.adjacency, self.edge_list, self.directed)
        check_grid(self.dt, self.t_end)
        return self

    @property
    def num_steps(self) -> int:
        """Number of dt steps, T − 1."""
        return round(self.t_end / self.dt)
