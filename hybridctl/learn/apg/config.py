"""The settings of the Ch. 7 learners (:class:`APGConfig`), the method names, the presets, and the
registry that maps a method name to its learner class (:data:`METHOD_CLASSES`, filled by
:mod:`.methods`: the one place where a method name picks code)."""

from __future__ import annotations

import math
from dataclasses import dataclass


from ... import systems as systems_mod
from ...parallel import BACKENDS
from ...systems.compiled import COMPILE_MODES
from ..config_check import check_fields, check_types
from ..policies import KINDS as POLICY_KINDS
from ..config_check import check_device_field

__all__ = ["APGConfig", "METHODS", "PRESETS", "OBSERVATIONS", "TAKEOVERS", "METHOD_CLASSES", "parse_policy",
           "lr_schedule"]

METHODS = ("apg", "shapg", "papg", "cem", "ce-apg")
PRESETS = ("thesis", "reduced")
OBSERVATIONS = ("trig", "state")
TAKEOVERS = ("none", "lqr")

METHOD_CLASSES: dict[str, type] = {}
"""Learner class by ``APGConfig.method`` (``"apg"``: :class:`~.methods.APG`, ``"shapg"``:
:class:`~.methods.ShortHorizonAPG`, ``"papg"``: :class:`~.methods.PAPG`, ``"cem"``:
:class:`~.methods.CEM`, ``"ce-apg"``: :class:`~.methods.CEAPG`), filled once by :mod:`.methods`.
What differs between the methods (member count, presets, a method's own config checks) is
read from the class here, never from a branch on the name."""


