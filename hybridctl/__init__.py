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


def lazy_exports(package: str, homes: dict[str, tuple[str, ...]]):
    """(``__getattr__``, ``__dir__``, ``__all__``) for a package whose names load on first use (PEP 562).

    ``homes`` maps a submodule to the names it defines; ``from hybridctl.analysis import
    build_mesh`` then imports ``hybridctl.analysis.reachable`` only when asked, so a light
    import stays light (no scipy.sparse for a section map, no pydrake for a training plot).
    """
    from importlib import import_module

    home_of = {name: module for module, names in homes.items() for name in names}
    namespace = import_module(package).__dict__

    def __getattr__(name: str):
        module = home_of.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(import_module(f".{module}", package), name)
        namespace[name] = value  # later look-ups skip this hook
        return value

    def __dir__():
        return sorted(set(namespace) | set(home_of))

    return __getattr__, __dir__, sorted(home_of)


__getattr__, __dir__, _lazy_names = lazy_exports(__name__, {
    "systems.switched": ("SwitchedController", "closed_loop_rollout"),
})
"""``from hybridctl import SwitchedController``: the switched controller (:mod:`hybridctl.systems.switched`),
loaded on first use, so ``import hybridctl`` stays free of torch."""
