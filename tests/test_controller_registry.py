"""Every checkpoint becomes a controller through the learner contract (issue 48 item 2).

A toy learner defined and registered in this file alone (no edit anywhere else) is used through
``simulate_and_write``, the torch balance map, fine-tuning and ``hybridctl train toy``; every shipped checkpoint loads through
``hybridctl.learn.load_controller`` into the SwitchedController the loaders built before the registry.
"""

from __future__ import annotations

import copy
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch

from hybridctl import experiments, systems
from hybridctl.experiments.controllers import controller_parts
from hybridctl.learn import SSAC, CheckpointError, FineTune, Learner, load_controller, registered_learners
from hybridctl.learn import checkpoint as ckpt
from hybridctl.learn.checkpoint import PROGRESS_FILE, Saved
from hybridctl.learn.gate import GateNet
from hybridctl.learn.networks import Actor, DeterministicPolicy, ObsTransform
from hybridctl.learn.registry import checkpoint_kinds, register_learner
from hybridctl.learn.run import EvalResult
from hybridctl.systems.switched import (CostToGoGate, LearnedGate, NeverGate, SwitchedController,
                                        closed_loop_rollout)

ROOT = Path(__file__).resolve().parents[1]
POLICIES = ROOT / "models" / "policies"


# ---------------------------------------------------------------------------------- a toy learner
@dataclass
class ToyConfig:
    gain: float = 2.0
    epochs: int = 1
    seed: int = 0

    def validate(self) -> None:     # what `hybridctl train` asks of a config: its checks, and its budget in words
        if not self.epochs >= 1:
            raise ValueError(f"ToyConfig.epochs must be >= 1, got {self.epochs!r}")

    def describe_budget(self) -> str:
        return f"{self.epochs} epochs"


class LinearSwingup(torch.nn.Module):
    """u = W x (float64), in the caller's dtype."""

    def __init__(self, n: int, m: int, gain: float):
        super().__init__()
        self.linear = torch.nn.Linear(n, m, bias=False, dtype=torch.float64)
        with torch.no_grad():
            self.linear.weight.copy_(gain * torch.linspace(-1.0, 1.0, n * m, dtype=torch.float64).reshape(m, n))

    def forward(self, x):
        x = torch.as_tensor(x)
        return self.linear(x.to(torch.float64)).to(x.dtype if x.is_floating_point() else torch.float64)


class Toy(Learner):
    """A linear swing-up under the spec's cost-to-go gate; ``learn`` doubles its weights per epoch."""

    algorithm_name = "TOY"          # registers it: checkpoints whose config.json says "TOY" load with Toy.load
    config_class = ToyConfig
    budget_field, unit, log_key, log_columns = "epochs", "epoch", "epoch", ("epoch",)
    saved = (Saved("swingup", "swingup", "state"), Saved("epoch", "epoch", file=PROGRESS_FILE, load=int))

    def __init__(self, system, config: ToyConfig | None = None):
        self.system = systems.load(system) if isinstance(system, str) else system
        self.config = config or ToyConfig()
        self.swingup = LinearSwingup(self.system.n_states, self.system.n_actions, self.config.gain)
        self.epoch, self.log_rows, self.wall_time = 0, [], 0.0

    @property
    def progress_count(self) -> int:
        return self.epoch

    def train(self, run, target, backend):
        while self.epoch < target and not run.stopped:
            with torch.no_grad():
                self.swingup.linear.weight.mul_(2.0)
            self.epoch += 1
            run.log({"epoch": self.epoch})
            run.advance(1)

    @classmethod
    def from_checkpoint(cls, found, meta, config, system, force):
        record = meta["system"]
        return cls(system or ckpt.recorded_system(found, record["name"], record.get("overrides", {})), config)

    def run_evaluation(self, episodes, seed, **options):
        """Returns: minus the final distance to the goal after 2 s from the spec's starts (no success test)."""
        starts = torch.as_tensor(self.system.sample_initial_states(episodes, np.random.default_rng(seed)))
        controller = self.controller()
        steps = round(2.0 / controller.decision_period)
        final = closed_loop_rollout(self.system, controller, starts, steps).final
        return EvalResult.from_returns((-self.system.state_error(final).norm(dim=1)).tolist(), None,
                                       first={"episodes": episodes})

    def controller(self, system=None) -> SwitchedController:
        system = self.system if system is None else system
        return SwitchedController.for_system(system, swingup=copy.deepcopy(self.swingup).eval(),
                                             gate=CostToGoGate(system))


