"""torch.compile in training (issue 15): the compiled env decision and SAC gradient step equal the
eager ones to rounding; LazyCompiled falls back to eager or raises as asked; the modes validate."""

import copy
import warnings

import numpy as np
import pytest
import torch

from hybridctl.envs import SwitchedVectorEnv, TorchVectorEnv
from hybridctl.learn import SAC, SACConfig
from hybridctl.learn.gate import GateNet
from hybridctl.learn.sac_grads import CompiledGrads, EagerGrads
from hybridctl.systems import compiled, load


def _double(x):
    return 2 * x


def test_lazy_compiled_off_calls_the_function_itself(monkeypatch):
    monkeypatch.setattr(torch, "compile", lambda *a, **k: pytest.fail("compile must not be called"))
    fn = compiled.LazyCompiled(_double, enabled=False)
    assert fn(torch.tensor(3.0)).item() == 6.0


def _broken_compile(fn, **kwargs):
    def run(*args):
        raise RuntimeError("no C++ compiler")
    return run


def test_lazy_compiled_falls_back_to_eager_with_a_warning(monkeypatch):
    monkeypatch.setattr(torch, "compile", _broken_compile)
    fn = compiled.LazyCompiled(_double, enabled=True, name="the doubler")
    with pytest.warns(RuntimeWarning, match="the doubler"):
        assert fn(torch.tensor(2.0)).item() == 4.0
    assert not fn.enabled
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert fn(torch.tensor(5.0)).item() == 10.0   # eager from then on, no second warning


def test_lazy_compiled_strict_raises_naming_the_way_out(monkeypatch):
    monkeypatch.setattr(torch, "compile", _broken_compile)
    fn = compiled.LazyCompiled(_double, enabled=True, strict=True, name="the doubler")
    with pytest.raises(RuntimeError, match="the doubler.*compile='off'"):
        fn(torch.tensor(2.0))


def test_a_fault_of_the_function_itself_is_raised_not_hidden(monkeypatch):
    monkeypatch.setattr(torch, "compile", _broken_compile)

    def faulty(x):
        raise ValueError("bad input")
    with pytest.raises(ValueError, match="bad input"):
        compiled.LazyCompiled(faulty, enabled=True)(torch.tensor(1.0))


def test_auto_compiles_long_runs_only():
    assert compiled.wants_compile("auto", compiled.AUTO_COMPILE_MIN_STEPS)
    assert not compiled.wants_compile("auto", compiled.AUTO_COMPILE_MIN_STEPS - 1)
    assert compiled.wants_compile("on", 10) and not compiled.wants_compile("off", 10**9)
    with pytest.raises(ValueError, match="compile must be one of"):
        compiled.wants_compile("yes", 10)


def test_bad_compile_modes_are_refused():
    with pytest.raises(ValueError, match="SACConfig.compile"):
        SACConfig(compile="fast").validate()
    with pytest.raises(ValueError, match="compile must be one of"):
        TorchVectorEnv("acrobot", 2, compile=True)


def test_short_learn_runs_stay_eager(one_torch_thread):
    agent = SAC("acrobot", seed=0, num_envs=4, exploration_steps=64, steps_per_update=64, replay_batch_size=8,
                minibatch_size=8)
    agent.learn(total=128, progress=False)
    assert type(agent._grads) is EagerGrads and agent.env.compile == "off"


def test_compiled_switched_env_equals_eager(one_torch_thread):
    """Same actions, same starts: the compiled decision (gate, hysteresis, LQR, saturation, dynamics)
    matches the eager one to rounding, modes and hand-overs included."""
    system = load("acrobot")
    gate = GateNet(system)
    envs = [SwitchedVectorEnv(system, 8, gate=gate, seed=3, decision_period=0.02, compile=mode)
            for mode in ("off", "on")]
    start = system.goal + np.random.default_rng(0).uniform(-0.05, 0.05, (8, system.n_states))
    start[:4] = system.sample_initial_states(4, np.random.default_rng(1))
    for env in envs:
        env.reset(options={"state": start})
    # a gate that hands over near the goal, so both branches of the switch run
    with torch.no_grad():
        gate.net[-1].bias.fill_(3.0)
    actions = torch.as_tensor(np.random.default_rng(2).uniform(-25, 25, (6, 8, 1)))
    for u in actions:
        eager, fast = (env.step(u) for env in envs)
        np.testing.assert_allclose(fast[0].numpy(), eager[0].numpy(), rtol=0, atol=1e-10)
        np.testing.assert_allclose(fast[1].numpy(), eager[1].numpy(), rtol=0, atol=1e-10)
        assert torch.equal(envs[0].mode, envs[1].mode)
        np.testing.assert_allclose(fast[4]["lqr_fraction"].numpy(), eager[4]["lqr_fraction"].numpy())
    assert bool(envs[0].mode.any())


