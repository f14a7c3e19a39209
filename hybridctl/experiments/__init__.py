"""Workflows built from the rooms below: named controllers (``energy``, ``ssac:PATH``), balance maps,
simulate-and-write, the mesh report, the demo and result records. The command line and the
notebooks call these same functions."""

from .balance_map import BalanceMap, balance_map, grid_axes, near_hanging_down
from .controllers import CONTROLLERS, build_named_diagram
from .demo import PRETRAINED_ACROBOT, PRETRAINED_CARTPOLE, run_demo
from .mesh_report import MESH_MAPS, mesh_report, section_map_by_name
from .simulation import simulate_and_write
from .training import (SSAC_VARIANTS, RunFolderError, TrainingRun, default_run_dir, learner_class, make_config,
                       newest_run_checkpoint, prepare_run_folder, train_and_evaluate, training_algorithms)

__all__ = ["BalanceMap", "balance_map", "grid_axes", "near_hanging_down", "CONTROLLERS", "build_named_diagram"]
__all__ += ["simulate_and_write", "run_demo", "PRETRAINED_ACROBOT", "PRETRAINED_CARTPOLE", "mesh_report",
            "MESH_MAPS", "section_map_by_name", "train_and_evaluate", "TrainingRun", "make_config",
            "default_run_dir", "newest_run_checkpoint", "learner_class", "training_algorithms", "SSAC_VARIANTS",
            "RunFolderError", "prepare_run_folder"]
