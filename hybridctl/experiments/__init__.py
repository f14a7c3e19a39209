"""Workflows built from the rooms below: named controllers (``energy``, ``ssac:PATH``), balance maps,
simulate-and-write, the mesh report, the demo and result records. The command line and the
notebooks call these same functions."""

from .balance_map import BalanceMap, balance_map, grid_axes
from .controllers import CONTROLLERS, build_named_diagram

__all__ = ["BalanceMap", "balance_map", "grid_axes", "CONTROLLERS", "build_named_diagram"]
