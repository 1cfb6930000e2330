"""The paper's datasets as named presets, and each system's data defaults.

A preset is a partial `GenerateConfig` (field → value); `mpnode generate --preset NAME`
starts from it and lets a config file and command-line options override any field.

Sources: the paper's appendix first, then the authors' code (MPNODE.jl); the choices and
their reasons are in docs/systems.md.
- lorenz: 1000 trajectories × 51 samples (dt 0.05, 2.5 s), the authors' shipped config
  (`configs/empode_sys_32_3.toml`); `lorenz10-long` stretches the horizon to 10 s (201
  samples), the paper's §4.2.
- gene: the paper's 200 trajectories over 5 graphs, dt 0.1, 5 s, for every topology and
  size (the paper states it for BA; the other graphs are treated the same way).
- kuramoto: the paper gives 500 trajectories at dt 0.05 but no horizon; we use the
  authors' 50 steps (2.5 s).
- pendulum: the paper's 500 trajectories, dt 0.1, 10 s, with the authors' initial-state
  box θ ∈ [−π/4, π/4], θ̇ ∈ [−0.5, 0.5] by default, because the appendix's wider box
  reaches the cos θ = 0 singularity; that box is `--ic-range paper`.
- quadrotor: the paper's 463 flights of 10 s sampled every 0.2 s (App. A.5) for three
  quads; the paper gives no count for six, so `quad6` has 463 as well.
"""

from __future__ import annotations

from typing import Any

# The authors' data defaults (configs/empode_sys_32_3.toml), for a system without its own
# entry below.
DEFAULTS: dict[str, Any] = {"trajectories": 1000, "t_end": 2.5, "dt": 0.05}

# Trajectories, horizon and spacing of `mpnode generate SYSTEM` without a preset.
SYSTEM_DEFAULTS: dict[str, dict[str, Any]] = {
    "pendulum": {"trajectories": 500, "t_end": 10.0, "dt": 0.1},
    "lorenz": {"trajectories": 1000, "t_end": 2.5, "dt": 0.05},
    "gene": {"trajectories": 200, "t_end": 5.0, "dt": 0.1},
    "kuramoto": {"trajectories": 500, "t_end": 2.5, "dt": 0.05},
    "quadrotor": {"trajectories": 463, "t_end": 10.0, "dt": 0.2},
}


def _lorenz(nodes: int, coupling: float = 0.01, t_end: float = 2.5) -> dict[str, Any]:
    return {
        "system": "lorenz",
        "nodes": nodes,
        "params": {"coupling": coupling},
        "trajectories": 1000,
        "t_end": t_end,
        "dt": 0.05,
    }


def _gene(topology: str, side: int) -> dict[str, Any]:
    return {
        "system": "gene",
        "grid": side,
        "topology": topology,
        "graphs": 5,
        "trajectories": 200,
        "t_end": 5.0,
        "dt": 0.1,
    }


def _kuramoto(topology: str) -> dict[str, Any]:
    return {
        "system": "kuramoto",
        "nodes": 10,
        "topology": topology,
        "trajectories": 500,
        "t_end": 2.5,
        "dt": 0.05,
    }


def _quadrotor(nodes: int) -> dict[str, Any]:
    return {"system": "quadrotor", "nodes": nodes, "trajectories": 463, "t_end": 10.0, "dt": 0.2}


PRESETS: dict[str, dict[str, Any]] = {
    "pendulum": {
        "system": "pendulum",
        "nodes": 2,
        "trajectories": 500,
        "t_end": 10.0,
        "dt": 0.1,
    },
    "lorenz3": _lorenz(3),
    "lorenz7": _lorenz(7),
    "lorenz10": _lorenz(10),
    "lorenz10-high": _lorenz(10, coupling=1.0),
    "lorenz10-long": _lorenz(10, t_end=10.0),
    **{
        f"gene-{topology}-{side}x{side}": _gene(topology, side)
        for side in (4, 8)
        for topology in ("ba", "er", "ws")
    },
    **{f"kuramoto10-{topology}": _kuramoto(topology) for topology in ("ba", "er", "ws")},
    **{f"quad{n}": _quadrotor(n) for n in (3, 6)},
}


# Fields that exclude each other: one given by a later layer drops the other from earlier
# layers, so `--preset gene-ba-4x4 --nodes 25` means 25 nodes rather than a conflict.
EXCLUSIVE = (("nodes", "grid"), ("topology", "edge_list"))
# Tables whose entries merge key by key across layers.
TABLES = ("params", "solver")


def get_preset(name: str) -> dict[str, Any]:
    """A copy of the preset called `name`, safe to modify.

    Raises:
        ValueError: an unknown name (the message lists the known ones).
    """
    if name not in PRESETS:
        raise ValueError(f"unknown preset '{name}' (choose from: {', '.join(PRESETS)})")
    preset = dict(PRESETS[name])
    if "params" in preset:
        preset["params"] = dict(preset["params"])
    return preset


def merge_layers(layers: list[tuple[str, dict[str, Any]]]) -> dict[str, Any]:
    """Generate config fields from layers (a preset, a config file, options, an experiment's
    overrides): later layers override earlier ones; `params` and `solver` merge key by key;
    a field given drops the one it excludes (`EXCLUSIVE`) from earlier layers.

    Args:
        layers: `(where it came from, fields)`, lowest precedence first.

    Raises:
        ValueError: two layers name different systems, or `params` or `solver` is not a
            table.
    """
    fields: dict[str, Any] = {}
    source = ""
    for where, layer in layers:
        layer = dict(layer)
        if "system" in layer and fields.get("system") not in (None, layer["system"]):
            raise ValueError(
                f"system '{layer['system']}' ({where}) disagrees with '{fields['system']}' "
                f"({source})"
            )
        source = where if "system" in layer else source
        for a, b in EXCLUSIVE:
            for given, other in ((a, b), (b, a)):
                if given in layer and other not in layer:
                    fields.pop(other, None)
        tables = {name: layer.pop(name, {}) for name in TABLES}
        for name, table in tables.items():
            if not isinstance(table, dict):
                raise ValueError(f"{name} ({where}) must be a table of NAME = value")
        fields.update(layer)
        for name, table in tables.items():
            if merged := {**fields.get(name, {}), **table}:
                fields[name] = merged
    return fields
