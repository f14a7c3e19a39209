"""Fine-tuning on a device, chunked from the worker count, its policy shipped once per update
(issue 32): a system's rollouts keep every tensor on the configured device (tests/device_trap.py)
and copy to the host once per chunk; automatic chunks give the numbers of a fixed size on every
backend; ``backend.put`` carries the policy; ``failure_rates`` takes a Ray address."""

import dataclasses
import pickle

import numpy as np
import pytest
import torch

from device_trap import HostSyncs, device_trap
from hybridctl.analysis.postprocess import PostProcessor
from hybridctl.envs import SwitchedVectorEnv, TorchVectorEnv
from hybridctl.learn.finetune import FineTune, FineTuneConfig
from hybridctl.learn.finetune_sources import TunablePolicy, load_policy
from hybridctl.learn.chunk_tasks import AUTO_CHUNK_MAX, ChunkInputs, batched_actions, chunk_slices, unflatten
from hybridctl.learn.run import seeded
from hybridctl.parallel import SerialBackend, make_backend
from hybridctl.systems import load as load_system

pytestmark = pytest.mark.usefixtures("one_torch_thread")
SSAC = "ssac:models/policies/ssac-acrobot"


def system_mlp(system: str, hidden: int = 8) -> torch.nn.Module:
    """A small tanh MLP from a system's states to its actions, built on the CPU (as learners build)."""
    s = load_system(system)
    with seeded(0):
        return torch.nn.Sequential(torch.nn.Linear(s.n_states, hidden), torch.nn.Tanh(),
                                   torch.nn.Linear(hidden, s.n_actions), torch.nn.Tanh())


def pendulum_tuner(**overrides) -> FineTune:
    cfg = dict(updates=2, n_directions=4, backend="serial", episode_steps=20, eval_episodes=2, chunk_size=None)
    cfg.update(overrides)
    return FineTune("pendulum", TunablePolicy(system_mlp("pendulum"), system="pendulum"), FineTuneConfig(**cfg))


# ----------------------------------------------------------------------------- the device

def test_fine_tuning_a_system_policy_keeps_every_tensor_on_its_device(tmp_path):
    """Plain and switched (SSAC's gate + LQR) system rollouts, the update, a checkpoint, evaluate and
    predict, all inside the trap: a tensor made without naming the device would be a meta tensor and fail."""
    gate = load_policy(SSAC, "acrobot").gate    # read outside: the checkpoint reader is not this test's
    with device_trap():
        plain = FineTune("pendulum", TunablePolicy(system_mlp("pendulum"), system="pendulum"), updates=2,
                         n_directions=2, backend="serial", episode_steps=20, device="cpu")
        plain.learn(out=tmp_path / "plain", progress=False)
        switched = FineTune("acrobot", TunablePolicy(system_mlp("acrobot"), system="acrobot", gate=gate), updates=1,
                            n_directions=2, backend="serial", episode_steps=10, device="cpu")
        switched.learn(progress=False)
        result = plain.evaluate(2)
        action = plain.predict(np.zeros(2))
    assert plain.update == 2 and switched.update == 1 and plain.env_steps == 2 * 4 * 20
    assert np.all(np.isfinite(plain.theta)) and not np.array_equal(plain.theta, plain.theta0)
    assert np.isfinite(result["mean_return"]) and action.shape == (1,)
    assert {p.device.type for p in plain.tunable.module.parameters()} == {"cpu"}


def test_a_system_rollout_copies_to_the_host_a_fixed_number_of_times():
    """No copy per env step: the host copies of an evaluation do not grow with the episode length."""
    tuner = pendulum_tuner()
    counts = {}
    for steps in (10, 40):
        with HostSyncs() as syncs:
            tuner.evaluate(4, episode_steps=steps)
        counts[steps] = syncs.count
    assert counts[10] == counts[40], counts


