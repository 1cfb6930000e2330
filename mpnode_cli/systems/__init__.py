"""Homogeneous dynamical systems on graphs: ground truth for the MP-NODE experiments, and
the base class of your own (docs/custom-systems.md)."""

from mpnode_cli.systems.base import RHS, Option, Simulation, System
from mpnode_cli.systems.neighbour_sum import NeighbourSum
from mpnode_cli.systems.registry import SYSTEMS, get_system, load_system_file, system_class

__all__ = ["RHS", "SYSTEMS", "NeighbourSum", "Option", "Simulation", "System", "get_system",
           "load_system_file", "system_class"]
