"""hybridctl: switched model-based control and learning for underactuated robots.

Implements the methods of S. Gillen, "Improving Reinforcement Learning for Robotics
with Control and Dynamical Systems Theory" (2022) on top of Drake.

Rooms, bottom to top (a module imports only from its own room or below; ARCHITECTURE.md):
    hybridctl.io, hybridctl.parallel   atomic writes and JSON; serial / process / Ray backends
    hybridctl.systems      specs, batched torch dynamics, Drake plants, control laws, success test
    hybridctl.analysis     meshes, dimensions, Poincare maps, Markov chains, MFPT (numpy/scipy)
    hybridctl.viz          meshcat viewing, HTML replays, plots
    hybridctl.drake        LeafSystems (policy, gate, switch) and hybrid diagram builders
    hybridctl.envs         gymnasium environments (single and batched torch vector envs)
    hybridctl.learn        SAC, SSAC, ARS on one training skeleton
    hybridctl.experiments  named controllers, balance maps, simulate-and-write, demo, mesh report
    hybridctl.cli          the `hybridctl` command line
"""

__version__ = "0.1.0"
