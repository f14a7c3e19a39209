"""The switched controller as one typed object (issue 48): its checks, its gates, its one batched rollout, and
the same object in torch and in Drake."""

import numpy as np
import pytest
import torch

from hybridctl import SwitchedController, closed_loop_rollout, systems
from hybridctl.envs import SwitchedVectorEnv
from test_switched_env import TanhPolicy   # one fixed smooth swing-up-like policy for both files
from hybridctl.systems import control
from hybridctl.systems.switched import (AlwaysGate, CostToGoGate, EnergySwingup, LearnedGate, NeverGate, TrajoptSwingup,
                                        ZeroSwingup)


@pytest.fixture(autouse=True)
def one_thread():
    torch.set_num_threads(1)


def test_one_class_from_the_package_and_the_systems_room():
    assert SwitchedController is systems.SwitchedController and closed_loop_rollout is systems.closed_loop_rollout


def test_for_system_fills_the_spec_defaults():
    acrobot = systems.load("acrobot")
    energy = SwitchedController.for_system(acrobot)
    assert isinstance(energy.swingup, EnergySwingup) and type(energy.gate) is CostToGoGate
    np.testing.assert_array_equal(energy.K, acrobot.lqr()[0])
    np.testing.assert_array_equal(energy.goal, acrobot.goal)
    assert (energy.gate_on, energy.gate_off) == (acrobot.gate.on, acrobot.gate.off)
    assert energy.decision_period == energy.gate_period == acrobot.control_period
    learned = SwitchedController.for_system(acrobot, swingup=TanhPolicy(1.0), gate=torch.nn.Linear(4, 1), gate_on=0.8)
    assert learned.decision_period == acrobot.swingup_period and learned.gate_on == 0.8
    assert isinstance(learned.gate, LearnedGate)


@pytest.mark.parametrize("overrides, error, message", [
    ({"gate_on": 0.4, "gate_off": 0.6}, ValueError, "0 < gate_off < gate_on < 1"),
    ({"gate_on": 1.0}, ValueError, "gate_on"),
    ({"decision_period": 0.0}, ValueError, "decision_period must be"),
    ({"gate_period": float("nan")}, ValueError, "gate_period must be"),
    ({"K": [[1.0, 2.0]]}, ValueError, "K has shape"),
    ({"goal": [0.0, np.inf, 0.0, 0.0]}, ValueError, "goal contains NaN"),
    ({"hold": 0.2}, TypeError, "unknown SwitchedController fields"),
])
def test_bad_fields_are_named(overrides, error, message):
    with pytest.raises(error, match=message):
        SwitchedController.for_system(systems.load("acrobot"), **overrides)


def test_gates_are_classes_not_strings():
    acrobot = systems.load("acrobot")
    for gate in ("always", "never", "cost", 3):
        with pytest.raises(TypeError, match="gate must be"):
            SwitchedController.for_system(acrobot, gate=gate)
    with pytest.raises(TypeError, match="gate must be a Gate"):
        SwitchedController(swingup=ZeroSwingup(), gate=control.CostToGoGate(acrobot), K=acrobot.lqr()[0],
                           goal=acrobot.goal, decision_period=0.01, gate_on=0.9, gate_off=0.5, gate_period=0.01)


def test_gate_probabilities():
    acrobot = systems.load("acrobot")
    rng = np.random.default_rng(0)
    x = acrobot.goal + rng.uniform(-1, 1, size=(50, 4))
    xt = torch.as_tensor(x)
    law, gate = control.CostToGoGate(acrobot), CostToGoGate(acrobot)     # the one formula, typed
    assert torch.equal(gate.probability(xt), law(xt)) and np.array_equal(gate.numpy_probability(x), law(x))
    assert isinstance(gate, control.CostToGoGate) and CostToGoGate.of(law).scale == law.scale
    assert torch.equal(AlwaysGate().probability(xt), torch.ones(50, 1, dtype=torch.float64))
    assert np.array_equal(NeverGate().numpy_probability(x[0]), [0.0])
    net = torch.nn.Sequential(torch.nn.Linear(4, 1), torch.nn.Sigmoid())
    learned = LearnedGate(net)
    assert learned.compute_dtype == torch.float32 and learned.probability(xt).dtype == torch.float64
    np.testing.assert_allclose(learned.numpy_probability(x), learned.probability(xt).numpy(), rtol=0, atol=1e-7)


