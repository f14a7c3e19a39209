"""The ``clone`` stage of ``hybridctl fit``: the TVLQR-tracked collocation swing-up cloned into SSAC's actor.

The swing-up stage measured the tracked swing-up at the kept decision period and wrote its table
(:data:`~hybridctl.experiments.fit_learn.TRACKING_TABLE`). Here SSAC is built on the fitted spec with the learner's
settings (its gate warm-started from the measured basin), the tracker's demonstrations are cloned into its actor
(:func:`hybridctl.learn.clone.clone_swingup`: DART, then DAgger rounds, the round whose clone balances most held-out
starts kept), and the learner is saved whole (replay buffers and gate data too) to ``DIR/clone``: the learner stage
starts SSAC from it, and the verification compares it with what SSAC made of it.
"""

from __future__ import annotations

import math
from dataclasses import asdict
from pathlib import Path

import numpy as np

from .fit_learn import TRACKING_TABLE, learner_settings
from .fit_stages import FitSettings, bar
from .fitted import CLONE

__all__ = ["stage_clone"]


def stage_clone(model_file: str, options: dict, earlier: dict, s: FitSettings, progress: bool, *,
                system, folder: Path, spec_file: Path, resources: dict | None = None, **_) -> dict:
    """Clone the tracked swing-up into a new SSAC learner's actor and save the learner to ``DIR/clone``; nothing
    to clone (no collocation swing-up, or its tracking balanced no start) is said and skipped."""
    from ..learn.clone import CloneConfig, TrackingSwingup, clone_swingup
    from .training import make_config, learner_class

    plan = earlier["swingup"]
    if not plan.get("tracking_table"):
        reason = ("no collocation swing-up" if not plan["found"] else
                  "the TVLQR-tracked swing-up balanced no start at any decision period tried")
        return {"cloned": False, "why": f"nothing to clone: {reason}; SSAC starts from scratch"}
    from ..drake.trajopt import TrackingGains

    with np.load(folder / TRACKING_TABLE, allow_pickle=False) as table:   # fit's own file: numbers only
        gains = TrackingGains(float(table["period"]), *(np.array(table[k]) for k in ("x0", "u0", "K", "k0")),
                              solve_time=0.0, key=TRACKING_TABLE)
    config = make_config("ssac", "hybridctl", **learner_settings(options, plan, s, cloned=True,
                                                                 device=(resources or {}).get("device")))
    progress_bar = bar(1, "clone: SSAC's gate warm start", progress)
    agent = learner_class("ssac")(str(spec_file), config)
    progress_bar.update()
    progress_bar.close()
    learned = agent.system
    if not math.isclose(gains.period, learned.swingup_period, rel_tol=1e-9):
        raise ValueError(f"the tracking table's period {gains.period} s is not the spec's swing-up period "
                         f"{learned.swingup_period} s (rerun fit without --resume)")
    clone_config = CloneConfig(**{"seed": options["seed"], **s.clone_settings})
    rng = np.random.default_rng(options["seed"] + 1)   # the clone's starts; the swing-up stage measured on seed's
    starts = learned.sample_initial_states(clone_config.rollouts, rng)
    test_starts = learned.sample_initial_states(s.track_samples, rng)
    progress_bar = bar(clone_config.dagger_rounds + 1, "clone: DART + DAgger rounds", progress)
    result = clone_swingup(learned, TrackingSwingup(gains, learned), agent.controller(), agent.actor, starts,
                           test_starts, learned.episode_duration, clone_config, progress=progress_bar)
    progress_bar.close()
    agent.save(folder / CLONE, include_replay=True)
    starts_ssac = result["fraction"] >= s.clone_start_min
    return {"cloned": True, "checkpoint": CLONE, **result, "samples": result["rounds"][-1]["samples"],
            "config": asdict(clone_config), "starts_ssac": starts_ssac,
            "why": (f"the tracked swing-up (balancing {result['tracker_fraction']:.2f} of {result['test_starts']} "
                    f"held-out starts) cloned into SSAC's actor, with SSAC's learned gate: round "
                    f"{result['kept_round']} of {len(result['rounds'])} balances {result['fraction']:.2f} of them; "
                    + ("SSAC starts from it" if starts_ssac else
                       f"below {s.clone_start_min:g}, so SSAC starts from scratch (the clone stays a candidate)"))}
