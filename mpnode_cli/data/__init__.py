"""Datasets: the HDF5 format (`hdf5`), the systems' presets (`presets`), the generator
that turns a system, its graphs and the solver into a file (`generate`), a user's own arrays
turned into a file (`importers`), and the complete check of a file that every reader runs
first (`validate`).

Names are re-exported lazily so that importing `mpnode_cli.data.presets` (for the CLI's
choices) does not pull in h5py or torch. The function `generate` shares its module's name,
so import it from `mpnode_cli.data.generate`.
"""

from __future__ import annotations

from importlib import import_module
from typing import Any

_EXPORTS = {
    "Dataset": "hdf5",
    "DatasetFormatError": "hdf5",
    "read_dataset": "hdf5",
    "read_header": "hdf5",
    "write_dataset": "hdf5",
    "fingerprint": "hdf5",
    "ImportSummary": "importers",
    "import_arrays": "importers",
    "Report": "validate",
    "check_dataset": "validate",
    "require_valid": "validate",
    "GenerateError": "generate",
    "GenerateSummary": "generate",
    "resolve_config": "generate",
    "PRESETS": "presets",
    "get_preset": "presets",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name not in _EXPORTS:
        raise AttributeError(f"module 'mpnode_cli.data' has no attribute '{name}'")
    return getattr(import_module(f"mpnode_cli.data.{_EXPORTS[name]}"), name)