@dataclass
class APGConfig:
    """Every setting of the Ch. 7 learners, with the thesis' value and its source.

    Sources: thesis Sec. 7.3.7 (table "CE-APG Hyperparameter") and the implementation
    notes, Ch. 7 (the author's sgillen/apg code). Our systems keep their own parameters
    (the thesis' Brax models differ), so no return here is comparable number for number.
    """

    method: str = "ce-apg"             # one of METHODS
    # --- task
    reward_kind: str = "angle_squared"  # a Ch. 7 reward kind of the spec (systems.spec.CH7_REWARD_KINDS); thesis
    #                                    Sec. 7.2.3-7.2.4 (acrobot, cart-pole); "tip_distance" eqs. 7.5-7.8
    alive_bonus: float = 0.0           # reward.alive_bonus; author's acrobot / double cart-pole: 10
    velocity_penalty: float = 0.0      # reward.velocity_penalty; author's acrobot / double cart-pole: 0.01
    position_weight: float = 0.0       # reward.position_weight (cart x^2); author's double cart-pole: 1
    linear_velocity_weight: float = 0.0  # reward.linear_velocity_weight (cart speed^2); hybridctl, not the thesis'
    cost_to_go_weight: float = 0.0     # reward.cost_to_go_weight (k log(1 + LQR cost-to-go / gate scale)); hybridctl
    horizon: int = 500                 # T policy steps per episode, thesis Sec. 7.3.4 ("at least 500 steps")
    control_period: float | None = None  # s per policy step; None: the spec's control.swingup_period
    start_noise: float | None = 0.01   # starts hanging down +- U(-0.01, 0.01) per state, author's envs
    #                                    (implementation notes Ch. 7); None: the spec's initial_state spread
    observation: str = "trig"          # "trig": [cart x, sin, cos of each angle error, velocities]; "state":
    #                                    the wrapped state error (jumps at +-pi). hybridctl choice.
    takeover: str = "none"             # "none": the policy acts all episode (thesis Ch. 7); "lqr": hybridctl, the
    #                                    switched controller as in Drake (Ch. 3): the spec's cost-to-go gate with
    #                                    hysteresis hands over to the saturated LQR every integrator step, and the
    #                                    gradient flows through the LQR phase (see LQRTakeover)
    # --- policy
    policy: str = "gru"                # "gru" (thesis Sec. 7.3.4), "linear" or "mlp:W1,W2,..." (ReLU widths)
    init_std: float = 0.05             # sigma_0 and the initial perturbation of zero weights, thesis Sec. 7.3.7
    normalize: bool = True             # running obs statistics, updated once per epoch, frozen during APG
    #                                    (implementation notes Ch. 7)
    dtype: str = "float32"             # "float32" (as JAX's default in the thesis' Brax) or "float64"
    compile: str = "auto"              # hybridctl: torch.compile the per-step work (policy, sub-steps, reward):
    #                                    "on", "off" or "auto" (runs of >= compiled.APG_AUTO_COMPILE_MIN_STEPS policy
    #                                    steps; a failure to compile falls back to eager). Older records' true /
    #                                    false read as "on" / "off". 5-15x faster an iteration once compiled
    compile_steps: int | None = None   # hybridctl: policy steps per compiled call (with compile); 1: one call per
    #                                    step (the records before this field); None: about compiled.COMPILED_INTEGRATOR_
    #                                    STEPS integrator steps a call (10 at 4 sub-steps). Acrobot, T 500, 24 x 4:
    #                                    0.35 s per APG iteration at 1, 0.17 s at 10 (benchmarks/apg.py)
    # --- APG
    batch: int = 4                     # N starts per APG iteration, thesis Sec. 7.3.7
    apg_iterations: int = 100          # APG iterations per CE epoch, thesis Sec. 7.3.7 ("APG Epochs")
    lr_start: float = 1e-3             # thesis Sec. 7.3.7: 1e-3 -> 1e-6,
    lr_end: float = 1e-6               # log-linear over the CE epochs (implementation notes Ch. 7)
    beta1: float = 0.9                 # Adam betas: optax/torch defaults (the author's optax.adam);
    beta2: float = 0.999               # shapg: (0.7, 0.95) as Brax APG 0.14 and SHAC
    truncation: int | None = None      # cut the graph every this many steps; None: full BPTT (thesis)
    clip: float | None = None          # gradient clipping; None: off (the author's, effectively)
    clip_mode: str = "norm"            # "norm" (per member's global norm) or "value" (elementwise)
    grad_bound: float = 1e8            # a member gradient with a larger norm is skipped (hybridctl guard)
    short_horizon: int = 32            # shapg unroll length (Brax APG 0.14, SHAC)
    # --- population
    population: int = 24               # K_a, thesis Sec. 7.3.7 (one per XLA CPU device in the author's code)
    elites: int = 8                    # K_e, thesis Sec. 7.3.7
    rank_window: int = 5               # elites ranked by the mean of the last 5 APG training returns (author)
    epochs: int = 200                  # CE epochs, thesis Sec. 7.3.7 ("Total Epochs"); cem: thesis 2000
    # --- bookkeeping
    seed: int = 0
    checkpoint_every: int = 1          # epochs between checkpoints
    eval_episodes: int = 16            # held-out starts in evaluate()
    torch_threads: int = 1             # see run.set_torch_threads (also in each worker)
    device: str = "cpu"                # hybridctl: where the population, its rollouts, Adam, the CEM draws and the
    #                                    start states live ("cpu", "cuda", "cuda:1"); initial weights are drawn on
    #                                    the CPU from the seed and moved, so a seed starts alike on every device.
    #                                    The split APG phase's workers use it too (arrays travel between them)
    # --- parallel (hybridctl; the thesis' author ran one member per XLA CPU device)
    backend: str = "serial"            # hybridctl: "serial" (one process), "processes" (spawned local processes)
    #                                    or "ray" (a population that does not fit one process): each epoch's
    #                                    APG phase runs as contiguous chunks of members, one per worker
    workers: int | None = None         # hybridctl: number of chunks; None: the backend's workers (every core,
    #                                    or the Ray cluster's CPUs)
    address: str | None = None         # hybridctl: the Ray cluster ("ray://host:10001", "auto"), as ARS's and
    #                                    fine-tuning's; None: RAY_ADDRESS, else a new local Ray instance (backend
    #                                    "ray" only). Older checkpoints recorded it as ``ray_address``

    def __post_init__(self):
        if isinstance(self.compile, bool):   # the field's former type: true / false in older records and calls
            self.compile = "on" if self.compile else "off"

    def total_policy_steps(self, members: int) -> int:
        """Policy steps of the whole run for ``members`` members (x batch x horizon x APG iterations x
        epochs): what ``compile = "auto"`` weighs against its compile time."""
        return int(members) * self.batch * self.horizon * self.apg_iterations * self.epochs

    RENAMED = {"ray_address": "address"}
    """Fields older checkpoints recorded under another name (old name -> today's), see :meth:`upgrade_recorded`."""

    @classmethod
    def upgrade_recorded(cls, recorded: dict) -> dict:
        """A checkpoint's recorded config in today's field names (``ray_address`` is ``address`` since
        the flag became ``--address`` for every learner); today's name wins when both are present. A
        record from before ``compile_steps`` ran one compiled call per policy step: it resumes so."""
        out = dict(recorded)
        out.setdefault("compile_steps", 1)
        for old, new in cls.RENAMED.items():
            if old in out:
                value = out.pop(old)
                out.setdefault(new, value)
        return out

    def describe_budget(self) -> str:
        """The run's budget in a run's account: epochs of members x batch x horizon steps."""
        return (f"{self.epochs} epochs of {METHOD_CLASSES[self.method].member_count(self)} x {self.batch} x "
                f"{self.horizon} steps, seed {self.seed}")

    def validate(self) -> None:
        """Raise ValueError naming the first invalid field."""
        check_types(self)
        check_fields(self, integers_from_1=("horizon", "batch", "apg_iterations", "short_horizon", "population",
                                            "elites", "rank_window", "epochs", "checkpoint_every", "eval_episodes",
                                            "torch_threads"),
                     integers_from_0=("seed",), positive=("lr_start", "lr_end", "grad_bound"))
        if self.compile_steps is not None:
            check_fields(self, integers_from_1=("compile_steps",))
        parse_policy(self.policy)
        for name, options in (("method", METHODS), ("observation", OBSERVATIONS), ("takeover", TAKEOVERS),
                              ("backend", BACKENDS), ("compile", COMPILE_MODES),
                              ("clip_mode", ("norm", "value")), ("dtype", ("float32", "float64"))):
            if getattr(self, name) not in options:
                raise ValueError(f"APGConfig.{name} must be one of {options}, got {getattr(self, name)!r}")
        if self.reward_kind not in systems_mod.spec.CH7_REWARD_KINDS:
            raise ValueError(f"APGConfig.reward_kind must be one of {systems_mod.spec.CH7_REWARD_KINDS}, "
                             f"got {self.reward_kind!r}")
        if self.workers is not None and self.workers < 1:
            raise ValueError(f"APGConfig.workers must be None (the backend's workers) or an integer >= 1, "
                             f"got {self.workers!r}")
        if self.address is not None and (self.backend != "ray" or not self.address.strip()):
            raise ValueError(f"APGConfig.address must be None or a non-empty address with backend 'ray', "
                             f"got {self.address!r} with backend {self.backend!r}")
        check_device_field(self)
        if self.elites > self.population:
            raise ValueError(f"APGConfig.elites ({self.elites}) must be <= population ({self.population})")
        for name in ("beta1", "beta2"):
            if not 0.0 <= getattr(self, name) < 1.0:
                raise ValueError(f"APGConfig.{name} must be in [0, 1), got {getattr(self, name)!r}")
        check_fields(self, non_negative=("init_std", "alive_bonus", "velocity_penalty", "position_weight",
                                          "linear_velocity_weight", "cost_to_go_weight"))
        for name in ("truncation", "clip", "control_period", "start_noise"):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and value > 0):
                raise ValueError(f"APGConfig.{name} must be None or a finite number > 0, got {value!r}")
        METHOD_CLASSES[self.method].check_config(self)   # the method's own checks (shapg: its unroll)
        # a graph cut longer than the episode would silently be the whole episode
        if self.truncation is not None and self.truncation > self.horizon:
            raise ValueError(f"APGConfig.truncation ({self.truncation}) must be None or <= horizon "
                             f"({self.horizon}): the graph is cut within an episode")

    @classmethod
    def preset(cls, name: str = "thesis", method: str = "ce-apg", **overrides) -> "APGConfig":
        """Settings for ``method`` from a preset, then ``overrides``.

        ``"thesis"``: the values above (Sec. 7.3.7). Per method (each learner class's
        ``preset_settings``): ``apg`` one member; ``shapg`` clip 1.0 by norm and Adam betas
        (0.7, 0.95) (Brax APG 0.14 / SHAC); ``cem`` 2000 epochs (thesis Sec. 7.5).

        ``"reduced"`` (trains in minutes on a shared 2-core CPU): population 8 (thesis 24),
        elites 3 (8), apg_iterations 20 (100), horizon 100 policy steps (500; with the
        cart-pole's 0.05 s period 5 s of swing-up), epochs 10 (200; cem 200), lr 1e-2 -> 1e-4
        (1e-3 -> 1e-6: fewer, larger steps), eval on 8 starts; the architecture, N = 4,
        sigma_0 and the update rules are the thesis'.
        """
        if name not in PRESETS:
            raise ValueError(f"unknown preset {name!r}; known: {', '.join(PRESETS)}")
        if method not in METHODS:
            raise ValueError(f"unknown method {method!r}; known: {', '.join(METHODS)}")
        values: dict = {"method": method, **METHOD_CLASSES[method].preset_settings["thesis"]}
        if name == "reduced":
            values.update(REDUCED)
            values.update(METHOD_CLASSES[method].preset_settings["reduced"])
        values.update(overrides)
        config = cls(**values)
        config.validate()
        return config


