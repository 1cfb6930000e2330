"""Named datasets (presets), collected from the systems that declare them, and the
layering of a preset, a config file and the command line into one generate config.

A preset is a partial `GenerateConfig` (field → value); `mpnode generate --preset NAME`
starts from it and lets a config file and command-line options override any field. Each
system declares its own presets (`System.presets`, with their sources: the paper's
appendix first, then the authors' code; docs/systems.md), so a system of your own brings
its presets along (docs/custom-systems.md).
"""

from __future__ import annotations

from typing import Any


def _collect(systems) -> dict[str, dict[str, Any]]:
    presets: dict[str, dict[str, Any]] = {}
    for cls in systems:
        for name, fields in cls.presets.items():
            if name in presets:
                raise ValueError(f"preset '{name}' is declared by both "
                                 f"'{presets[name]['system']}' and '{cls.name}'")
            presets[name] = {"system": cls.name, **fields}
    return presets


def _builtin() -> dict[str, dict[str, Any]]:
    from mpnode_cli.systems.registry import SYSTEMS

    return _collect(SYSTEMS.values())


# The built-in systems' presets (the paper's datasets).
PRESETS: dict[str, dict[str, Any]] = _builtin()


def all_presets() -> dict[str, dict[str, Any]]:
    """The presets of every system known to this process (built in and plug-ins)."""
    from mpnode_cli.systems.registry import all_systems

    return _collect(all_systems().values())


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
    presets = PRESETS if name in PRESETS else all_presets()
    if name not in presets:
        raise ValueError(f"unknown preset '{name}' (choose from: {', '.join(presets)})")
    preset = dict(presets[name])
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