@pytest.fixture(scope="module")
def toy(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("toy") / "toy"
    Toy("pendulum").save(path)
    return path


def test_the_toy_learner_registered_itself():
    assert registered_learners()["TOY"] is Toy
    assert "toy" in checkpoint_kinds()
    assert {"SAC", "SSAC", "APG", "ARS", "FineTune"} <= set(registered_learners())


def test_the_toy_checkpoint_is_a_controller(toy):
    pendulum = systems.load("pendulum")
    controller = load_controller(toy, pendulum)
    assert isinstance(controller, SwitchedController) and isinstance(controller.gate, CostToGoGate)
    assert isinstance(controller.swingup, LinearSwingup)
    assert load_controller(toy, pendulum, gate="never").gate.__class__ is NeverGate
    with pytest.raises(ValueError, match="without a learned gate"):
        load_controller(toy, pendulum, gate="learned")
    with pytest.raises(CheckpointError, match="trained on system 'pendulum', but this system is 'acrobot'"):
        load_controller(toy, systems.load("acrobot"))


def test_the_toy_checkpoint_simulates_in_drake(toy, tmp_path):
    summary = experiments.simulate_and_write("pendulum", f"toy:{toy}", tmp_path / "sim", duration=1.0, html=False)
    assert (tmp_path / "sim" / "trajectory.npz").is_file() and "balanced" in json.dumps(summary)
    # the generic kind names no learner
    experiments.simulate_and_write("pendulum", f"checkpoint:{toy}", tmp_path / "sim2", duration=1.0, html=False)


def test_the_toy_checkpoint_makes_a_torch_balance_map(toy):
    result = experiments.balance_map("pendulum", f"toy:{toy}", grid=3, duration=1.0, engine="torch", progress=False)
    assert result.balanced.shape == (3, 3)
    again = experiments.balance_map("pendulum", f"checkpoint:{toy}", grid=3, duration=1.0, engine="torch",
                                    progress=False)
    np.testing.assert_array_equal(result.balanced, again.balanced)


def test_the_toy_checkpoint_fine_tunes_and_its_result_is_a_controller(toy, tmp_path):
    tuner = FineTune("pendulum", f"toy:{toy}", updates=2, n_directions=2, episode_steps=20, backend="serial",
                     eval_episodes=2, chunk_size=2)
    assert isinstance(tuner.tunable.gate, CostToGoGate) and tuner.tunable.meta["trained_algorithm"] == "TOY"
    tuner.learn(out=tmp_path / "ft", progress=False)
    assert tuner.update == 2 and not np.array_equal(tuner.theta, tuner.theta0)
    pendulum = systems.load("pendulum")
    tuned = load_controller(tmp_path / "ft", pendulum)             # a FineTune checkpoint, through the registry
    assert isinstance(tuned.gate, CostToGoGate)
    assert not torch.equal(tuned.swingup.linear.weight, load_controller(toy, pendulum).swingup.linear.weight)
    parts = controller_parts(pendulum, f"finetune:{tmp_path / 'ft'}")
    assert torch.equal(parts.swingup.linear.weight, tuned.swingup.linear.weight)


def test_an_unregistered_algorithm_and_a_learner_without_a_swingup_say_so(toy, tmp_path):
    import shutil
    other = tmp_path / "other"
    shutil.copytree(toy, other)
    meta = json.loads((other / "config.json").read_text())
    meta["algorithm"] = "NOPE"
    (other / "config.json").write_text(json.dumps(meta))
    with pytest.raises(CheckpointError, match=r"no learner is registered for algorithm 'NOPE'; registered: .*SSAC"):
        load_controller(other, systems.load("pendulum"))
    with pytest.raises(CheckpointError, match="ARS checkpoints hold no swing-up"):
        load_controller(POLICIES / "ars-hopper", systems.load("pendulum"))


def test_the_toy_learner_trains_from_the_command_line(tmp_path, capsys):
    """Registering it made it a `hybridctl train` sub-command: its config's fields are flags, the run writes
    final/ and eval.json, and the checkpoint is a controller."""
    from hybridctl.cli import main
    from hybridctl.experiments import training_algorithms

    assert training_algorithms()["toy"] is Toy and "finetune" not in training_algorithms()
    with pytest.raises(SystemExit):
        main(["train", "--help"])
    assert "toy" in capsys.readouterr().out
    out = tmp_path / "run"
    assert main(["train", "toy", "pendulum", "--epochs", "2", "--gain", "0.5", "--eval-episodes", "3",
                 "--out", str(out), "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "deterministic return over 3 episodes" in printed and "no success test" in printed
    record = json.loads((out / "eval.json").read_text())
    assert record["episodes"] == 3 and record["epoch"] == 2
    trained = Toy.load(out / "final")
    assert torch.equal(trained.swingup.linear.weight, LinearSwingup(2, 1, 0.5 * 4).linear.weight)   # doubled twice
    assert isinstance(load_controller(out, systems.load("pendulum")).swingup, LinearSwingup)


def test_a_taken_algorithm_name_is_refused():
    class Impostor(Learner):
        pass
    with pytest.raises(ValueError, match="'SSAC' is registered to hybridctl.learn.ssac.SSAC"):
        register_learner("SSAC", Impostor)
    assert registered_learners()["SSAC"] is SSAC


# ------------------------------------------------------------------- every shipped checkpoint
def _shipped():
    out = []
    for folder in sorted(POLICIES.iterdir()):
        if (folder / "config.json").is_file():
            meta = json.loads((folder / "config.json").read_text())
            if registered_learners()[meta["algorithm"]].drives_systems():
                out.append(folder.name)
    return out


def _system_of(folder: Path):
    record = json.loads((folder / "config.json").read_text())["system"]
    if isinstance(record, str):
        return systems.load(record)
    overrides = {k: v for k, v in (record.get("overrides") or {}).items() if not k.startswith("reward")}
    return systems.load(record["name"], **overrides)


def _ssac_as_before(folder: Path, system) -> SwitchedController:
    """What hybridctl.learn.export.load_controller and experiments' ssac: branch built before the registry:
    the actor from config.json's sizes and model.pt's 'actor', the gate from 'extra.gate', the hysteresis
    from config.json's 'gate'."""
    meta = json.loads((folder / "config.json").read_text())
    cfg, model = meta["config"], torch.load(folder / "model.pt", weights_only=True)
    actor = Actor(ObsTransform(cfg.get("obs_transform", "none"), meta["obs_dim"], system.angle_indices),
                  meta["action_dim"], torch.as_tensor(meta["action_scale"], dtype=torch.float32),
                  cfg["hidden_layers"], cfg["hidden_size"], cfg.get("log_std_min", -20.0), cfg.get("log_std_max", 2.0))
    actor.load_state_dict(model["actor"])
    gate = GateNet(system, tuple(meta["gate"]["hidden"]), cost_feature=bool(cfg.get("gate_cost_feature", True)))
    gate.load_state_dict(model["extra"]["gate"])
    gate.eval()
    return SwitchedController.for_system(system, swingup=DeterministicPolicy(actor), gate=LearnedGate(gate),
                                         gate_on=meta["gate"]["gate_on"], gate_off=meta["gate"]["gate_off"])


def _apg_as_before(folder: Path, system) -> SwitchedController:
    from hybridctl.learn import APG
    agent = APG.load(folder, device="cpu")
    return SwitchedController.for_system(system, swingup=agent.closed_loop_policy(), gate=CostToGoGate(system),
                                         decision_period=agent.period)


@pytest.mark.parametrize("name", _shipped())
def test_every_shipped_checkpoint_is_the_controller_it_was(name):
    folder = POLICIES / name
    system = _system_of(folder)
    algorithm = json.loads((folder / "config.json").read_text())["algorithm"]
    new = load_controller(folder, system)
    old = (_ssac_as_before if algorithm == "SSAC" else _apg_as_before)(folder, system)
    assert type(new.gate) is type(old.gate) and type(new.swingup) is type(old.swingup)
    for field in ("K", "goal"):
        np.testing.assert_array_equal(getattr(new, field), getattr(old, field))
    for field in ("decision_period", "gate_on", "gate_off", "gate_period"):
        assert getattr(new, field) == getattr(old, field), field
    rng = np.random.default_rng(0)
    starts = system.initial_state.nominal[None] + rng.normal(0.0, 0.3, (4, system.n_states))
    steps = int(round(1.0 / new.decision_period))
    a = closed_loop_rollout(system, new, starts, steps)
    b = closed_loop_rollout(system, old, starts, steps)
    assert torch.equal(a.states, b.states)


@pytest.mark.parametrize("kind, name", [("ssac", "ssac-acrobot"), ("ce-apg", "ceapg-gru-acrobot")])
def test_one_torch_balance_map_per_algorithm_runs_the_named_controller(kind, name):
    """The named controller (``KIND:PATH``) and ``load_controller`` are one controller: the torch balance map
    of the name equals closed_loop_rollout of the loaded object."""
    folder = POLICIES / name
    system = _system_of(folder)
    result = experiments.balance_map(system, f"{kind}:{folder}", grid=2, duration=1.0, engine="torch",
                                     progress=False)
    assert result.balanced.shape == (2, 2)
    sac = controller_parts(system, f"sac:{folder}")
    costgate = controller_parts(system, f"ssac-costgate:{folder}")
    assert isinstance(sac.gate, NeverGate) and isinstance(costgate.gate, CostToGoGate)


def test_a_registered_learner_without_a_config_dataclass_is_no_train_sub_command():
    """A learner registered without a config dataclass (tests/test_run.py's COUNTER) trains from Python only;
    `hybridctl train` lists the others and still builds its parser (it crashed on one such learner)."""
    from hybridctl.cli import main
    from hybridctl.learn.registry import _LEARNERS, trainable_learners

    class Bare(Learner):
        pass
    _LEARNERS["BARE"] = Bare
    try:
        assert "bare" not in trainable_learners() and "toy" in trainable_learners()
        with pytest.raises(SystemExit) as done:
            main(["train", "--help"])
        assert done.value.code == 0
    finally:
        del _LEARNERS["BARE"]
