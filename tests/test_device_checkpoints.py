"""A run trained on a GPU loads on a machine without one when the caller names another device; the
Drake controllers load every checkpoint onto the CPU (before: the recorded device was checked
against this machine before the caller's device applied, so a CUDA checkpoint never loaded here)."""

import json

import pytest
import torch

from hybridctl.learn import APG
from hybridctl.learn.apg import APGConfig
from hybridctl.learn.checkpoint import CheckpointError, config_from_meta
from hybridctl.learn.sac import SACConfig

pytestmark = pytest.mark.skipif(torch.cuda.is_available(), reason="checks a CUDA checkpoint on a machine without CUDA")


def test_a_recorded_cuda_device_is_replaced_by_the_callers_device():
    meta = {"config": {"device": "cuda:0", "seed": 4}}
    with pytest.raises(CheckpointError, match="CUDA is not available here"):
        config_from_meta(SACConfig, meta)
    config = config_from_meta(SACConfig, meta, {"device": "cpu"})
    assert config.device == "cpu" and config.seed == 4


def test_a_cuda_apg_checkpoint_loads_on_the_cpu_and_into_drake(tmp_path):
    from hybridctl.experiments.controllers import controller_parts
    from hybridctl.systems import System  # noqa: F401  (the controller resolves the system by name)
    config = APGConfig(method="papg", epochs=1, population=2, elites=1, batch=2, horizon=20, apg_iterations=1,
                       seed=3, backend="serial", compile=False, eval_episodes=2)
    agent = APG("cartpole", config)
    agent.learn(out=tmp_path / "run", progress=False)
    path = tmp_path / "run" / "final" / "config.json"
    meta = json.loads(path.read_text())
    meta["config"]["device"] = "cuda"                  # as a GPU run records it
    path.write_text(json.dumps(meta))
    with pytest.raises(CheckpointError, match="device"):
        APG.load(tmp_path / "run" / "final")
    assert APG.load(tmp_path / "run" / "final", device="cpu").config.device == "cpu"
    parts = controller_parts(agent.system, f"papg:{tmp_path / 'run' / 'final'}")
    assert next(parts.swingup.parameters()).device.type == "cpu"
