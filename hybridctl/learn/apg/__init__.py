"""Analytic policy gradients through the differentiable dynamics (thesis Ch. 7): APG, short-horizon
APG, PAPG, CEM and CE-APG, all as ONE batched torch computation over a population of policies.

The torch dynamics (:meth:`hybridctl.systems.System.step_unchecked`) are differentiable, so the
return R(theta) = sum_t r(s_t) of a deterministic policy has an exact gradient (eq. 7.10):

    theta <- theta + alpha grad_theta (1/N) sum_i sum_t r(s_t^i)          (APG, Adam)

The package, as Brax splits its agents:

* :mod:`.config` -- :class:`APGConfig` (every setting with the thesis' value and source), the
  presets, and :data:`METHOD_CLASSES`, the registry from ``APGConfig.method`` to its class;
* :mod:`.core` -- what every method shares, as functions over tensors: the differentiable
  rollout (:func:`population_returns`), the member gradients, the batched Adam, clipping, the
  LQR takeover, the CEM update, one APG iteration / episode / phase (:class:`APGProblem`);
* :mod:`.split` -- the APG phase as chunks of members on a parallel backend (arrays in, arrays out);
* :mod:`.family` -- :class:`APGFamily`, the base learner: shared state, checkpoints, the epoch loop
  on the training skeleton, evaluation, the trained policy;
* :mod:`.methods` -- one small class per method, each writing only what differs:

  - :class:`APG` (``"apg"``) -- one policy, full backpropagation through time over the T-step
    episode (optional truncation: the graph is cut every ``truncation`` steps);
  - :class:`ShortHorizonAPG` (``"shapg"``) -- the short-horizon peer (today's Brax APG, SHAC's
    actor without critic): ``short_horizon``-step unrolls from the carried state, one update
    each, clip 1.0, Adam betas (0.7, 0.95);
  - :class:`PAPG` (``"papg"``) -- K APG runs side by side; the BEST member (by its last training
    returns) is the result (the author's script returns the initial parameters by mistake);
  - :class:`CEM` (``"cem"``) -- the cross-entropy method on the parameters (diagonal Gaussian,
    eqs. 7.11, 7.13);
  - :class:`CEAPG` (``"ce-apg"``) -- Alg. 9: each epoch draws K_a candidates from N(mean, std^2),
    improves each by ``apg_iterations`` APG steps, and the K_e best (mean of the last
    ``rank_window`` training returns, as the author's code) give the new mean (eq. 7.11) and the
    new per-parameter std sqrt(mean_e (old mean - theta_e)^2) (eq. 7.13), measured about the OLD
    mean as the author's code does.

``APG(system, config)`` and ``APG.load(path)`` build the class of ``config.method``; every
method's checkpoint records algorithm "APG" and its method.

Faults: a member's gradient that is NaN/inf or whose norm exceeds ``grad_bound`` is counted
(``nan_grads``, ``large_grads``), skipped and logged, never applied; a member whose rollout
diverges (non-finite return) gets the worst score (-inf) and no update; NaN parameters stop
training with FloatingPointError before they are applied, so the last good checkpoint
stays intact (the training skeleton writes none after an error).

The parallel backends (``APGConfig.backend`` "processes" or "ray", :mod:`hybridctl.parallel`):
for ce-apg, papg and shapg an epoch's APG phase runs as ``workers`` contiguous chunks of
members, one task each (:mod:`.split`); the parent joins the chunks in member order and goes on
as in one process (CEM update, best member, normalisation, counters), so a split run equals the
serial one up to float rounding. apg (one member) and cem (no APG phase) always run here. The
backend opens on the first split epoch and closes when ``learn`` returns or fails
(:meth:`APGFamily.close_backend` after calling ``train_epoch`` directly). ``APGConfig.address``
names a Ray cluster (``--address``, as for every learner; older checkpoints' ``ray_address``
loads as ``address``).

Devices (``APGConfig.device``, ``--device cuda``): the population's parameters (MLP, GRU or
linear), the members, the CEM mean, std and draws (the epoch's generator is on the device),
the Adam moments, the start states and every rollout, evaluation included, live on the
device; the host reads back once per APG update (the NaN guard) and per epoch (the progress
row). The initial members are drawn on the CPU from the seed and moved, so one seed starts
alike everywhere (a CUDA generator's CEM draws differ from the CPU's). A split phase sends
CPU arrays to its workers and moves the results back; checkpoints load onto the configured
device whichever device wrote them.

Interactions are counted honestly: K x N x T policy steps per APG iteration (x the
integrator sub-steps per policy step for the physics steps, logged separately).

Speed: ``APGConfig.compile`` runs the per-step work (observe, act, sub-steps, reward) through
``torch.compile`` (``"auto"``, the default: runs of at least 5e6 policy steps; :mod:`.compiled`); measured
here (benchmarks/apg.py, 24 x 4 x 500 acrobot, float32, 1 thread) 1.22 s per eager iteration, 0.14-0.23 s
compiled, 30 s for the loop over members.

Results: with ``takeover="lqr"`` PAPG trains a cart-pole swing-up that balances in Drake
(models/policies/papg-cartpole: 93.4 % of the 11 x 11 balance map; seeds 0-3: 71-93 %, ~200 s
each, results/ch7/papg-takeover-cartpole.json). Without the takeover no method stabilises within
5 s at ~1/500 of the thesis' budget (results/ch7/table71.json).

>>> agent = APG("cartpole", APGConfig.preset("reduced", method="ce-apg"))
>>> agent.learn(out="runs/ce-apg-cartpole")                   # progress, CSV, checkpoints
>>> agent.evaluate(episodes=16)                                   # held-out starts, stabilisation rate
>>> APG.load("runs/ce-apg-cartpole/final").policy()               # a policies.Policy
"""

from __future__ import annotations

from .config import (METHOD_CLASSES, METHODS, OBSERVATIONS, PRESETS, TAKEOVERS, APGConfig, lr_schedule,
                     parse_policy)
from .core import (APGProblem, BatchedAdam, ClosedLoopPolicy, LQRTakeover, Phase, apg_episode, apg_iteration,
                   apg_phase, cem_update, clip_gradients, compiled_policy_step, compiled_policy_steps,
                   evaluate_members,
                   gradient_norms_by_horizon, member_gradients, observation_size, observe, policy_step, policy_steps,
                   population_returns, returns_along_direction, start_array, start_states, takeover_controller)
from .split import apg_chunk, split_apg_phase
from .family import APGFamily, EpochStep
from .methods import APG, CEAPG, CEM, PAPG, ShortHorizonAPG

__all__ = ["APG", "ShortHorizonAPG", "PAPG", "CEM", "CEAPG", "APGFamily", "EpochStep", "APGConfig",
           "METHOD_CLASSES", "METHODS", "PRESETS", "OBSERVATIONS", "TAKEOVERS", "APGProblem", "Phase",
           "BatchedAdam", "LQRTakeover", "takeover_controller", "ClosedLoopPolicy", "apg_chunk", "split_apg_phase",
           "policy_step",
           "policy_steps", "compiled_policy_step", "compiled_policy_steps", "observe", "observation_size",
           "population_returns", "member_gradients",
           "clip_gradients", "lr_schedule", "parse_policy", "cem_update", "start_states", "start_array",
           "apg_iteration", "apg_episode", "apg_phase", "evaluate_members", "gradient_norms_by_horizon",
           "returns_along_direction"]
