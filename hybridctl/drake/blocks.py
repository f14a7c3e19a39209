"""Drake LeafSystems of the switched controller (thesis Fig. 3.1).

All learned or Python-side blocks are evaluated in a *periodic discrete update*
and hold their result in discrete state (a zero-order hold). Their outputs are
not feedthrough, so Drake does not call Python at every derivative evaluation
(implementation notes: about 5 us per call otherwise), and the mode of the gate
lives in the Context, so it resets with the Context.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import torch
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import (BasicVector, Context, Diagram, DiagramBuilder, DiscreteValues, InputPortIndex,
                                       LeafSystem, State)
from pydrake.systems.primitives import AffineSystem, MatrixGain, Saturation, WrapToSystem, ZeroOrderHold

from ..systems import control

ArrayFn = Callable[[np.ndarray], np.ndarray]


def _as_numpy_fn(fn, name: str) -> ArrayFn:
    """Wrap a torch module (or any callable) as numpy (n,) -> numpy (k,), without autograd.

    An object with a ``numpy_forward`` method (e.g. ``CostToGoGate``) is called
    through it, skipping the torch round trip on single states.
    """
    if hasattr(fn, "numpy_forward"):
        return lambda x: np.asarray(fn.numpy_forward(x), dtype=float).reshape(-1)
    if isinstance(fn, torch.nn.Module):
        fn.eval()
        try:
            dtype = next(fn.parameters()).dtype
        except StopIteration:
            dtype = torch.float64

        def call(x: np.ndarray) -> np.ndarray:
            with torch.no_grad():
                out = fn(torch.as_tensor(x, dtype=dtype).unsqueeze(0))
            return np.asarray(out.squeeze(0).double().numpy(), dtype=float).reshape(-1)
        return call
    if callable(fn):
        return lambda x: np.asarray(fn(x), dtype=float).reshape(-1)
    raise TypeError(f"{name} must be a torch.nn.Module or a callable, got {type(fn).__name__}")


def _check_period(period: float, name: str = "period") -> float:
    period = float(period)
    if not np.isfinite(period) or period <= 0:
        raise ValueError(f"{name} must be a finite number > 0, got {period}")
    return period


class HeldController(LeafSystem):
    """u = f(x) evaluated every ``period`` seconds and held in between (zero-order hold).

    Ports: input ``state`` (n_states), output ``command`` (n_outputs). ``f`` is a
    numpy callable or a torch module; ``limit`` (optional) clips the command to
    [-limit, limit]. The held value starts at ``initial`` (default zeros) and is
    replaced at t = 0 by the first update.
    """

    def __init__(self, fn, n_states: int, n_outputs: int, period: float,
                 limit: float | None = None, initial: np.ndarray | None = None, name: str = "controller"):
        super().__init__()
        self._fn = _as_numpy_fn(fn, "fn")
        self._limit = None if limit is None else float(limit)
        self.period = _check_period(period)
        self.n_outputs = int(n_outputs)
        self.DeclareVectorInputPort("state", n_states)
        init = np.zeros(n_outputs) if initial is None else np.asarray(initial, dtype=float)
        self._held = self.DeclareDiscreteState(init)
        self.DeclarePeriodicDiscreteUpdateEvent(self.period, 0.0, self._update)
        self.DeclareStateOutputPort("command", self._held)
        self.set_name(name)

    def compute(self, x: np.ndarray) -> np.ndarray:
        """The command for one state (clipped), as used by the discrete update."""
        u = self._fn(x)
        if u.shape != (self.n_outputs,):
            raise ValueError(f"{self.get_name()}: fn returned shape {u.shape}, expected ({self.n_outputs},)")
        if self._limit is not None:
            u = np.clip(u, -self._limit, self._limit)
        return u

    def _update(self, context: Context, discrete_state: DiscreteValues) -> None:
        x = self.get_input_port(0).Eval(context)
        discrete_state.set_value(0, self.compute(x))


class TorchPolicy(HeldController):
    """A torch policy as a Drake block: ``action = module(state)``, held for ``period``.

    ``module`` maps a batch of states (1, n) to actions (1, m); it is called under
    ``torch.no_grad`` in a periodic discrete update, never as feedthrough.
    """

    def __init__(self, module: torch.nn.Module, n_states: int, n_actions: int, period: float,
                 limit: float | None = None, name: str = "swingup"):
        if not isinstance(module, torch.nn.Module):
            raise TypeError(f"module must be a torch.nn.Module, got {type(module).__name__}")
        super().__init__(module, n_states, n_actions, period, limit=limit, name=name)
        self.module = module


class RecurrentTorchPolicy(LeafSystem):
    """A recurrent torch policy as a Drake block: ``(action, h) = module(state, h)`` every ``period``.

    ``module`` has ``initial_state(batch)`` (zero state [batch, hidden]) and
    ``forward(x [1, n], h [1, hidden]) -> (action [1, m], h)`` on raw plant states (our
    convention), e.g. :meth:`hybridctl.learn.APG.closed_loop_policy`. The recurrent state h lives
    in the Context as discrete state (group 1, beside the held action in group 0), so the
    block resets with the Context, and a periodic discrete update (offset 0) computes the
    action and the next h together, under ``torch.no_grad`` in the module's dtype. The action
    is held over the period (zero-order hold), as the torch rollout holds it.

    Ports: input ``state`` (n_states), output ``command`` (n_actions).
    """

    def __init__(self, module: torch.nn.Module, n_states: int, n_actions: int, period: float,
                 limit: float | None = None, name: str = "swingup"):
        super().__init__()
        if not isinstance(module, torch.nn.Module) or not hasattr(module, "initial_state"):
            raise TypeError("module must be a torch.nn.Module with initial_state(batch) and "
                            f"forward(x, h) -> (action, h), got {type(module).__name__}")
        self.module = module.eval()
        self.period = _check_period(period)
        self.n_actions = int(n_actions)
        self._limit = None if limit is None else float(limit)
        h0 = module.initial_state(1)
        self._dtype = h0.dtype
        self.hidden_dim = int(h0.shape[-1])
        self.DeclareVectorInputPort("state", n_states)
        self._held = self.DeclareDiscreteState(np.zeros(self.n_actions))
        # Drake needs a non-empty vector: a stateless policy keeps one unused entry
        self._hidden = self.DeclareDiscreteState(np.zeros(max(self.hidden_dim, 1)))
        self.DeclarePeriodicDiscreteUpdateEvent(self.period, 0.0, self._update)
        self.DeclareStateOutputPort("command", self._held)
        self.set_name(name)

    def compute(self, x: np.ndarray, h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(action, next h) for one state and recurrent state (the action clipped to ``limit``).

        A module with ``numpy_forward(x, h)`` (``hybridctl.learn.apg.ClosedLoopPolicy``) runs in
        numpy, without torch's per-call overhead; others through torch.
        """
        if hasattr(self.module, "numpy_forward"):
            u, h_next = self.module.numpy_forward(np.asarray(x, dtype=float), np.asarray(h, dtype=float)[:self.hidden_dim])
            u = np.asarray(u, dtype=float).reshape(-1)
            if u.shape != (self.n_actions,):
                raise ValueError(f"{self.get_name()}: the module returned shape {u.shape}, expected ({self.n_actions},)")
            if self._limit is not None:
                u = np.clip(u, -self._limit, self._limit)
            return u, np.asarray(h_next, dtype=float).reshape(-1)
        with torch.no_grad():
            xt = torch.as_tensor(np.asarray(x, dtype=float), dtype=self._dtype).reshape(1, -1)
            ht = torch.as_tensor(np.asarray(h, dtype=float)[:self.hidden_dim], dtype=self._dtype).reshape(1, -1)
            u, h_next = self.module(xt, ht)
        u = u.reshape(-1).double().numpy().copy()
        if u.shape != (self.n_actions,):
            raise ValueError(f"{self.get_name()}: the module returned shape {u.shape}, expected ({self.n_actions},)")
        if self._limit is not None:
            u = np.clip(u, -self._limit, self._limit)
        return u, h_next.reshape(-1).double().numpy().copy()

    def _update(self, context: Context, discrete_state: DiscreteValues) -> None:
        x = self.get_input_port(0).Eval(context)
        h = context.get_discrete_state(self._hidden).CopyToVector()
        u, h_next = self.compute(x, h)
        discrete_state.set_value(self._held, u)
        if self.hidden_dim:
            discrete_state.set_value(self._hidden, h_next)