def test_compiled_sac_gradients_equal_eager(one_torch_thread):
    """The compiled torch.func gradients (twin critics as one batched product) equal eager autograd's
    on the same minibatch and noise, for the critic and the actor loss; a compiled update then runs.

    (Weights after an Adam step are no test of this: Adam's first step is lr * sign(g), so a gradient
    element of ~1e-9 whose rounding differs flips a weight by 2 lr.)"""
    agent = SAC("acrobot", seed=0, num_envs=8, exploration_steps=0, replay_batch_size=64, minibatch_size=16,
                obs_transform="angle_sincos", compile="on")
    assert agent.use_compile(10**6) and isinstance(agent._grads, CompiledGrads)
    obs, _ = agent.env.reset(seed=0)
    agent._obs = obs.float()
    for _ in range(10):
        agent.collect()
    batch = [agent.replay.data[f][:16] for f in ("obs", "actions", "rewards", "next_obs", "dones")]
    eps = torch.randn(16, 1, generator=torch.Generator().manual_seed(1))
    alpha = agent.alpha

    def close(fast, eager):
        scale = max(float(eager.abs().max()), 1e-12)
        torch.testing.assert_close(fast, eager, rtol=1e-4, atol=1e-5 * scale)

    # both gradient providers through the interface gradient_step uses: the loss, and the gradients left in .grad
    eager_grads, fast_grads = EagerGrads(agent), agent._grads
    loss = eager_grads.critic(*batch, eps, alpha)
    eager = [p.grad.clone() for p in agent._q_params]
    for p in agent._q_params:
        p.grad = None          # what the compiled provider leaves is its own
    fast_loss = fast_grads.critic(*batch, eps, alpha)
    close(fast_loss, loss.detach())
    for fast, slow in zip([p.grad for p in agent._q_params], eager, strict=True):
        close(fast, slow)

    loss, _ = eager_grads.actor(batch[0], eps, alpha)
    eager = [p.grad.clone() for p in agent.actor.parameters()]
    for p in agent.actor.parameters():
        p.grad = None
    fast_loss, _ = fast_grads.actor(batch[0], eps, alpha)
    close(fast_loss, loss.detach())
    for fast, slow in zip([p.grad for p in agent.actor.parameters()], eager, strict=True):
        close(fast, slow)

    # one real compiled step on this minibatch and noise: the optimizer sees the eager gradients
    # (Adam's first moment after one step is (1 - beta1) g; a gradient handed over transposed and
    # read in the wrong order by the fused kernel made training diverge)
    loss = agent.critic_loss(None, *batch, eps, alpha)
    eager = torch.autograd.grad(loss, agent._q_params)
    state = agent.generator.get_state()
    eps_step = torch.randn(eps.shape, generator=agent.generator)
    agent.generator.set_state(state)
    if not torch.equal(eps_step, eps):
        loss = agent.critic_loss(None, *batch, eps_step, alpha)
        eager = torch.autograd.grad(loss, agent._q_params)
    agent.gradient_step(dict(zip(("obs", "actions", "rewards", "next_obs", "dones"), batch)))
    beta1 = agent.q_opt.param_groups[0]["betas"][0]
    for p, g in zip(agent._q_params, eager, strict=True):
        close(agent.q_opt.state[p]["exp_avg"], (1 - beta1) * g)

    before = [p.clone() for p in agent.q1.parameters()]
    agent.update()
    assert agent.num_gradient_steps == 5 and agent._loss_sums["n"] == 4
    assert any(not torch.equal(a, b) for a, b in zip(before, agent.q1.parameters()))


def test_fused_adam_step_is_the_optimizers_step_bit_for_bit(one_torch_thread):
    from hybridctl.learn.sac import FusedAdamStep, _adam

    torch.manual_seed(0)
    nets = [torch.nn.Sequential(torch.nn.Linear(3, 5), torch.nn.ReLU(), torch.nn.Linear(5, 1)) for _ in range(2)]
    nets[1].load_state_dict(nets[0].state_dict())
    opts = [_adam(net.parameters(), 1e-3) for net in nets]
    lean = FusedAdamStep(opts[1])
    assert lean.lean
    def backward_both():        # the same gradients on both nets
        x = torch.randn(8, 3)
        for net, opt in zip(nets, opts):
            opt.zero_grad()
            net(x).pow(2).mean().backward()

    for step in range(4):
        backward_both()
        opts[0].step()
        lean()                     # the first call creates the state through opts[1].step()
        for a, b in zip(nets[0].parameters(), nets[1].parameters()):
            assert torch.equal(a, b), step
    for a, b in zip(opts[0].state.values(), opts[1].state.values()):
        assert all(torch.equal(a[k], b[k]) for k in ("step", "exp_avg", "exp_avg_sq"))
    # the shared step counters: each parameter's own 0-d tensor still, through optimizer.step(),
    # a state_dict round trip (counters replaced from outside) and more lean steps
    steps = [s["step"] for s in opts[1].state.values()]
    assert len({s.data_ptr() for s in steps}) == len(steps) and all(s.dim() == 0 for s in steps)
    saved = copy.deepcopy(opts[1].state_dict())
    for step in range(6):
        backward_both()
        opts[0].step()
        if step == 1:
            opts[1].step()          # the optimizer's own step on the shared counters: +1 each, once
        elif step == 3:
            opts[1].load_state_dict(opts[1].state_dict())   # new counter tensors: gathered again
            lean()
        else:
            lean()
        for a, b in zip(nets[0].parameters(), nets[1].parameters()):
            assert torch.equal(a, b), step
    for a, b in zip(opts[0].state.values(), opts[1].state.values()):
        assert all(torch.equal(a[k], b[k]) for k in ("step", "exp_avg", "exp_avg_sq"))
    assert float(next(iter(opts[1].state.values()))["step"]) == 10
    assert float(next(iter(saved["state"].values()))["step"]) == 4   # a saved state is a copy
    opts[1].param_groups[0]["weight_decay"] = 0.1   # another setting: the optimizer's own step
    assert not FusedAdamStep(opts[1]).lean