def test_closed_loop_rollout_is_the_switched_env_bit_for_bit():
    """One decision of the env is one step of closed_loop_rollout: a whole episode of both is the same run."""
    system = systems.load("acrobot")
    policy = TanhPolicy(system.action_limit)
    gate = CostToGoGate(system, scale=1e5)      # switches both ways from this start (tests/test_switched_env.py)
    x0 = np.array([[1.2, -0.4, 0.5, -1.0], [0.3, 0.2, -0.1, 0.4]])
    env = SwitchedVectorEnv(system, num_envs=2, gate=gate)
    obs, _ = env.reset(options={"state": x0})
    states, fractions = [obs], []
    for _ in range(env.max_decisions - 1):        # the last step autoresets
        obs, _, _, _, info = env.step(policy(obs))
        states.append(obs)
        fractions.append(info["lqr_fraction"])
    controller = SwitchedController.for_system(system, swingup=policy, gate=gate)
    run = closed_loop_rollout(system, controller, x0, env.max_decisions - 1)
    assert torch.equal(run.states, torch.stack(states, dim=1))
    assert torch.equal(run.lqr_steps / env.substeps, torch.stack(fractions, dim=1))
    assert 0 < float(run.lqr_steps.mean()) / env.substeps < 1 and not bool(run.diverged.any())


def test_divergence_policies():
    """A row given a NaN action diverges in the first decision; the policy says what it does next."""
    system = systems.load("pendulum")
    nan_first = lambda x: torch.where(torch.arange(len(x))[:, None] == 0, torch.nan, 0.0).to(x.dtype)  # noqa: E731
    controller = SwitchedController.for_system(system, swingup=nan_first, gate=NeverGate(), decision_period=0.1)
    x0 = torch.tensor([[0.5, 0.0], [0.4, 0.1]], dtype=torch.float64)
    runs = {policy: closed_loop_rollout(system, controller, x0, 5, on_divergence=policy)
            for policy in ("freeze", "continue", "restart")}
    for policy, run in runs.items():
        assert not bool(run.actions_finite) and run.diverged_at.tolist() == [1, 6], policy
        assert torch.equal(run.states[0], x0[0].expand(6, 2)), policy          # back at its last finite state
        assert torch.equal(run.states[1], runs["freeze"].states[1]), policy   # the other row runs on
        assert bool(run.diverged[0].all()) and not bool(run.diverged[1].any()), policy   # the NaN row, every time
    with pytest.raises(ValueError, match="on_divergence must be one of"):
        closed_loop_rollout(system, controller, x0, 1, on_divergence="zero-reward")


def test_hand_designed_swingups_need_the_drake_room_in_torch():
    from hybridctl import drake

    acrobot = systems.load("acrobot")
    x0 = acrobot.nudged_nominal_state()[None]
    with pytest.raises(ValueError, match="resolve_swingup"):
        closed_loop_rollout(acrobot, SwitchedController.for_system(acrobot), x0, 1)
    with pytest.raises(ValueError, match="Drake only"):
        closed_loop_rollout(acrobot, SwitchedController.for_system(acrobot, swingup=TrajoptSwingup()), x0, 1)
    run = closed_loop_rollout(acrobot, drake.resolve_swingup(acrobot, SwitchedController.for_system(acrobot)), x0, 3)
    assert run.states.shape == (1, 4, 4)


def _ssac(system):
    from hybridctl.learn import load_controller

    controller = load_controller("models/policies/ssac-acrobot", system)
    assert isinstance(controller, SwitchedController) and isinstance(controller.gate, LearnedGate)
    return controller


# tests/test_balance_engines.py's tolerances: the acrobot agrees to 1e-6 while the run is not chaotic
@pytest.mark.parametrize("which, seconds", [("ssac", 6.0), ("energy", 3.0)])
def test_torch_equals_drake_on_one_controller(which, seconds):
    pytest.importorskip("pydrake")
    from hybridctl import drake

    system = systems.load("acrobot")
    controller = _ssac(system) if which == "ssac" else SwitchedController.for_system(
        system, swingup=EnergySwingup(), gate=CostToGoGate(system))
    x0 = system.nudged_nominal_state()
    traj = drake.simulate(drake.build_hybrid_diagram(system, controller), x0, seconds)
    stride = int(round(controller.decision_period / system.dt))
    decisions = int(round(seconds / controller.decision_period))
    run = closed_loop_rollout(system, drake.resolve_swingup(system, controller), x0[None], decisions)
    np.testing.assert_allclose(run.states[0].numpy(), traj.x[::stride][:decisions + 1], rtol=0, atol=1e-6)
    lqr_share = float(run.lqr_steps.sum()) / (decisions * stride)
    assert lqr_share == pytest.approx(traj.gate[:decisions * stride].mean(), abs=0.02)
    assert (lqr_share > 0) == (which == "ssac")     # SSAC hands over to the LQR within 6 s; energy not in 3 s


