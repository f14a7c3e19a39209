"""hybridctl.reproduce.table44's cell cache: a measured per-seed cell is read back (from memory and
from disk) instead of run again, only for the same policy weights, condition, episodes and env seed,
and the pooled numbers are the same either way."""

import pytest


@pytest.fixture(scope="module")
def t44():
    from hybridctl.reproduce import table44

    return table44


@pytest.fixture
def fake_rates(t44, monkeypatch):
    """failure_rates replaced by a counter whose failures depend on the agent and the env seed."""
    calls = []

    def fake(agent, conditions, episodes, episode_steps, seed, backend, workers):
        calls.append((agent, seed))
        failures = (agent * 7 + seed) % (episodes + 1)
        return {"c": {"failures": failures, "mean_steps": 10_000.0 - failures, "mean_return": float(seed)}}

    monkeypatch.setattr(t44, "failure_rates", fake)
    return calls


def test_cells_are_measured_once_and_survive_a_restart(t44, fake_rates, tmp_path):
    agents, prints = {6: 1, 16: 2}, {6: "aaaa", 16: "bbbb"}
    path = tmp_path / "t.cache.json"
    first = t44.pooled(agents, {"push": (0.2, 30.0)}, 20, 1, 1, t44.CellCache(path), prints)
    assert len(fake_rates) == 2 and path.is_file()
    again = t44.pooled(agents, {"push": (0.2, 30.0)}, 20, 1, 1, t44.CellCache(path), prints)   # a new process
    assert again == first and len(fake_rates) == 2
    # one more seed: only its cell runs; the shared seeds' cells are reused
    more = t44.pooled({**agents, 7: 3}, {"push": (0.2, 30.0)}, 20, 1, 1, t44.CellCache(path), {**prints, 7: "cccc"})
    assert len(fake_rates) == 3 and more["per_seed"]["6"] == first["per_seed"]["6"] and more["episodes"] == 60


@pytest.mark.parametrize("change", ["policy", "condition", "episodes", "seed"])
def test_a_cell_is_reused_only_for_the_same_key(t44, fake_rates, tmp_path, change):
    cache = t44.CellCache(tmp_path / "t.cache.json")
    base = dict(cond={"action_noise": 0.05}, episodes=20, seed=1, prints={6: "aaaa"})
    t44.pooled({6: 1}, base["cond"], base["episodes"], base["seed"], 1, cache, base["prints"])
    other = {**base, **{"policy": {"prints": {6: "retrained"}}, "condition": {"cond": {"action_noise": 0.0658}},
                        "episodes": {"episodes": 25}, "seed": {"seed": 2}}[change]}
    t44.pooled({6: 1}, other["cond"], other["episodes"], other["seed"], 1, cache, other["prints"])
    assert len(fake_rates) == 2


def test_fingerprint_follows_the_weights(t44, tmp_path):
    (tmp_path / "model.pt").write_bytes(b"weights")
    (tmp_path / "normalization.json").write_text("{}")
    before = t44.policy_fingerprint(tmp_path)
    (tmp_path / "normalization.json").write_text('{"mean": [1.0]}')
    assert t44.policy_fingerprint(tmp_path) != before
