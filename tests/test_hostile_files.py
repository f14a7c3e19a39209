"""A file from someone else is data, never code (issue 29 items 1, 2, the SB3 parts of 4 and 5, item 7).

- env ids recorded in a checkpoint's config.json never import a module (``"module:Env"``);
- SB3 zips are read entry by entry with bounds (zip bombs), their tensors, JSON fields and class
  names checked at load, and zips we write are rebuilt from what was parsed: a planted pickle
  payload does not survive into our output, so SB3's own ``load`` of our output never runs it;
- SB3 builds our envs by id (``render_mode="rgb_array"``).

Each bad input is a row of a ``*_CASES`` table: the Python API raises the documented
:class:`CheckpointError`, the CLI prints one line and exits 2 (the ``cli_error`` fixture).
"""

from __future__ import annotations

import base64
import io
import json
import pickle
import sys
import tracemalloc
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

from hybridctl import limits
from hybridctl.learn.checkpoint import CheckpointError

pytestmark = pytest.mark.usefixtures("one_torch_thread")

FAST_FINETUNE = ["--updates", "1", "--directions", "2", "--eval-episodes", "2", "--episode-steps", "20",
                 "--backend", "serial", "--quiet"]


def _one_line(text: str) -> bool:
    return text.strip().count("\n") == 0


# ============================================================================ env ids from config.json

class _Payload:
    """A module that, imported, writes a marker file (it stands for any code)."""

    def __init__(self, root: Path, name: str):
        self.package, self.marker = f"hostile_{name}", root / f"ran_{name}"
        folder = root / self.package
        folder.mkdir(parents=True)
        (folder / "__init__.py").write_text("")
        (folder / "payload.py").write_text(f"open({str(self.marker)!r}, 'w').close()\n")
        self.id = f"{self.package}.payload:Pendulum-v1"


@pytest.fixture
def payload(tmp_path, monkeypatch, request):
    """A payload package on sys.path (a fresh name per test, so no earlier import hides a run)."""
    made = _Payload(tmp_path / "plant", request.node.name.replace("[", "_").replace("]", "").replace("-", "_"))
    monkeypatch.syspath_prepend(str(made.marker.parent))
    yield made
    for name in [m for m in sys.modules if m.startswith(made.package)]:
        del sys.modules[name]


@pytest.fixture(scope="module")
def ars_run(tmp_path_factory):
    """An ARS checkpoint on Pendulum-v1 (final/) and a FineTune checkpoint of it (its final/)."""
    from hybridctl.learn import ARS, ARSConfig
    from hybridctl.learn.finetune import FineTune

    root = tmp_path_factory.mktemp("ars")
    ARS("Pendulum-v1", ARSConfig(n_directions=2, top_directions=1, backend="serial", episode_steps=20)
        ).learn(total=1, out=root / "ars", progress=False)
    FineTune("Pendulum-v1", f"ars:{root / 'ars' / 'final'}", updates=1, n_directions=2, backend="serial",
             episode_steps=20, eval_episodes=2).learn(out=root / "ft", progress=False)
    return root / "ars" / "final", root / "ft" / "final"


def _copy_with_config(src: Path, dst: Path, **changes) -> Path:
    """A copy of checkpoint ``src`` at ``dst`` whose config.json has ``changes`` applied."""
    dst.mkdir(parents=True)
    for file in src.iterdir():
        (dst / file.name).write_bytes(file.read_bytes())
    meta = json.loads((dst / "config.json").read_text())
    for key, value in changes.items():   # "a.b": b inside object a; DELETE removes the key
        *parents, last = key.split(".")
        where = meta
        for part in parents:
            where = where[part]
        if value is DELETE:
            where.pop(last, None)
        else:
            where[last] = value
    (dst / "config.json").write_text(json.dumps(meta))
    return dst


DELETE = object()


# (id, config.json changes ("PAYLOAD": the planted module's id), what the one-line error says)
ENV_ID_CASES = [
    ("module-part", {"system.name": "PAYLOAD"}, r"config\.json: 'system\.name' is .*'module:' part would import code"),
    ("stdlib-module", {"system.name": "json:Pendulum-v1"},
     r"config\.json: 'system\.name' is 'json:Pendulum-v1'.*'module:' part"),
    ("not-a-string", {"system.name": 5}, r"config\.json: 'system\.name' must be a string .*got int 5"),
    ("list", {"system.name": ["Pendulum-v1"]}, r"config\.json: 'system\.name' must be a string"),
    ("unregistered", {"system.name": "NoSuchEnv-v0"}, r"config\.json: 'system\.name' is 'NoSuchEnv-v0', not a "
                                                      r"hybridctl system name or an id already registered"),
    ("kwargs-list", {"system.kwargs": []}, r"config\.json: 'system\.kwargs' must be null or an object"),
    # a format-1 checkpoint recorded the env as 'env' and 'env_kwargs': read as the system record, refused the same
    ("format-1-module-part", {"system": DELETE, "env": "PAYLOAD"},
     r"config\.json: 'system\.name' is .*'module:' part would import code"),
    ("format-1-kwargs-list", {"system": DELETE, "env": "Pendulum-v1", "env_kwargs": []},
     r"config\.json: 'system\.kwargs' must be null or an object"),
]


def _planted(changes: dict, payload: _Payload) -> dict:
    return {k: (payload.id if v == "PAYLOAD" else v) for k, v in changes.items()}


