"""Antithetic random search, written once: ARS (thesis Ch. 4) and fine-tuning (thesis Ch. 6, Alg. 8).

One update: draw N Gaussian directions delta_k and one env seed per direction from
``SeedSequence([seed, update])``; roll out theta + sigma delta_k and theta - sigma delta_k on
the same env seed; keep the b directions with the largest max(r+, r-) (ARS's top-b; fine-tuning
keeps all, b = N, in draw order); step

    theta <- theta + alpha / (b sigma_R + eps) * sum_k (r+_k - r-_k) delta_k

with sigma_R the std of the 2b kept returns. ARS: alpha and sigma constant, eps 0 (no step when
sigma_R is 0); fine-tuning: alpha and sigma on linear schedules, eps 1e-6 (the author's code).

:class:`RandomSearchLearner` is the learner both subclass: its :meth:`~RandomSearchLearner.train_update`
is the update above, its :meth:`~RandomSearchLearner.train` the loop (:meth:`hybridctl.learn.run.Run.updates`
on a backend of :mod:`hybridctl.parallel`). A subclass says how to roll out a batch of
parameter vectors (:meth:`~RandomSearchLearner.perturbed_rollouts`, on
:mod:`hybridctl.learn.rollouts`), its step size and noise per update
(:meth:`~RandomSearchLearner.schedule`), b and eps, and what it does with the rollouts
after the step (ARS: the running observation normalisation).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..parallel import make_backend
from .base import Learner
from .run import check_finite, set_torch_threads

__all__ = ["draws", "antithetic", "random_search_step", "RandomSearchLearner"]


def draws(seed: int, update: int, n_directions: int, n_params: int) -> tuple[np.ndarray, list[int]]:
    """Directions (n_directions, n_params) and one env seed per direction for ``update``, from the seed alone
    (so every backend, and a resumed run, draws the same)."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, update]))
    directions = rng.standard_normal((n_directions, n_params))
    seeds = [int(s) for s in rng.integers(0, 2 ** 31 - 1, size=n_directions)]
    return directions, seeds


def antithetic(theta: np.ndarray, directions: np.ndarray, noise: float) -> np.ndarray:
    """The perturbed parameters (2N, P): rows theta + noise delta_k, theta - noise delta_k for each k."""
    return np.stack([theta + sign * noise * d for d in directions for sign in (1.0, -1.0)])


def random_search_step(theta: np.ndarray, directions: np.ndarray, returns: np.ndarray, step_size: float,
                       top: int | None = None, eps: float = 0.0) -> tuple[np.ndarray | None, float]:
    """(the stepped theta, sigma_R) for ``returns`` (N, 2: r+, r-) of ``directions`` (N, P).

    ``top``: keep the ``top`` directions with the largest max(r+, r-) (ARS's b; a stable sort);
    None keeps all in draw order. The step is ``step_size / (b sigma_R + eps)`` times the
    return-weighted sum of the kept directions; None instead of theta when that denominator is 0
    (ARS with equal returns: no step).
    """
    if top is None:
        kept, kept_directions, b = returns, directions, len(returns)
    else:
        order = np.argsort(-np.max(returns, axis=1), kind="stable")[:top]
        kept, kept_directions, b = returns[order], directions[order], top
    sigma_r = kept.std()
    denominator = b * sigma_r + eps
    if not denominator > 0:
        return None, float(sigma_r)
    return theta + step_size / denominator * ((kept[:, 0] - kept[:, 1]) @ kept_directions), float(sigma_r)


