"""The `call` verb: a benchmark's job (`spec.CallStep`, run by `jobs`), a function of the
benchmark with JSON arguments, as a step of the experiments' engine."""

from __future__ import annotations

from pathlib import Path


def call(step, options, folder: Path, inputs, status, emit):
    """A benchmark's job (`jobs`): `target(folder=, inputs=, resumed=, **args)` → its record;
    `inputs`: the records (folder, result) of the steps it reads."""
    import importlib

    module, name = step.target.split(":")
    try:  # a job's failure of any kind is the step's (the engine keeps going past it)
        function = getattr(importlib.import_module(module), name)
        result = function(folder=folder, inputs=inputs, resumed=status == "resumed",
                          **step.args)
    except Exception as exc:
        raise ValueError(f"{type(exc).__name__}: {exc}") from exc
    return result, [], [], []