@pytest.mark.parametrize("source", ["sac", "ssac"])
def test_a_system_rollout_is_its_vector_envs_episode(source):
    """The device rollout steps the env's dynamics itself: returns, lengths, terminations, success and
    every state (the last one the episode's final state, not the next episode's first) equal a
    TorchVectorEnv / SwitchedVectorEnv run of the same policies, bit for bit."""
    tuner = FineTune("acrobot", f"{source}:models/policies/ssac-acrobot", n_directions=2, backend="serial")
    system, n, seeds = load_system("acrobot"), 6, list(range(6))
    thetas = tuner.theta[None] + 0.02 * np.random.default_rng(1).standard_normal((n, tuner.theta.size))
    with SerialBackend() as backend:
        got = tuner._rollouts(thetas, seeds, backend, PostProcessor("identity"), keep_states=True)

    env = (SwitchedVectorEnv(system, n, gate=tuner.tunable.gate, dtype=torch.float64) if source == "ssac"
           else TorchVectorEnv(system, n, dtype=torch.float64))
    x0 = np.concatenate([system.sample_initial_states(1, np.random.default_rng(s)) for s in seeds])
    obs, _ = env.reset(options={"state": x0})
    module = tuner.tunable.module
    params = unflatten(module, tuner.names, torch.as_tensor(thetas, dtype=torch.float64))
    dtype = next(module.parameters()).dtype
    states, returns = [[row] for row in obs.numpy()], np.zeros(n)
    ended, success, terminated = np.zeros(n, bool), np.zeros(n, bool), np.zeros(n, bool)
    while not ended.all():
        actions = batched_actions(module, params, obs.to(dtype)).to(torch.float64)
        obs, rewards, term, trunc, infos = env.step(actions)
        for i in np.flatnonzero(~ended):
            returns[i] += float(rewards[i])
            states[i].append(infos["final_obs"][i].numpy() if bool(infos["_final_obs"][i]) else obs[i].numpy())
            if bool(term[i]) or bool(trunc[i]):
                ended[i], terminated[i], success[i] = True, bool(term[i]), bool(infos["success"][i])
    for i, r in enumerate(got):
        assert r["raw_return"] == returns[i] and r["steps"] == len(states[i]) - 1
        assert r["terminated"] == terminated[i] and r["success"] == success[i]
        np.testing.assert_array_equal(r["states"], np.stack(states[i]))
    if source == "ssac":
        assert success.any()     # the gate and LQR balance: the success test was exercised


def test_device_is_checked_and_applies_to_system_rollouts_only():
    with pytest.raises(ValueError, match="FineTuneConfig.device must be a torch device"):
        FineTuneConfig(device="gpu please").validate()
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="FineTuneConfig.device is 'cuda:0', but CUDA is not available"):
            FineTuneConfig(device="cuda:0").validate()
    FineTuneConfig(device="cuda:0", backend="ray").validate()   # a cluster's workers may have the GPU
    with seeded(0):
        module = torch.nn.Sequential(torch.nn.Linear(3, 1), torch.nn.Tanh())
    with pytest.raises(ValueError, match="Pendulum-v1 steps on the host"):
        FineTune("Pendulum-v1", module, device="cuda:0", backend="ray")
    with pytest.raises(ValueError, match="chunk_size"):
        FineTuneConfig(chunk_size=0).validate()


# ----------------------------------------------------------------------------- chunks from the worker count