@pytest.mark.parametrize("name, changes, message", ENV_ID_CASES, ids=[c[0] for c in ENV_ID_CASES])
def test_ars_load_refuses_a_recorded_env_id(ars_run, payload, tmp_path, name, changes, message):
    from hybridctl.learn import ARS

    bad = _copy_with_config(ars_run[0], tmp_path / "final", **_planted(changes, payload))
    with pytest.raises(CheckpointError, match=message) as caught:
        ARS.load(bad)
    assert _one_line(str(caught.value))
    assert not payload.marker.exists(), "the payload module was imported"


@pytest.mark.parametrize("name, changes, message", ENV_ID_CASES, ids=[c[0] for c in ENV_ID_CASES])
def test_cli_finetune_of_an_ars_checkpoint_refuses_a_recorded_env_id(ars_run, payload, tmp_path, cli_error, name,
                                                                      changes, message):
    bad = _copy_with_config(ars_run[0], tmp_path / "final", **_planted(changes, payload))
    err = cli_error(["finetune", "Pendulum-v1", "--policy", f"ars:{bad}", "--out", tmp_path / "out", *FAST_FINETUNE])
    assert _one_line(err) and err.startswith("error: ") and __import__("re").search(message, err), err
    assert not payload.marker.exists(), "the payload module was imported"
    assert not (tmp_path / "out" / "report.json").exists()


@pytest.mark.parametrize("name, changes, message", ENV_ID_CASES, ids=[c[0] for c in ENV_ID_CASES])
def test_simulate_a_finetune_checkpoint_refuses_a_recorded_env_id(ars_run, payload, tmp_path, cli_error, name,
                                                                   changes, message):
    from hybridctl.learn.finetune import FineTune

    bad = _copy_with_config(ars_run[1], tmp_path / "final", **_planted(changes, payload))
    with pytest.raises(CheckpointError, match=message):
        FineTune.load(bad)
    err = cli_error(["simulate", "acrobot", "--controller", f"finetune:{bad}", "--duration", "0.1", "--no-html",
                     "--out", tmp_path / "sim"])
    assert _one_line(err) and __import__("re").search(message, err), err
    assert not payload.marker.exists(), "the payload module was imported"


def test_a_finetune_checkpoint_with_a_non_string_source_names_the_key(ars_run, tmp_path):
    from hybridctl.learn.finetune import FineTune

    bad = _copy_with_config(ars_run[1], tmp_path / "final", source=5)
    with pytest.raises(CheckpointError, match=r"config\.json: 'source' must be a string KIND:PATH"):
        FineTune.load(bad)


def test_an_id_with_a_module_part_the_user_passes_directly_is_allowed(ars_run, payload):
    """The refusal is for ids read from files: the same id passed in Python imports its module (the
    user's own choice), which shows the planted payload of the rows above really would run."""
    from hybridctl.learn import ARS, ARSConfig

    agent = ARS(payload.id, ARSConfig(n_directions=2, top_directions=1, backend="serial", episode_steps=20))
    assert payload.marker.exists() and agent.policy.obs_dim == 3
    # and ARS.load with env= given by the caller does not read the recorded id at all
    with pytest.warns(UserWarning, match="trained on env 'Pendulum-v1'"):
        again = ARS.load(ars_run[0], system=payload.id, force=True)
    assert again.policy.act_dim == 1


# ============================================================================ SB3 zips

sb3 = pytest.importorskip("stable_baselines3")


@pytest.fixture(scope="module")
def ppo_zip(tmp_path_factory):
    """A tiny PPO on Pendulum-v1 saved by SB3 (the real format)."""
    folder = tmp_path_factory.mktemp("ppo")
    model = sb3.PPO("MlpPolicy", "Pendulum-v1", n_steps=32, batch_size=32, n_epochs=1, seed=0, device="cpu",
                    policy_kwargs={"net_arch": [8, 8], "activation_fn": torch.nn.ReLU})
    model.learn(32)
    model.save(folder / "model.zip")
    return folder / "model.zip"


def _rewrite(src: Path, dst: Path, replace: dict | None = None, extra: dict | None = None,
             stream: tuple[str, int] | None = None) -> Path:
    """A copy of zip ``src`` with entries replaced / added; ``stream=(entry, MiB)``: that entry is MiB of
    zeros written in chunks (a zip bomb: 64 MiB deflate to about 64 KiB)."""
    replace = replace or {}
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w", zipfile.ZIP_DEFLATED) as zout:
        for entry in zin.namelist():
            if stream is None or entry != stream[0]:
                zout.writestr(entry, replace.get(entry, zin.read(entry)))
        for entry, payload in (extra or {}).items():
            zout.writestr(entry, payload)
        if stream is not None:
            with zout.open(stream[0], "w") as f:
                zeros = bytes(1 << 20)
                for _ in range(stream[1]):
                    f.write(zeros)
    return dst


def _edit_data(src: Path, dst: Path, edit) -> Path:
    data = json.loads(zipfile.ZipFile(src).read("data"))
    edit(data)
    return _rewrite(src, dst, replace={"data": json.dumps(data).encode()})


def _edit_policy(src: Path, dst: Path, edit) -> Path:
    state = torch.load(io.BytesIO(zipfile.ZipFile(src).read("policy.pth")), weights_only=True)
    edit(state)
    buffer = io.BytesIO()
    torch.save(state, buffer)
    return _rewrite(src, dst, replace={"policy.pth": buffer.getvalue()})


def _torch_bytes(obj) -> bytes:
    buffer = io.BytesIO()
    torch.save(obj, buffer)
    return buffer.getvalue()


