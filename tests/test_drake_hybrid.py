"""Drake blocks, the hybrid diagram and simulate(): behaviour a Drake user relies on."""

import numpy as np
import pytest
import torch
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantVectorSource, LogVectorOutput

from hybridctl import drake, systems
from hybridctl.systems.control import lqr_basin_level

HANGING = {"acrobot": [-np.pi / 2 + 1e-3, 0, 0, 0], "cartpole": [0.1, 0.05, 0, 0], "pendulum": [0.05, 0.0]}


def _drive(block, values, n_inputs):
    """Feed a sequence of constant inputs (one per period) through a block; return held outputs."""
    outputs = []
    context = block.CreateDefaultContext()
    for i, value in enumerate(values):
        block.get_input_port(0).FixValue(context, np.full(n_inputs, value))
        simulator = Simulator(block, context)
        simulator.AdvanceTo((i + 0.5) * block.period)
        outputs.append(block.get_output_port(0).Eval(context).copy())
        context = simulator.get_mutable_context()
    return outputs


def test_gate_hysteresis_switches_on_above_on_and_off_below_off():
    gate = drake.Gate(lambda x: [x[0]], n_states=1, period=0.01, on=0.9, off=0.5)
    probabilities = [0.2, 0.85, 0.95, 0.7, 0.55, 0.49, 0.6, 0.91]
    modes = [float(o[0]) for o in _drive(gate, probabilities, 1)]
    assert modes == [0, 0, 1, 1, 1, 0, 0, 1]


def test_gate_mode_lives_in_context_and_resets():
    gate = drake.Gate(lambda x: [0.95], n_states=1, period=0.01, on=0.9, off=0.5)
    context = gate.CreateDefaultContext()
    gate.get_input_port(0).FixValue(context, [0.0])
    simulator = Simulator(gate, context)
    simulator.AdvanceTo(0.005)
    assert gate.GetOutputPort("mode").Eval(context)[0] == 1.0
    fresh = gate.CreateDefaultContext()
    assert gate.GetOutputPort("mode").Eval(fresh)[0] == 0.0


def test_gate_rejects_bad_thresholds():
    with pytest.raises(ValueError, match="off < on"):
        drake.Gate(lambda x: [0.0], 1, 0.01, on=0.5, off=0.9)


def test_torch_policy_is_zero_order_hold_not_feedthrough():
    module = torch.nn.Linear(2, 1, dtype=torch.float64)
    with torch.no_grad():
        module.weight[:] = torch.tensor([[2.0, -1.0]])
        module.bias[:] = 0.5
    policy = drake.TorchPolicy(module, n_states=2, n_actions=1, period=0.2, limit=1.0)
    assert not policy.HasDirectFeedthrough(0, 0)
    builder = DiagramBuilder()
    block = builder.AddSystem(policy)
    source = builder.AddSystem(ConstantVectorSource([0.1, 0.0]))
    builder.Connect(source.get_output_port(), block.get_input_port(0))
    logger = LogVectorOutput(block.get_output_port(0), builder, 0.05)
    diagram = builder.Build()
    context = diagram.CreateDefaultContext()
    Simulator(diagram, context).AdvanceTo(0.5)
    values = logger.FindLog(context).data()[0]
    # 2 * 0.1 + 0.5 = 0.7, computed at t = 0 and held (the logger at t=0 sees the initial 0).
    np.testing.assert_allclose(values[1:], 0.7)
    clipped = drake.TorchPolicy(module, 2, 1, 0.2, limit=0.6).compute(np.array([0.1, 0.0]))
    np.testing.assert_allclose(clipped, [0.6])


def test_diagram_has_named_ports_and_spec_parameters():
    system = systems.load("acrobot")
    diagram = drake.build_hybrid_diagram(system)
    names = {diagram.get_output_port(i).get_name() for i in range(diagram.num_output_ports())}
    assert {"state", "command", "mode", "probability", "swingup_command", "balance_command"} <= names
    context = diagram.CreateDefaultContext()
    params = diagram.plant.get_parameters(diagram.plant.GetMyContextFromRoot(context))
    assert params.Ic1() == 0.2 and params.Ic2() == 1.0 and params.gravity() == 9.8
    diagram.set_state(context, [0.3, 0.2, 0.0, 0.0])
    np.testing.assert_allclose(diagram.GetOutputPort("state").Eval(context), [0.3, 0.2, 0.0, 0.0])


