"""MuJoCo rollouts: the batched closed-loop stepper against gymnasium and the physics limit.

Measured in one run, on Hopper-v5 under the shipped ARS hopper (a linear policy with its
observation normalisation), every episode reset from a gymnasium reset state when it falls:

* ``gym``: gymnasium's ``env.step`` (``gym.make("Hopper-v5")``, wrappers included), the
  policy evaluated per observation, as a user's loop does (the peer);
* ``mj_step``: the time of one ``mujoco.mj_step`` (one physics step, no Python in it) along
  the same closed loop on one ``MjData``, timed around ``mj_step`` only; the physics limit
  of ``nthread`` threads is ``nthread / (frame_skip x mj_step time)`` env steps/s;
* ``batched``: :class:`hybridctl.envs.mujoco_batch.MujocoBatchEnv` at batch 64 and 256 on 1
  and 2 threads, the policy evaluated for the whole batch in numpy between env steps, with
  its env steps/s, ``ratio_vs_gym`` (aim >= 2.5) and ``limit_over_measured`` (physics limit /
  measured; aim <= 1.5);
* ``rollout_open_loop_calls``: ``mujoco.rollout.rollout`` called once per env step with
  ``nstep = frame_skip`` (the closed loop the issue first proposed; not bit-identical to
  gymnasium, since its state output drops the solver's warm start), for comparison;
* ``hopper_section_map``: apex-to-apex transitions/s of the Ch. 5 hopper map (8 apexes x 25
  pushes), gymnasium path against the batched one (1 thread), projected to the issue's mesh;
* ``ars_epoch``: one ARS epoch at the thesis' N = 50 on HalfCheetah-v5 (100 episodes of 1000
  steps) on one core, one gymnasium rollout per task against the batched stepper, projected to
  the Ch. 4 lane at N = 50 (220 epochs).

    .venv/bin/python benchmarks/mujoco_rollout.py [--quick] [--steps N] [--out FILE]

Prints one JSON document (no thresholds; tests/test_benchmarks.py checks its structure).
"""

from __future__ import annotations

import argparse
import importlib.metadata
import os
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402

from common import emit, machine_info  # noqa: E402

ENV_ID = "Hopper-v5"
CHECKPOINT = ROOT / "models" / "policies" / "ars-hopper"


def linear_policy():
    """The shipped ARS hopper as (M, mean, std, low, high): action = clip(M (obs - mean) / std)."""
    from hybridctl.learn.ars import ARS
    agent = ARS.load(CHECKPOINT, backend="serial")
    frozen = agent.frozen_policy()
    M = frozen.theta.reshape(agent.policy.act_dim, agent.policy.obs_dim)
    return M, frozen.obs_mean, frozen.obs_std, agent.policy.low, agent.policy.high, frozen


def gym_rate(steps: int, frozen, seed: int = 0) -> dict:
    """gymnasium env.step with the policy per observation, resetting when an episode ends."""
    import gymnasium as gym
    env = gym.make(ENV_ID)
    obs, _ = env.reset(seed=seed)
    episodes = 1
    start = time.perf_counter()
    for _ in range(steps):
        obs, _, terminated, truncated, _ = env.step(frozen(obs))
        if terminated or truncated:
            obs, _ = env.reset(seed=seed + episodes)
            episodes += 1
    wall = time.perf_counter() - start
    env.close()
    return {"env_steps_per_s": steps / wall, "steps": steps, "episodes": episodes, "wall_s": wall}


