"""Homogeneous dynamical systems on graphs: ground truth for the MP-NODE experiments."""

from mpnode_cli.systems.base import System
from mpnode_cli.systems.registry import SYSTEMS, get_system

__all__ = ["SYSTEMS", "System", "get_system"]
