"""``hybridctl finetune ENV --policy KIND:PATH``: fine-tune a trained agent by direct policy search (thesis Ch. 6)."""

from __future__ import annotations

import argparse

from ..analysis.postprocess import FORMS, KINDS
from ..experiments.finetune import finetune_and_report
from ..learn.finetune import DIMENSION_SETTINGS, SELECTIONS, FineTuneConfig
from ._common import (add_backend_flags, add_debug_flag, add_force_flag, add_quiet_flag, check_backend_flags,
                      cli_errors, positive, ray_options_for)

DEFAULTS = FineTuneConfig()


def add_parser(sub) -> None:
    """Register ``finetune`` on the top-level sub-parsers."""
    p = sub.add_parser("finetune", help="fine-tune a trained agent by direct policy search (thesis Ch. 6)",
                       description=__doc__ + "\n\nPolicies: sb3:PATH.zip (Stable-Baselines3 PPO, A2C, SAC, TD3, DDPG, "
                       "TQC; read without unpickling; normaliser from vecnormalize.npz beside it or --normalizer), "
                       "ars:PATH, sac:PATH, ssac:PATH, and the APG family's ce-apg:PATH, papg:PATH, apg:PATH, "
                       "cem:PATH, shapg:PATH "
                       "(hybridctl checkpoints; these need a system name as ENV; an APG-family swing-up is tuned "
                       "recurrent, inside the spec's cost-to-go gate and LQR, on its training's reward and starts).")
    p.add_argument("env", help="gymnasium env id (e.g. Pendulum-v1, Hopper-v5) or a hybridctl system "
                                "(sac/ssac/APG family)")
    p.add_argument("--policy", required=True, metavar="KIND:PATH",
                   help="the trained agent (sb3:, ars:, sac:, ssac:, ce-apg:, papg:, apg:, cem:, shapg:)")
    p.add_argument("--reward", choices=KINDS, default=DEFAULTS.reward,
                   help="identity (plain return) or a dimension term, e.g. mesh-mean (eq. 6.1 / 6.2)")
    p.add_argument("--reward-form", choices=FORMS, default=DEFAULTS.reward_form,
                   help="divide (eq. 6.1), multiply (eq. 6.2), auto: by the return's sign (default)")
    p.add_argument("--dimension-settings", choices=DIMENSION_SETTINGS, default=DEFAULTS.dimension_settings,
                   help="author: f 1.2, d0 1, whole episode (the thesis' code; default); ch4: the Ch. 4 defaults")
    p.add_argument("--updates", type=positive(int), default=DEFAULTS.updates, help="updates (thesis: 200)")
    p.add_argument("--directions", type=positive(int), default=DEFAULTS.n_directions,
                   help="directions n per update; 2n rollouts (thesis: 64)")
    p.add_argument("--step-size", type=positive(float), nargs=2, metavar=("START", "END"),
                   default=(DEFAULTS.step_size_start, DEFAULTS.step_size_end),
                   help="step size alpha, linear from START to END (thesis: 0.02 0.002)")
    p.add_argument("--noise", type=positive(float), nargs=2, metavar=("START", "END"),
                   default=(DEFAULTS.noise_start, DEFAULTS.noise_end),
                   help="perturbation sigma, linear from START to END (thesis: 0.025 0.0025)")
    p.add_argument("--select", choices=SELECTIONS, default=DEFAULTS.select,
                   help="parameters perturbed: the action path (default), all (the author's code), last layer")
    p.add_argument("--episode-steps", type=positive(int), help="cap on episode length (default: the env's)")
    p.add_argument("--seed", type=int, default=DEFAULTS.seed, help="seed of directions and env seeds (default 0)")
    add_backend_flags(p, DEFAULTS.backend, "the rollouts")
    p.add_argument("--chunk-size", type=positive(int), default=DEFAULTS.chunk_size,
                   help="perturbed policies per batched rollout task (default: from the workers, at least 2 tasks "
                        "each; a fixed size gives the same numbers on any worker count)")
    p.add_argument("--device", default=DEFAULTS.device,
                   help="torch device of a sac/ssac source's batched rollouts (cpu, cuda, cuda:1; default cpu)")
    p.add_argument("--eval-episodes", type=positive(int), default=DEFAULTS.eval_episodes,
                   help="deterministic episodes before and after (thesis: 100)")
    p.add_argument("--normalizer", metavar="NPZ", help="observation statistics of an sb3 agent (.npz)")
    p.add_argument("--trust", action="store_true",
                   help="allow unpickling a VecNormalize .pkl (only for files you trust)")
    p.add_argument("--checkpoint-every", type=positive(int), default=DEFAULTS.checkpoint_every, metavar="UPDATES")
    p.add_argument("--resume", action="store_true", help="continue the run in --out from its newest checkpoint")
    p.add_argument("--overwrite", action="store_true", help="replace the run the --out folder holds")
    p.add_argument("--out", help="output folder (default runs/finetune/ENV-KIND)")
    add_force_flag(p)
    add_quiet_flag(p)
    add_debug_flag(p)
    p.set_defaults(func=run_finetune)


@cli_errors
def run_finetune(args: argparse.Namespace) -> int:
    """Fine-tune, then print before / after and where the outputs are."""
    check_backend_flags(args)
    config = FineTuneConfig(updates=args.updates, n_directions=args.directions, select=args.select,
                            step_size_start=args.step_size[0], step_size_end=args.step_size[1],
                            noise_start=args.noise[0], noise_end=args.noise[1],
                            reward=args.reward, reward_form=args.reward_form,
                            dimension_settings=args.dimension_settings, episode_steps=args.episode_steps,
                            seed=args.seed, backend=args.backend, workers=args.workers, address=args.address,
                            chunk_size=args.chunk_size, eval_episodes=args.eval_episodes, device=args.device,
                            checkpoint_every=args.checkpoint_every)
    # an empty --out is refused by finetune_and_report, not replaced by the default
    out = args.out if args.out is not None else f"runs/finetune/{args.env}-{args.policy.partition(':')[0]}"
    with ray_options_for(args):   # --task-cpus/--task-gpus/--task-memory/--runtime-env for the Ray tasks
        report = finetune_and_report(args.env, args.policy, out, config, resume=args.resume,
                                     overwrite=args.overwrite, trust=args.trust, normalizer=args.normalizer,
                                     progress=not args.quiet, command=args.command_line)
    for name in ("before", "after"):
        r = report[name]
        lo, hi = r["failure_interval"]
        success = "" if r.get("success_rate") is None else f", success {100 * r['success_rate']:.1f} %"
        print(f"{name:6s} return {r['mean_return']:.2f} ± {r['std_return']:.2f} over {r['episodes']} episodes; "
              f"early terminations {100 * r['failure_rate']:.1f} % [{100 * lo:.1f}, {100 * hi:.1f}]; "
              f"dimension {r['mean_dimension']:.2f}{success}")
    print(f"{report['updates']} updates, {report['env_steps']} env steps, {report['train_wall_time_s']:.0f} s; "
          f"wrote {out}/report.json, finetune.png, final/" + (", model.zip" if report["sb3_zip"] else ""))
    return 0
