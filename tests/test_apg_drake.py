"""A GRU policy trained by APG runs in the Drake diagram with its hidden state in the Context
and reproduces the torch rollout (same integrator, same hold)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

pytest.importorskip("pydrake")

from pydrake.systems.analysis import ResetIntegratorFromFlags, Simulator  # noqa: E402
from pydrake.systems.framework import DiagramBuilder  # noqa: E402
from pydrake.systems.primitives import AffineSystem  # noqa: E402

from hybridctl.drake import RecurrentTorchPolicy  # noqa: E402
from hybridctl.learn.apg import APG, APGConfig, population_returns  # noqa: E402
from hybridctl.learn.checkpoint_schema import CheckpointError  # noqa: E402
from hybridctl.systems.plants import add_plant  # noqa: E402


@pytest.mark.parametrize("name", ["cartpole", "acrobot"])
def test_recurrent_policy_in_drake_reproduces_the_torch_rollout(name):
    torch.set_num_threads(1)
    agent = APG(name, APGConfig(method="papg", population=2, elites=1, dtype="float64", init_std=0.3, seed=3))
    system, period, substeps, steps = agent.system, agent.period, agent.substeps, 30
    closed = agent.closed_loop_policy("best")
    x0 = system.initial_state.nominal + np.array([0.05, 0.1, -0.2, 0.3])

    # torch: the rollout the learner trains on, states every policy step
    with torch.no_grad():
        _, _, _, _, states = population_returns(system, closed.policy.population, torch.as_tensor(x0[None]),
                                                steps, substeps, keep_states=True)
    expected = states[0, 0].numpy()
    assert np.abs(expected[-1] - expected[0]).max() > 1e-2      # the policy does move the system

    builder = DiagramBuilder()
    handle, _ = add_plant(system, builder)
    block = builder.AddSystem(RecurrentTorchPolicy(closed, system.n_states, system.n_actions, period,
                                                   limit=system.action_limit))
    state_port = handle.state_output
    offset = system.drake_state_offset()
    if np.any(offset):   # the acrobot's Drake plant measures th1 from hanging down: convert, as the diagram does
        n = system.n_states
        convert = builder.AddSystem(AffineSystem(np.zeros((0, 0)), np.zeros((0, n)), np.zeros(0), np.zeros((n, 0)),
                                                 np.eye(n), -offset))
        builder.Connect(state_port, convert.get_input_port())
        state_port = convert.get_output_port()
    builder.Connect(state_port, block.get_input_port(0))
    builder.Connect(block.get_output_port(0), handle.actuation_input)
    diagram = builder.Build()
    context = diagram.CreateDefaultContext()
    plant_context = handle.plant.GetMyContextFromRoot(context)
    handle.apply_parameters(plant_context)
    simulator = Simulator(diagram, context)
    integrator = ResetIntegratorFromFlags(simulator, {"euler": "explicit_euler"}.get(system.integrator,
                                                                                     system.integrator), system.dt)
    integrator.set_fixed_step_mode(True)

    def run() -> np.ndarray:
        context.SetTime(0.0)
        plant_context.SetContinuousState(system.to_drake_state(x0))
        simulator.Initialize()
        got = [system.from_drake_state(plant_context.get_continuous_state_vector().CopyToVector())]
        for k in range(1, steps + 1):
            simulator.AdvanceTo(k * period)
            got.append(system.from_drake_state(plant_context.get_continuous_state_vector().CopyToVector()))
        return np.array(got)

    block_context = block.GetMyContextFromRoot(context)
    fresh_hidden = block_context.get_discrete_state(1).CopyToVector().copy()
    got = run()
    np.testing.assert_allclose(got, expected, rtol=1e-9, atol=1e-9)
    assert np.abs(block_context.get_discrete_state(1).CopyToVector()).max() > 0   # h lives in the Context
    # a fresh default Context starts from the zero hidden state again, and the rerun matches
    context.SetTimeStateAndParametersFrom(diagram.CreateDefaultContext())
    handle.apply_parameters(plant_context)
    assert np.array_equal(block_context.get_discrete_state(1).CopyToVector(), fresh_hidden)
    np.testing.assert_allclose(run(), expected, rtol=1e-9, atol=1e-9)


def test_the_hybrid_diagram_takes_a_recurrent_swing_up():
    from hybridctl.drake import build_hybrid_diagram, simulate

    agent = APG("cartpole", APGConfig(method="papg", population=2, elites=1, dtype="float64", seed=1))
    diagram = build_hybrid_diagram(agent.system, swingup=agent.closed_loop_policy())
    assert isinstance(diagram.swingup, RecurrentTorchPolicy)
    first = simulate(diagram, agent.system.nudged_nominal_state(), duration=0.5)
    second = simulate(diagram, agent.system.nudged_nominal_state(), duration=0.5)   # a fresh Context each run
    assert np.isfinite(first.x).all() and np.abs(first.u).max() > 0
    assert np.array_equal(first.x, second.x)


def test_named_controller_runs_an_apg_checkpoint(tmp_path):
    from hybridctl import systems
    from hybridctl.drake import simulate
    from hybridctl.experiments.controllers import build_named_diagram

    agent = APG("cartpole", APGConfig(method="ce-apg", population=3, elites=2, apg_iterations=1, horizon=5,
                                      epochs=1, dtype="float64"))
    agent.learn(out=tmp_path, progress=False)
    system = systems.load("cartpole")
    diagram = build_named_diagram(system, f"ce-apg:{tmp_path / 'final'}")
    assert isinstance(diagram.swingup, RecurrentTorchPolicy) and diagram.swingup.period == agent.period
    traj = simulate(diagram, system.nudged_nominal_state(), duration=0.3)
    assert np.isfinite(traj.x).all()
    with pytest.raises(CheckpointError, match="trained on system 'cartpole', but this system is 'acrobot'"):
        build_named_diagram(systems.load("acrobot"), f"apg:{tmp_path / 'final'}")