class RandomSearchLearner(Learner):
    """A learner that improves a parameter vector ``theta`` by antithetic random search (ARS, fine-tuning).

    A subclass has ``config`` with ``seed``, ``n_directions``, ``checkpoint_every``, ``backend``,
    ``workers``, ``address``; the attributes ``theta``, ``env_steps``, ``wall_time``, ``history``
    and its counter named by ``log_key`` (``epoch``, ``update``); and writes
    :meth:`perturbed_rollouts`, :meth:`schedule`, :meth:`top_directions`.
    """

    uses_backend = True
    step_eps = 0.0             # eps of the step's denominator
    display_name = "random search"   # in error messages: "<display_name> <unit> <n>: ..."
    theta_name = "theta"       # in the NaN guard's message

    # -- what a subclass says ----------------------------------------------------------------
    def perturbed_rollouts(self, thetas: np.ndarray, seeds: list[int], backend) -> list[dict]:
        """One training episode per row of ``thetas`` on env seed ``seeds[i]``
        (:mod:`hybridctl.learn.rollouts` results, in row order)."""
        raise NotImplementedError

    def schedule(self, update: int) -> tuple[float, float]:
        """(step size alpha, noise sigma) of ``update`` (0-based)."""
        raise NotImplementedError

    def top_directions(self) -> int | None:
        """b, the directions kept per update (None: all, in draw order)."""
        return None

    def after_rollouts(self, results: list[dict]) -> None:
        """Hook after the step: e.g. ARS's normalisation update (V2), in task order."""

    def update_row(self, step_size: float, noise: float) -> dict:
        """Hook: the update's own columns of its progress row."""
        return {}

    # -- state ----------------------------------------------------------------------------------
    def _start(self, config, env, env_kwargs: dict | None, overrides: dict) -> None:
        """A fresh learner's settings (``config`` with ``overrides``, validated; torch threads), env
        (``env_name``: an id as given, a factory by its name) and counters (zero, empty history)."""
        self.config = dataclasses.replace(config, **overrides)
        self.config.validate()
        set_torch_threads(self.config.torch_threads)
        self.env, self.env_kwargs = env, env_kwargs
        self.env_name = env if isinstance(env, str) else getattr(env, "__name__", repr(env))
        setattr(self, self.log_key, 0)
        self.env_steps, self.wall_time = 0, 0.0
        self.history: list[dict] = []
        self.log_rows: list[dict] = []

    @property
    def progress_count(self) -> int:
        """Updates so far (ARS's epochs, fine-tuning's updates: the progress.csv key)."""
        return getattr(self, self.log_key)

    # -- the update ----------------------------------------------------------------------------
    @property
    def n_params(self) -> int:
        """Length of theta."""
        return int(self.theta.size)

    def draws(self, update: int) -> tuple[np.ndarray, list[int]]:
        """Directions (N, n_params) and one env seed per direction for ``update`` (from the seed alone)."""
        return draws(self.config.seed, update, self.config.n_directions, self.n_params)

    def train_update(self, backend) -> dict:
        """One update: 2N rollouts on ``backend``, top-b directions, step scaled by the kept returns' std;
        the progress row."""
        n = self.progress_count
        step_size, noise = self.schedule(n)
        directions, seeds = self.draws(n)
        results = self.perturbed_rollouts(antithetic(self.theta, directions, noise),
                                          [s for s in seeds for _ in (0, 1)], backend)
        bad = [i for i, r in enumerate(results) if not r["finite"]]
        if bad:
            raise FloatingPointError(f"{self.display_name} {self.unit} {n}: {len(bad)} rollouts produced NaN/inf states "
                                     f"or rewards (first: direction {bad[0] // 2}); training stopped, the last "
                                     f"checkpoint is intact")
        r = np.array([res["return"] for res in results]).reshape(self.config.n_directions, 2)
        theta, sigma_r = random_search_step(self.theta, directions, r, step_size, self.top_directions(),
                                            self.step_eps)
        if theta is not None:
            check_finite(self.theta_name, theta, f"at {self.unit} {n + 1}")
            self.theta = theta
        self.after_rollouts(results)
        steps = sum(res["steps"] for res in results)
        self.env_steps += steps
        setattr(self, self.log_key, n + 1)
        return {self.log_key: n + 1, "env_steps": self.env_steps, "mean_return": float(r.mean()),
                "max_return": float(r.max()), "mean_raw_return": float(np.mean([x["raw_return"] for x in results])),
                "mean_dimension": float(np.mean([x["dimension"] for x in results])), "sigma_r": sigma_r,
                **self.update_row(step_size, noise), "episode_steps": steps / len(results)}

    def train(self, run, target: int, backend) -> None:
        """The loop inside ``learn``'s run: one update (2 x ``n_directions`` rollouts on ``backend``,
        default the config's, opened for the run) at a time, a checkpoint every ``checkpoint_every``
        updates and at least every ``checkpoint_minutes``."""
        own = backend is None
        pool = backend or make_backend(self.config.backend, self.config.workers, self.config.address)
        try:
            run.updates(target, lambda: self.train_update(pool), 2 * self.config.n_directions,
                        self.config.checkpoint_every,
                        lambda row: {"ret": f"{row['mean_raw_return']:.1f}", "dim": f"{row['mean_dimension']:.2f}",
                                     "sps": f"{row['steps_per_s']:.0f}"})
        finally:
            if own:
                pool.close()