def mj_step_time(steps: int, M, mean, std, low, high, batch_env) -> dict:
    """Seconds per mj_step along the closed loop on one MjData (timed around mj_step only)."""
    import mujoco
    model, frame_skip = batch_env.model, batch_env.frame_skip
    data = mujoco.MjData(model)
    qpos0, qvel0 = batch_env.reset_states(range(1000, 1000 + 64))

    def reset(k):
        mujoco.mj_resetData(model, data)
        data.qpos[:], data.qvel[:] = qpos0[k % 64], qvel0[k % 64]
        mujoco.mj_forward(model, data)
    reset(0)
    episodes, inside, length = 1, 0.0, 0
    for _ in range(steps):
        obs = batch_env.observation(data.qpos[None, :], data.qvel[None, :])[0]
        data.ctrl[:] = np.clip(M @ ((obs - mean) / std), low, high)
        t0 = time.perf_counter()
        mujoco.mj_step(model, data, nstep=frame_skip)
        inside += time.perf_counter() - t0
        length += 1
        if not batch_env.is_healthy(data.qpos[None, :], data.qvel[None, :])[0] or length >= 1000:
            reset(episodes)
            episodes += 1
            length = 0
    return {"seconds": inside / (steps * frame_skip), "physics_steps": steps * frame_skip, "episodes": episodes}


def batched_rate(batch: int, nthread: int, steps: int, M, mean, std, low, high) -> dict:
    """MujocoBatchEnv with the batched linear policy; fallen episodes restart from reset states."""
    from hybridctl.envs.mujoco_batch import MujocoBatchEnv
    env = MujocoBatchEnv(ENV_ID, num_envs=batch, nthread=nthread)
    qpos0, qvel0 = env.reset_states(range(1000, 1000 + batch))
    obs = env.set_state(qpos0, qvel0)
    length = np.zeros(batch, dtype=np.int64)
    resets = 0
    start = time.perf_counter()
    for _ in range(steps):
        actions = np.clip(((obs - mean) / std) @ M.T, low, high)
        obs, _, terminated, _ = env.step(actions)
        length += 1
        done = np.flatnonzero(terminated | (length >= 1000))
        if done.size:
            obs[done] = env.set_state(qpos0[done], qvel0[done], done)
            length[done] = 0
            resets += done.size
    wall = time.perf_counter() - start
    env.close()
    return {"batch": batch, "nthread": nthread, "env_steps_per_s": batch * steps / wall, "steps": steps,
            "resets": resets, "wall_s": wall}


def rollout_rate(batch: int, nthread: int, steps: int, M, mean, std, low, high) -> dict:
    """mujoco.rollout.rollout called once per env step (nstep = frame_skip), fallen episodes restarted."""
    import mujoco
    from mujoco import rollout

    from hybridctl.envs.mujoco_batch import MujocoBatchEnv
    env = MujocoBatchEnv(ENV_ID, num_envs=1)
    model, frame_skip, nq, nv = env.model, env.frame_skip, env.nq, env.nv
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    nstate = mujoco.mj_stateSize(model, spec)
    qpos0, qvel0 = env.reset_states(range(1000, 1000 + batch))
    state0 = np.zeros((batch, nstate))
    state0[:, 1:1 + nq], state0[:, 1 + nq:1 + nq + nv] = qpos0, qvel0
    state = state0.copy()
    datas = [mujoco.MjData(model) for _ in range(nthread)]
    length = np.zeros(batch, dtype=np.int64)
    out = np.zeros((batch, frame_skip, nstate))
    with rollout.Rollout(nthread=nthread) as pool:
        start = time.perf_counter()
        for _ in range(steps):
            qpos, qvel = state[:, 1:1 + nq], state[:, 1 + nq:1 + nq + nv]
            actions = np.clip(((env.observation(qpos, qvel) - mean) / std) @ M.T, low, high)
            pool.rollout(model, datas, state, np.repeat(actions[:, None, :], frame_skip, axis=1), state=out)
            state = out[:, -1].copy()
            length += 1
            done = np.flatnonzero(~env.is_healthy(state[:, 1:1 + nq], state[:, 1 + nq:1 + nq + nv])
                                  | (length >= 1000))
            state[done], length[done] = state0[done], 0
        wall = time.perf_counter() - start
    env.close()
    return {"batch": batch, "nthread": nthread, "env_steps_per_s": batch * steps / wall, "steps": steps,
            "wall_s": wall}