def _set(data, path, value):
    for key in path[:-1]:
        data = data[key]
    data[path[-1]] = value


def _cast(key, dtype):
    return lambda state: state.__setitem__(key, state[key].to(dtype))


# (id, how to spoil the zip: f(src, dst, monkeypatch) -> path, what the one-line error says)
SB3_ZIP_CASES = [
    ("data-bomb", lambda s, d, mp: (mp.setattr(limits, "MAX_JSON_BYTES", 1 << 20),
                                    _rewrite(s, d, stream=("data", 64)))[1],
     r"model\.zip: entry 'data' inflates past 1,048,576 bytes"),
    ("system-info-bomb", lambda s, d, mp: (mp.setattr(limits, "MAX_JSON_BYTES", 1 << 20),
                                           _rewrite(s, d, stream=("system_info.txt", 64)))[1],
     r"model\.zip: entry 'system_info\.txt' inflates past"),
    ("version-bomb", lambda s, d, mp: (mp.setattr(limits, "MAX_JSON_BYTES", 1 << 20),
                                       _rewrite(s, d, stream=("_stable_baselines3_version", 64)))[1],
     r"model\.zip: entry '_stable_baselines3_version' inflates past"),
    ("variables-bomb", lambda s, d, mp: (mp.setattr(limits, "MAX_ZIP_ENTRY_BYTES", 4 << 20),
                                         _rewrite(s, d, stream=("pytorch_variables.pth", 64)))[1],
     r"model\.zip: entry 'pytorch_variables\.pth' inflates past [\d,]+ bytes, what is left of the limit of "
     r"4,194,304 bytes for all entries together"),
    ("unknown-entry-bomb", lambda s, d, mp: (mp.setattr(limits, "MAX_ZIP_ENTRY_BYTES", 4 << 20),
                                             _rewrite(s, d, stream=("../../x", 64)))[1],
     r"model\.zip: entry '\.\./\.\./x' inflates past"),
    ("too-many-entries", lambda s, d, mp: (mp.setattr(limits, "MAX_ZIP_ENTRIES", 8),
                                           _rewrite(s, d, extra={f"x{i}": b"" for i in range(5)}))[1],
     r"model\.zip holds 11 entries, above the limit of 8"),
    ("bool-tensor", lambda s, d, mp: _edit_policy(s, d, _cast("action_net.weight", torch.bool)),
     r"model\.zip: entry 'policy\.pth': tensor 'action_net\.weight' has dtype torch\.bool"),
    ("int64-tensor", lambda s, d, mp: _edit_policy(s, d, _cast("action_net.bias", torch.int64)),
     r"entry 'policy\.pth': tensor 'action_net\.bias' has dtype torch\.int64"),
    ("complex-tensor", lambda s, d, mp: _edit_policy(s, d, _cast("log_std", torch.complex64)),
     r"entry 'policy\.pth': tensor 'log_std' has dtype torch\.complex64"),
    ("wrong-shape", lambda s, d, mp: _edit_policy(s, d, lambda st: st.__setitem__("action_net.weight",
                                                                                    torch.zeros(1, 5))),
     r"entry 'policy\.pth': action_net\.weight has shape \(1, 5\); its input must be 8"),
    ("not-a-state-dict", lambda s, d, mp: _rewrite(s, d, replace={"policy.pth": _torch_bytes([torch.zeros(2)])}),
     r"entry 'policy\.pth' is not a dict of tensors"),
    ("clip-mean-object", lambda s, d, mp: _edit_data(s, d, lambda x: _set(x, ["policy_kwargs", "clip_mean"], {})),
     r"entry 'data': policy_kwargs\['clip_mean'\] must be a finite positive number, got \{\}"),
    ("squash-output-text", lambda s, d, mp: _edit_data(s, d, lambda x: _set(x, ["policy_kwargs", "squash_output"],
                                                                             "yes")),
     r"policy_kwargs\['squash_output'\] must be true or false"),
    ("activation-elsewhere", lambda s, d, mp: _edit_data(s, d, lambda x: _set(
        x, ["policy_kwargs", "activation_fn"], "<class 'evil.module.ReLU'>")),
     r"policy_kwargs\['activation_fn'\] is \"<class 'evil\.module\.ReLU'>\", not one of \['ELU'"),
    ("activation-unknown", lambda s, d, mp: _edit_data(s, d, lambda x: _set(
        x, ["policy_kwargs", "activation_fn"], "<class 'torch.nn.modules.activation.Threshold'>")),
     r"policy_kwargs\['activation_fn'\] .*Threshold.*not one of"),
    ("optimizer-unknown", lambda s, d, mp: _edit_data(s, d, lambda x: _set(
        x, ["policy_kwargs", "optimizer_class"], "<class 'evil.Optimizer'>")),
     r"policy_kwargs\['optimizer_class'\] .*not one of \['Adam', 'AdamW', 'RMSprop', 'SGD'\]"),
    ("extractor-unknown", lambda s, d, mp: _edit_data(s, d, lambda x: _set(
        x, ["policy_kwargs", "features_extractor_class"],
        "<class 'stable_baselines3.common.torch_layers.NatureCNN'>")),
     r"policy_kwargs\['features_extractor_class'\] .*NatureCNN.*not one of \['FlattenExtractor'\]"),
    ("function-in-kwargs", lambda s, d, mp: _edit_data(s, d, lambda x: _set(
        x, ["policy_kwargs", "net_arch"], "<function make_arch at 0x7f>")),
     r"policy_kwargs\['net_arch'\] is '<function make_arch.*cannot be read without unpickling"),
    ("policy-module", lambda s, d, mp: _edit_data(s, d, lambda x: _set(x, ["policy_class", "__module__"],
                                                                        "evil.policies")),
     r"entry 'data' key 'policy_class' names module 'evil\.policies', not one of"),
    ("space-too-large", lambda s, d, mp: _edit_data(s, d, lambda x: _set(x, ["observation_space", "_shape"],
                                                                          [10 ** 9])),
     r"data\['observation_space'\]\['_shape'\] is \[1000000000\]: .*at most 1,000,000 elements"),
    ("space-dtype", lambda s, d, mp: _edit_data(s, d, lambda x: _set(x, ["action_space", "dtype"], "object")),
     r"data\['action_space'\]\['dtype'\] is 'object', not float16, float32 or float64"),
    ("space-shape-text", lambda s, d, mp: _edit_data(s, d, lambda x: _set(x, ["observation_space", "_shape"], "3")),
     r"data\['observation_space'\]\['_shape'\] is 3: it must be a list"),
    ("deep-json", lambda s, d, mp: _rewrite(s, d, replace={"data": b"[" * 100_000}),
     r"entry 'data' is not valid JSON"),
    ("variables-unknown-name", lambda s, d, mp: _rewrite(s, d, replace={"pytorch_variables.pth": _torch_bytes(
        {"policy.action_net.weight": torch.zeros(1)})}),
     r"entry 'pytorch_variables\.pth' must map names of \('log_ent_coef', 'ent_coef_tensor'\)"),
    ("optimizer-not-a-state", lambda s, d, mp: _rewrite(s, d, replace={"policy.optimizer.pth": _torch_bytes(
        {"state": []})}),
     r"entry 'policy\.optimizer\.pth' is not an optimizer state dict"),
    ("duplicate-entry", lambda s, d, mp: _rewrite(s, d, extra={"data": b"{}"}),
     r"model\.zip holds the entry 'data' twice"),
]


