"""Reachable-state meshes of a disturbed Poincare map (thesis Ch. 5, Algorithm 7) and Monte Carlo checks.

Starting from seed states, every mesh state is mapped through the section map under
each disturbance of a finite set; the next state's box key (thesis Alg. 5: rounded
normalised state / ``box_size``) either names a known mesh state or adds a new one,
which is expanded in turn (breadth first). Failure is one absorbing state, index 0.
Each box keeps the first state that reached it as its representative, from which it
is expanded. With ``samples_per_box=k > 1`` a box keeps the first ``k`` states that reach it
(Ulam's method with arrival samples): every sample is expanded, and the box's row of the chain
is the average of its samples' rows, so a box's transitions spread over where states in it
actually go instead of following one representative. The result is a Markov chain: :meth:`ReachableMesh.transition_matrix`
(CSR, rows sum to 1) and :meth:`ReachableMesh.mfpt` (:func:`~hybridctl.analysis.absorbing_mfpt`).

>>> wheel = RimlessWheel()
>>> slopes = GaussianDisturbance(mean=0.15, std=0.06, count=25)
>>> mesh = build_mesh(wheel, seeds=[[wheel.fixed_point(0.15)]], disturbances=slopes, box_size=1e-3)
>>> mesh.mfpt().mean(mesh.seed_distribution())
>>> monte_carlo_mfpt(wheel, [[1.29]], slopes, episodes=2000)    # on the true map, with a 95 % interval

Expansion runs in batches of states on a :mod:`hybridctl.parallel` backend ("serial" by
default here; "processes" or "ray" for simulator-backed maps). Results are merged in
batch order, so every backend builds the same mesh. With ``checkpoint=PATH`` the mesh
so far is written atomically every ``checkpoint_every`` batches and ``resume=True``
continues from it; a worker that dies has its batch rerun by the process backend.
"""

from __future__ import annotations

import contextlib
import contextvars
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator, Sequence

import numpy as np
import scipy.sparse as sp

from ..io import atomic_write
from ..limits import MAX_DISTURBANCES, MAX_MONTE_CARLO, check_at_most, check_fits_memory
from ..parallel import PARALLEL_MIN_ROUND_SECONDS, SizedRounds, make_backend
from .markov import MFPTResult, _krylov_solve, absorbing_mfpt, states_that_can_fail_surely
from .mesh import box_keys
from .poincare import FiniteDisturbances, SectionMap

_SHARED: contextvars.ContextVar[tuple | None] = contextvars.ContextVar("hybridctl_shared_mesh_backend", default=None)


@contextlib.contextmanager
def shared_backend(backend: str = "serial", workers: int | None = None, address: str | None = None) -> Iterator[Any]:
    """One parallel backend for every :func:`build_mesh` and :func:`monte_carlo_mfpt` inside the block that names
    the same ``backend``, ``workers`` and ``address``: a job of several stages (the mesh report's refined meshes,
    Monte Carlo runs and mesh sizes) starts its worker processes once, not once per stage. Closed at the end."""
    pool = make_backend(backend, workers, address)
    token = _SHARED.set(((backend, workers, address), pool))
    try:
        yield pool
    finally:
        _SHARED.reset(token)
        pool.close()


def _backend(backend: str, workers: int | None, address: str | None) -> Any:
    """The block's shared backend when it matches (:func:`shared_backend`), else a new one."""
    shared = _SHARED.get()
    if shared is not None and shared[0] == (backend, workers, address):
        return shared[1]
    return make_backend(backend, workers, address)


def _release(pool: Any) -> None:
    """Close ``pool`` unless it is the block's shared backend (the block closes that one)."""
    shared = _SHARED.get()
    if shared is None or pool is not shared[1]:
        pool.close()

FAILURE = 0


