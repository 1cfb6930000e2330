"""Datasets as tensors for learning: splits, normalization, per-trajectory graphs.

`TrajectoryData` holds a dataset file's trajectories as torch tensors beside the file's G
graphs and each trajectory's `graph_index`, so a batch is just an index and its graphs are
built per batch (`TrajectoryData.graph`): `[B, N, N]` matrices for small graphs, an edge
list above `DENSE_GRAPH_MAX_NODES` nodes (memory O(E), never O(K·N²)).

`Normalizer` is the z-score of the authors' `ztransform` (MPNODE.jl
`src/datatransform.jl:20-35`; docs/authors-code.md): one mean and std per node feature,
pooled over nodes, time and trajectories — but fitted on the **train split only** (the
authors fitted on all data, validation included).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from mpnode_cli.data.fingerprint import fingerprint
from mpnode_cli.data.hdf5 import NodeSizes, read_dataset
from mpnode_cli.data.validate import require_valid
from mpnode_cli.graphs.matrices import EdgeBatch, Graphs

SPLITS = {"train": 0, "validation": 1, "test": 2}
_STD_FLOOR = 1e-8  # a constant feature is centred, not divided by zero


@dataclass(frozen=True)
class Normalizer:
    """Per-feature z-score of node states (and controls).

    Attributes:
        x_mean, x_std: `[D]` float32. u_mean, u_std: `[U]` float32 (empty when U = 0).
    """

    x_mean: torch.Tensor
    x_std: torch.Tensor
    u_mean: torch.Tensor
    u_std: torch.Tensor

    @staticmethod
    def fit(states: torch.Tensor | Sequence[torch.Tensor],
            controls: torch.Tensor | Sequence[torch.Tensor] | None = None) -> Normalizer:
        """Fit on `states [K, T, N, D]` (and `controls [K, T, N, U]`), or on lists of them,
        one per dataset (N and T may differ): pooled, every value counts once."""
        x_mean, x_std = _moments(states)
        if controls is None or _features(controls) == 0:
            u_mean = u_std = torch.zeros(0)
        else:
            u_mean, u_std = _moments(controls)
        return Normalizer(x_mean, x_std, u_mean, u_std)

    def unscaled(self, dims: Sequence[int]) -> Normalizer:
        """This normalization with the state components `dims` left as they are (mean 0,
        std 1): angles whose sin and cos a model takes (MP-NODE's `periodic="embed"`) stay
        in radians."""
        if not dims:
            return self
        index = torch.as_tensor(list(dims), dtype=torch.long)
        x_mean, x_std = self.x_mean.clone(), self.x_std.clone()
        x_mean[index], x_std[index] = 0.0, 1.0
        return Normalizer(x_mean, x_std, self.u_mean, self.u_std)

    def to_dict(self) -> dict[str, list[float]]:
        return {name: getattr(self, name).tolist()
                for name in ("x_mean", "x_std", "u_mean", "u_std")}

    @staticmethod
    def from_dict(d: dict[str, Any]) -> Normalizer:
        return Normalizer(**{name: torch.tensor(d[name], dtype=torch.float32)
                             for name in ("x_mean", "x_std", "u_mean", "u_std")})

    def norm_x(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.x_mean.to(x)) / self.x_std.to(x)

    def denorm_x(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.x_std.to(x) + self.x_mean.to(x)

    def denorm_spread(self, s: torch.Tensor) -> torch.Tensor:
        """A spread of states (a standard deviation, `[..., D]`) in physical units: scaled
        by the state std, not shifted by the mean."""
        return s * self.x_std.to(s)

    def norm_u(self, u: torch.Tensor) -> torch.Tensor:
        return (u - self.u_mean.to(u)) / self.u_std.to(u)


def _recipe(raw: Any) -> dict[str, Any] | None:
    """A dataset's recommended training recipe (optional JSON attribute), or None."""
    if raw is None:
        return None
    try:
        recipe = json.loads(raw)
    except (TypeError, ValueError):
        return None
    return recipe if isinstance(recipe, dict) else None


def _features(v: torch.Tensor | Sequence[torch.Tensor]) -> int:
    return (v if isinstance(v, torch.Tensor) else v[0]).shape[-1]


def _parts(v: torch.Tensor | Sequence[torch.Tensor]) -> list[torch.Tensor]:
    """One dataset's tensor, or several datasets' (N and T may differ), as a list."""
    return [v] if isinstance(v, torch.Tensor) else list(v)


def _flat(v: torch.Tensor | Sequence[torch.Tensor]) -> torch.Tensor:
    """Every value of `v` per feature, float64: `(K·T·N, F)`, or `(Σ K·T·N, F)` pooled."""
    parts = _parts(v)
    if len(parts) == 1:
        return parts[0].reshape(-1, parts[0].shape[-1]).double()
    return torch.cat([part.reshape(-1, part.shape[-1]).double() for part in parts])


def _moments(v: torch.Tensor | Sequence[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
    flat = _flat(v)
    mean, std = flat.mean(dim=0), flat.std(dim=0, correction=0)
    std = torch.where(std > _STD_FLOOR, std, torch.ones_like(std))
    return mean.float(), std.float()


@dataclass(frozen=True)
class TrajectoryData(NodeSizes):
    """Trajectories of one dataset file (or a subset) as tensors.

    Attributes:
        states: float32 `[K, T, N, D]`. controls: float32 `[K, T, N, U]` or None.
        graphs: the file's G graphs. graph_index: int64 `[K]`, each trajectory's graph.
        time: float64 `[T]`. split: uint8 `[K]` (0 train, 1 validation, 2 test).
        system, state_names, control_names: from the file. path: where it was read.
        fingerprint: sha256 of states, adjacency and time of the whole file.
        attrs: other facts from the file (`topology`, `config`, ...).
    """

    states: torch.Tensor
    controls: torch.Tensor | None
    graphs: Graphs
    graph_index: torch.Tensor
    time: torch.Tensor
    split: torch.Tensor
    system: str
    state_names: tuple[str, ...]
    control_names: tuple[str, ...]
    path: Path
    fingerprint: str
    attrs: dict[str, Any] = field(default_factory=dict)

    @staticmethod
    def load(path: str | Path) -> TrajectoryData:
        """Read an mpnode dataset file after checking it completely
        (`mpnode_cli.data.validate.require_valid`: a bad file raises `DatasetFormatError`
        with one line, before any run starts)."""
        require_valid(path)
        ds = read_dataset(path)
        states = np.ascontiguousarray(ds.states, dtype=np.float32)
        controls = None
        if ds.controls is not None and ds.controls.shape[-1] > 0:
            controls = torch.from_numpy(np.ascontiguousarray(ds.controls, dtype=np.float32))
        topology = ds.config.get("topology") if isinstance(ds.config, dict) else None
        return TrajectoryData(
            states=torch.from_numpy(states), controls=controls,
            graphs=ds.graphs,
            graph_index=torch.from_numpy(ds.graph_index.astype(np.int64)),
            time=torch.from_numpy(np.asarray(ds.time, dtype=np.float64)),
            split=torch.from_numpy(ds.split.astype(np.uint8)),
            system=ds.system, state_names=tuple(ds.state_names),
            control_names=tuple(ds.control_names), path=Path(path),
            fingerprint=fingerprint(states, ds.graphs, ds.graph_index, ds.time,
                                    controls=ds.controls),
            attrs={"topology": topology, "config": ds.config, "dt": ds.dt,
                   "recipe": _recipe(ds.extra_attrs.get("recipe")),
                   "prediction": ds.extra_attrs.get("prediction"),
                   "periodic_states": tuple(ds.periodic_states)})

    def __len__(self) -> int:
        return self.states.shape[0]

    @property
    def control_dim(self) -> int:
        return 0 if self.controls is None else self.controls.shape[3]

    def graph(self, device: str | torch.device = "cpu") -> torch.Tensor | EdgeBatch:
        """Each trajectory's graph, as models and `fit_statistics` take it: float32
        `[K, N, N]` matrices (`A[k, i, j] = 1` iff j sends to i) when N ≤
        `DENSE_GRAPH_MAX_NODES`, else an `EdgeBatch` (each distinct graph's edges once)."""
        if self.graphs.dense_ok:
            return self.adjacency.to(device)
        return self.graphs.batch(self.graph_index.numpy(), device)

    @property
    def adjacency(self) -> torch.Tensor:
        """float32 `[K, N, N]`, each trajectory's graph matrix (graphs of at most
        `DENSE_GRAPH_MAX_NODES` nodes; `graph` serves any size).

        Raises:
            ValueError: N > `DENSE_GRAPH_MAX_NODES`.
        """
        dense = self.graphs.dense()[self.graph_index.numpy()]  # [K, N, N]
        return torch.from_numpy(dense.astype(np.float32))

    def take(self, index: torch.Tensor) -> TrajectoryData:
        """The trajectories at `index` (`[K']` int64 or bool), sharing the file's facts."""
        return replace(self, states=self.states[index], graph_index=self.graph_index[index],
                       controls=None if self.controls is None else self.controls[index],
                       split=self.split[index])

    def select(self, index: torch.Tensor) -> TrajectoryData:
        """`take`: in memory, a view of some trajectories is those trajectories (a
        `mpnode_cli.data.stream.StreamedTrajectories` selects without reading)."""
        return self.take(index)

    def subset(self, which: str) -> TrajectoryData:
        """One split ("train", "validation", "test") or "all"."""
        return split_subset(self, which)


def split_subset(data: Any, which: str) -> Any:
    """One split ("train", "validation", "test") or "all" of `data`: anything with a
    `split [K]` and a `select(index)`, in memory or on disk.

    Raises:
        ValueError: another name.
    """
    if which == "all":
        return data
    if which not in SPLITS:
        raise ValueError(f"unknown split '{which}' (choose from: train, validation, test, all)")
    return data.select(data.split == SPLITS[which])
