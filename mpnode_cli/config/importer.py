"""The config of `mpnode import`."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from mpnode_cli.config.fields import (
    ADJACENCY_HELP,
    DIRECTED_HELP,
    EDGE_LIST_HELP,
    SEED_MAX,
    check_graph_source,
    name_list,
    split_fractions,
    valid_split,
)


class ImportConfig(BaseModel):
    """What `mpnode import` makes: one dataset file (system "custom") from a user's arrays.

    Each field's description is its `mpnode import` option's help
    (`mpnode_cli.cli.importer`; the edge list is read by
    `mpnode_cli.graphs.edge_files.read_edge_list`, the split drawn as generate's,
    `numpy.random.default_rng([seed, 1])`).
    """

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    states: Path = Field(description=(
        "Trajectories [K, T, N, D]: .npy, .npz (array 'states', optional 'time') or a long "
        "CSV with columns trajectory, time, node and one per state."))
    adjacency: Path | None = Field(None, description=ADJACENCY_HELP)
    edge_list: Path | None = Field(None, description=EDGE_LIST_HELP)
    directed: bool = Field(False, description=DIRECTED_HELP)
    dt: float = Field(gt=0, description=(
        "Sample spacing (a time column or array must step by it)."))
    controls: Path | None = Field(None, description=(
        "Zero-order-hold controls [K, T, N, U] as .npy."))
    state_names: list[str] | None = Field(None, description=(
        "Comma-separated names of the D states (default: the CSV's columns, else x0, x1, "
        "...)."))
    control_names: list[str] | None = Field(None, description=(
        "Comma-separated names of the U controls (default u0, u1, ...)."))
    split: tuple[float, float, float] = Field((0.7, 0.15, 0.15), description=(
        "Train, validation, test fractions by trajectory, summing to 1."))
    seed: int = Field(0, ge=0, le=SEED_MAX, description="Seed of the split.")
    dtype: Literal["float32", "float64"] = Field("float32", description=(
        "Storage dtype of the states and controls."))
    out: Path | None = Field(None, description=(
        "Output file (default datasets/<states>.h5); a path ending in / is refused: name "
        "the file."))
    periodic: list[str] = Field(default_factory=list, description=(
        "A state that is an angle (mod 2π), by name; repeat for more. Recorded as the "
        "dataset's periodic_states (docs/dataset-format.md)."))

    _parse_split = field_validator("split", mode="before")(split_fractions)
    _check_split = field_validator("split")(valid_split)
    _parse_names = field_validator("state_names", "control_names", mode="before")(name_list)

    @model_validator(mode="after")
    def _check(self) -> ImportConfig:
        check_graph_source(self.adjacency, self.edge_list, self.directed)
        for field in ("state_names", "control_names"):
            names = getattr(self, field) or []
            if any(not name for name in names) or len(set(names)) != len(names):
                raise ValueError(f"{field} must be distinct, non-empty names, got "
                                 f"{','.join(names)!r}")
        return self
