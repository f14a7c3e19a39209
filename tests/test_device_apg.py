"""The APG family keeps every tensor, generator and rollout on its configured device (tests/device_trap.py),
and its Ray cluster setting is ``address`` (``--address``) as for every other learner."""

import json
import warnings

import pytest
import torch

from device_trap import HostSyncs, device_trap
from hybridctl.learn.apg import APG, APGConfig, METHODS, apg_phase, split_apg_phase
from hybridctl.learn.checkpoint import config_from_meta
from hybridctl.parallel import SerialBackend

pytestmark = pytest.mark.usefixtures("one_torch_thread")   # tests/conftest.py

# tests/learner_fingerprints.py's APG settings (compile off)
TINY = dict(epochs=2, population=3, elites=2, batch=2, horizon=40, short_horizon=20, apg_iterations=2, seed=3,
            eval_episodes=3, backend="serial", compile=False)


def tiny(method: str, **overrides) -> APGConfig:
    """A run of seconds: TINY for ``method`` (apg: one member, so no population settings)."""
    values = {k: v for k, v in TINY.items() if method != "apg" or k not in ("population", "elites")}
    return APGConfig(method=method, **{"device": "cpu", **values, **overrides})


def weights(agent) -> dict:
    """The learner's state that a device slip would change (CPU copies, outside the trap)."""
    return {"members": agent.members.clone(), "best": agent.best.clone(), "mean": agent.mean.clone(),
            "std": agent.std.clone(), "stats": agent.stats.clone(), "adam_m": agent.adam.m.clone()}


CASES = [(method, "gru", "none") for method in METHODS] + [("papg", "mlp:8,8", "none"), ("papg", "gru", "lqr"),
                                                           ("cem", "mlp:8", "lqr")]


@pytest.mark.parametrize("method, policy, takeover", CASES)
def test_trains_and_evaluates_with_every_tensor_on_its_device(method, policy, takeover, tmp_path):
    """Population, members, CEM draws, Adam, starts, rollouts (the LQR takeover's too), evaluation,
    save and load: a tensor made without a device would be a meta tensor and fail the run. The run
    inside the trap is the run outside it, number for number (nothing drifted to another path)."""
    config = tiny(method, policy=policy, takeover=takeover)
    with device_trap():
        agent = APG("cartpole", config)
        agent.learn(progress=False)
        result = agent.evaluate(episodes=3)
        agent.save(tmp_path / "saved")
        loaded = APG.load(tmp_path / "saved")
        again = loaded.evaluate(episodes=3)
    assert agent.epoch == 2 and agent.env_steps > 0
    assert {p.device.type for p in agent.pop.parameters()} == {"cpu"}
    assert {t.device.type for t in (agent.members, agent.best, agent.mean, agent.std, agent.stats, agent.adam.m,
                                    agent.adam.v, agent.adam.t, agent.last_scores)} == {"cpu"}
    assert torch.equal(loaded.best, agent.best) and torch.equal(loaded.adam.m, agent.adam.m)
    assert again["mean_return"] == result["mean_return"]

    reference = APG("cartpole", config)   # outside the trap: torch's default device
    reference.learn(progress=False)
    for name, value in weights(reference).items():
        assert torch.equal(weights(agent)[name], value), name
    assert reference.evaluate(episodes=3)["mean_return"] == result["mean_return"]


def test_the_split_phase_sends_arrays_and_brings_them_back_to_the_device():
    """split.py's chunks carry CPU arrays; the joined phase is back on the learner's device and
    equals the phase in one process (the serial backend runs the chunks here, inside the trap)."""
    with device_trap():
        agent = APG("cartpole", tiny("papg"))
        theta, problem = agent.members, agent.problem
        whole = apg_phase(problem, theta, agent.adam, 1e-2, 0, 0, agent.unroll(agent.config))
        split = split_apg_phase(SerialBackend(), problem, "cartpole", theta, agent.adam, 1e-2, 0, 0,
                                agent.unroll(agent.config))
    for name in ("theta", "returns", "norms"):
        assert getattr(split, name).device == agent.device
        assert torch.equal(getattr(split, name), getattr(whole, name)), name
    assert split.adam.m.device == agent.device and torch.equal(split.adam.m, whole.adam.m)
    assert all(s.device == agent.device for s in split.obs_sums[:2])


def _boolean_mask(index) -> bool:
    items = index if isinstance(index, tuple) else (index,)
    return any(isinstance(i, torch.Tensor) and i.dtype == torch.bool for i in items)


class HostReads(HostSyncs):
    """HostSyncs, and also indexing by a boolean mask (``x[mask]``, ``x[mask] = v``): on a GPU it
    waits for the device to count the mask's rows."""

    def __torch_function__(self, func, types, args=(), kwargs=None):
        if getattr(func, "__name__", "") in ("__getitem__", "__setitem__") and len(args) > 1 \
                and _boolean_mask(args[1]):
            self.count += 1
            self.by_name["boolean index"] = self.by_name.get("boolean index", 0) + 1
        return super().__torch_function__(func, types, args, kwargs)


@pytest.mark.parametrize("method", ["papg", "cem"])
def test_an_epoch_reads_back_to_the_host_as_often_whatever_the_horizon(method):
    """No read-back per policy step: an epoch of a 40-step horizon makes as many host reads as one of
    20 steps (the guards and the progress row read once per APG update or epoch)."""
    counts = []
    for horizon in (20, 40):
        agent = APG("cartpole", tiny(method, horizon=horizon, takeover="lqr"))
        agent.train_epoch()                     # the second epoch applies the observation statistics too
        with HostReads() as reads:
            agent.train_epoch()
        counts.append(reads.by_name)
    assert counts[0] == counts[1]


def test_the_device_is_a_config_field_checked_like_sacs():
    """``device`` defaults to the CPU; a name torch does not know, or CUDA on a machine without it,
    is refused naming the field."""
    assert APGConfig().device == "cpu"
    with pytest.raises(ValueError, match="APGConfig.device must be a torch device"):
        tiny("papg", device="gpu-please").validate()
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="APGConfig.device is 'cuda', but CUDA is not available"):
            tiny("papg", device="cuda").validate()


def test_an_old_checkpoint_with_ray_address_loads_it_as_address(tmp_path):
    """config.json written before the rename records ``ray_address``: it loads as ``address``, with no
    warning about a dropped field."""
    APG("cartpole", tiny("papg", epochs=1)).save(tmp_path / "old")
    path = tmp_path / "old" / "config.json"
    meta = json.loads(path.read_text())
    meta["config"].pop("address", None)
    meta["config"].pop("device", None)               # an old checkpoint had neither field
    meta["config"].update(backend="ray", ray_address="ray://head:10001")
    path.write_text(json.dumps(meta))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        loaded = APG.load(tmp_path / "old")
    assert loaded.config.address == "ray://head:10001" and loaded.config.backend == "ray"
    assert loaded.config.device == "cpu"
    config = config_from_meta(APGConfig, {"config": {"method": "papg", "backend": "ray", "ray_address": "auto"}})
    assert config.address == "auto"


def test_the_cli_flag_is_address_for_an_apg_method(capsys):
    """``hybridctl train papg --help`` shows ``--address`` (as ARS and fine-tuning) and ``--device``,
    and no ``--ray-address``."""
    from hybridctl.cli import main

    with pytest.raises(SystemExit) as stop:
        main(["train", "papg", "cartpole", "--help"])
    assert stop.value.code == 0
    shown = capsys.readouterr().out
    assert "--address" in shown and "--device" in shown
    assert "--ray-address" not in shown