@pytest.fixture
def no_duplicate_warning():
    import warnings
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", "Duplicate name", UserWarning)
        yield


@pytest.mark.usefixtures("no_duplicate_warning")
@pytest.mark.parametrize("name, spoil, message", SB3_ZIP_CASES, ids=[c[0] for c in SB3_ZIP_CASES])
def test_a_spoiled_sb3_zip_gives_one_line(ppo_zip, tmp_path, monkeypatch, cli_error, name, spoil, message):
    from hybridctl.learn.sb3 import load_sb3

    (tmp_path / "in").mkdir()
    bad = spoil(ppo_zip, tmp_path / "in" / "model.zip", monkeypatch)
    with pytest.raises(CheckpointError, match=message) as caught:
        load_sb3(bad)
    assert _one_line(str(caught.value)), str(caught.value)
    err = cli_error(["finetune", "Pendulum-v1", "--policy", f"sb3:{bad}", "--out", tmp_path / "out", *FAST_FINETUNE])
    assert _one_line(err) and __import__("re").search(message, err), err
    assert not (tmp_path / "out" / "report.json").exists() and not (tmp_path / "out" / "model.zip").exists()


def test_a_zip_bomb_is_stopped_without_allocating_it(ppo_zip, tmp_path, monkeypatch):
    """64 MiB of zeros in ``data`` (64 KiB on disk): reading stops at the (lowered) limit of 1 MiB."""
    from hybridctl.learn.sb3 import load_sb3

    monkeypatch.setattr(limits, "MAX_JSON_BYTES", 1 << 20)
    bomb = _rewrite(ppo_zip, tmp_path / "bomb.zip", stream=("data", 64))
    assert bomb.stat().st_size < 1 << 20
    tracemalloc.start()
    try:
        with pytest.raises(CheckpointError, match="inflates past"):
            load_sb3(bomb)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 8 << 20, f"{peak / 2**20:.1f} MiB allocated while reading a bomb"


# ---------------------------------------------------------------------------- what we write

class _Marker:
    """Unpickled, it creates ``path`` (a stand-in for any code a pickle can run)."""

    def __init__(self, path: Path):
        self.path = str(path)

    def __reduce__(self):
        return (open, (self.path, "w"))


def _planted_zip(src: Path, dst: Path, marker: Path) -> Path:
    """``src`` with a pickle payload in policy_kwargs[":serialized:"] (the issue's case), in a new
    top-level entry, in observation_space[":serialized:"], and entries named ../../x and /abs."""
    payload = base64.b64encode(pickle.dumps(_Marker(marker))).decode()
    data = json.loads(zipfile.ZipFile(src).read("data"))
    data["policy_kwargs"][":serialized:"] = payload
    data["extra_object"] = {":type:": "<class 'dict'>", ":serialized:": payload}
    data["nested"] = {"inner": {":serialized:": payload}}
    data["env"] = "json:Pendulum-v1"
    return _rewrite(src, dst, replace={"data": json.dumps(data).encode()},
                    extra={"../../x": b"outside", "/abs": b"absolute"})


ALLOWED_GLOBALS = {"stable_baselines3.common.policies.ActorCriticPolicy", "torch.nn.modules.activation.ReLU",
                   "gymnasium.spaces.box.Box", "numpy.dtype", "numpy.ndarray", "numpy.core.multiarray._reconstruct",
                   "numpy._core.multiarray._reconstruct", "numpy.core.multiarray.scalar",
                   "numpy._core.multiarray.scalar"}
