"""A damaged or hostile checkpoint is one line naming the file and key, never a traceback (issue 29).

Copies of the shipped checkpoints (``models/policies/ssac-acrobot``, ``papg-cartpole``; never
modified) are damaged one key at a time and loaded the four ways a user loads them: ``SSAC.load``,
``load_controller``, ``APG.load`` and the named controllers of ``hybridctl simulate``. Every
case is a row of a table; the fuzz table mutates every key of the JSON files with the values an
adversary tries. The shape checks all live in :data:`hybridctl.learn.checkpoint.SCHEMAS`.
"""

from __future__ import annotations

import json
import math
import re
import shutil
import warnings
from pathlib import Path

import pytest
import torch

from hybridctl import systems
from hybridctl.experiments.controllers import controller_parts
from hybridctl.learn import APG, SSAC, CheckpointError, load_controller
from hybridctl.learn.checkpoint import SCHEMAS

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = {"ssac": ROOT / "models" / "policies" / "ssac-acrobot", "papg": ROOT / "models" / "policies" / "papg-cartpole"}
SYSTEM_OF = {"ssac": "acrobot", "papg": "cartpole"}
NAN = float("nan")


def copy_of(kind: str, tmp_path: Path) -> Path:
    """A copy of a shipped checkpoint (its files only) that a test may damage."""
    out = tmp_path / kind
    shutil.copytree(SHIPPED[kind], out, ignore=shutil.ignore_patterns("*.png", "*.md", "*.csv"))
    return out


def edit_json(path: Path, key: str | None, value) -> None:
    """Set ``key`` ('a.b': b inside a; None: the whole document) of the JSON file at ``path``."""
    if key is None:
        path.write_text(json.dumps(value))
        return
    doc = json.loads(path.read_text())
    parts = key.split(".")
    target = doc
    for part in parts[:-1]:
        target = target[part]
    target[parts[-1]] = value
    path.write_text(json.dumps(doc))


def edit_tensor(path: Path, key: str, value: float) -> None:
    """Fill the tensor at ``key`` of a torch file with ``value``: 'extra.gate.net.0.weight' is the state
    dict entry 'net.0.weight' of ``content['extra']['gate']``."""
    content = torch.load(path, weights_only=True)
    target, rest = content, key
    while rest not in target:
        head, rest = rest.split(".", 1)
        target = target[head]
    target[rest] = torch.full_like(target[rest], value)
    torch.save(content, path)


def load(kind: str, path: Path, how: str):
    """Load the checkpoint at ``path`` one of the ways a user does."""
    system = systems.load(SYSTEM_OF[kind])
    if how == "load":
        return SSAC.load(path) if kind == "ssac" else APG.load(path)
    if how == "load_controller":
        return load_controller(path, system)
    return controller_parts(system, f"{kind}:{path}")