def section_map_rates(quick: bool, frozen) -> dict:
    """Hopper apex-to-apex transitions/s (thesis Ch. 5 mesh and Monte Carlo work) on the gymnasium path
    and on the batched stepper (1 thread), the same states and pushes, with the projection to the
    3,715-state x 25-push hopper mesh (1,410 s on the gymnasium path and 2 processes)."""
    from hybridctl.envs.sections import HopperApexMap, x_pushes
    gym_map = HopperApexMap(frozen, engine="gym")
    starts = gym_map.apex_states(steps=400 if quick else 2000)
    apexes, count = (2, 3) if quick else (8, 25)
    pushes = x_pushes(15.0, count).values
    states, disturbances = np.repeat(starts[:apexes], count, axis=0), pushes * apexes
    out = {"transitions": len(states)}
    for name, section in (("gym", gym_map), ("batched_1_thread", HopperApexMap(frozen, engine="batch"))):
        section.step_many(states[:2], disturbances[:2])      # build the env outside the timing
        t0 = time.perf_counter()
        result = section.step_many(states, disturbances)
        wall = time.perf_counter() - t0
        out[name] = {"transitions_per_s": len(states) / wall, "wall_s": wall,
                     "failures": int(np.isnan(result).any(axis=1).sum())}
    out["ratio_vs_gym"] = out["batched_1_thread"]["transitions_per_s"] / out["gym"]["transitions_per_s"]
    out["projected_mesh_3715x25_s_per_core"] = {k: 3715 * 25 / out[k]["transitions_per_s"]
                                                 for k in ("gym", "batched_1_thread")}
    return out


def ars_epoch_rates(quick: bool) -> dict:
    """One ARS epoch at the thesis' N = 50 (b = 20) on HalfCheetah-v5 (episodes always 1000 steps), one core:
    one gymnasium rollout per task against the batched stepper (1 thread), with the projection to the
    Ch. 4 lane (100 identity epochs + 3 x 40 continued, python -m hybridctl.reproduce.table41 --train) at N = 50."""
    from hybridctl.learn.ars import ARS, ARSConfig
    from hybridctl.parallel import make_backend
    n, steps = (2, 50) if quick else (50, None)
    out = {"env": "HalfCheetah-v5", "n_directions": n, "episode_steps": steps or 1000}
    for engine in ("backend", "auto"):
        agent = ARS("HalfCheetah-v5", ARSConfig(backend="serial", engine=engine, workers=1, n_directions=n,
                                                top_directions=min(20, n), episode_steps=steps, seed=0))
        t0 = time.perf_counter()
        row = agent.train_epoch(make_backend("serial"))
        wall = time.perf_counter() - t0
        out["gym_per_task" if engine == "backend" else "batched_1_thread"] = {
            "epoch_s": wall, "env_steps_per_s": row["episode_steps"] * 2 * n / wall, "mean_return": row["mean_return"]}
    out["ratio_vs_gym"] = out["gym_per_task"]["epoch_s"] / out["batched_1_thread"]["epoch_s"]
    out["projected_ch4_lane_n50_min"] = {k: 220 * 100 * 1000 / out[k]["env_steps_per_s"] / 60
                                         for k in ("gym_per_task", "batched_1_thread")}
    return out


