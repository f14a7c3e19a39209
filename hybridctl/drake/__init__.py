"""Drake blocks and diagrams of the switched controller (thesis Ch. 3); Poincare sections of Drake
hybrid systems by witness functions (Ch. 5).

>>> from hybridctl import systems, drake
>>> acrobot = systems.load("acrobot")
>>> diagram = drake.build_hybrid_diagram(acrobot)       # energy swing-up + cost-to-go gate + LQR
>>> traj = drake.simulate(diagram, x0=[-1.5708, 0, 0, 0], duration=10.0)
>>> traj.balanced, traj.episode_return
>>> diagram = drake.build_hybrid_diagram(acrobot, swingup="trajopt")   # collocation + TVLQR + gate + LQR
>>> from hybridctl import SwitchedController
>>> diagram = drake.build_hybrid_diagram(acrobot, SwitchedController.for_system(acrobot))   # the typed form
"""

from .blocks import Gate, HeldController, HeldLQR, ModeSwitch, RecurrentTorchPolicy, TorchPolicy
from ..systems.control import CostToGoGate, lqr_basin_level
from .controllers import (AcrobotEnergySwingup, CartpoleEnergySwingup, LQRController, PendulumEnergySwingup,
                          energy_swingup, resolve_swingup)
from .diagram import HybridDiagram, build_hybrid_diagram
from .sections import DrakeCompassGaitMap, DrakeRimlessWheelMap, SectionObserver
from .simulate import Trajectory, simulate
from .trajopt import (SwingupTrajectory, TrackingGains, TrajectoryTracker, TrajoptSettings, swingup_trajectory,
                      tracking_gains, trajopt_swingup)

__all__ = [
    "Gate", "HeldController", "HeldLQR", "ModeSwitch", "TorchPolicy", "RecurrentTorchPolicy",
    "AcrobotEnergySwingup", "CartpoleEnergySwingup", "PendulumEnergySwingup", "CostToGoGate",
    "LQRController", "energy_swingup", "resolve_swingup", "lqr_basin_level", "HybridDiagram",
    "build_hybrid_diagram", "Trajectory", "simulate", "DrakeRimlessWheelMap",
    "DrakeCompassGaitMap", "SectionObserver", "TrajoptSettings", "SwingupTrajectory", "TrackingGains",
    "TrajectoryTracker", "swingup_trajectory", "tracking_gains", "trajopt_swingup",
]
