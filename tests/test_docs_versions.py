"""The format versions that docs/architecture.md and docs/dataset-format.md quote are the ones
the code writes (a reader of the docs trusts them to say which files they describe)."""

from __future__ import annotations

import re
from pathlib import Path

from mpnode_cli.data import hdf5
from mpnode_cli.training import checkpoint

DOCS = Path(__file__).resolve().parents[1] / "docs"


def test_architecture_quotes_the_versions_written():
    text = " ".join((DOCS / "architecture.md").read_text(encoding="utf-8").split())
    data = re.search(r"`mpnode-dataset`, version (\d+), or (\d+) when its graphs are multigraphs",
                     text)
    ckpt = re.search(r"`mpnode-checkpoint`, version (\d+) \(`training/checkpoint\.py`\)", text)
    assert data and ckpt, "docs/architecture.md no longer states the format versions"
    assert (int(data[1]), int(data[2])) == (hdf5.PLAIN_GRAPHS_VERSION, hdf5.FORMAT_VERSION)
    assert int(ckpt[1]) == checkpoint.FORMAT_VERSION


def test_dataset_format_page_names_the_newest_version():
    first = (DOCS / "dataset-format.md").read_text(encoding="utf-8").splitlines()[0]
    assert first == f"# Dataset files: format `mpnode-dataset`, version {hdf5.FORMAT_VERSION}"