"""What the pickles in our written ``data`` may name: the policy class, the activation, Boxes and numpy arrays."""


class _Checked(pickle.Unpickler):
    """Refuses (before it is called) any global outside :data:`ALLOWED_GLOBALS`, recording those it meets."""

    def __init__(self, data: bytes, seen: set):
        super().__init__(io.BytesIO(data))
        self.seen = seen

    def find_class(self, module, name):
        self.seen.add(f"{module}.{name}")
        if f"{module}.{name}" not in ALLOWED_GLOBALS:
            raise pickle.UnpicklingError(f"{module}.{name} is not allowed")
        return super().find_class(module, name)


def test_a_planted_payload_is_not_written_and_does_not_run_when_sb3_loads_our_output(ppo_zip, tmp_path):
    from hybridctl.learn.sb3 import load_sb3
    from hybridctl.learn.sb3_zip import OPTIMIZER_ENTRIES

    marker = tmp_path / "ran"
    hostile = _planted_zip(ppo_zip, tmp_path / "hostile.zip", marker)
    # the payload is real: SB3 loading the hostile input runs it
    try:
        sb3.PPO.load(hostile, device="cpu")
    except Exception:  # noqa: BLE001 - the payload replaces policy_kwargs; the load may fail after it ran
        pass
    assert marker.exists(), "the planted payload should run under SB3's own load of the input"
    marker.unlink()

    agent = load_sb3(hostile)
    assert not marker.exists()
    (tmp_path / "out").mkdir()
    out = agent.save_zip(tmp_path / "out" / "model.zip")
    with zipfile.ZipFile(out) as z:
        names = z.namelist()
        raw = z.read("data")
    order = ("data", "pytorch_variables.pth", "policy.pth", *OPTIMIZER_ENTRIES, "_stable_baselines3_version")
    assert names == [entry for entry in order if entry in zipfile.ZipFile(ppo_zip).namelist()]
    assert "../../x" not in names and "/abs" not in names
    planted = json.loads(zipfile.ZipFile(hostile).read("data"))["policy_kwargs"][":serialized:"]
    assert str(marker).encode() not in raw and planted.encode() not in raw
    data = json.loads(raw)
    assert "env" not in data and "extra_object" not in data and data["nested"] == {"inner": {}}
    referenced = set()
    for value in data.values():
        if isinstance(value, dict) and ":serialized:" in value:
            _Checked(base64.b64decode(value[":serialized:"]), referenced).load()
    assert {"stable_baselines3.common.policies.ActorCriticPolicy", "gymnasium.spaces.box.Box"} <= referenced

    loaded = sb3.PPO.load(out, device="cpu")  # SB3's load of our output: nothing of the input's runs
    assert not marker.exists()
    obs = np.random.default_rng(0).uniform(-1, 1, size=(20, 3)).astype(np.float32)
    np.testing.assert_allclose(loaded.predict(obs, deterministic=True)[0], agent.predict(obs)[0], atol=1e-6)
    np.testing.assert_allclose(loaded.predict(obs, deterministic=True)[0],
                               sb3.PPO.load(ppo_zip, device="cpu").predict(obs, deterministic=True)[0], atol=1e-6)
    assert loaded.policy_kwargs["activation_fn"] is torch.nn.ReLU and loaded.policy_kwargs["net_arch"] == [8, 8]


def test_cli_finetune_of_a_planted_zip_writes_a_clean_zip(ppo_zip, tmp_path, capsys):
    """The issue's case end to end: exit 0, and SB3's load of the written model.zip runs nothing."""
    from hybridctl.cli import main

    marker = tmp_path / "ran"
    (tmp_path / "in").mkdir()
    hostile = _planted_zip(ppo_zip, tmp_path / "in" / "model.zip", marker)
    assert main(["finetune", "Pendulum-v1", "--policy", f"sb3:{hostile}", "--out", str(tmp_path / "out"),
                 *FAST_FINETUNE]) == 0
    capsys.readouterr()
    written = tmp_path / "out" / "model.zip"
    assert written.is_file() and not marker.exists()
    sb3.PPO.load(written, device="cpu")
    assert not marker.exists()
    assert not (tmp_path / "x").exists() and not Path("/abs").exists()


# ============================================================================ SB3 builds our envs by id

def test_swingup_env_renders_rgb_frames_of_its_state():
    from hybridctl.envs import SwingupEnv
    from hybridctl.envs.single import RENDER_SIZE, chain_points

    for name in ("acrobot", "cartpole"):
        env = SwingupEnv(name, render_mode="rgb_array")
        assert "rgb_array" in env.metadata["render_modes"] and env.metadata["render_fps"] > 0
        env.reset(seed=0)
        first = env.render()
        assert first.shape == (RENDER_SIZE, RENDER_SIZE, 3) and first.dtype == np.uint8
        assert (first != 255).any(), "something is drawn"
        env.step(env.action_space.high)
        env.step(env.action_space.high)
        assert (env.render() != first).any(), "the frame follows the state"
        points = chain_points(env.system, env.state)
        tip = env.system.dynamics.tip_position(env.state[None])
        np.testing.assert_allclose(points[-1], [tip[0][0], tip[1][0]], atol=1e-12)
    with pytest.raises(ValueError, match=r"render_mode must be None or one of \['rgb_array'\].*'human'"):
        SwingupEnv("acrobot", render_mode="human")
    with pytest.warns(UserWarning, match="render_mode"):
        assert SwingupEnv("acrobot").render() is None


