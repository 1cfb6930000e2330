"""Size limits shared by the configs (which must not import numpy, so that `--help` stays
fast) and by the graph code that enforces them."""

# The largest graph held as an N×N matrix: stored as `graph/adjacency` in a dataset file
# (docs/dataset-format.md), given to systems as an ndarray and to models as a dense
# `[B, N, N]` batch. 256² = 65 536 entries, 64 KiB per uint8 graph: as small as the edge
# list of a graph of mean degree ≈ 4, and far below any memory concern.
DENSE_GRAPH_MAX_NODES = 256

# The most parallel edges between two nodes (`mpnode generate --hub-multiplicity`): a
# dataset's matrices are uint8.
MULTIPLICITY_MAX = 255