# ---------------------------------------------------------------- the cases, each loaded every way
# (kind, file, key or None for the whole file, value, message)
CONFIG_CASES = [
    ("ssac", "config.json", None, [], r"config\.json is damaged: expected an object \{\.\.\.\}, got a list"),
    ("ssac", "config.json", None, None, r"config\.json is damaged: expected an object \{\.\.\.\}, got null"),
    ("ssac", "config.json", None, "SSAC", r"config\.json is damaged: expected an object \{\.\.\.\}, got a string"),
    ("ssac", "config.json", "algorithm", 5, r"config\.json: 'algorithm' must be a string, got 5"),
    ("ssac", "config.json", "config", [], r"config\.json: 'config' must be an object"),
    ("ssac", "config.json", "system", "acrobot", r"config\.json: 'system' must be an object"),
    ("ssac", "config.json", "system.overrides", [], r"config\.json: 'system\.overrides' must be an object"),
    ("ssac", "config.json", "system.name", "../../evil", r"config\.json: 'system\.name' must be a system name"),
    ("ssac", "config.json", "gate", "x", r"config\.json: 'gate' must be an object"),
    ("ssac", "config.json", "gate.hidden", [10 ** 9], r"config\.json: 'gate\.hidden' must be a list of 1 to 64"),
    ("ssac", "config.json", "config.num_envs", 1e12, r"config\.json: 'config\.num_envs' must be an integer in \[1, 1,000,000\]"),
    ("ssac", "config.json", "config.hidden_size", 1e308, r"config\.json: 'config\.hidden_size' must be an integer in \[1, 65536\]"),
    ("ssac", "config.json", "config.log_std_min", None, r"config\.json: 'config\.log_std_min' must be a finite number"),
    ("ssac", "config.json", "obs_dim", NAN, r"config\.json: 'obs_dim' must be an integer"),
    ("ssac", "progress.json", "env_steps", 1e300, r"progress\.json: 'env_steps' must be an integer in \[0, 2\*\*53\]"),
    ("ssac", "normalization.json", None, [], r"normalization\.json is damaged: expected an object"),
    ("papg", "config.json", "plant", "x", r"config\.json: 'plant' must be an object"),
    ("papg", "config.json", "system", "../../evil", r"config\.json: 'system' must be a system record"),
    ("papg", "config.json", "system_overrides", [], r"config\.json: 'system_overrides' must be an object"),
    ("papg", "config.json", "config", None, r"config\.json: 'config' must be an object"),
    ("papg", "config.json", "policy.hidden", "x", r"config\.json: 'policy\.hidden' must be a list"),
    ("papg", "normalization.json", "mean", [NAN], r"normalization\.json: 'mean' must be a list of finite numbers"),
    # issue 47: sizes are checked against stated limits before anything is allocated
    ("ssac", "config.json", "config.hidden_size", 65536,
     r"config\.json: 'obs_dim', 'action_dim', 'config\.hidden_layers' x 'config\.hidden_size' describe a network of "
     r"[\d,]+ parameters .*MAX_NETWORK_PARAMETERS"),
    ("ssac", "config.json", "obs_dim", 2 ** 52, r"config\.json: .* describe a network of [\d,]+ parameters"),
    ("ssac", "config.json", "gate.hidden", [65536] * 64, r"config\.json: 'obs_dim', 'gate\.hidden' describe a network"),
    ("ssac", "config.json", "system.recorded", "x" * 5000,
     r"config\.json: 'system\.recorded' is a string of 5,000 characters, above the limit of 4,096"),
    ("papg", "config.json", "policy.hidden", [65536] * 64,
     r"config\.json: 'policy\.obs_dim', 'policy\.hidden', 'policy\.act_dim' describe a network"),
    ("papg", "config.json", "policy.n_params", 2 ** 40, r"config\.json: 'policy\.n_params' describe a network"),
]
LOADERS = {"ssac": ("load", "load_controller", "parts"), "papg": ("load", "parts")}


def _case_rows(cases):
    return [(how, *case) for case in cases for how in LOADERS[case[0]]
            # load_controller (also behind ssac:PATH) deploys a policy: it does not read progress.json
            if not (case[0] == "ssac" and how != "load" and case[1] == "progress.json")]


@pytest.mark.parametrize("how, kind, name, key, value, message", _case_rows(CONFIG_CASES),
                         ids=[f"{h}:{k}:{n}:{key}={v!r}" for h, k, n, key, v, _ in _case_rows(CONFIG_CASES)])
def test_a_damaged_json_file_is_refused_naming_the_file_and_key(tmp_path, how, kind, name, key, value, message):
    path = copy_of(kind, tmp_path)
    edit_json(path / name, key, value)
    with pytest.raises(CheckpointError, match=message) as info:
        load(kind, path, how)
    assert str(path / name) in str(info.value) and "\n" not in str(info.value)


# (kind, file, tensor key, value, message)
TENSOR_CASES = [
    ("ssac", "model.pt", "actor.net.0.weight", NAN, r"model\.pt: tensor 'actor\.net\.0\.weight' holds NaN or Inf"),
    ("ssac", "model.pt", "extra.gate.net.0.weight", math.inf, r"model\.pt: tensor 'extra\.gate\.net\.0\.weight' holds"),
    ("ssac", "model.pt", "q1.net.0.bias", -math.inf, r"model\.pt: tensor 'q1\.net\.0\.bias' holds NaN or Inf"),
    ("papg", "model.pt", "best", NAN, r"model\.pt: tensor 'best' holds NaN or Inf"),
]