def test_sb3_builds_our_env_by_id_with_make_vec_env_and_ppo():
    from stable_baselines3.common.env_util import make_vec_env

    import hybridctl.envs  # noqa: F401 - registers the ids
    env_id = "hybridctl/AcrobotSwingup-v0"
    venv = make_vec_env(env_id, n_envs=2, seed=0)
    assert venv.render_mode == "rgb_array"
    venv.reset()
    frames = venv.get_images()
    assert len(frames) == 2 and frames[0].shape[2] == 3 and frames[0].dtype == np.uint8
    model = sb3.PPO("MlpPolicy", env_id, n_steps=64, batch_size=64, n_epochs=1, seed=0, device="cpu",
                    policy_kwargs={"net_arch": [8]})
    model.learn(256)
    assert model.num_timesteps == 256 and model.observation_space.shape == (4,)


# ============================================================================ model files (issue 47)
# A URDF / SDF / MJCF from someone else names files that Drake opens and meshcat embeds in a replay page;
# every such file is checked first (hybridctl.systems.model_files). Its numbers are checked before code is
# generated from them, and the derivation is bounded in size and time.

SECRET = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n# the secret: 7f3a9c1e-hostile-47\n"


def _urdf(visual: str = "", mass: str = "1", inertia: str = 'ixx="0.01" iyy="0.01" izz="0.01"',
          origin: str = "0 0 0", limit: str = 'effort="5" velocity="100"', extra: str = "") -> str:
    return f"""<?xml version="1.0"?>
<robot name="pendulum">
  <link name="base"/>
  <link name="arm">
    <inertial><origin xyz="0 0 -0.5"/><mass value="{mass}"/><inertia {inertia} ixy="0" ixz="0" iyz="0"/></inertial>
    {visual}
  </link>
  <joint name="weld" type="fixed"><parent link="world"/><child link="base"/></joint>
  <joint name="pivot" type="continuous"><parent link="base"/><child link="arm"/><origin xyz="{origin}"/>
    <axis xyz="0 1 0"/><limit {limit}/></joint>
  <transmission type="SimpleTransmission" name="t"><actuator name="m"/><joint name="pivot"/></transmission>
  {extra}
</robot>
"""


def _mesh(filename: str) -> str:
    return f'<visual><geometry><mesh filename="{filename}"/></geometry></visual>'


@pytest.fixture
def model_cache(tmp_path, monkeypatch):
    from hybridctl.systems import symbolic
    monkeypatch.setenv(symbolic.CACHE_ENV, str(tmp_path / "cache"))


def _from_file(path: Path):
    from hybridctl import systems
    return systems.from_drake(str(path), goal=[0.0, 0.0], Q=np.eye(2), R=np.eye(1))


def _replay_payload(html: str) -> bytes:
    """Every base64 payload of a replay page, decoded (meshcat embeds each command as msgpack in a data: URL)."""
    import re
    return b"".join(base64.b64decode(m) for m in re.findall(r"base64,([A-Za-z0-9+/=]+)", html))


def _replay(system) -> str:
    from hybridctl.viz.meshcat import replay_html
    return replay_html(system, np.array([0.0, 0.1]), np.zeros((2, 2)))


def _refused(path: Path, *needles: str):
    """from_drake and the replay of the model at ``path`` refuse it in one line naming the file and ``needles``."""
    from hybridctl.systems import ModelError
    with pytest.raises(ModelError) as raised:
        _replay(_from_file(path))
    message = str(raised.value)
    assert _one_line(message) and str(path) in message, message
    for needle in needles:
        assert needle in message, message
    return message


def _model(tmp_path: Path, text: str, name: str = "robot.urdf") -> Path:
    folder = tmp_path / "model"
    folder.mkdir(exist_ok=True)
    (folder / name).write_text(text)
    return folder / name


def test_a_mesh_inside_the_model_folder_is_drawn(tmp_path, model_cache):
    """The control: a mesh in the model's folder reaches the page (so the check below can see a leak)."""
    folder = tmp_path / "model"
    folder.mkdir()
    (folder / "arm.obj").write_bytes(SECRET)
    html = _replay(_from_file(_model(tmp_path, _urdf(visual=_mesh("arm.obj")))))
    assert SECRET in _replay_payload(html)


@pytest.mark.parametrize("how", ["absolute", "file_url", "symlink", "dotdot"])
def test_a_mesh_outside_the_model_folder_never_reaches_a_replay(tmp_path, model_cache, how):
    secret = tmp_path / "secret.obj"
    secret.write_bytes(SECRET)
    folder = tmp_path / "model"
    folder.mkdir()
    if how == "symlink":
        (folder / "arm.obj").symlink_to(secret)
    ref = {"absolute": str(secret), "file_url": f"file://{secret}", "symlink": "arm.obj",
           "dotdot": "../secret.obj"}[how]
    path = _model(tmp_path, _urdf(visual=_mesh(ref)))
    _refused(path, "outside the model's folder", repr(ref))


@pytest.mark.timeout(30, method="thread")   # a regression hangs in C++; the thread method ends the run
@pytest.mark.parametrize("how", ["dev_random", "dev_zero", "symlink_urandom", "fifo", "not_a_mesh"])
def test_a_device_fifo_or_other_file_as_a_mesh_is_refused_without_opening_it(tmp_path, model_cache, how):
    import os
    folder = tmp_path / "model"
    folder.mkdir()
    if how == "symlink_urandom":
        (folder / "arm.obj").symlink_to("/dev/urandom")
    if how == "fifo":
        os.mkfifo(folder / "arm.obj")
    if how == "not_a_mesh":
        (folder / "notes.txt").write_bytes(SECRET)
    ref = {"dev_random": "/dev/random", "dev_zero": "/dev/zero", "symlink_urandom": "arm.obj", "fifo": "arm.obj",
           "not_a_mesh": "notes.txt"}[how]
    needle = {"fifo": "is a FIFO, not a regular file", "not_a_mesh": "a mesh must be a .obj"}.get(how, "outside")
    _refused(_model(tmp_path, _urdf(visual=_mesh(ref))), needle)