def run(quick: bool, steps: int | None, repeats: int) -> dict:
    """All measurements, in one run."""
    import mujoco
    from hybridctl.envs.mujoco_batch import MujocoBatchEnv
    load_before = list(os.getloadavg())
    M, mean, std, low, high, frozen = linear_policy()
    probe = MujocoBatchEnv(ENV_ID, num_envs=1)
    batched_steps = steps or (10 if quick else 200)
    gym_steps = 200 if quick else 4000
    repeats = 1 if quick else repeats
    median = lambda rows, key: statistics.median(r[key] for r in rows)   # noqa: E731

    # the repeats are interleaved (gym, mj_step, every batched setting, then again), so that a change of
    # load on a shared machine touches every measurement alike
    configs = [(nthread, batch) for nthread in (1, 2) for batch in ((16,) if quick else (64, 256))]
    gym_runs, mj_runs, batched_runs = [], [], {c: [] for c in configs}
    for _ in range(repeats):
        gym_runs.append(gym_rate(gym_steps, frozen))
        mj_runs.append(mj_step_time(gym_steps, M, mean, std, low, high, probe))
        for nthread, batch in configs:
            batched_runs[nthread, batch].append(batched_rate(batch, nthread, batched_steps, M, mean, std, low, high))
    gym = {**gym_runs[0], "env_steps_per_s": median(gym_runs, "env_steps_per_s"),
           "all": [r["env_steps_per_s"] for r in gym_runs]}
    mj = {**mj_runs[0], "seconds": median(mj_runs, "seconds"), "all": [r["seconds"] for r in mj_runs]}
    frame_skip = probe.frame_skip
    rows = []
    for nthread in (1, 2):
        limit = nthread / (frame_skip * mj["seconds"])
        for batch in ((16,) if quick else (64, 256)):
            runs = batched_runs[nthread, batch]
            rate = median(runs, "env_steps_per_s")
            rows.append({**runs[0], "env_steps_per_s": rate, "all": [r["env_steps_per_s"] for r in runs],
                         "physics_limit_steps_per_s": limit, "ratio_vs_gym": rate / gym["env_steps_per_s"],
                         "limit_over_measured": limit / rate,
                         # paired with the peers measured just before it in the same repeat (same load)
                         "ratio_vs_gym_by_repeat": [r["env_steps_per_s"] / g["env_steps_per_s"]
                                                    for r, g in zip(runs, gym_runs)],
                         "limit_over_measured_by_repeat": [nthread / (frame_skip * m["seconds"]) / r["env_steps_per_s"]
                                                           for r, m in zip(runs, mj_runs)]})
    rollout_rows = []
    for nthread in (1, 2):
        batch = 16 if quick else 256
        r = rollout_rate(batch, nthread, batched_steps, M, mean, std, low, high)
        limit = nthread / (frame_skip * mj["seconds"])
        rollout_rows.append({**r, "ratio_vs_gym": r["env_steps_per_s"] / gym["env_steps_per_s"],
                             "limit_over_measured": limit / r["env_steps_per_s"]})
    probe.close()
    sections = section_map_rates(quick, frozen)
    ars = ars_epoch_rates(quick)
    machine = machine_info()
    machine["mujoco"] = mujoco.__version__
    try:
        machine["gymnasium_mujoco_envs"] = importlib.metadata.version("gymnasium")
    except importlib.metadata.PackageNotFoundError:
        pass
    machine["load_average_before"] = load_before
    return {"benchmark": "mujoco_rollout", "quick": quick, "env": ENV_ID, "frame_skip": frame_skip,
            "policy": "the shipped ARS hopper (models/policies/ars-hopper), linear",
            "timestamp": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "machine": machine, "repeats": repeats,
            "gym": gym, "mj_step": mj, "batched": rows, "rollout_open_loop_calls": rollout_rows,
            "hopper_section_map": sections, "ars_epoch": ars,
            "aims": {"ratio_vs_gym": ">= 2.5", "limit_over_measured": "<= 1.5"}}


def main() -> None:
    """Command line."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="a few steps and batch 16 only (for tests)")
    parser.add_argument("--steps", type=int, default=None, help="env steps per batched measurement")
    parser.add_argument("--repeats", type=int, default=3, help="repeats of every measurement (median)")
    parser.add_argument("--out", type=Path, help="also write the JSON to this file")
    args = parser.parse_args()
    try:
        import mujoco.batch  # noqa: F401
    except ImportError as exc:
        emit({"benchmark": "mujoco_rollout", "quick": args.quick, "skipped": f"mujoco >= 3.17 is missing: {exc}"},
             args.out)
        return
    emit(run(args.quick, args.steps, args.repeats), args.out)


if __name__ == "__main__":
    main()
