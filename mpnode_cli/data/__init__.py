"""Datasets: the HDF5 format (`hdf5`, written by `hdf5_write`), the systems' presets
(`presets`), the generator that turns a system, its graphs and the solver into a file
(`generate`), a user's own arrays (`user_inputs`) turned into a file (`importers`), and
the complete check of a file that every reader runs first (`validate`).

Names are re-exported lazily so that importing `mpnode_cli.data.presets` (for the CLI's
choices) does not pull in h5py or torch. The function `generate` shares its module's name,
so import it from `mpnode_cli.data.generate`.
"""

from __future__ import annotations

from mpnode_cli.lazy import lazy_exports

__getattr__, __all__ = lazy_exports(__name__, {
    "hdf5": ["Dataset", "DatasetFormatError", "read_dataset", "read_header"],
    "hdf5_write": ["write_dataset"],
    "fingerprint": ["fingerprint"],
    "importers": ["ImportSummary", "import_arrays"],
    "validate": ["Report", "check_dataset", "require_valid"],
    "generate": ["GenerateError", "GenerateSummary", "resolve_generate_config"],
    "presets": ["PRESETS", "get_preset"],
}, globals())