def test_compiled_gate_fit_follows_the_eager_fit(one_torch_thread):
    """fit_gate(compiled=True): the same minibatches, losses and weights as the eager fit (to float32
    rounding), a fused Adam step, and a refit of the same gate reuses its compiled step."""
    from hybridctl.learn.gate import fit_gate, warm_start_states
    from hybridctl.learn.optim import adam

    system = load("acrobot")
    rng = np.random.default_rng(0)
    states = warm_start_states(system, 3000, rng)
    labels = rng.random(3000) < 0.2
    gates, losses = [], []
    for compiled_fit in (False, True):
        torch.manual_seed(0)
        gate = GateNet(system)
        opt = adam(gate.parameters(), 3e-3)
        gen = torch.Generator().manual_seed(1)
        losses.append(fit_gate(gate, states, labels, 30, 3e-3, 0.01, 512, gen, opt, compiled=compiled_fit)
                      + fit_gate(gate, states, labels, 20, 3e-3, 0.01, 512, gen, opt, class_weight=2.0,
                                 compiled=compiled_fit))
        gates.append(gate)
    assert np.allclose(losses[0], losses[1], rtol=1e-4, atol=1e-6)
    assert losses[0][0] != losses[0][-1]          # the fit moved
    for a, b in zip(gates[0].parameters(), gates[1].parameters()):
        assert torch.allclose(a, b, rtol=1e-4, atol=1e-5)
    assert not gates[1].training
    # more gates of the same layout use the same compiled graph: no recompiles, no eager fallback
    from hybridctl.learn.gate import COMPILED_GATE_GRADS
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for seed in range(10):
            torch.manual_seed(seed)
            fit_gate(GateNet(system), states, labels, 2, batch_size=512, compiled=True)
    assert COMPILED_GATE_GRADS.enabled


def test_compile_garbage_freezes_after_a_new_graph_and_releases_at_the_end(monkeypatch):
    """A training run's full garbage collections skip what a compile left: after an update in which a graph was
    built, the survivors are frozen (once per new graph, not per update), and the run's end unfreezes them."""
    import gc

    from hybridctl.systems import compiled

    graphs = {"n": 0}
    monkeypatch.setattr(compiled, "compiled_graph_count", lambda: graphs["n"])
    gc.unfreeze()
    keeper = compiled.CompileGarbage()
    keeper.settle()
    assert gc.get_freeze_count() == 0 and not keeper.froze            # nothing compiled: nothing frozen
    graphs["n"] = 1                                                    # an update built a graph
    keeper.settle()
    frozen = gc.get_freeze_count()
    assert frozen > 0 and keeper.froze
    survivor = [object() for _ in range(10)]
    keeper.settle()                                                    # no new graph: no second freeze
    assert gc.get_freeze_count() == frozen
    keeper.release()
    assert gc.get_freeze_count() == 0 and not keeper.froze and survivor


def test_a_training_run_freezes_after_a_compile_and_releases_at_its_end(monkeypatch):
    """The training skeleton settles after each update (here every update "built a graph") and releases at its
    end: objects are frozen during the run and none after it."""
    import gc

    from hybridctl.learn import SAC
    from hybridctl.learn.callbacks import Callback

    calls = {"n": 0}

    def more_graphs():
        calls["n"] += 1
        return calls["n"]
    monkeypatch.setattr(compiled, "compiled_graph_count", more_graphs)
    seen = []

    class Watch(Callback):
        def on_update(self, learner):
            seen.append(gc.get_freeze_count())
    gc.unfreeze()
    SAC("pendulum", total_steps=60, num_envs=2, exploration_steps=20, hidden_size=8, steps_per_update=10).learn(
        progress=False, callback=Watch())
    assert seen and max(seen) > 0 and gc.get_freeze_count() == 0
