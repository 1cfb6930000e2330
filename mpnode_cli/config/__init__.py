"""Pydantic models of each verb's configuration: the one source of truth for what a run did.

A config is built from (lowest precedence first) a preset, a TOML/JSON file, and command-line
options; its resolved form (every default filled in) is written next to the artifact it made,
so any dataset or run can be reproduced from its own files.

The package checks what can be checked without knowing the system (types, ranges, `dt` vs
`t_end`, the split). System-dependent defaults and checks (its topologies, node counts,
parameters) are filled in by `mpnode_cli.data.generate.resolve_generate_config`, which
keeps this package free of imports from higher floors.

One module per verb's config (`generate`, `importer`, `simulate`, `train`), what they share
(`fields`), the reading of a `--config` file (`file`) and of configs stored by earlier
versions (`upgrade`).
"""
