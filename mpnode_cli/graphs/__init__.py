"""Graphs: matrices and edge lists (`matrices`), random topologies (`topologies`, with the
S¹ model in `s1`), and a user's graph as a text file of edges (`edge_files`).

The graph types are re-exported here because plug-in systems import them from
`mpnode_cli.graphs`.
"""

from mpnode_cli.graphs.matrices import EdgeBatch, EdgeList, Graphs

__all__ = ["EdgeBatch", "EdgeList", "Graphs"]