def test_a_mesh_above_the_size_limit_is_refused(tmp_path, model_cache, monkeypatch):
    from hybridctl.systems import model_files
    monkeypatch.setattr(model_files, "MAX_MESH_BYTES", 16)
    folder = tmp_path / "model"
    folder.mkdir()
    (folder / "arm.obj").write_bytes(SECRET)
    _refused(_model(tmp_path, _urdf(visual=_mesh("arm.obj"))), "above the limit of 16")


def test_what_a_mesh_names_is_checked_too(tmp_path, model_cache):
    """An .obj's material library and its textures, a glTF's buffers: meshcat embeds them as well."""
    secret = tmp_path / "secret.png"
    secret.write_bytes(SECRET)
    folder = tmp_path / "model"
    folder.mkdir()
    (folder / "arm.obj").write_bytes(b"mtllib arm.mtl\n" + SECRET)
    (folder / "arm.mtl").write_text(f"newmtl m\nmap_Kd {secret}\n")
    _refused(_model(tmp_path, _urdf(visual=_mesh("arm.obj"))), "outside the model's folder", "arm.mtl")
    (folder / "arm.gltf").write_text(json.dumps({"asset": {"version": "2.0"}, "buffers": [{"uri": "../secret.png"}]}))
    _refused(_model(tmp_path, _urdf(visual=_mesh("arm.gltf"))), "outside the model's folder", "arm.gltf")


def test_a_package_other_than_drake_is_refused(tmp_path, model_cache):
    _refused(_model(tmp_path, _urdf(visual=_mesh("package://drake_models/x/arm.obj"))), "declared package")


@pytest.mark.parametrize("declaration", ['<!DOCTYPE robot [<!ENTITY a "aaaaaaaaaa">]>',
                                         '<!DOCTYPE robot SYSTEM "/etc/passwd">'])
def test_a_model_file_with_a_doctype_or_entities_is_refused(tmp_path, model_cache, declaration):
    text = _urdf().replace('<?xml version="1.0"?>', f'<?xml version="1.0"?>\n{declaration}')
    _refused(_model(tmp_path, text), "DOCTYPE or ENTITY")


MJCF_BODY = """<worldbody><body name="arm"><joint name="pivot" type="hinge" axis="0 1 0"/>
  <geom type="capsule" fromto="0 0 0 0 0 -1" size="0.05" mass="1"/></body></worldbody>
  <actuator><motor joint="pivot" gear="1"/></actuator>"""


@pytest.mark.timeout(30, method="thread")
def test_an_mjcf_that_includes_itself_is_refused(tmp_path, model_cache):
    path = _model(tmp_path, f'<mujoco model="x"><include file="robot.xml"/>{MJCF_BODY}</mujoco>', "robot.xml")
    _refused(path, "includes itself")
    _model(tmp_path, '<mujoco model="y"><include file="robot.xml"/></mujoco>', "other.xml")
    path = _model(tmp_path, f'<mujoco model="x"><include file="other.xml"/>{MJCF_BODY}</mujoco>', "robot.xml")
    _refused(path, "includes itself", "robot.xml -> other.xml -> robot.xml")


def test_includes_are_bounded_in_depth_and_expansion(tmp_path, model_cache):
    from hybridctl import limits
    for k in range(limits.MAX_INCLUDE_DEPTH + 2):
        _model(tmp_path, f'<mujoco model="m{k}"><include file="f{k + 1}.xml"/></mujoco>', f"f{k}.xml")
    _model(tmp_path, '<mujoco model="end"/>', f"f{limits.MAX_INCLUDE_DEPTH + 2}.xml")
    _refused(tmp_path / "model" / "f0.xml", "nest deeper than")
    # each file includes the next 10 times: 10^6 files as the parser would expand them
    for k in range(6):
        _model(tmp_path, f'<mujoco model="g{k}">' + f'<include file="g{k + 1}.xml"/>' * 10 + "</mujoco>", f"g{k}.xml")
    _model(tmp_path, '<mujoco model="end"><worldbody><body name="b"/></worldbody></mujoco>', "g6.xml")
    _refused(tmp_path / "model" / "g0.xml", "with its includes expanded")


