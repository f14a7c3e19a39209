"""Training speed of SAC and Switched SAC (thesis Ch. 3) against Stable-Baselines3 SAC, in one run.

Measured, each the median of ``--repeats``:

* ``sb3_sac`` (the peer): SB3 ``SAC("MlpPolicy")`` on our gymnasium acrobot env
  (``hybridctl/AcrobotSwingup-v0``, one env) with the same networks (4 x 32 ReLU for the actor and
  both critics), minibatch 128 and our SSAC's update ratio (128 gradient steps per 500 env steps:
  ``train_freq=500, gradient_steps=128``): env steps/s of its collection (``learn`` before
  ``learning_starts``) and gradient steps/s of ``model.train``;
* ``sac``: :class:`hybridctl.learn.SAC` on the batched torch env (32 episodes), eager and compiled
  (``SACConfig.compile``): env steps/s of ``collect`` and gradient steps/s of ``update``;
* ``ssac_env``: SSAC's switched env (gate MLP + LQR + dynamics every 0.01 s), eager and compiled:
  env steps/s of ``collect``;
* ``projected_ssac_2e6``: seconds of a 2e6-step SSAC run from these rates (env steps / env rate +
  gradient steps / gradient rate; gate refits and the warm start not included), beside SB3's
  rates at the same budget and update ratio.

Every rate also has ``ratio_vs_sb3``. Compiling happens once per process and is reported
(``compile_s``), not counted in the rates.

* ``sac_update_variants`` (``--update-variants``): the update differentiated other ways than the
  compiled per-loss graphs (``torch.compile`` of the losses' forward only; the whole gradient
  step with compiled autograd), each with ``ratio_vs_compiled`` and its projected 2e6-step time.

    .venv/bin/python benchmarks/training.py [--quick] [--no-compile] [--update-variants] [--repeats 3] [--out FILE]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import torch  # noqa: E402

from common import emit, machine_info  # noqa: E402

HIDDEN = [32, 32, 32, 32]   # thesis appendix: 4 x 32 ReLU (SACConfig.hidden_layers / hidden_size)
MINIBATCH = 128             # SACConfig.minibatch_size
STEPS_PER_UPDATE = 500      # SACConfig.steps_per_update
GRAD_PER_ROUND = 128        # 4 updates x 4096 / 128 minibatches (SACConfig.gradient_steps_per_update x updates)


def _median_rate(fn, count: int, repeats: int) -> dict:
    """Run ``fn`` (which does ``count`` units of work) ``repeats`` times; rates in units/s."""
    rates = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        rates.append(count / (time.perf_counter() - start))
    return {"per_s": statistics.median(rates), "min": min(rates), "max": max(rates), "repeats": repeats}


def bench_sb3(env_steps: int, grad_steps: int, repeats: int) -> dict:
    """SB3 SAC on the same gymnasium env: collection and gradient-step rates."""
    try:
        import gymnasium as gym
        from stable_baselines3 import SAC as SB3SAC
    except ImportError as error:
        return {"skipped": f"stable-baselines3 not installed ({error}); pip install -e '.[sb3]'"}
    import hybridctl.envs  # noqa: F401  (registers the gymnasium ids)
    from hybridctl.envs import env_id

    env = gym.make(env_id("acrobot"))
    model = SB3SAC("MlpPolicy", env, policy_kwargs={"net_arch": HIDDEN}, batch_size=MINIBATCH,
                   learning_starts=10**9, train_freq=STEPS_PER_UPDATE, gradient_steps=GRAD_PER_ROUND,
                   buffer_size=10**6, gamma=0.95, ent_coef=0.05, device="cpu", seed=0, verbose=0)
    collect = _median_rate(lambda: model.learn(env_steps, reset_num_timesteps=False), env_steps, repeats)
    model.learn(max(0, 4 * MINIBATCH - model.num_timesteps), reset_num_timesteps=False)
    model._setup_learn(0)  # noqa: SLF001 - the logger train() writes to
    train = _median_rate(lambda: model.train(gradient_steps=grad_steps, batch_size=MINIBATCH), grad_steps, repeats)
    return {"env": env_id("acrobot"), "num_envs": 1, "net_arch": HIDDEN, "env_steps_per_s": collect,
            "gradient_steps_per_s": train}


def _filled_agent(cls, compile_mode: str, **kwargs):
    """An agent past exploration with some replay, its compile mode set up for a long run."""
    agent = cls("acrobot", seed=0, exploration_steps=0, compile=compile_mode, **kwargs)
    agent.use_compile(2_000_000)
    obs, _ = agent.env.reset(seed=0)
    agent._obs = obs.to(torch.float32)  # noqa: SLF001 - the agent's current observations
    for _ in range(40):
        agent.collect()
    return agent


def bench_ours(env_steps: int, grad_steps: int, repeats: int, modes: list[str]) -> dict:
    """Our SAC (batched env) and SSAC's switched env, eager and compiled."""
    from hybridctl.learn import SAC, SSAC
    from hybridctl.learn.gate import GateNet
    from hybridctl.systems import load

    out: dict = {"sac": {}, "ssac_env": {}}
    gate = GateNet(load("acrobot"))
    for mode in modes:
        for name, make in (("sac", lambda m: _filled_agent(SAC, m, obs_transform="angle_sincos")),
                           ("ssac_env", lambda m: _filled_agent(SSAC, m, gate=gate))):
            agent = make(mode)
            n_calls = max(1, env_steps // agent.config.num_envs)
            start = time.perf_counter()
            agent.collect()  # compiles the env's decision (compiled mode)
            entry = {"compile_s_env": time.perf_counter() - start,
                     "env_steps_per_s": _median_rate(lambda: [agent.collect() for _ in range(n_calls)],
                                                     n_calls * agent.config.num_envs, repeats)}
            if name == "sac":
                updates = max(1, grad_steps // agent.config.gradient_steps_per_update)
                start = time.perf_counter()
                agent.update()  # compiles the losses (compiled mode)
                entry["compile_s_gradients"] = time.perf_counter() - start
                entry["gradient_steps_per_s"] = _median_rate(
                    lambda: [agent.update() for _ in range(updates)],
                    updates * agent.config.gradient_steps_per_update, repeats)
            out[name][mode] = entry
    return out


def bench_update_variants(grad_steps: int, repeats: int) -> dict:
    """Gradient steps/s of SAC's update differentiated other ways than :class:`CompiledGrads`, the
    alternatives to it: ``torch.compile`` of the two losses' forward with autograd's backward
    (one eager gradient step wrapped), and the whole gradient step compiled with compiled
    autograd. The update written as one compiled step would replace the per-loss graphs only if
    it were about as fast (within 10 %)."""
    import torch._dynamo
    from hybridctl.learn import SAC
    from hybridctl.learn.sac_grads import EagerGrads
    from hybridctl.systems.compiled import LazyCompiled

    out = {}
    for name in ("compiled_forward", "compiled_autograd_step"):
        agent = _filled_agent(SAC, "off", obs_transform="angle_sincos")
        agent._grads = EagerGrads(agent)  # noqa: SLF001
        if name == "compiled_forward":
            agent.critic_loss = LazyCompiled(agent.critic_loss, True, True, "critic loss")
            agent.actor_loss = LazyCompiled(agent.actor_loss, True, True, "actor loss")
        else:
            torch._dynamo.config.compiled_autograd = True
            agent._check_finite = lambda *args: None  # noqa: SLF001 - a graph break per call otherwise
            agent.gradient_step = torch.compile(agent.gradient_step)
        updates = max(1, grad_steps // agent.config.gradient_steps_per_update)
        start = time.perf_counter()
        agent.update()
        entry = {"compile_s_gradients": time.perf_counter() - start}
        entry["gradient_steps_per_s"] = _median_rate(lambda: [agent.update() for _ in range(updates)],
                                                     updates * agent.config.gradient_steps_per_update, repeats)
        torch._dynamo.config.compiled_autograd = False
        out[name] = entry
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="short measurements (structure check)")
    parser.add_argument("--no-compile", action="store_true", help="eager only (compiling takes ~1 min)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--update-variants", action="store_true",
                        help="also time the alternatives to the compiled per-loss gradients (~2 min)")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    torch.set_num_threads(1)
    env_steps, grad_steps = (640, 64) if args.quick else (6400, 1024)
    repeats = 1 if args.quick else args.repeats
    modes = ["off"] if args.no_compile else ["off", "on"]

    sb3 = bench_sb3(env_steps // 4 if args.quick else env_steps, grad_steps, repeats)
    ours = bench_ours(env_steps, grad_steps, repeats, modes)
    peer_env = sb3.get("env_steps_per_s", {}).get("per_s")
    peer_grad = sb3.get("gradient_steps_per_s", {}).get("per_s")
    for name, per_mode in ours.items():
        for entry in per_mode.values():
            if peer_env:
                entry["env_steps_per_s"]["ratio_vs_sb3"] = entry["env_steps_per_s"]["per_s"] / peer_env
            if peer_grad and "gradient_steps_per_s" in entry:
                entry["gradient_steps_per_s"]["ratio_vs_sb3"] = entry["gradient_steps_per_s"]["per_s"] / peer_grad

    from hybridctl.learn.ssac import SSACConfig
    cfg = SSACConfig()
    rounds = (cfg.total_steps - cfg.exploration_steps) // cfg.steps_per_update
    total_grad = rounds * cfg.updates_per_round * cfg.gradient_steps_per_update
    projected = {"env_steps": cfg.total_steps, "gradient_steps": total_grad, "excludes": "gate warm start and refits"}
    for mode in modes:
        env_rate = ours["ssac_env"][mode]["env_steps_per_s"]["per_s"]
        grad_rate = ours["sac"][mode]["gradient_steps_per_s"]["per_s"]
        projected[f"hybridctl_{mode}_s"] = cfg.total_steps / env_rate + total_grad / grad_rate
    if peer_env and peer_grad:
        projected["sb3_s"] = cfg.total_steps / peer_env + total_grad / peer_grad
    variants = bench_update_variants(grad_steps, repeats) if args.update_variants and "on" in modes else {}
    for name, entry in variants.items():   # the same env rate (compiled), another gradient rate
        rate = entry["gradient_steps_per_s"]["per_s"]
        entry["gradient_steps_per_s"]["ratio_vs_compiled"] = rate / ours["sac"]["on"]["gradient_steps_per_s"]["per_s"]
        projected[f"{name}_s"] = cfg.total_steps / ours["ssac_env"]["on"]["env_steps_per_s"]["per_s"] + total_grad / rate
    emit({"benchmark": "training", "machine": machine_info(), "settings": {
        "env_steps": env_steps, "gradient_steps": grad_steps, "repeats": repeats, "minibatch": MINIBATCH,
        "hidden": HIDDEN, "compile_modes": modes},
        "sb3_sac": sb3, **ours, "sac_update_variants": variants, "projected_ssac_2e6": projected}, args.out)


if __name__ == "__main__":
    main()