@pytest.mark.parametrize("kind, name, key, value, message", TENSOR_CASES, ids=[f"{c[0]}:{c[2]}={c[3]}" for c in TENSOR_CASES])
def test_non_finite_weights_are_refused_at_load_naming_the_file_and_tensor(tmp_path, kind, name, key, value, message):
    path = copy_of(kind, tmp_path)
    edit_tensor(path / name, key, value)
    for how in LOADERS[kind]:
        with pytest.raises(CheckpointError, match=message):
            load(kind, path, how)


class Payload:
    """A pickled object torch's weights-only loader refuses (it never runs)."""

    def __reduce__(self):
        return (print, ("this must never run",))


def _pickled(path: Path) -> None:
    torch.save({"actor": Payload()}, path)


def _truncated(path: Path) -> None:
    path.write_bytes(path.read_bytes()[:1000])


def _not_torch(path: Path) -> None:
    path.write_bytes(b"\x00\x01 not a torch file")


FILE_CASES = [
    ("pickled", _pickled, r"model\.pt holds pickled Python objects, which hybridctl refuses to load"),
    ("truncated", _truncated, r"could not read .*model\.pt: it is damaged or not a torch file"),
    ("not a torch file", _not_torch, r"could not read .*model\.pt: it is damaged or not a torch file"),
]


@pytest.mark.parametrize("name, damage, message", FILE_CASES, ids=[c[0] for c in FILE_CASES])
def test_a_damaged_or_pickled_model_file_is_one_line_without_unpickling_advice(tmp_path, capsys, name, damage, message):
    path = copy_of("ssac", tmp_path)
    damage(path / "model.pt")
    for how in LOADERS["ssac"]:
        with pytest.raises(CheckpointError, match=message) as info:
            load("ssac", path, how)
        assert "weights_only" not in str(info.value) and "\n" not in str(info.value)
    assert "this must never run" not in capsys.readouterr().out


# ---------------------------------------------------------------- the command line: exit 2, one line
CLI_CASES = [
    (["simulate", "acrobot", "--controller", "ssac:{ckpt}"], "config.json", "gate", "x", "'gate' must be an object"),
    (["simulate", "acrobot", "--controller", "ssac:{ckpt}"], "config.json", None, None, "config.json is damaged"),
    (["simulate", "acrobot", "--controller", "ssac:{ckpt}"], "model.pt", "extra.gate.net.0.weight", math.inf,
     "tensor 'extra.gate.net.0.weight' holds NaN or Inf"),
    (["simulate", "acrobot", "--controller", "ssac:{ckpt}"], "model.pt", "actor.net.0.weight", NAN,
     "tensor 'actor.net.0.weight' holds NaN or Inf"),
    (["simulate", "cartpole", "--controller", "papg:{ckpt}"], "config.json", "plant", "x", "'plant' must be an object"),
    (["train", "ssac", "acrobot", "--resume", "--out", "{run}", "--steps", "16", "--quiet"], "config.json",
     "system.overrides", [], "'system.overrides' must be an object"),
    (["train", "ssac", "acrobot", "--resume", "--out", "{run}", "--steps", "16", "--quiet"], "config.json",
     "config.num_envs", 1e12, "'config.num_envs' must be an integer"),
    (["train", "ssac", "acrobot", "--resume", "--out", "{run}", "--steps", "16", "--quiet"], "progress.json",
     "env_steps", 1e300, "'env_steps' must be an integer"),
    (["train", "ssac", "acrobot", "--resume", "--out", "{run}", "--steps", "16", "--quiet"], "model.pt",
     "extra.gate.net.0.weight", math.inf, "holds NaN or Inf"),
]


@pytest.mark.parametrize("argv, name, key, value, message", CLI_CASES,
                         ids=[f"{a[0]}:{n}:{k}={v!r}" for a, n, k, v, _ in CLI_CASES])
