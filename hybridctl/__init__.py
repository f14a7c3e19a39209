"""hybridctl: switched model-based control and learning for underactuated robots.

Implements the methods of S. Gillen, "Improving Reinforcement Learning for Robotics
with Control and Dynamical Systems Theory" (2022) on top of Drake.

Rooms:
    hybridctl.systems   benchmark system specs, batched torch dynamics, Drake plants, LQR
    hybridctl.drake     LeafSystems (policy, gate, switch) and hybrid diagram builders
    hybridctl.envs      gymnasium environments (single and batched torch vector envs)
    hybridctl.analysis  success test, balance maps
    hybridctl.viz       meshcat viewing, HTML replays, plots
    hybridctl.cli       the `hybridctl` command line
"""

__version__ = "0.1.0"
