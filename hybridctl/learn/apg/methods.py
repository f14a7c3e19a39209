"""One small class per Ch. 7 method, each writing only what differs from :class:`~.family.APGFamily`,
and the registry :data:`~.config.METHOD_CLASSES` that maps ``APGConfig.method`` to its class.

* :class:`APG` (``"apg"``) -- one policy, full backpropagation through time over the episode;
  the family's entry point: ``APG(system, config)`` builds the class of ``config.method``;
* :class:`PAPG` (``"papg"``) -- K APG runs side by side, the best member the result;
* :class:`ShortHorizonAPG` (``"shapg"``) -- PAPG whose updates unroll ``short_horizon`` steps;
* :class:`CEM` (``"cem"``) -- the cross-entropy method on the parameters, candidates scored by one rollout;
* :class:`CEAPG` (``"ce-apg"``) -- CEM whose candidates are first improved by an APG phase (Alg. 9).
"""

from __future__ import annotations

import torch

from .config import METHOD_CLASSES, METHODS, APGConfig
from .core import BatchedAdam, cem_update, evaluate_members, median_norm
from .family import APGFamily, EpochStep

__all__ = ["APG", "PAPG", "ShortHorizonAPG", "CEM", "CEAPG"]


class APG(APGFamily):
    """APG (thesis eq. 7.10): theta <- theta + alpha grad_theta (1/N) sum_i sum_t r(s_t^i) with Adam,
    ``apg_iterations`` updates per epoch, each through the whole episode (``truncation``: the
    graph cut every that many steps); the member after the epoch is the result.

    The family's entry point: ``APG(system, config)`` (and :meth:`load`) build the class of
    ``config.method`` from :data:`~.config.METHOD_CLASSES`; ``APG(system)`` without a config
    is CE-APG (``APGConfig``'s default, the thesis' method).
    """

    algorithm_name = "APG"                 # the family's checkpoints load through this entry point
    controller_aliases = METHODS           # named controllers apg:PATH, papg:PATH, ...
    train_names, train_order = METHODS, 3  # hybridctl train apg / shapg / papg / cem / ce-apg
    method = "apg"
    preset_settings = {"thesis": {"population": 1, "elites": 1}, "reduced": {}}

    def __new__(cls, system=None, config: APGConfig | None = None, **overrides):
        if "method" in overrides:
            method = overrides["method"]
        elif config is not None:
            method = config.method
        else:   # the class's own method; the entry point's default config is APGConfig()'s (CE-APG)
            method = APGConfig().method if cls is APG else cls.method
        target = METHOD_CLASSES.get(method, cls)   # an unknown method: __init__'s validate names it
        if not issubclass(target, cls):
            raise ValueError(f"{cls.__name__} runs method {cls.method!r}, not {method!r}; "
                             f"APG(system, config) builds the class of config.method")
        return super().__new__(target)

    @classmethod
    def member_count(cls, config: APGConfig) -> int:
        """One policy."""
        return 1

    def epoch_update(self, lr: float) -> EpochStep:
        """The APG phase of the members with their own Adam moments (kept across epochs); ranked by
        the mean of their last ``rank_window`` training returns."""
        cfg = self.config
        phase = self.run_apg_phase(self.members, lr, self.adam)
        self.adam = phase.adam
        scores = phase.returns[-cfg.rank_window:].mean(0)
        elite = torch.argsort(scores, descending=True, stable=True)[:cfg.elites]
        return EpochStep(phase.theta, phase.returns, scores, elite, median_norm(phase.norms), phase.obs_sums)

    def keep_best(self, finals: torch.Tensor, scores: torch.Tensor, top: int) -> None:
        """The best member NOW is the result (the author's PAPG script returns the initial parameters
        by mistake)."""
        self.best, self.best_score = finals[top].clone(), float(scores[top])


class PAPG(APG):
    """PAPG (thesis Sec. 7.5): K = ``population`` APG runs side by side; the best member (by its
    last training returns) is the result."""

    method = "papg"
    preset_settings = {"thesis": {}, "reduced": {"population": 8, "elites": 3}}

    @classmethod
    def member_count(cls, config: APGConfig) -> int:
        """The population."""
        return config.population