# --------------------------------------------------------------- the APG family's LQR takeover is this controller
def test_the_apg_takeover_is_a_view_of_the_switched_controller_and_decides_as_closed_loop_rollout():
    """``learn.apg.LQRTakeover`` (inside the APG population rollout, differentiable) is built from
    ``SwitchedController.for_system(system, gate=CostToGoGate(system))`` with the gate every integrator step
    (``gate_period = dt``: what a checkpoint's ``takeover = "lqr"`` means) and decides through the same
    ``switched_decision`` / ``gate_command``: the population rollout and ``closed_loop_rollout`` of that controller
    reach the same states and gate modes bit for bit, decision by decision."""
    from hybridctl.learn.apg import ClosedLoopPolicy, LQRTakeover, population_returns
    from hybridctl.learn.policies import Policy, PolicyPopulation
    from hybridctl.systems.switched import gate_command

    system = systems.load("cartpole")
    takeover = LQRTakeover(system, decision_period=system.swingup_period)
    controller = takeover.controller
    assert type(controller.gate) is CostToGoGate and controller.swingup is None
    assert controller.gate_period == system.dt and takeover.stride == 1
    np.testing.assert_array_equal(controller.K, system.lqr()[0])
    assert (controller.gate_on, controller.gate_off) == (system.gate.on, system.gate.off)

    gen = torch.Generator().manual_seed(3)
    scales = torch.logspace(-2.5, 0.3, 12, dtype=torch.float64)[:, None]     # inside the gate's region ... far out
    x0 = torch.as_tensor(system.goal) + torch.randn(12, 4, generator=gen, dtype=torch.float64) * scales
    substeps, steps = controller.substeps(system), 15

    # 1. given actions: the takeover's decision against closed_loop_rollout's, decision by decision
    actions = system.action_limit * (2 * torch.rand(12, steps, 1, generator=gen, dtype=torch.float64) - 1)
    run = closed_loop_rollout(system, controller, x0, steps, actions=actions, on_divergence="propagate")
    x, mode = x0, None
    for j in range(steps):
        x, mode = takeover.decide(x, actions[:, j], mode, substeps)
        assert torch.equal(x, run.states[:, j + 1])
    assert torch.equal(mode, run.mode)
    assert bool(run.lqr_steps.gt(0).any()) and not bool(run.lqr_steps.eq(substeps).all())

    # 2. the APG population rollout (a recurrent policy acting on observations) against closed_loop_rollout of the
    # same policy as the controller's swing-up
    torch.manual_seed(0)
    pop = PolicyPopulation.build("gru", 5, 1, system.action_limit, members=1, init_std=0.5, dtype=torch.float64)
    swingup = ClosedLoopPolicy(system, Policy(pop))
    _, _, (_, apg_mode), _, apg_states = population_returns(system, pop, x0, steps, substeps, takeover=takeover,
                                                            keep_states=True)
    run = closed_loop_rollout(system, controller.replace(swingup=swingup), x0, steps, on_divergence="propagate")
    assert torch.equal(apg_states[0], run.states) and torch.equal(apg_mode[0], run.mode)
    assert bool(run.mode.any()) and not bool(run.mode.all())

    # 3. one gate evaluation: the takeover's command is gate_command's, the LQR saturated where the mode is on
    u = torch.full((12, 1), 3.0, dtype=torch.float64)
    command, on = takeover(x0, None, u)
    same, same_on = gate_command(system, controller.gate, x0, u, torch.zeros(12, dtype=torch.bool),
                                 torch.as_tensor(controller.K), torch.float64, controller.gate_on, controller.gate_off)
    assert torch.equal(command, same) and torch.equal(on, same_on)
    lqr = control.saturate(control.lqr_command(system.state_error(x0), torch.as_tensor(controller.K)),
                           system.action_limit)
    assert torch.equal(command, torch.where(on[:, None], lqr, u)) and bool(on.any()) and not bool(on.all())


def test_the_apg_takeover_keeps_autograd_as_a_differentiable_closed_loop_rollout():
    """The takeover's gradients (the APG's) are ``closed_loop_rollout(differentiable=True)``'s:
    d(final state)/d(actions) through the LQR phase, the switch a hard choice."""
    from hybridctl.learn.apg import LQRTakeover

    system = systems.load("cartpole")
    takeover = LQRTakeover(system, decision_period=system.swingup_period)
    substeps = takeover.controller.substeps(system)
    x0 = torch.as_tensor(system.goal) + torch.tensor([[0.01, 0.02, 0.0, 0.0], [0.0, 0.6, 0.0, 0.0]],
                                                     dtype=torch.float64)
    actions = torch.full((2, 4, 1), 5.0, dtype=torch.float64, requires_grad=True)
    run = closed_loop_rollout(system, takeover.controller, x0, 4, actions=actions, differentiable=True,
                              on_divergence="propagate")
    (grad_rollout,) = torch.autograd.grad(run.final.sum(), actions)
    x, mode = x0, None
    for j in range(4):
        x, mode = takeover.decide(x, actions[:, j], mode, substeps)
    (grad_takeover,) = torch.autograd.grad(x.sum(), actions)
    assert torch.equal(grad_rollout, grad_takeover)
    assert bool(grad_rollout[0].eq(0).all()) and bool(grad_rollout[1].ne(0).any())   # the LQR row ignores the actions