@dataclass
class ReachableMesh:
    """Mesh states (representatives; id i is row i - 1 of ``states``), successor ids (0 = failure).

    A mesh built with ``samples_per_box > 1`` has ``owners``: then ``states`` holds every sample
    (the first sample of a box is its representative), ``owners[i]`` is the box id (1-based) of
    sample ``i`` and ``successors`` has one row per expanded sample.
    """

    states: np.ndarray            # (n_states, n_dims) representatives (or samples, with owners)
    successors: np.ndarray        # (n_expanded, n_disturbances) ids in 0..n_states
    weights: np.ndarray           # disturbance probabilities
    box_size: float
    mean: np.ndarray
    std: np.ndarray
    seed_ids: np.ndarray
    complete: bool
    wall_time: float = 0.0
    settings: dict = field(default_factory=dict)
    owners: np.ndarray | None = None   # (n_samples,) box id of each sample; None: one sample per box
    rounds: dict = field(default_factory=dict)   # expansion rounds run in process / on the backend (build_mesh)

    @property
    def size(self) -> int:
        """Number of mesh states (the failure state not counted)."""
        if self.owners is not None:
            return int(self.owners.max()) if self.owners.size else 0
        return int(self.states.shape[0])

    @property
    def representatives(self) -> np.ndarray:
        """One state per box (row i - 1 for id i): the first state that reached it."""
        if self.owners is None:
            return self.states
        first = np.zeros(self.size, dtype=np.int64)
        order = np.arange(self.owners.size)[::-1]
        first[self.owners[order] - 1] = order                       # the last write wins: the first sample
        return self.states[first]

    def transition_matrix(self) -> sp.csr_matrix:
        """Stochastic matrix (n_states + 1 square, CSR): T[i, j] = P(next id j | id i); failure 0 absorbing.

        Raises ValueError for an incomplete mesh (stopped at ``max_states``): its unexpanded
        states have no rows.
        """
        if not self.complete:
            # rows of `states` (with owners: samples) that were never expanded
            raise ValueError(f"the mesh is incomplete: {self.states.shape[0] - self.successors.shape[0]} of "
                             f"{self.states.shape[0]} states were never expanded (max_states reached); use a larger "
                             f"box_size or max_states")
        n, k = self.successors.shape
        if self.owners is None:
            rows = np.repeat(np.arange(1, n + 1), k)
            vals = np.tile(self.weights, n)
        else:   # a box's row: the mean of its samples' rows
            owner = self.owners[:n]
            count = np.bincount(owner, minlength=self.size + 1)
            rows = np.repeat(owner, k)
            vals = np.tile(self.weights, n) / count[rows]
            n = self.size
        T = sp.csr_matrix((np.r_[1.0, vals], (np.r_[0, rows], np.r_[0, self.successors.ravel()])),
                          shape=(n + 1, n + 1))
        T.sum_duplicates()
        return T

    def mfpt(self, method: str = "krylov", **kwargs) -> MFPTResult:
        """Mean first passage time to failure from every mesh state (index i = state id i)."""
        return absorbing_mfpt(self.transition_matrix(), FAILURE, method=method, **kwargs)

    def seed_distribution(self) -> np.ndarray:
        """Uniform weights over the seeds' mesh states (index 0 = failure)."""
        p = np.zeros(self.size + 1)
        np.add.at(p, self.seed_ids, 1.0)
        return p / p.sum()

    def failure_probability(self) -> np.ndarray:
        """One-step probability of failure from each mesh state (index i - 1 for id i)."""
        per_row = (self.successors == FAILURE) @ self.weights
        if self.owners is None:
            return per_row
        owner = self.owners[:per_row.size]
        return np.bincount(owner, per_row, self.size + 1)[1:] / np.bincount(owner, minlength=self.size + 1)[1:]

    def save(self, path: str | os.PathLike) -> Path:
        """Write the mesh to one ``.npz`` file (atomically; read back with :meth:`load`, no pickle)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        arrays = dict(states=self.states, successors=self.successors, weights=self.weights,
                      box_size=self.box_size, mean=self.mean, std=self.std, seed_ids=self.seed_ids,
                      complete=self.complete, wall_time=self.wall_time,
                      state_names=np.array(self.settings.get("state_names") or [], dtype=str),
                      owners=np.zeros(0, dtype=np.int64) if self.owners is None else self.owners)
        return atomic_write(path, lambda f: np.savez(f, **arrays))

    @classmethod
    def load(cls, path: str | os.PathLike) -> "ReachableMesh":
        """A mesh written by :meth:`save`."""
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"no mesh file at {path}")
        data = np.load(path, allow_pickle=False)
        missing = {"states", "successors", "weights", "box_size"} - set(data.files)
        if missing:
            raise ValueError(f"{path} is not a mesh file: missing {sorted(missing)}")
        settings = {"box_size": float(data["box_size"]), "disturbances": int(data["weights"].size),
                    "state_names": [str(n) for n in data["state_names"]]}
        owners = data["owners"] if "owners" in data.files and data["owners"].size else None
        return cls(data["states"], data["successors"], data["weights"], float(data["box_size"]), data["mean"],
                   data["std"], data["seed_ids"], bool(data["complete"]), float(data["wall_time"]), settings, owners)

    def summary(self) -> dict:
        """JSON-ready description."""
        samples = {} if self.owners is None else {"samples": int(self.owners.size)}
        return {"states": self.size, **samples, "box_size": self.box_size, "disturbances": int(self.weights.size),
                "complete": self.complete, "seeds": int(self.seed_ids.size), "wall_time_s": self.wall_time,
                "transitions_to_failure": int((self.successors == FAILURE).sum()), **self.settings}


def _expand(task) -> np.ndarray:
    """Worker: next states (m, K, n) of a batch of states under every disturbance (NaN = failure)."""
    section_map, states, values = task
    m, k = states.shape[0], len(values)
    flat_states = np.repeat(states, k, axis=0)
    flat_dist = [values[j] for _ in range(m) for j in range(k)]
    try:
        out = np.asarray(section_map.step_many(flat_states, flat_dist), dtype=np.float64)
    except Exception as exc:  # name the first state that fails, one by one
        for i, s in enumerate(states):
            for j, d in enumerate(values):
                try:
                    section_map.step_many(s[None, :], [d])
                except Exception as inner:
                    raise RuntimeError(f"section map raised at state {s.tolist()} with disturbance {d!r} "
                                       f"(mesh batch row {i}, disturbance {j}): {type(inner).__name__}: {inner}") from inner
        raise RuntimeError(f"section map raised on a batch: {type(exc).__name__}: {exc}") from exc
    if out.shape != flat_states.shape:
        raise RuntimeError(f"section map returned shape {out.shape} for {flat_states.shape} states")
    return out.reshape(m, k, -1)


class _Keys:
    """Box keys -> mesh ids (1-based), as in thesis Alg. 5."""

    def __init__(self, box_size: float, mean: np.ndarray, std: np.ndarray):
        self.box_size, self.mean, self.std = box_size, mean, std
        self.ids: dict[bytes, int] = {}

    def keys(self, states: np.ndarray) -> list[bytes]:
        """One hashable key per state: the box-mesh rule of :func:`~hybridctl.analysis.mesh.box_keys`."""
        if len(states) == 0:
            return []
        k = np.ascontiguousarray(box_keys(states, self.box_size, self.mean, self.std))
        return [row.tobytes() for row in k]


def _save_checkpoint(path: Path, mesh_states: list, successors: list, box_size: float, n_disturbances: int,
                     wall_time: float = 0.0, owners: list | None = None, samples_per_box: int = 1) -> None:
    """Write the mesh so far to ``path`` (.npz) atomically (:func:`hybridctl.io.atomic_write`: a
    temporary file, fsynced, then a rename)."""
    states = np.array(mesh_states)
    succ = np.array(successors, dtype=np.int64).reshape(len(successors), n_disturbances)
    path.parent.mkdir(parents=True, exist_ok=True)
    extra = {} if samples_per_box == 1 else {"owners": np.array(owners, dtype=np.int64),
                                             "samples_per_box": samples_per_box}
    atomic_write(path, lambda f: np.savez(f, states=states, box_size=box_size, n_disturbances=n_disturbances,
                                          wall_time=wall_time, successors=succ, **extra))


def _load_checkpoint(path: Path):
    """The arrays of a mesh checkpoint, ValueError naming the file when it is damaged."""
    try:
        saved = np.load(path, allow_pickle=False)
        data = {k: saved[k] for k in saved.files}
    except Exception as exc:  # noqa: BLE001 - re-raised with the file named
        raise ValueError(f"mesh checkpoint {path} is damaged ({type(exc).__name__}: {exc}); remove it to start "
                         f"anew") from exc
    missing = [k for k in ("states", "successors", "box_size", "n_disturbances") if k not in data]
    if missing:
        raise ValueError(f"mesh checkpoint {path} is damaged: it lacks {', '.join(missing)}")
    return data


def _undo_row(marks: tuple[int, int], mesh_states: list, owners: list, counts: list, keys: _Keys) -> None:
    """Forget the samples and boxes a row added before the cap stopped it. Its expansion is redone
    on resume; samples kept from half a row would be added twice there (with one sample per box a
    kept box is found again and nothing is added twice, so that case keeps them, as it always did)."""
    n_samples, n_boxes = marks
    for owner in owners[n_samples:]:
        counts[owner] -= 1
    del mesh_states[n_samples:], owners[n_samples:], counts[n_boxes:]
    for key in [key for key, box in keys.ids.items() if box >= n_boxes]:
        del keys.ids[key]


def check_disturbances(count: int, max_states: int, samples_per_box: int = 1, force: bool = False) -> None:
    """Raise LimitError when a mesh of ``count`` disturbances is too large to start (see :func:`build_mesh`)."""
    check_at_most("disturbances (--disturbances)", count, MAX_DISTURBANCES, force,
                  why="disturbance samples per mesh state")
    check_fits_memory("disturbances (--disturbances) x max_states (--max-states)",
                      8.0 * count * max_states * samples_per_box, "the mesh's successor table")


def build_mesh(section_map: SectionMap, seeds, disturbances, box_size: float, mean=None, std=None,
               max_states: int = 1_000_000, backend: str = "serial", workers: int | None = None,
               address: str | None = None, batch_size: int = 256, checkpoint: str | os.PathLike | None = None, checkpoint_every: int = 20,
               resume: bool = False, progress: bool = True, checkpoint_minutes: float = 5.0,
               samples_per_box: int = 1, force: bool = False,
               in_process_below: float = PARALLEL_MIN_ROUND_SECONDS) -> ReachableMesh:
    """Reachable-state mesh of ``section_map`` from ``seeds`` under ``disturbances`` (thesis Alg. 7).

    ``disturbances``: a :class:`FiniteDisturbances`, anything with ``finite_set()`` (e.g.
    :class:`GaussianDisturbance`), or a plain sequence (uniform weights). ``box_size``: the
    side of a box in normalised units, ``(state - mean) / std`` (default mean 0, std 1: the
    state's own units). ``max_states``: a cap; when reached, building stops and the mesh is
    marked incomplete. Seeds that fail or are non-finite raise ValueError. Batches run on
    ``backend`` (``workers``; ``address``: the Ray cluster, default ``RAY_ADDRESS``), ``batch_size``
    states a task; a round whose cost, measured on the rounds run here, is below ``in_process_below``
    seconds runs in this process instead (0: every round goes out), and the backend is
    started only when a round goes out. The mesh is the same either way; ``mesh.rounds`` counts both.

    ``checkpoint``: a .npz file the mesh so far is written to (atomically) every
    ``checkpoint_every`` batches and at least every ``checkpoint_minutes`` of wall time (0:
    by batches only), and at the end; ``resume=True`` continues from it (a damaged one, or
    one built with another box size or disturbance count, raises ValueError naming it).

    ``samples_per_box``: how many of the states that reach a box are kept and expanded (1: the
    thesis' one representative per box; k > 1: the first k arrivals, the box's row being the mean
    of theirs). ``max_states`` counts boxes, not samples.

    Before any work, more than :data:`~hybridctl.limits.MAX_DISTURBANCES` disturbances raise
    LimitError (``force`` lifts it), and so does a successor table of ``max_states`` x
    disturbances ids beyond the memory budget (nothing lifts that).
    """
    from tqdm.auto import tqdm

    box_size = float(box_size)
    if not (math.isfinite(box_size) and box_size > 0):
        raise ValueError(f"box_size must be a finite number > 0, got {box_size!r}")
    if not (isinstance(max_states, int) and max_states >= 1):
        raise ValueError(f"max_states must be an integer >= 1, got {max_states!r}")
    if not (isinstance(samples_per_box, (int, np.integer)) and samples_per_box >= 1):
        raise ValueError(f"samples_per_box must be an integer >= 1, got {samples_per_box!r}")
    samples_per_box = int(samples_per_box)
    if not (isinstance(in_process_below, (int, float)) and math.isfinite(in_process_below) and in_process_below >= 0):
        raise ValueError(f"in_process_below must be a finite number of seconds >= 0, got {in_process_below!r}")
    count = getattr(disturbances, "count", None) if hasattr(disturbances, "finite_set") else len(disturbances)
    if isinstance(count, (int, np.integer)):  # before a Gaussian's quantiles are computed
        check_disturbances(int(count), max_states, samples_per_box, force)
    finite = disturbances.finite_set() if hasattr(disturbances, "finite_set") else FiniteDisturbances(list(disturbances))
    values, weights = list(finite.values), np.asarray(finite.weights)
    check_disturbances(len(values), max_states, samples_per_box, force)
    seeds = np.atleast_2d(np.asarray(seeds, dtype=np.float64))
    if seeds.size == 0 or not np.all(np.isfinite(seeds)):
        raise ValueError("seeds must be a non-empty array of finite states (one per row)")
    dim = seeds.shape[1]
    mean = np.zeros(dim) if mean is None else np.broadcast_to(np.asarray(mean, dtype=np.float64), (dim,)).copy()
    std = np.ones(dim) if std is None else np.broadcast_to(np.asarray(std, dtype=np.float64), (dim,)).copy()
    if np.any(std <= 0):
        raise ValueError(f"std must be > 0 in every coordinate, got {std}")
    keys = _Keys(box_size, mean, std)
    settings = {"box_size": box_size, "disturbances": len(values), "max_states": max_states,
                "state_names": list(getattr(section_map, "state_names", ()) or [])}
    if samples_per_box > 1:
        settings["samples_per_box"] = samples_per_box
    path = Path(checkpoint) if checkpoint is not None else None

    mesh_states: list[np.ndarray] = []     # samples; with one per box, the representatives
    owners: list[int] = []                 # box id of each sample
    counts: list[int] = [0]                # samples per box id (index 0: failure)
    successors: list[np.ndarray] = []
    earlier = 0.0
    if not (isinstance(checkpoint_minutes, (int, float)) and math.isfinite(checkpoint_minutes)
            and checkpoint_minutes >= 0):
        raise ValueError(f"checkpoint_minutes must be a finite number >= 0, got {checkpoint_minutes!r}")
    if resume and path is not None and path.exists():
        saved = _load_checkpoint(path)
        if float(saved["box_size"]) != box_size or int(saved["n_disturbances"]) != len(values):
            raise ValueError(f"checkpoint {path} was built with box_size {float(saved['box_size']):g} and "
                             f"{int(saved['n_disturbances'])} disturbances, not {box_size:g} and {len(values)}")
        saved_k = int(saved.get("samples_per_box", 1))
        if saved_k != samples_per_box:
            raise ValueError(f"checkpoint {path} was built with samples_per_box {saved_k}, not {samples_per_box}")
        mesh_states = list(saved["states"])
        owners = [int(o) for o in saved["owners"]] if "owners" in saved else list(range(1, len(mesh_states) + 1))
        counts = np.bincount(owners, minlength=1).tolist() if owners else [0]
        earlier = float(saved["wall_time"]) if "wall_time" in saved else 0.0   # time of the earlier parts
        successors = list(saved["successors"])
        for owner, k in zip(owners, keys.keys(np.array(mesh_states))):
            keys.ids.setdefault(k, owner)
    def add(state: np.ndarray, key: bytes) -> int | None:
        """Box id of ``state`` (a new box, or a further sample of a box with room); None at the cap."""
        found = keys.ids.get(key)
        if found is None:
            if len(counts) - 1 >= max_states:
                return None
            found = keys.ids[key] = len(counts)
            counts.append(0)
        if counts[found] < samples_per_box:
            mesh_states.append(state)
            owners.append(found)
            counts[found] += 1
        return found

    seed_ids = []
    fresh = not mesh_states
    for s, k in zip(seeds, keys.keys(seeds)):
        if not fresh and k in keys.ids:    # resumed: the seeds' boxes are known, their samples kept
            seed_ids.append(keys.ids[k])
            continue
        found = add(s, k)
        if found is None:
            break
        seed_ids.append(found)

    start = time.perf_counter()
    complete = True
    bar = tqdm(total=len(mesh_states), initial=len(successors), desc="mesh", unit="state", disable=not progress)
    # a round whose measured cost is small runs here (a cheap formula map never waits on workers); the
    # backend is made on the first round worth sending out, with batch_size states per worker
    # (serial: every round here, which is what the serial backend would do)
    rounds = SizedRounds(lambda: _backend(backend, workers, address),
                         math.inf if backend == "serial" else in_process_below)
    last_checkpoint = time.monotonic()
    try:
        batches = 0
        while len(successors) < len(mesh_states):
            lo = len(successors)
            here = rounds.here(min(batch_size, len(mesh_states) - lo) * len(values))
            hi = min(len(mesh_states), lo + batch_size * (1 if here else getattr(rounds.made(), "workers", 1)))
            chunk = np.array(mesh_states[lo:hi])
            parts = [(section_map, chunk[i:i + batch_size], values) for i in range(0, hi - lo, batch_size)]
            nxt = rounds.run((hi - lo) * len(values), lambda: _expand((section_map, chunk, values)),
                             lambda pool: np.concatenate(pool.map(_expand, parts)))    # (hi - lo, K, dim), in order
            failed = np.isnan(nxt).any(axis=2)
            for row, fail_row in zip(nxt, failed):
                ids = np.zeros(len(values), dtype=np.int64)
                ok = np.flatnonzero(~fail_row)
                marks = (len(mesh_states), len(counts))
                for j, k in zip(ok, keys.keys(row[ok])):
                    found = add(row[j], k)
                    if found is None:
                        complete = False
                        break
                    ids[j] = found
                if not complete:
                    if samples_per_box > 1:
                        _undo_row(marks, mesh_states, owners, counts, keys)
                    break
                successors.append(ids)
            bar.total = len(mesh_states)
            bar.update(len(successors) - bar.n)
            batches += 1
            by_time = checkpoint_minutes > 0 and time.monotonic() - last_checkpoint >= 60.0 * checkpoint_minutes
            if path is not None and (batches % checkpoint_every == 0 or by_time or not complete):
                _save_checkpoint(path, mesh_states, successors, box_size, len(values),
                                 earlier + time.perf_counter() - start, owners, samples_per_box)
                last_checkpoint = time.monotonic()
            if not complete:
                break
    finally:
        bar.close()
        if rounds.backend is not None:
            _release(rounds.backend)
    if path is not None:
        _save_checkpoint(path, mesh_states, successors, box_size, len(values), earlier + time.perf_counter() - start,
                         owners, samples_per_box)
    return ReachableMesh(np.array(mesh_states).reshape(-1, dim),
                         np.array(successors, dtype=np.int64).reshape(-1, len(values)), weights, box_size, mean, std,
                         np.array(seed_ids, dtype=np.int64), complete, earlier + time.perf_counter() - start, settings,
                         None if samples_per_box == 1 else np.array(owners, dtype=np.int64), dict(rounds.rounds))


@dataclass
class MonteCarloResult:
    """Steps to failure of Monte Carlo runs on the true map, with a 95 % interval of the mean."""

    steps: np.ndarray
    censored: int
    max_steps: int

    @property
    def mean(self) -> float:
        """Mean steps to failure (a lower bound when runs were censored at ``max_steps``)."""
        return float(self.steps.mean())

    @property
    def interval95(self) -> tuple[float, float]:
        """Normal-approximation 95 % interval of the mean."""
        half = 1.96 * self.steps.std(ddof=1) / math.sqrt(self.steps.size) if self.steps.size > 1 else float("inf")
        return (self.mean - half, self.mean + half)

    def summary(self) -> dict:
        """JSON-ready summary."""
        lo, hi = self.interval95
        return {"episodes": int(self.steps.size), "mean_steps_to_failure": self.mean, "std": float(self.steps.std()),
                "interval95": [lo, hi], "censored": self.censored, "max_steps": self.max_steps,
                "note": (f"{self.censored} runs reached max_steps without failing: the mean is a lower bound"
                         if self.censored else "")}


def monte_carlo_mfpt(section_map: SectionMap, starts, disturbances, episodes: int = 1000, max_steps: int = 100_000,
                     seed: int = 0, chunks: int = 1, backend: str = "serial", workers: int | None = None,
                     progress: bool = False, force: bool = False, address: str | None = None) -> MonteCarloResult:
    """Steps until failure on the true map, each step's disturbance drawn from ``disturbances``
    (``sample(rng, n)``: a Gaussian model draws continuous values, a finite set draws from the set).

    ``starts``: one state, or several drawn uniformly per episode. The episodes are split into
    ``chunks`` groups (each with its own random stream from ``SeedSequence(seed)``); a group's
    episodes advance together through ``section_map.step_many``. Groups run on ``backend``
    ("serial", "processes", "ray"; ``address``: the Ray cluster, default ``RAY_ADDRESS``), so for
    simulator-backed maps use several chunks and processes; the result depends on ``seed`` and
    ``chunks`` only, not on the backend.

    Before any work, more than :data:`~hybridctl.limits.MAX_MONTE_CARLO` episodes raise
    LimitError (``force`` lifts it), and so do their states beyond the memory budget.
    """
    if episodes < 2 or max_steps < 1:
        raise ValueError(f"episodes must be >= 2 and max_steps >= 1, got {episodes} and {max_steps}")
    check_at_most("episodes (--monte-carlo)", episodes, MAX_MONTE_CARLO, force, why="Monte Carlo runs")
    if not (isinstance(chunks, int) and 1 <= chunks <= episodes):
        raise ValueError(f"chunks must be an integer in [1, episodes={episodes}], got {chunks!r}")
    starts = np.atleast_2d(np.asarray(starts, dtype=np.float64))
    # per episode: its state, the next one, its step count and its index (float64 / int64)
    check_fits_memory("episodes (--monte-carlo)", 8.0 * episodes * (2 * starts.shape[1] + 2), "the episodes' states")
    sizes = [len(part) for part in np.array_split(np.arange(episodes), chunks)]
    streams = [np.random.default_rng(seed)] if chunks == 1 else \
        [np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(chunks)]
    tasks = [(section_map, starts, disturbances, n, max_steps, rng) for n, rng in zip(sizes, streams)]
    pool = _backend(backend, workers, address)
    try:
        if progress and chunks > 1:
            from tqdm.auto import tqdm
            parts, step = [], max(1, getattr(pool, "workers", 1))   # one batch of chunks per round of workers
            with tqdm(total=len(tasks), desc="monte carlo", unit="chunk") as bar:
                for i in range(0, len(tasks), step):
                    parts.extend(pool.map(_monte_carlo_chunk, tasks[i:i + step]))
                    bar.update(len(tasks[i:i + step]))
        else:
            parts = pool.map(_monte_carlo_chunk, tasks)
    finally:
        _release(pool)
    passage = np.concatenate([p[0] for p in parts])
    return MonteCarloResult(passage.astype(np.float64), int(sum(p[1] for p in parts)), max_steps)


def _monte_carlo_chunk(task) -> tuple[np.ndarray, int]:
    """Worker: first passage times of ``n`` episodes (and how many were censored)."""
    section_map, starts, disturbances, n, max_steps, rng = task
    x = starts[rng.integers(0, starts.shape[0], size=n)].copy()
    steps = np.zeros(n, dtype=np.int64)
    alive = np.ones(n, dtype=bool)
    for _ in range(max_steps):
        idx = np.flatnonzero(alive)
        if idx.size == 0:
            break
        nxt = np.asarray(section_map.step_many(x[idx], list(disturbances.sample(rng, idx.size))), dtype=np.float64)
        ok = ~np.isnan(nxt).any(axis=1)
        steps[idx[ok]] += 1
        x[idx[ok]] = nxt[ok]
        alive[idx[~ok]] = False
    # a step that fails is counted as the passage into failure: first passage time = successes + 1
    return steps + (~alive), int(alive.sum())


def mesh_sizes(section_map: SectionMap, seeds, disturbances, box_sizes: Sequence[float], **kwargs) -> list[dict]:
    """Mesh size (and completeness) for each box size: the reachable-mesh curve of thesis Table 5.1."""
    out = []
    for d in box_sizes:
        mesh = build_mesh(section_map, seeds, disturbances, d, progress=False, **kwargs)
        out.append({"box_size": float(d), "states": mesh.size, "complete": mesh.complete,
                    "wall_time_s": mesh.wall_time})
    return out


def reachable_dimension(rows: list[dict]) -> float:
    """Dimension of the reachable set: least-squares slope of -log(mesh size) over log(box size)
    for the complete meshes of :func:`mesh_sizes` (thesis Table 5.2)."""
    done = [r for r in rows if r["complete"] and r["states"] > 0]
    if len(done) < 2:
        raise ValueError(f"need at least 2 complete meshes of different box sizes, got {len(done)}")
    d = np.log([r["box_size"] for r in done])
    m = np.log([r["states"] for r in done])
    return float(np.polyfit(d, -m, 1)[0])


def failure_states(mesh: ReachableMesh, share: float = 0.99, start=None) -> np.ndarray:
    """Mesh rows (0-based) of the fewest states that account for ``share`` of all failures
    (thesis Fig. 5.6, red). Failures are weighted by each state's one-step failure probability
    times its expected visits before failure from ``start`` (default: the seeds). States that can
    avoid failure forever have no finite visit count; they are weighted by their failure probability."""
    if not 0 < share <= 1:
        raise ValueError(f"share must be in (0, 1], got {share!r}")
    T = mesh.transition_matrix()
    p0 = mesh.seed_distribution() if start is None else np.asarray(start, dtype=np.float64)
    sure = states_that_can_fail_surely(T, FAILURE)[1:]          # (I - Q) is invertible only on these
    visits = np.ones(mesh.size)   # states that can avoid failure forever: ranked by failure probability alone
    idx = np.flatnonzero(sure)
    if idx.size and p0[1:][idx].sum() > 0:
        Q = T[idx + 1][:, idx + 1].tocsr()
        A = (sp.identity(idx.size, format="csr") - Q).T.tocsr()
        visits[idx], _ = _krylov_solve(A, p0[1:][idx], rtol=1e-10)   # expected visits before failure
    weight = np.maximum(visits, 0) * mesh.failure_probability()
    if weight.sum() <= 0:
        return np.zeros(0, dtype=np.int64)
    order = np.argsort(-weight)
    cum = np.cumsum(weight[order]) / weight.sum()
    count = min(int(np.searchsorted(cum, share * (1 - 1e-12)) + 1), int(np.count_nonzero(weight > 0)))
    return np.sort(order[:count])