@pytest.mark.parametrize("case, kwargs, needles", [
    ("origin 1e300", {"origin": "1e300 0 0"}, ("at most 1000 m", "MAX_MODEL_LENGTH")),
    ("origin inf", {"origin": "inf 0 0"}, ("must be finite",)),
    ("origin overflows", {"origin": "1e400 0 0"}, ("must be finite",)),
    ("effort inf", {"limit": 'effort="inf" velocity="100"'}, ("must be finite", "effort")),
    ("velocity nan", {"limit": 'effort="5" velocity="nan"'}, ("must be finite", "velocity")),
    ("mass -1", {"mass": "-1"}, ("a mass must be > 0",)),
    ("mass 0", {"mass": "0"}, ("a mass must be > 0",)),
    ("mass 1e300", {"mass": "1e300"}, ("mass",)),
    ("negative inertia", {"inertia": 'ixx="-0.01" iyy="0.01" izz="0.01"'}, ("body 'arm'", "positive semidefinite")),
    ("triangle inequality", {"inertia": 'ixx="0.01" iyy="0.01" izz="0.05"'}, ("body 'arm'", "triangle inequality")),
])
def test_non_finite_and_non_physical_numbers_are_refused_before_code_is_generated(tmp_path, model_cache, case,
                                                                                  kwargs, needles):
    from hybridctl.systems import ModelError
    path = _model(tmp_path, _urdf(**kwargs))
    with pytest.raises(ModelError) as raised:
        _from_file(path)
    message = str(raised.value)
    assert _one_line(message) and str(path) in message, message
    for needle in needles:
        assert needle in message, message


def _chain(n: int, welded: int = 0) -> str:
    inertial = ('<inertial><origin xyz="0 0 -0.25"/><mass value="1"/><inertia ixx="0.02" ixy="0" ixz="0" iyy="0.02" '
                'iyz="0" izz="0.01"/></inertial>')
    parts, parent = ['<link name="base"/><joint name="weld" type="fixed"><parent link="world"/><child link="base"/>'
                     '</joint>'], "base"
    for i in range(n):
        parts.append(f'<link name="l{i}">{inertial}</link><joint name="j{i}" type="continuous"><parent link="{parent}"/>'
                     f'<child link="l{i}"/><origin xyz="0 0 -0.5"/><axis xyz="0 1 0"/></joint><transmission '
                     f'type="SimpleTransmission" name="t{i}"><actuator name="m{i}"/><joint name="j{i}"/></transmission>')
        parent = f"l{i}"
    for k in range(welded):
        parts.append(f'<link name="w{k}">{inertial}</link><joint name="wj{k}" type="fixed"><parent '
                     f'link="{"base" if k == 0 else f"w{k - 1}"}"/><child link="w{k}"/></joint>')
    return '<?xml version="1.0"?>\n<robot name="chain">' + "".join(parts) + "</robot>"


@pytest.mark.timeout(60, method="thread")
def test_twenty_thousand_welded_links_are_refused_before_drake_parses_them(tmp_path, model_cache):
    import time
    from hybridctl import limits
    started = time.perf_counter()
    _refused(_model(tmp_path, _chain(1, welded=20_000)), f"more than {limits.MAX_BODIES:,} bodies")
    assert time.perf_counter() - started < 10


@pytest.mark.timeout(60, method="thread")
def test_a_twelve_joint_chain_is_refused_promptly(tmp_path, model_cache):
    """Its expressions are measured stage by stage: Drake's symbolic kinetic energy of it alone takes minutes."""
    import time
    from hybridctl.systems import ModelError, symbolic
    started = time.perf_counter()
    with pytest.raises(ModelError, match="too large to generate code for"):
        symbolic.derive(symbolic.ModelRequest(str(_model(tmp_path, _chain(12)))))
    assert time.perf_counter() - started < 20


@pytest.mark.timeout(60, method="thread")
def test_the_derivation_has_a_deadline_checked_as_it_goes(tmp_path, model_cache, monkeypatch):
    """A 4-joint chain takes about 2 s; with a 0.3 s limit it stops within a few entries."""
    import time
    from hybridctl.systems import ModelError, symbolic
    monkeypatch.setattr(symbolic, "MAX_DERIVE_SECONDS", 0.3)
    started = time.perf_counter()
    with pytest.raises(ModelError, match=r"took more than 0.3 s \(hybridctl.limits.MAX_DERIVE_SECONDS\)") as raised:
        symbolic.derive(symbolic.ModelRequest(str(_model(tmp_path, _chain(4)))))
    assert _one_line(str(raised.value))
    assert time.perf_counter() - started < 1.5


@pytest.mark.timeout(60, method="thread")
def test_cli_simulate_of_a_hostile_model_is_one_line(tmp_path, model_cache, cli_error):
    """``hybridctl simulate`` of a spec whose model names a FIFO as a mesh: one line, exit 2, nothing hangs."""
    import os
    from hybridctl.systems.spec import MODELS_DIR, SPEC_DIR
    folder = tmp_path / "model"
    folder.mkdir()
    os.mkfifo(folder / "wheel.obj")
    urdf = (MODELS_DIR / "reaction_wheel.urdf").read_text().replace("<inertial>", _mesh("wheel.obj") + "<inertial>", 1)
    (folder / "reaction_wheel.urdf").write_text(urdf)
    (folder / "wheel_spec.toml").write_text((SPEC_DIR / "reaction_wheel.toml").read_text())
    err = cli_error(["simulate", folder / "wheel_spec.toml", "--controller", "zero", "--duration", "0.1",
                     "--out", tmp_path / "run"])
    assert "is a FIFO, not a regular file" in err and _one_line(err), err


@pytest.mark.timeout(30, method="thread")
@pytest.mark.parametrize("template", ["/etc/passwd", "../../../../etc/passwd.sdf", "/dev/zero"])
def test_a_cart_pole_template_is_one_of_the_packages_models(template):
    """``model.drake = "multibody:FILE.sdf"`` names a template in models/ by its bare name, nothing else."""
    from hybridctl import systems
    system = systems.load("cartpole", model__drake=f"multibody:{template}")
    with pytest.raises(ValueError, match="must name an .sdf template in the package's models/ folder") as raised:
        system.drake_plant()
    assert _one_line(str(raised.value))