def test_the_cli_names_the_damaged_file_in_one_line(tmp_path, cli_error, argv, name, key, value, message):
    kind = "papg" if any("papg:" in a for a in argv) else "ssac"
    run = tmp_path / "run"
    path = copy_of(kind, tmp_path)
    if argv[0] == "train":  # a run folder whose final/ is the damaged checkpoint
        run.mkdir()
        path = path.rename(run / "final")
    (edit_tensor if name.endswith(".pt") else edit_json)(path / name, key, value)
    argv = [a.replace("{ckpt}", str(path)).replace("{run}", str(run)) for a in argv]
    if argv[0] == "simulate":
        argv += ["--duration", "0.1", "--out", str(tmp_path / "out")]
    err = cli_error(argv)
    assert message in err and len(err.strip().splitlines()) == 1, err


# ---------------------------------------------------------------- the fuzz: every key, every hostile value
HOSTILE = [[], {}, None, "x", 5, 1e308, NAN]


def _keys(doc: dict, prefix: str = ""):
    for key, value in doc.items():
        yield prefix + key
        if isinstance(value, dict) and key != "spec_values":
            yield from _keys(value, f"{prefix}{key}.")


def _fuzz_rows():
    rows = []
    for kind in ("ssac", "papg"):
        for name in SCHEMAS:
            doc = json.loads((SHIPPED[kind] / name).read_text())
            # one hostile value per key, taken in turn, so that every value meets many keys
            rows += [(kind, name, key, HOSTILE[i % len(HOSTILE)]) for i, key in enumerate(_keys(doc))]
    return rows


FUZZ_CASES = _fuzz_rows()


@pytest.mark.parametrize("kind, name, key, value", FUZZ_CASES, ids=[f"{k}:{n}:{key}={v!r}" for k, n, key, v in FUZZ_CASES])
def test_every_key_set_to_a_hostile_value_loads_or_raises_the_documented_error(tmp_path, kind, name, key, value):
    """The Python API raises CheckpointError or ValueError (one line), or loads; nothing else escapes."""
    path = copy_of(kind, tmp_path)
    edit_json(path / name, key, value)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for how in ("load", "parts"):
            try:
                load(kind, path, how)
            except (CheckpointError, ValueError) as exc:
                assert "\n" not in str(exc) and str(exc), (how, exc)


def test_the_fuzz_covers_every_key_and_value():
    """Every key of the shipped checkpoints' JSON files is fuzzed, and every hostile value is used."""
    assert len(FUZZ_CASES) > 150
    assert {repr(v) for *_, v in FUZZ_CASES} == {repr(v) for v in HOSTILE}


def test_the_shipped_checkpoints_pass_the_schema_and_the_finite_check():
    """The checks refuse damage, not the checkpoints we ship."""
    for kind, path in SHIPPED.items():
        for how in LOADERS[kind]:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                assert load(kind, path, how) is not None


def test_error_text_is_one_line_even_when_wrapping_a_multi_line_error():
    assert str(CheckpointError("a.pt: does not fit\n  Missing key(s): x\n  Unexpected: y")) == \
        "a.pt: does not fit; Missing key(s): x; Unexpected: y"
    assert re.fullmatch(r"plain", str(CheckpointError("plain")))


# ---------------------------------------------------------------- a run too short to learn says so
def test_a_run_within_exploration_steps_says_it_makes_no_gradient_step():
    from hybridctl.learn import SAC, SACConfig
    assert SACConfig(total_steps=50_001).exploration_note() is None
    note = SACConfig(total_steps=20_000).exploration_note()
    assert "20,000 env steps" in note and "exploration_steps (50,000)" in note and "no gradient step" in note
    agent = SAC("acrobot", num_envs=8, exploration_steps=400, steps_per_update=200, updates_per_round=1,
                replay_batch_size=128, minibatch_size=64, buffer_size=2_000, needle_buffer_size=2_000,
                tensorboard=False)
    with pytest.warns(UserWarning, match=r"16 env steps are no more than exploration_steps \(400\)"):
        agent.learn(total=16, progress=False)
    assert agent.num_gradient_steps == 0