class ShortHorizonAPG(PAPG):
    """Short-horizon APG, the peer of today's Brax APG (SHAC's actor without critic): each episode
    as ``short_horizon``-step unrolls from the carried state, one update each; its preset clips
    at 1.0 and uses Adam betas (0.7, 0.95) (Brax APG 0.14, SHAC)."""

    method = "shapg"
    preset_settings = {"thesis": {"clip": 1.0, "clip_mode": "norm", "beta1": 0.7, "beta2": 0.95},
                       "reduced": {"population": 8, "elites": 3}}

    @classmethod
    def unroll(cls, config: APGConfig) -> int:
        """``short_horizon`` policy steps."""
        return config.short_horizon

    @classmethod
    def check_config(cls, config: APGConfig) -> None:
        """An unroll longer than the episode would silently be the whole episode."""
        if config.short_horizon > config.horizon:
            raise ValueError(f"APGConfig.short_horizon ({config.short_horizon}) must be <= horizon "
                             f"({config.horizon}): an unroll is part of an episode")


class CEM(APG):
    """The cross-entropy method on the parameters (thesis eqs. 7.11, 7.13): each epoch draws K
    candidates from N(mean, std^2) (a diagonal Gaussian, theta = 0 with std sigma_0 at first),
    scores them (:meth:`improve`), and the ``elites`` best give the new mean and the new
    per-parameter std sqrt(mean_e (old mean - theta_e)^2), measured about the OLD mean as the
    author's code does (about the new mean would be the textbook CEM variance; about the old
    mean it also grows when the elites move together, which keeps exploring). The result is the
    mean; ``best`` is the best candidate seen (the author's metric)."""

    method = "cem"
    default_policy = "mean"
    preset_settings = {"thesis": {"epochs": 2000},                      # thesis Sec. 7.5
                       "reduced": {"population": 8, "elites": 3, "epochs": 200}}

    @classmethod
    def member_count(cls, config: APGConfig) -> int:
        """The population of candidates."""
        return config.population

    def improve(self, candidates: torch.Tensor, lr: float):
        """CEM: one rollout of the candidates from ``batch`` starts seeded (seed, epoch, 0, 1), no
        gradient. Returns (final candidates, history [1, K], scores [K], grad norm, obs sums)."""
        cfg = self.config
        x0 = self.starts(cfg.batch, [cfg.seed, self.epoch, 0, 1])
        scores, obs_sums = evaluate_members(self.problem, candidates, x0)
        self.iterations += 1
        self.env_steps += self.K * cfg.batch * cfg.horizon
        return candidates, scores[None], scores, float("nan"), obs_sums

    def epoch_update(self, lr: float) -> EpochStep:
        """Candidates from N(mean, std^2) (the epoch's own generator), :meth:`improve`, the CEM update."""
        noise = torch.randn((self.K, self.pop.n_params), dtype=torch.float64, generator=self._generator(self.epoch),
                            device=self.device)
        candidates = self.mean[None] + self.std[None] * noise
        finals, history, scores, grad_norm, obs_sums = self.improve(candidates, lr)
        self.mean, self.std, elite = cem_update(self.mean, finals, scores, self.config.elites)
        return EpochStep(finals, history, scores, elite, grad_norm, obs_sums)

    def keep_best(self, finals: torch.Tensor, scores: torch.Tensor, top: int) -> None:
        """The best candidate seen in any epoch (the author's metric)."""
        if float(scores[top]) > self.best_score:
            self.best, self.best_score = finals[top].clone(), float(scores[top])


class CEAPG(CEM):
    """CE-APG, thesis Alg. 9: each epoch draws K_a candidates from N(mean, std^2), improves each by
    ``apg_iterations`` APG steps (fresh Adam moments), and the K_e best (mean of the last
    ``rank_window`` training returns, as the author's code) give the new mean (eq. 7.11) and
    std (eq. 7.13) as in :class:`CEM`."""

    method = "ce-apg"
    preset_settings = {"thesis": {}, "reduced": {"population": 8, "elites": 3}}

    def improve(self, candidates: torch.Tensor, lr: float):
        """The APG phase of the candidates; ranked by the mean of their last ``rank_window`` returns."""
        cfg = self.config
        phase = self.run_apg_phase(candidates, lr, BatchedAdam(self.K, self.pop.n_params, (cfg.beta1, cfg.beta2),
                                                               device=self.device))
        scores = phase.returns[-cfg.rank_window:].mean(0)
        return phase.theta, phase.returns, scores, median_norm(phase.norms), phase.obs_sums


METHOD_CLASSES.update({"apg": APG, "shapg": ShortHorizonAPG, "papg": PAPG, "cem": CEM, "ce-apg": CEAPG})
assert tuple(METHOD_CLASSES) == METHODS and all(METHOD_CLASSES[m].method == m for m in METHODS)