@pytest.mark.parametrize("name", ["acrobot", "cartpole", "pendulum"])
def test_simulation_equals_torch_closed_loop(name):
    """Drake's run of the hybrid loop equals the same loop written with System.step (1e-9)."""
    system = systems.load(name)
    diagram = drake.build_hybrid_diagram(system)
    x0 = np.asarray(HANGING[name], dtype=float)
    traj = drake.simulate(diagram, x0, duration=2.0)
    swing = drake.energy_swingup(system)
    lqr = drake.LQRController(system)
    gate = drake.CostToGoGate(system)
    limit = system.action_limit
    x, mode = x0.copy(), 0.0
    states, inputs, modes = [], [], []
    for _ in range(len(traj.t)):
        p = float(gate(x)[0])
        mode = 1.0 if p > 0.9 else (0.0 if p < 0.5 else mode)
        u = np.clip(lqr(x) if mode else swing(x), -limit, limit)
        states.append(x.copy()), inputs.append(u), modes.append(mode)
        x = system.step(torch.tensor(x[None]), torch.tensor(u[None]))[0].numpy()
    np.testing.assert_allclose(traj.x, np.array(states), rtol=1e-9, atol=1e-9)
    # u[k] and gate[k] are what acted over [t_k, t_k+1): the pairs (x[k], u[k]) are transitions.
    np.testing.assert_allclose(traj.u, np.array(inputs), rtol=1e-9, atol=1e-9)
    np.testing.assert_array_equal(traj.gate, np.array(modes))


@pytest.mark.parametrize("name, duration", [("acrobot", 15.0), ("cartpole", 10.0), ("pendulum", 10.0)])
def test_energy_swingup_balances_from_hanging_down(name, duration):
    system = systems.load(name)
    traj = drake.simulate(drake.build_hybrid_diagram(system), HANGING[name], duration=duration)
    summary = traj.summary()
    assert summary["balanced"], summary
    assert not summary["diverged"]
    assert summary["first_balance_time"] is not None and summary["first_balance_time"] > 0.5
    assert np.abs(traj.u).max() <= system.action_limit + 1e-12


def test_double_cartpole_lqr_balances_near_upright():
    system = systems.load("double_cartpole")
    diagram = drake.build_hybrid_diagram(system, swingup=lambda x: np.zeros(1))
    traj = drake.simulate(diagram, system.goal + np.array([0.1, 0.05, -0.05, 0, 0, 0]), duration=5.0)
    assert traj.balanced and traj.gate[-1] == 1.0


def test_lqr_basin_level_gate_only_hands_over_balanceable_states():
    system = systems.load("pendulum")
    result = lqr_basin_level(system, n_samples=2000, horizon=5.0, spread=np.array([1.0, 3.0]))
    assert 0 < result["level"] < np.inf
    assert result["success_below_1x"] == 1.0
    assert result["success_below_4x"] < 1.0


def test_diverging_simulation_is_flagged_not_raised():
    system = systems.load("pendulum")
    # Commands are clipped to the torque limit, so divergence is forced with a huge speed: the angle
    # passes the divergence bound (1e6) after about 1.1 s; a start beyond the bound is refused.
    diagram = drake.build_hybrid_diagram(system, swingup=lambda x: np.array([1e300]), gate=lambda x: [0.0])
    traj = drake.simulate(diagram, [0.0, 9e5], duration=2.0)
    assert traj.diverged and not traj.balanced and traj.summary()["diverged"]
    assert 1.0 < traj.t[-1] < 2.0  # stopped early, at the step that crossed the bound


@pytest.mark.parametrize("x0, message", [
    ([0.0, np.nan, 0.0, 0.0], "x0 contains NaN"),
    ([0.0, 0.0, 0.0], r"x0 must have shape \(4,\)"),
])
def test_bad_initial_state(x0, message):
    diagram = drake.build_hybrid_diagram(systems.load("acrobot"))
    with pytest.raises(ValueError, match=message):
        drake.simulate(diagram, x0, duration=1.0)


def test_bad_duration():
    diagram = drake.build_hybrid_diagram(systems.load("pendulum"))
    with pytest.raises(ValueError, match="duration must be"):
        drake.simulate(diagram, [0.0, 0.0], duration=-1.0)


def test_meshcat_viewer_does_not_change_the_run():
    """Viewer publish events must not cut the fixed integration steps."""
    from hybridctl.viz import start_meshcat
    system = systems.load("acrobot")
    plain = drake.simulate(drake.build_hybrid_diagram(system), HANGING["acrobot"], duration=3.0)
    viewed = drake.simulate(drake.build_hybrid_diagram(system, meshcat=start_meshcat()), HANGING["acrobot"],
                            duration=3.0)
    np.testing.assert_allclose(viewed.x, plain.x, rtol=1e-12, atol=1e-12)


def test_balance_map_workers_keep_the_systems_overrides():
    from hybridctl.experiments import balance_map
    system = systems.load("pendulum", limit=0.01)   # too weak to swing up or hold
    weak = balance_map(system, grid=2, workers=2, progress=False)
    strong = balance_map("pendulum", grid=2, workers=1, progress=False)
    assert weak.fraction < strong.fraction


def test_trajectory_save_writes_arrays_and_summary(tmp_path):
    system = systems.load("pendulum")
    traj = drake.simulate(drake.build_hybrid_diagram(system), HANGING["pendulum"], duration=1.0)
    summary = traj.save(tmp_path)
    data = np.load(tmp_path / "trajectory.npz")
    assert set(data.files) >= {"t", "x", "u", "gate"}
    assert data["x"].shape == (len(data["t"]), 2)
    assert {"balanced", "return", "diverged"} <= set(summary)
    assert not list(tmp_path.glob(".*"))  # no temporary files left behind