# ------------------------------------------------ issue 47: sizes, files and env settings from a checkpoint
def test_a_network_of_64_layers_of_65536_units_is_refused_before_it_is_built(tmp_path, cli_error):
    path = copy_of("ssac", tmp_path)
    meta = json.loads((path / "config.json").read_text())
    meta["config"].update(hidden_layers=64, hidden_size=65536)
    (path / "config.json").write_text(json.dumps(meta))
    err = cli_error(["simulate", "acrobot", "--controller", f"ssac:{path}", "--duration", "0.1",
                     "--out", tmp_path / "out"])
    assert "describe a network of 270,587,592,706 parameters" in err and len(err.strip().splitlines()) == 1, err


@pytest.mark.parametrize("what", ["device", "fifo", "folder"])
def test_a_checkpoint_file_that_is_not_a_regular_file_is_never_opened(tmp_path, what):
    from hybridctl.learn.checkpoint import load_tensors, read_json
    import os
    path = copy_of("ssac", tmp_path)
    for name in ("progress.json", "model.pt"):
        (path / name).unlink()
        if what == "device":
            (path / name).symlink_to("/dev/zero")
        elif what == "fifo":
            os.mkfifo(path / name)
        else:
            (path / name).mkdir()
    with pytest.raises(CheckpointError, match=r"progress\.json is not a regular file \(a device, a FIFO or a folder\)"):
        read_json(path / "progress.json")
    with pytest.raises(CheckpointError, match=r"model\.pt is not a regular file"):
        load_tensors(path / "model.pt")
    with pytest.raises(CheckpointError):
        SSAC.load(path)


def test_a_model_file_above_its_limit_is_refused_before_it_is_read(tmp_path, monkeypatch):
    import hybridctl.learn.checkpoint as ckpt
    path = copy_of("ssac", tmp_path)
    monkeypatch.setattr(ckpt, "MAX_CHECKPOINT_FILE_BYTES", 1000)
    with pytest.raises(CheckpointError, match=r"model\.pt has [\d,]+ bytes, above the limit of 1,000"):
        ckpt.load_tensors(path / "model.pt")


ENV_KWARGS_CASES = [
    ({"render_mode": "human"}, r"system\.kwargs\.'render_mode' is \"human\"; a recorded env renders as null or "
                               r"'rgb_array' only"),
    ({"render_mode": 3}, r"'render_mode' is 3"),
    ({"autoreset": True}, r"'autoreset': not a keyword argument a recorded env may set"),
    ({"max_episode_steps": 10 ** 12}, r"'max_episode_steps' is 1000000000000, not a value gymnasium.make accepts"),
    ({"xml_file": "/dev/zero"}, r"'xml_file' is \"/dev/zero\", not a regular file"),
    ({"ctrl_cost_weight": {"nested": 1}}, r"'ctrl_cost_weight' must be null, true/false, a finite number"),
    ({"ctrl_cost_weight": NAN}, r"'ctrl_cost_weight' must be null"),
    ({f"k{i}": 1 for i in range(65)}, r"has 65 keyword arguments, above the limit of 64"),
]


@pytest.mark.parametrize("kwargs, message", ENV_KWARGS_CASES, ids=[str(k)[:40] for k, _ in ENV_KWARGS_CASES])
def test_recorded_env_kwargs_are_known_keys_and_plain_values(kwargs, message):
    from hybridctl.learn.rollout_envs import recorded_env_kwargs
    with pytest.raises(CheckpointError, match=message):
        recorded_env_kwargs(kwargs, "config.json", "system.kwargs")
    assert recorded_env_kwargs({"render_mode": "rgb_array", "ctrl_cost_weight": 1e-3}, "c", "k") is not None
    assert recorded_env_kwargs(None, "c", "k") is None


def test_ars_init_from_a_checkpoint_asking_for_a_window_is_refused_in_one_line(tmp_path, cli_error):
    pytest.importorskip("mujoco")
    init = tmp_path / "ars-hopper"
    shutil.copytree(ROOT / "models" / "policies" / "ars-hopper", init, ignore=shutil.ignore_patterns("*.md"))
    edit_json(init / "config.json", "env_kwargs", {"render_mode": "human"})
    err = cli_error(["train", "ars", "Hopper-v5", "--init", init, "--epochs", "1", "--out", tmp_path / "run"])
    assert "'render_mode' is \"human\"; a recorded env renders as null or 'rgb_array' only" in err, err
    assert len(err.strip().splitlines()) == 1