class Gate(LeafSystem):
    """Classifier gate with hysteresis (thesis Sec. 3.3).

    Every ``period`` seconds: p = classifier(state); the mode switches to the
    balancing controller (1) when p > ``on`` and back to swing-up (0) when
    p < ``off``; in between it keeps its mode. Mode and p are discrete state, so a
    new Context starts in swing-up (thesis: reset to swing-up at episode start).

    Ports: input ``state``; outputs ``mode`` (1), ``probability`` (1) and ``selector``
    (abstract ``InputPortIndex``: ``selector_ports[mode]``), which drives Drake's C++
    ``PortSwitch`` (``build_hybrid_diagram``), so no Python runs between updates. The
    selector is abstract state written by the same (unrestricted) periodic update.
    ``on`` and ``off`` have no defaults: a system's are ``system.gate.on`` / ``.off``
    (``build_hybrid_diagram`` passes them). ``selector_ports``: the switch's input port
    indices of the swing-up and the balancing command (a ``PortSwitch`` numbers its
    selector 0 and the declared inputs from 1).
    """

    def __init__(self, classifier, n_states: int, period: float, *, on: float, off: float,
                 name: str = "gate", selector_ports: tuple[int, int] = (1, 2)):
        super().__init__()
        if not 0.0 < off < on < 1.0:
            raise ValueError(f"gate thresholds need 0 < off < on < 1, got off={off}, on={on}")
        if len(selector_ports) != 2 or min(selector_ports) < 0:
            raise ValueError(f"selector_ports must be two input port indices >= 0, got {selector_ports!r}")
        self._classify = _as_numpy_fn(classifier, "classifier")
        self.on, self.off = float(on), float(off)
        self.period = _check_period(period)
        self.selector_ports = tuple(int(i) for i in selector_ports)
        self._selectors = tuple(InputPortIndex(i) for i in self.selector_ports)
        self._state_port = self.DeclareVectorInputPort("state", n_states)
        self._mode = self.DeclareDiscreteState(1)
        self._probability = self.DeclareDiscreteState(1)
        self._selector = self.DeclareAbstractState(AbstractValue.Make(self._selectors[0]))
        self.DeclarePeriodicUnrestrictedUpdateEvent(self.period, 0.0, self._update)
        self.DeclareStateOutputPort("mode", self._mode)
        self.DeclareStateOutputPort("probability", self._probability)
        self.DeclareStateOutputPort("selector", self._selector)
        self.set_name(name)

    def next_mode(self, mode: float, probability: float) -> float:
        """Hysteresis (:func:`hybridctl.systems.control.hysteresis`): on above ``on``, off below ``off``."""
        return control.hysteresis(float(probability), float(mode), self.on, self.off)

    def _update(self, context: Context, state: State) -> None:
        # Called at every control period: kept to the fewest Drake calls (the state handed in is a
        # copy of the current one, so an unchanged mode and selector need no write).
        p = float(self._classify(self._state_port.Eval(context))[0])
        mode = context.get_discrete_state(self._mode).GetAtIndex(0)
        new_mode = self.next_mode(mode, p)
        state.get_mutable_discrete_state(self._probability).SetAtIndex(0, p)
        if new_mode != mode:
            state.get_mutable_discrete_state(self._mode).SetAtIndex(0, new_mode)
            state.get_mutable_abstract_state(self._selector).set_value(self._selectors[int(new_mode > 0.5)])


