"""Specs, torch dynamics against the Drake plants, LQR against the thesis, bad input."""

from pathlib import Path

import numpy as np
import pytest
import torch

from hybridctl import systems
from hybridctl.systems import SpecError

ALL = systems.known_systems()


def test_known_systems():
    assert ALL == ["acrobot", "acrobot_urdf", "cartpole", "double_cartpole", "furuta", "pendulum", "reaction_wheel"]


def test_acrobot_lqr_reproduces_thesis_gain():
    K, S = systems.load("acrobot").lqr()
    thesis = np.array([-1649.8, -460.2, -716.1, -278.2])  # thesis Sec. 3.3

    def four_significant(v):
        return np.array([float(f"{x:.4g}") for x in v])

    np.testing.assert_array_equal(four_significant(K.ravel()), four_significant(thesis))
    # The implementation notes give two decimals: [-1649.87, -460.16, -716.07, -278.15].
    np.testing.assert_allclose(K.ravel(), [-1649.87, -460.16, -716.07, -278.15], atol=0.006)
    assert np.all(np.linalg.eigvalsh(S) > 0)


@pytest.mark.parametrize("name", ALL)
def test_derivatives_match_drake(name, rng):
    system = systems.load(name)
    plant = system.drake_plant()
    context = system.drake_context(plant)
    n = 1000
    X = rng.uniform(-np.pi, np.pi, size=(n, system.n_states)) * 2
    U = rng.uniform(-1, 1, size=(n, system.n_actions)) * system.action_limit
    ours = system.derivatives(torch.tensor(X), torch.tensor(U)).numpy()
    drake = np.stack([system.drake_derivatives(plant, context, X[i], U[i]) for i in range(n)])
    np.testing.assert_allclose(ours, drake, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("name", ["acrobot", "pendulum"])
def test_the_plants_own_default_context_holds_the_spec_parameters(name, rng):
    """The newcomer's path: ``plant.CreateDefaultContext()`` of ``drake_plant()`` holds the spec's parameters (the
    thesis acrobot's lc2 0.5, Ic2 1.0), not Drake's defaults (1.0, 0.33), so Drake agrees with our dynamics; in a
    Diagram of one's own, ``apply_drake_parameters`` writes them into the plant's subcontext."""
    from pydrake.systems.framework import DiagramBuilder

    system = systems.load(name)
    plant = system.drake_plant()
    X = rng.uniform(-np.pi, np.pi, size=(20, system.n_states))
    U = rng.uniform(-1, 1, size=(20, system.n_actions)) * system.action_limit
    ours = system.derivatives(torch.tensor(X), torch.tensor(U)).numpy()
    own = plant.CreateDefaultContext()
    np.testing.assert_allclose([system.drake_derivatives(plant, own, x, u) for x, u in zip(X, U)], ours,
                               rtol=1e-9, atol=1e-9)
    builder = DiagramBuilder()
    builder.AddSystem(plant)
    diagram = builder.Build()
    root = diagram.CreateDefaultContext()
    sub = plant.GetMyMutableContextFromRoot(root)
    drakes_defaults = [system.drake_derivatives(plant, sub, x, u) for x, u in zip(X, U)]
    if name == "acrobot":                  # Drake's own AcrobotParams differ from the thesis acrobot's
        assert not np.allclose(drakes_defaults, ours, rtol=1e-6)
    system.apply_drake_parameters(plant, sub)
    np.testing.assert_allclose([system.drake_derivatives(plant, sub, x, u) for x, u in zip(X, U)], ours,
                               rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("name", ALL)
def test_lqr_closed_loop_is_stable(name):
    system = systems.load(name)
    K, _ = system.lqr()
    plant = system.drake_plant()
    from pydrake.systems.primitives import Linearize
    from pydrake.systems.framework import OutputPortSelection
    from hybridctl.systems.plants import actuation_port
    context = system.drake_context(plant)
    context.SetContinuousState(system.to_drake_state(system.goal))
    actuation_port(plant).FixValue(context, np.zeros(system.n_actions))
    lin = Linearize(plant, context, input_port_index=actuation_port(plant).get_index(),
                    output_port_index=OutputPortSelection.kNoOutput)
    closed = lin.A() - lin.B() @ K
    assert np.max(np.linalg.eigvals(closed).real) < 0


@pytest.mark.parametrize("name", ALL)
def test_step_matches_drake_simulator(name, rng):
    """System.step equals Drake's fixed-step integrator of the same name on the plant."""
    from pydrake.systems.analysis import ResetIntegratorFromFlags, Simulator
    from hybridctl.systems.plants import actuation_port
    system = systems.load(name)
    plant = system.drake_plant()
    context = system.drake_context(plant)
    x0 = system.sample_initial_states(1, rng)[0]
    u = rng.uniform(-0.2, 0.2, size=system.n_actions) * system.action_limit
    actuation_port(plant).FixValue(context, u)
    context.SetContinuousState(system.to_drake_state(x0))
    simulator = Simulator(plant, context)
    flag = {"euler": "explicit_euler", "runge_kutta2": "runge_kutta2"}[system.integrator]
    integrator = ResetIntegratorFromFlags(simulator, flag, system.dt)
    integrator.set_fixed_step_mode(True)
    simulator.Initialize()
    steps = 50
    simulator.AdvanceTo(steps * system.dt)
    drake_x = system.from_drake_state(context.get_continuous_state_vector().CopyToVector())
    # one state (the plain-float path), the batched torch path (two copies) and step_single
    for x in (torch.tensor(x0[None]), torch.tensor(np.stack([x0, x0]))):
        ut = torch.tensor(np.stack([u] * len(x)))
        for _ in range(steps):
            x = system.step(x, ut)
        np.testing.assert_allclose(x[0].numpy(), drake_x, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(system.step_single(x0.tolist(), u.tolist(), steps), drake_x, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("name", ALL)
def test_single_state_path_matches_torch(name, rng):
    """One float64 state steps on plain floats (System.step_single, ChainDynamics.scalar); it
    agrees with the batched torch path to rounding, for every spec, integrator and step count."""
    system = systems.load(name)
    n = 300
    X = rng.uniform(-np.pi, np.pi, size=(n, system.n_states)) * 2
    U = rng.uniform(-1, 1, size=(n, system.n_actions)) * system.action_limit
    Xt, Ut = torch.tensor(X), torch.tensor(U)
    batched = system.step(Xt, Ut).numpy()                     # a batch: the torch path
    scale = np.abs(batched).max()
    single = np.stack([system.step_single(X[i].tolist(), U[i].tolist()) for i in range(n)])
    np.testing.assert_allclose(single, batched, rtol=1e-12, atol=1e-12 * scale)
    for i in range(5):                                        # System.step on (1, n) and (n,), unchecked too
        for method in (system.step, system.step_unchecked):
            row, flat = method(Xt[i:i + 1], Ut[i:i + 1]), method(Xt[i], Ut[i])
            assert row.shape == (1, system.n_states) and flat.shape == (system.n_states,)
            assert row.dtype == flat.dtype == torch.float64
            np.testing.assert_array_equal(row[0].numpy(), single[i])
            np.testing.assert_array_equal(flat.numpy(), single[i])
    derivatives = system.dynamics.derivatives(Xt, Ut).numpy()
    scalar = np.stack([system.dynamics.scalar()(X[i].tolist(), U[i].tolist()) for i in range(n)])
    np.testing.assert_allclose(scalar, derivatives, rtol=1e-12, atol=1e-12 * np.abs(derivatives).max())
    # 20 steps in one call (an env decision) against 20 batched steps from near the start state
    X0 = system.sample_initial_states(8, rng)
    x = torch.tensor(X0)
    for _ in range(20):
        x = system.step(x, Ut[:8])
    many = np.stack([system.step_single(X0[i].tolist(), U[i].tolist(), 20) for i in range(8)])
    np.testing.assert_allclose(many, x.numpy(), rtol=1e-12, atol=1e-12)
    heights = system.dynamics.tip_height(torch.tensor(X)).numpy()
    np.testing.assert_allclose([system.reward_single(X[i].tolist()) for i in range(n)],
                               system.reward(torch.tensor(X)).numpy(), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose([system.dynamics.tip_height_single(X[i].tolist()) for i in range(n)], heights,
                               rtol=1e-12, atol=1e-12)


def test_single_state_path_bound_and_fallbacks():
    system = systems.load("acrobot")
    x0, u0 = [0.0, 0.0, 1e5, -1e5], [0.0]
    assert system.step_single(x0, u0, 1) is not None                  # no bound: no check
    assert system.step_single(x0, u0, 20, bound=1e6) is None          # leaves +-1e6 within 0.2 s
    assert system.step_single([0.1, 0.2, 0.0, 0.0], u0, 5, bound=1e6) is not None
    # requires_grad: the torch path, and the gradient flows through one state
    x = torch.tensor([[0.3, 0.2, 0.1, 0.0]], dtype=torch.float64, requires_grad=True)
    system.step(x, torch.ones(1, 1, dtype=torch.float64)).sum().backward()
    assert x.grad is not None and x.grad.abs().sum() > 0
    # float32 stays on torch (float32 results), and bad single states still raise
    assert system.step(torch.zeros(1, 4), torch.zeros(1, 1)).dtype == torch.float32
    with pytest.raises(ValueError, match="x contains NaN"):
        system.step(torch.tensor([[float("nan"), 0.0, 0.0, 0.0]], dtype=torch.float64), torch.zeros(1, 1, dtype=torch.float64))
    with pytest.raises(ValueError, match="u contains NaN"):
        system.step(torch.zeros(4, dtype=torch.float64), torch.tensor([float("inf")], dtype=torch.float64))
    # functorch transforms see per-sample tensors: they must take the torch path
    X = torch.tensor(system.sample_initial_states(3, np.random.default_rng(0)))
    U = torch.zeros(3, 1, dtype=torch.float64)
    torch.testing.assert_close(torch.vmap(system.step_unchecked)(X, U), system.step(X, U), rtol=0, atol=0)
    # step_unchecked of an infinite state: math.sin(inf) raises inside, torch answers (NaN)
    out = system.step_unchecked(torch.tensor([[float("inf"), 0.0, 0.0, 0.0]], dtype=torch.float64),
                                torch.zeros(1, 1, dtype=torch.float64))
    assert torch.isnan(out).any()
    # dt and integrator are attributes: the plain-float path follows changes
    changed = systems.load("acrobot")
    changed.integrator, changed.dt = "runge_kutta2", 0.005
    xs = torch.tensor([[0.3, 0.2, 0.1, 0.0]] * 2, dtype=torch.float64)
    np.testing.assert_allclose(changed.step(xs[:1], U[:1])[0].numpy(), changed.step(xs, U[:2])[0].numpy(), rtol=1e-12)


@pytest.mark.parametrize("name", ALL)
def test_derivatives_float32_batched_differentiable(name):
    system = systems.load(name)
    x = torch.tensor(system.sample_initial_states(64, np.random.default_rng(0)), dtype=torch.float32)
    u = torch.zeros(64, system.n_actions, requires_grad=True)
    xdot = system.derivatives(x, u)
    assert xdot.shape == (64, system.n_states) and xdot.dtype == torch.float32
    xdot.pow(2).sum().backward()
    assert u.grad is not None and torch.isfinite(u.grad).all() and u.grad.abs().sum() > 0
    single = system.derivatives(x[0], u[0].detach())
    torch.testing.assert_close(single, xdot[0].detach())


def test_energy_is_conserved_without_input_or_damping():
    system = systems.load("acrobot", integrator__dt=0.0005)
    x = torch.tensor([[0.3, 1.0, 0.0, 0.0]], dtype=torch.float64)
    e0 = system.energy(x)
    u = torch.zeros(1, 1, dtype=torch.float64)
    # Heun's method on 1 s: energy drift is O(dt^2).
    system.integrator = "runge_kutta2"
    for _ in range(2000):
        x = system.step(x, u)
    assert abs(float(system.energy(x) - e0)) < 1e-4 * (1 + abs(float(e0)))


def test_reward_is_thesis_tip_height():
    system = systems.load("acrobot")
    x = np.array([[0.4, -1.1, 0.0, 0.0]])
    expected = np.sin(0.4) + np.sin(0.4 - 1.1)
    np.testing.assert_allclose(system.reward(x), [expected], rtol=1e-12)
    np.testing.assert_allclose(system.reward(system.goal[None]), [2.0])


def test_state_error_wraps_angles():
    system = systems.load("acrobot")
    x = system.goal + np.array([2 * np.pi + 0.1, -2 * np.pi, 0.5, 0.0])
    np.testing.assert_allclose(system.state_error(x), [0.1, 0.0, 0.5, 0.0], atol=1e-12)


def test_overrides_and_sources():
    system = systems.load("acrobot", dt=0.005, link_mass=[2.0, 1.0])
    assert system.dt == 0.005 and system.chain.link_mass[0] == 2.0
    assert system.spec.sources["integrator.dt"] == "user override"
    assert "thesis" in systems.load("acrobot").spec.sources["params.link_mass"]


# ----------------------------------------------------------------- bad input
def test_unknown_system_lists_known():
    with pytest.raises(KeyError, match="acrobot.*cartpole"):
        systems.load("acrobott")


@pytest.mark.parametrize("override, key", [
    ({"link_mass": [-1.0, 1.0]}, "params.link_mass"),
    ({"dt": 0.0}, "integrator.dt"),
    ({"dt": -0.01}, "integrator.dt"),
    ({"control__period": 0.015}, "control.period"),
    ({"gate__on": 0.4}, "gate.on"),
])
def test_out_of_range_override_names_the_override_and_key(override, key):
    with pytest.raises(SpecError) as info:
        systems.load("acrobot", **override)
    message = str(info.value)
    (name, value), = override.items()
    assert key in message and f"override {name}={value!r}" in message and "of acrobot" in message
    assert "acrobot.toml" not in message  # the file is fine: the override is what is wrong


def test_bad_spec_file_names_key_and_file(tmp_path: Path):
    text = (systems.spec.SPEC_DIR / "cartpole.toml").read_text()
    bad = tmp_path / "bad.toml"
    bad.write_text(text.replace('cart_mass    = { value = 10.0', 'cart_mass    = { value = -3.0'))
    with pytest.raises(SpecError, match=r"bad\.toml.*params\.cart_mass"):
        systems.load(str(bad))


@pytest.mark.parametrize("x, u, message", [
    (torch.full((2, 4), float("nan")), torch.zeros(2, 1), "x contains NaN"),
    (torch.zeros(2, 4), torch.tensor([[float("inf")], [0.0]]), "u contains NaN or Inf"),
    (torch.zeros(2, 3), torch.zeros(2, 1), r"x must have shape"),
    (torch.zeros(2, 4), torch.zeros(2, 2), r"u must have shape"),
    (torch.zeros(2, 4), torch.zeros(3, 1), "batch sizes differ"),
])
def test_bad_states_and_actions_raise_value_error(x, u, message):
    system = systems.load("acrobot")
    with pytest.raises(ValueError, match=message):
        system.step(x, u)
    with pytest.raises(ValueError, match=message):
        system.derivatives(x, u)


def test_tip_height_centered_penalises_only_the_cart():
    """tip_height_centered = tip height - 0.1 x^2 over positions that are not angles."""
    import torch
    cartpole = systems.load("cartpole", **{"reward.kind": "tip_height_centered"})
    plain = systems.load("cartpole")
    x = torch.tensor([[2.0, np.pi, 0.3, -1.0], [0.0, 0.2, 0.0, 0.0]], dtype=torch.float64)
    torch.testing.assert_close(cartpole.reward(x), plain.reward(x) - 0.1 * x[:, 0] ** 2)
    acrobot = systems.load("acrobot", **{"reward.kind": "tip_height_centered"})
    xa = torch.tensor([[1.0, 0.3, 2.0, -1.0]], dtype=torch.float64)
    torch.testing.assert_close(acrobot.reward(xa), systems.load("acrobot").reward(xa))   # no cart: unchanged


def test_upright_centered_is_upright_times_gaussians_of_cart_distance_and_speed():
    """upright_centered = (1 + h / L) / 2 * exp(-x^2 / (2 s_p^2) - v^2 / (2 s_v^2)); no cart: upright alone."""
    import torch
    cartpole = systems.load("cartpole", **{"reward.kind": "upright_centered", "reward.position_scale": 2.0,
                                           "reward.speed_scale": 0.5})
    x = np.array([[0.0, np.pi, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0], [1.0, np.pi, 0.5, 3.0], [0.3, np.pi / 2, 0.0, 0.0]])
    expected = [1.0, 0.0, np.exp(-1 / 8 - 0.5), 0.5 * np.exp(-0.09 / 8)]
    np.testing.assert_allclose(cartpole.reward(x), expected, atol=1e-12)
    torch.testing.assert_close(cartpole.reward(torch.tensor(x)), torch.tensor(expected, dtype=torch.float64))
    assert cartpole.reward_single(x[2]) == pytest.approx(expected[2], abs=1e-12)
    double = systems.load("double_cartpole", **{"reward.kind": "upright_centered"})
    assert float(double.reward(double.goal[None])[0]) == pytest.approx(1.0)
    acrobot = systems.load("acrobot", **{"reward.kind": "upright_centered"})
    xa = np.array([[1.0, 0.3, 2.0, -1.0]])
    total = float(np.sum(acrobot.chain.link_length))
    np.testing.assert_allclose(acrobot.reward(xa), 0.5 * (1 + systems.load("acrobot").reward(xa) / total))
    with pytest.raises(systems.SpecError, match="reward.speed_scale"):
        systems.load("cartpole", **{"reward.speed_scale": 0.0})


def test_finite_check_is_not_fooled_by_an_overflowing_sum():
    """Validation sums the batch once; finite entries whose sum overflows are still accepted."""
    system = systems.load("acrobot")
    x = torch.full((2, 4), 1e308, dtype=torch.float64)          # the sum is inf, every entry finite
    assert system.derivatives(x, torch.zeros(2, 1, dtype=torch.float64)).shape == (2, 4)
    x[1, 2] = float("-inf")
    with pytest.raises(ValueError, match="x contains NaN or Inf"):
        system.step(x, torch.zeros(2, 1, dtype=torch.float64))


@pytest.mark.parametrize("name", ALL)
def test_column_major_step_equals_step(name, rng):
    """step_columns on (n, B) states: bit for bit System.step on the transposed (B, n) batch, and
    differentiable."""
    system = systems.load(name)
    X = torch.tensor(system.sample_initial_states(50, rng))
    U = torch.tensor(rng.uniform(-1, 1, size=(50, system.n_actions)) * system.action_limit)
    out = system.step_columns(X.T.contiguous(), U.T.contiguous())
    assert out.shape == (system.n_states, 50) and out.is_contiguous()
    assert torch.equal(out.T, system.step(X, U))
    u = U.T.contiguous().requires_grad_(True)
    system.step_columns(X.T.contiguous(), u).pow(2).sum().backward()
    assert u.grad is not None and u.grad.abs().sum() > 0
    with pytest.raises(ValueError, match=r"x must be \(\d, B\)"):
        system.step_columns(X, U)                       # rows, not columns


@pytest.mark.slow
@pytest.mark.parametrize("name", ["acrobot", "furuta"])   # the chain family and generated multibody code
def test_compiled_column_major_step_agrees(name):
    """torch.compile of the column-major step (one fused loop) agrees with eager to rounding."""
    system = systems.load(name)
    rng = np.random.default_rng(0)
    x = torch.tensor(system.sample_initial_states(256, rng).T.copy())
    u = torch.tensor(rng.uniform(-1, 1, size=(1, 256)) * system.action_limit)
    eager = system.step_columns(x, u)
    for _ in range(2):                                   # built once, then reused
        compiled = system.step_columns(x, u, compiled=True)
        np.testing.assert_allclose(compiled.numpy(), eager.numpy(), rtol=1e-12, atol=1e-12)


def test_two_loads_of_a_system_share_their_generated_functions_and_other_parameters_do_not():
    # torch.compile guards on a traced function's code object: a step generated afresh per System made
    # every training run recompile, and past torch's recompile limit the rollout silently ran eager
    first, second = systems.load("acrobot"), systems.load("acrobot")
    step = first.dynamics.generate_torch_step(first.dt, first.integrator)
    assert step is second.dynamics.generate_torch_step(second.dt, second.integrator)
    assert first.dynamics.scalar() is second.dynamics.scalar()
    other = systems.load("acrobot", dt=first.dt / 2)
    other_step = other.dynamics.generate_torch_step(other.dt, other.integrator)
    assert other_step is not step


def test_two_loads_of_a_multibody_system_share_their_generated_step():
    first, second = systems.load("furuta"), systems.load("furuta")
    assert first.dynamics.generate_torch_step(first.dt, first.integrator) is \
        second.dynamics.generate_torch_step(second.dt, second.integrator)


def test_a_system_pickles_as_its_spec_and_steps_alike():
    import copy
    import pickle
    system = systems.load("double_cartpole", dt=0.0025)
    again = pickle.loads(pickle.dumps(system))
    assert again is not system and again.dt == 0.0025 and again.spec.overrides == {"dt": 0.0025}
    x = torch.rand(5, system.n_states, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    u = torch.linspace(-50, 50, 5, dtype=torch.float64)[:, None]
    torch.testing.assert_close(again.step(x, u), system.step(x, u), rtol=0, atol=0)
    np.testing.assert_array_equal(again.lqr()[0], system.lqr()[0])
    assert copy.deepcopy(system) is system                  # shared, never copied: it does not change
    assert copy.copy(system) is system