REDUCED = dict(apg_iterations=20, horizon=100, epochs=10, lr_start=1e-2, lr_end=1e-4, eval_episodes=8)
"""The ``"reduced"`` preset's settings of every method (a method's own follow: population 8, elites 3)."""


def parse_policy(text: str) -> tuple[str, tuple[int, ...]]:
    """"gru" -> ("gru", ()); "linear" -> ("linear", ()); "mlp:32,32" -> ("mlp", (32, 32))."""
    if text in ("gru", "linear"):
        return text, ()
    if isinstance(text, str) and text.startswith("mlp:"):
        try:
            widths = tuple(int(w) for w in text[4:].split(",") if w)
        except ValueError:
            widths = ()
        if widths and all(w > 0 for w in widths):
            return "mlp", widths
    raise ValueError(f"APGConfig.policy must be one of {POLICY_KINDS[0]!r}, 'linear' or 'mlp:W1,W2,...' "
                     f"(positive widths), got {text!r}")


def lr_schedule(config: APGConfig, epoch: int) -> float:
    """Learning rate of ``epoch``: 10^(log10 lr_start -> log10 lr_end) linearly over the epochs (author)."""
    if config.epochs <= 1:
        return config.lr_start
    f = min(epoch, config.epochs - 1) / (config.epochs - 1)
    return float(10 ** ((1 - f) * math.log10(config.lr_start) + f * math.log10(config.lr_end)))

