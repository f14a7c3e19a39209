"""One contract for every learner (SB3's BaseAlgorithm): the same learn / evaluate / load, written once
in hybridctl.learn.base, and one config.json schema."""

import inspect
import json

import pytest
import torch

from hybridctl.learn import APG, ARS, SAC, SSAC, APGConfig, FineTune
from hybridctl.learn.base import Learner
from hybridctl.learn.checkpoint import FORMAT_VERSION, upgrade_meta

LEARNERS = [SAC, SSAC, ARS, APG, FineTune]


@pytest.mark.parametrize("cls", LEARNERS, ids=lambda c: c.__name__)
def test_every_learner_has_the_base_learn_evaluate_and_load(cls):
    # written once: no learner overrides them (each writes train / run_evaluation / from_checkpoint)
    assert cls.learn is Learner.learn and cls.evaluate is Learner.evaluate
    assert cls.load.__func__ is Learner.load.__func__
    learn = inspect.signature(cls.learn).parameters
    assert list(learn) == ["self", "total", "out", "resume", "force", "callback", "progress", "backend"]
    assert all(learn[name].kind is inspect.Parameter.KEYWORD_ONLY for name in list(learn)[2:])
    load = inspect.signature(cls.load).parameters
    assert [n for n, p in load.items() if p.kind is inspect.Parameter.KEYWORD_ONLY] == ["system", "force"]
    assert inspect.signature(cls.evaluate).parameters["seed"].kind is inspect.Parameter.KEYWORD_ONLY
    assert cls.config_class is not None and hasattr(cls.config_class(), cls.budget_field)


def _learners():
    tiny_apg = APGConfig.preset("reduced", method="papg", epochs=1, population=2, elites=1, horizon=20,
                                short_horizon=10, compile=False)
    policy = torch.nn.Sequential(torch.nn.Linear(3, 4), torch.nn.Tanh(), torch.nn.Linear(4, 1)).double()
    return [SAC("pendulum", num_envs=2, hidden_size=8), ARS("Pendulum-v1", backend="serial"),
            APG("cartpole", tiny_apg), FineTune("Pendulum-v1", policy, backend="serial")]


def test_config_json_has_one_schema_and_loads_back(tmp_path):
    for agent in _learners():
        folder = agent.save(tmp_path / agent.algorithm_name)
        meta = json.loads((folder / "config.json").read_text())
        assert meta["algorithm"] == agent.algorithm_name and meta["format"] == FORMAT_VERSION
        assert isinstance(meta["system"], dict) and isinstance(meta["system"]["name"], str)
        assert isinstance(meta["config"], dict) and {"torch", "numpy"} <= set(meta["versions"])
        assert not {"env", "env_kwargs", "plant", "system_overrides"} & set(meta)   # the format-1 keys
        kwargs = {"policy": agent.tunable} if isinstance(agent, FineTune) else {}
        again = type(agent).load(folder, **kwargs)
        assert type(again) is type(agent) and again.progress_count == agent.progress_count


def test_format_1_records_are_read_as_the_system_record():
    apg = upgrade_meta({"algorithm": "APG", "system": "cartpole", "system_overrides": {"dt": 0.01},
                        "plant": {"name": "cartpole", "overrides": {"dt": 0.01, "reward__kind": "x"},
                                  "spec_hash": "abc", "spec_values": {}}, "config": {}})
    assert apg["system"] == {"name": "cartpole", "overrides": {"dt": 0.01}, "spec_hash": "abc", "spec_values": {}}
    assert "plant" not in apg and "system_overrides" not in apg
    ars = upgrade_meta({"algorithm": "ARS", "env": "Pendulum-v1", "env_kwargs": None, "config": {}})
    assert ars["system"] == {"name": "Pendulum-v1", "kind": "gymnasium", "kwargs": {}} and "env" not in ars


def test_learn_refuses_a_bad_total_and_a_backend_it_cannot_use():
    agent = SAC("pendulum", num_envs=2, hidden_size=8)
    with pytest.raises(ValueError, match=r"total \(total_steps\) must be an integer >= 1, got 0"):
        agent.learn(0)
    with pytest.raises(ValueError, match="runs no parallel rollouts"):
        agent.learn(10, backend=object())
    with pytest.raises(ValueError, match="episodes must be an integer >= 1"):
        agent.evaluate(0)
    with pytest.raises(TypeError):
        agent.learn(10, "runs/x")            # out is keyword-only
    with pytest.raises(ValueError, match="not a SACConfig field"):
        SAC.load("nowhere", nonsense=1)