class HeldLQR(Diagram):
    """The saturated LQR u = clip(-K wrap(x - goal)), sampled every ``period`` and held, in C++ only.

    Drake primitives: an ``AffineSystem`` (x - goal), ``WrapToSystem`` (the angle coordinates to
    [-pi, pi), as :func:`hybridctl.systems.control.wrap_angles`), ``MatrixGain`` (-K), ``Saturation``
    (+-``limit``) and a ``ZeroOrderHold`` (sampled at t = k * period, starting from 0, as
    ``HeldController``). The law is :func:`hybridctl.systems.control.lqr_command`'s; it agrees with
    ``HeldController(LQRController(system))`` to rounding (~1e-16: C++ sums the product in its own
    order, and ``WrapToSystem`` returns an angle already in range unchanged). No Python runs in it.

    Ports: input ``state`` (spec convention), output ``command``.
    """

    def __init__(self, system, K: np.ndarray, period: float, limit: float | None = None, name: str = "balance"):
        super().__init__()
        n, m = system.n_states, system.n_actions
        K = np.atleast_2d(np.asarray(K, dtype=float))
        if K.shape != (m, n):
            raise ValueError(f"K must have shape ({m}, {n}), got {K.shape}")
        self.K = K
        self.period = _check_period(period)
        self.limit = None if limit is None else float(limit)
        builder = DiagramBuilder()
        error = builder.AddSystem(AffineSystem(np.zeros((0, 0)), np.zeros((0, n)), np.zeros(0), np.zeros((n, 0)),
                                               np.eye(n), -np.asarray(system.goal, dtype=float)))
        error.set_name("error")
        wrap = builder.AddSystem(WrapToSystem(n))
        wrap.set_name("wrap")
        for i in system.angle_indices:
            wrap.set_interval(i, -np.pi, np.pi)
        gain = builder.AddSystem(MatrixGain(-K))
        gain.set_name("gain")
        hold = builder.AddSystem(ZeroOrderHold(self.period, m))
        hold.set_name("hold")
        builder.Connect(error.get_output_port(), wrap.get_input_port())
        builder.Connect(wrap.get_output_port(), gain.get_input_port())
        last = gain.get_output_port()
        if self.limit is not None:
            saturation = builder.AddSystem(Saturation(np.full(m, -self.limit), np.full(m, self.limit)))
            saturation.set_name("saturation")
            builder.Connect(last, saturation.get_input_port())
            last = saturation.get_output_port()
        builder.Connect(last, hold.get_input_port())
        builder.ExportInput(error.get_input_port(), "state")
        builder.ExportOutput(hold.get_output_port(), "command")
        builder.BuildInto(self)
        self.set_name(name)


class ModeSwitch(LeafSystem):
    """Passes ``balance`` when ``mode`` > 0.5, else ``swingup`` (output ``command``).

    A Python feedthrough block: Drake evaluates it at every derivative evaluation.
    ``build_hybrid_diagram`` uses Drake's C++ ``PortSwitch`` driven by the gate's
    ``selector`` instead; this block is its ``switch="python"`` option (the loop the C++
    ``PortSwitch`` replaced for speed, kept to measure against in ``benchmarks/dynamics.py``).
    """

    def __init__(self, n_actions: int, name: str = "switch"):
        super().__init__()
        self._mode = self.DeclareVectorInputPort("mode", 1)
        self._swingup = self.DeclareVectorInputPort("swingup", n_actions)
        self._balance = self.DeclareVectorInputPort("balance", n_actions)
        self.DeclareVectorOutputPort("command", n_actions, self._select)
        self.set_name(name)

    def _select(self, context: Context, output: BasicVector) -> None:
        port = self._balance if self._mode.Eval(context)[0] > 0.5 else self._swingup
        output.SetFromVector(port.Eval(context))