def test_automatic_chunks_give_every_worker_two_tasks_of_two_rows_or_more():
    fixed = chunk_slices(10, 4)
    assert [(s.start, s.stop) for s in fixed] == [(0, 4), (4, 8), (8, 10)]     # an int: as before
    for total, workers in [(128, 1), (128, 2), (128, 16), (128, 100), (7, 3), (1000, 1), (2, 8), (1, 4), (129, 1)]:
        slices = chunk_slices(total, None, workers)
        sizes = [s.stop - s.start for s in slices]
        assert sum(sizes) == total and slices[0].start == 0
        assert all(a.stop == b.start for a, b in zip(slices, slices[1:]))
        assert max(sizes) - min(sizes) <= 1 and max(sizes) <= AUTO_CHUNK_MAX
        assert min(sizes) >= 2 or total < 2          # a one-row system chunk takes the plain-float path
        assert len(slices) >= min(2 * workers, total // 2)
    assert len(chunk_slices(128, None, 1)) == 2 and len(chunk_slices(128, None, 16)) == 32
    assert len(chunk_slices(4096, None, 1, largest=4096)) == 2


class RecordingBackend:
    """A backend that records the tasks of every map (and how many there were), then runs them on ``inner``."""

    def __init__(self, inner):
        self.inner, self.maps = inner, []
        self.name, self.workers = inner.name, inner.workers

    def put(self, value):
        return self.inner.put(value)

    def map(self, fn, tasks):
        self.maps.append(list(tasks))
        return self.inner.map(fn, tasks)


@pytest.mark.parametrize("backend", ["serial", "processes", pytest.param("ray", marks=pytest.mark.xdist_group("ray"))])
def test_automatic_chunks_give_the_fixed_size_numbers_on_every_backend(backend, request):
    """Auto (chunks from the backend's workers) and chunk_size=64 give the same run bit for bit, on a
    system (its batched torch dynamics) and on a gymnasium env."""
    if backend == "ray":
        request.getfixturevalue("local_ray")
    from hybridctl.envs.toy import point_reach
    with seeded(1):
        point_policy = torch.nn.Sequential(torch.nn.Linear(4, 8), torch.nn.Tanh(), torch.nn.Linear(8, 2))

    def runs(chunk_size, pool):
        a = pendulum_tuner(chunk_size=chunk_size, n_directions=6).learn(progress=False, backend=pool)
        b = FineTune(point_reach, TunablePolicy(point_policy), updates=2, n_directions=6, backend="serial",
                     chunk_size=chunk_size).learn(progress=False, backend=pool)
        return a, b

    with SerialBackend() as serial:
        reference = runs(64, serial)
    with make_backend(backend, 2) as inner:
        pool = RecordingBackend(inner)
        auto = runs(None, pool)
    for ref, got in zip(reference, auto):
        np.testing.assert_array_equal(got.theta, ref.theta)
        assert [r["mean_return"] for r in got.history] == [r["mean_return"] for r in ref.history]
    # 12 rollouts per update: 2 per worker -> 4 chunks of 3 (the fixed 64 made 1)
    assert {len(tasks) for tasks in pool.maps} == {2 * pool.workers}
    # the shared inputs travel as put's result: Ray's reference (nested in a task, which Ray does not
    # resolve: the worker fetches it), the value itself elsewhere
    kinds = {type(t.inputs).__name__ for tasks in pool.maps for t in tasks}
    assert kinds == ({"ObjectRef"} if backend == "ray" else {"ChunkInputs"})


# ----------------------------------------------------------------------------- the policy shipped once

class CountingBackend(SerialBackend):
    """A serial backend whose ``put`` stores the value and returns a token (as Ray's object store does);
    ``map`` records the tasks it was given, then runs them with the token's value in their place."""

    def __init__(self):
        self.store, self.tasks = [], []

    def put(self, value):
        self.store.append(value)
        return ("token", len(self.store) - 1)

    def map(self, fn, tasks):
        self.tasks.append(list(tasks))
        return [fn(dataclasses.replace(t, inputs=self.store[t.inputs[1]])) for t in tasks]


def test_the_policy_goes_to_the_backend_once_per_update_and_the_tasks_carry_the_reference():
    with seeded(0):
        big = torch.nn.Sequential(torch.nn.Linear(2, 128), torch.nn.Tanh(), torch.nn.Linear(128, 128), torch.nn.Tanh(),
                                  torch.nn.Linear(128, 1), torch.nn.Tanh())   # only the last layer's 129 are perturbed
    tuner = FineTune("pendulum", TunablePolicy(big, system="pendulum"), updates=3, n_directions=4, backend="serial",
                     episode_steps=5, select="last", chunk_size=2)
    backend = CountingBackend()
    for _ in range(3):
        tuner.train_update(backend)
    assert len(backend.store) == 3 and all(isinstance(v, ChunkInputs) for v in backend.store)
    blob = len(backend.store[0].shipped.blob)
    for update, tasks in enumerate(backend.tasks):
        assert len(tasks) == 4                                       # 8 rollouts in chunks of 2
        assert all(t.inputs == ("token", update) for t in tasks)     # the reference, not a copy
        assert all(len(pickle.dumps(t)) < blob / 4 for t in tasks)   # no module inside a task


# ----------------------------------------------------------------------------- failure rates on a cluster

def test_failure_rates_take_a_ray_address(monkeypatch):
    from hybridctl.learn import robustness

    opened = []

    def recording_make_backend(name="processes", workers=None, address=None, **kwargs):
        opened.append((name, workers, address))
        return SerialBackend()

    monkeypatch.setattr(robustness, "make_backend", recording_make_backend)
    report = robustness.failure_rates(lambda obs: np.zeros(1), env="Pendulum-v1", episodes=2, episode_steps=5,
                                      backend="ray", workers=3, address="10.0.0.1:6379", engine="backend")
    assert opened == [("ray", 3, "10.0.0.1:6379")]
    assert report["none"]["episodes"] == 2 and report["none"]["failures"] == 0
