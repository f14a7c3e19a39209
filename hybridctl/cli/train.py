"""``hybridctl train ALGO SYSTEM`` (ALGO: sac, ssac, ars, apg, shapg, papg, cem, ce-apg): one sub-command per learner.

Each learner's flags are generated from its config dataclass (SACConfig, SSACConfig,
ARSConfig): ``--field-name VALUE`` typed as the field, ``--flag/--no-flag`` for booleans,
choices where the config accepts a fixed set, the default and the field's source comment in
``--help``. ``--set key=value`` (values read as JSON) still works. A flag that another learner
takes but this one does not is a usage error (exit 2) naming who takes it.
"""

from __future__ import annotations

import argparse
import dataclasses
import inspect
import json
import textwrap
import types
import typing
from typing import Any, Callable

from ..analysis.postprocess import FORMS as POSTPROCESS_FORMS
from ..analysis.postprocess import KINDS as POSTPROCESS_KINDS
from ..experiments import SSAC_VARIANTS, train_and_evaluate, training_algorithms
from ..experiments.resume import RESUME_APPLIED
from ..learn.apg import METHODS as APG_METHODS
from ..learn.config_check import FIELD_LIMITS
from ..learn.apg import OBSERVATIONS as APG_OBSERVATIONS
from ..learn.apg import PRESETS as APG_PRESETS
from ..systems.spec import CH7_REWARD_KINDS
from ..learn.sac import OBS_TRANSFORMS
from ..learn.ssac import REWARDS
from ..parallel import BACKENDS
from ._common import (CommandParser, add_debug_flag, add_quiet_flag, add_ray_task_flags, add_system_argument,
                      check_ray_task_flags, cli_errors, positive, ray_options_for)

CHOICES = {"obs_transform": OBS_TRANSFORMS, "reward": REWARDS, "gate_class_weight_from": ("warm", "all"),
           "postprocess": POSTPROCESS_KINDS, "postprocess_form": POSTPROCESS_FORMS, "backend": BACKENDS,
           "reward_kind": CH7_REWARD_KINDS, "observation": APG_OBSERVATIONS, "clip_mode": ("norm", "value")}
"""The fixed sets that the configs' ``validate()`` accepts, by field name."""

INIT_NOTES = {"ars": " (the thesis trains 750 identity epochs, then 250 with post-processing)",
              "sac": " (the replay buffers go on too)",
              "ssac": " (the replay buffers and the gate data go on too; hybridctl fit starts SSAC from its clone so)",
              **{name: " (--force to go on under another reward)" for name in APG_METHODS}}
"""What ``--init`` carries over beyond the policy, per learner."""
ALIASES = {"total_steps": ("--steps",)}
"""Shorter flags kept from the first command line (``--steps`` for ``total_steps``)."""

POSITIVE_FIELDS = {"total_steps", "epochs", "workers"}
"""Fields whose flags reject values <= 0 at parse time, as the first command line did."""

NOT_FLAGS = {"ssac": {"variant_name"}, "ars": {"eval_episodes"}}
NOT_FLAGS.update({method: {"method", "eval_episodes"} for method in APG_METHODS})  # set by the sub-command
"""Config fields without a generated flag: ``variant_name`` is set by ``--variant``; ARS's
``eval_episodes`` is the common ``--eval-episodes``."""

INSTEAD = {("ars", "--steps"): "ars counts --epochs", ("ars", "--total-steps"): "ars counts --epochs",
           ("sac", "--epochs"): "sac counts --steps", ("ssac", "--epochs"): "ssac counts --steps"}
"""What to use instead of another learner's flag."""

GYM_SYSTEM_HELP = "gymnasium env id (e.g. Hopper-v5) or system name"
SYSTEM_HELP = {"sac": None, "ssac": None, "ars": GYM_SYSTEM_HELP}   # None: the known systems (systems_help)
"""SYSTEM's help per learner; another learner's: the known systems, or also env ids if it ``takes_gym_envs``."""
TITLES = {"sac": "plain SAC (thesis Ch. 3 baseline) on a system's torch vector env",
          "ssac": "Switched SAC (thesis Ch. 3): learned swing-up + learned gate + LQR",
          "ars": "ARS V2-t with dimension post-processing (thesis Ch. 4) on a gymnasium env or system",
          "apg": "analytic policy gradients, full BPTT (thesis Ch. 7)",
          "shapg": "short-horizon APG (32-step unrolls, Brax APG / SHAC style) (thesis Ch. 7 peer)",
          "papg": "parallel APG: K APG runs, the best member returned (thesis Sec. 7.5)",
          "cem": "cross-entropy method on the policy parameters (thesis Sec. 7.3.2, 7.5)",
          "ce-apg": "cross-entropy analytic policy gradients, Alg. 9 (thesis Ch. 7)"}
"""The one-line help of each learner's sub-command; another learner's: its class docstring's first sentence."""
SYSTEM_HELP.update({method: None for method in APG_METHODS})


def learner_title(algorithm: str, learner: type) -> str:
    """The sub-command's one-line help: :data:`TITLES`, else the first sentence of the learner class's docstring."""
    if algorithm in TITLES:
        return TITLES[algorithm]
    first = (inspect.getdoc(learner) or learner.__name__).split("\n\n")[0].replace("\n", " ")
    return first.split(". ")[0].rstrip(".")
CONFIG_DEST = "config:"
"""Namespace prefix of the generated config-field options (set only when given)."""


# ------------------------------------------------------------------ flags from a config dataclass

def field_comments(config_class: type) -> dict[str, str]:
    """Field name -> the comment after it in the class source (continuation lines joined).

    A subclass's comment replaces its base's for a field it redefines. A field without a
    comment maps to ""; the dict is empty when the source cannot be read (e.g. a frozen
    executable).
    """
    names = {f.name for f in dataclasses.fields(config_class)}
    comments: dict[str, str] = {}
    for cls in reversed(config_class.__mro__):
        if not dataclasses.is_dataclass(cls):
            continue
        try:
            lines = inspect.getsource(cls).splitlines()
        except (OSError, TypeError):
            continue
        current = None
        for line in lines:
            stripped = line.strip()
            body, hash_, comment = line.partition("#")
            head = body.strip().split(":", 1)[0].strip()
            if line.startswith("    ") and not line.startswith("     ") and head in names and ":" in body:
                current = head
                comments[current] = comment.strip() if hash_ else comments.get(head, "")
            elif current and stripped.startswith("#") and line.partition("#")[2].startswith("  ") \
                    and not stripped.lstrip("# ").startswith("---"):
                comments[current] = (comments[current] + " " + stripped.lstrip("# ").strip()).strip()
            else:
                current = None
    return comments


def parse_int(text: str) -> int:
    """An integer, also written as an integral float ("2e6")."""
    try:
        return int(text)
    except ValueError:
        value = float(text)
        if not value.is_integer():
            raise ValueError(f"not an integer: {text}") from None
        return int(value)


parse_int.__name__ = "int"


def value_parser(hint: Any) -> tuple[Callable[[str], Any], str]:
    """An argparse ``type`` for a field's type hint and its metavar.

    int, float, str; ``X | None`` ("none" gives None); unions tried in order (``float | str``:
    a number, else the text); ``tuple[X, ...]`` / ``list[X]``: comma-separated; else JSON.
    """
    if hint is int:
        return parse_int, "N"
    if hint is float:
        return float, "X"
    if hint is str:
        return str, "TEXT"
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        optional = type(None) in args
        options = [value_parser(a)[0] for a in args if a is not type(None)]
        metavars = [value_parser(a)[1] for a in args if a is not type(None)]

        def parse_union(text: str):
            if optional and text.lower() in ("none", "null"):
                return None
            for parse in options:
                try:
                    return parse(text)
                except (TypeError, ValueError, argparse.ArgumentTypeError):
                    continue
            raise argparse.ArgumentTypeError(f"invalid value {text!r}")
        parse_union.__name__ = "|".join(metavars)
        return parse_union, "|".join(metavars + (["none"] if optional else []))
    if origin in (tuple, list):
        item = value_parser(args[0] if args else str)[0]

        def parse_sequence(text: str):
            values = [item(v) for v in text.replace(" ", "").split(",") if v]
            return origin(values)
        parse_sequence.__name__ = "list"
        return parse_sequence, "A,B,..."
    return json.loads, "JSON"


def _positive_or_none(parse: Callable[[str], Any]) -> Callable[[str], Any]:
    """``parse``, rejecting values <= 0 (None passes) with "must be > 0"."""
    def parse_positive(text: str):
        value = parse(text)
        if value is not None and value <= 0:
            raise argparse.ArgumentTypeError(f"must be > 0, got {text}")
        return value
    parse_positive.__name__ = parse.__name__
    return parse_positive


def _at_most(parse: Callable[[str], Any], limit: int, why: str, low: int | None) -> Callable[[str], Any]:
    """``parse``, rejecting a value above ``limit`` (hybridctl.limits; None passes) with the accepted range."""
    def parse_bounded(text: str):
        value = parse(text)
        if isinstance(value, int) and value > limit:
            shown = f"in [{low}, {limit:,}]" if low is not None else f"at most {limit:,}"
            raise argparse.ArgumentTypeError(f"must be an integer {shown} ({why}), got {text}")
        return value
    parse_bounded.__name__ = parse.__name__
    return parse_bounded


def field_default(f: dataclasses.Field) -> Any:
    """A dataclass field's default value (its factory's product; MISSING when required)."""
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return dataclasses.MISSING


def variant_defaults(algorithm: str) -> dict[str, dict[str, Any]]:
    """For SSAC: variant name -> the fields where that preset differs from hybridctl's defaults."""
    if algorithm != "ssac":
        return {}
    config_class = training_algorithms()["ssac"].config_class
    base = dataclasses.asdict(config_class())
    out = {}
    for name in SSAC_VARIANTS:
        if name == "hybridctl":
            continue
        values = dataclasses.asdict(config_class.variant(name))
        out[name] = {k: v for k, v in values.items() if k != "variant_name" and v != base[k]}
    return out


def add_config_flags(parser: argparse.ArgumentParser, algorithm: str) -> set[str]:
    """Add ``--field-name`` for every field of ``algorithm``'s config; return the option strings."""
    config_class = training_algorithms()[algorithm].config_class
    hints = typing.get_type_hints(config_class)
    comments = field_comments(config_class)
    presets = variant_defaults(algorithm)
    group = parser.add_argument_group(f"{config_class.__name__} fields (default and source of each; "
                                      "also settable as --set FIELD=VALUE)")
    options = set()
    for f in dataclasses.fields(config_class):
        if f.name in NOT_FLAGS.get(algorithm, ()):
            continue
        flag = "--" + f.name.replace("_", "-")
        names = [*ALIASES.get(f.name, ()), flag]
        default = field_default(f)
        text = comments.get(f.name, "")
        shown = [f"default: {default}"] + [f"--variant {preset}: {changed[f.name]}"
                                           for preset, changed in presets.items() if f.name in changed]
        text += (" " if text else "") + "(" + "; ".join(shown) + ")"
        kwargs: dict[str, Any] = {"dest": CONFIG_DEST + f.name, "default": argparse.SUPPRESS,
                                  "help": text.replace("%", "%%")}
        hint = hints.get(f.name, str)
        if hint is bool:
            kwargs["action"] = argparse.BooleanOptionalAction
        else:
            parse, metavar = value_parser(hint)
            if f.name in POSITIVE_FIELDS:
                parse = _positive_or_none(parse)
            if f.name in FIELD_LIMITS and int in (hint, *typing.get_args(hint)):
                limit, why = FIELD_LIMITS[f.name]
                parse = _at_most(parse, limit(), why, 1 if f.name in POSITIVE_FIELDS else None)
            kwargs["type"] = parse
            if f.name in CHOICES:
                # an optional field (``reward: str | None``) also takes "none", which parses to None
                kwargs["choices"] = (*CHOICES[f.name], None) if metavar.endswith("|none") else CHOICES[f.name]
                kwargs["metavar"] = "{" + ",".join(map(str, CHOICES[f.name])) + ("}|none" if None in kwargs["choices"]
                                                                                   else "}")
            else:
                kwargs["metavar"] = metavar
        action = group.add_argument(*names, **kwargs)
        options.update(action.option_strings)
    return options


def parse_set_pairs(pairs: list[str] | None, config_class: type) -> dict:
    """``--set key=value`` pairs -> config overrides (values parsed as JSON, else kept as text)."""
    fields = {f.name for f in dataclasses.fields(config_class)}
    out = {}
    for pair in pairs or []:
        key, sep, text = pair.partition("=")
        key = key.strip().replace("-", "_")
        if not sep or not key:
            raise ValueError(f"--set expects key=value, got {pair!r}")
        if key not in fields:
            raise ValueError(f"--set {key}: not a {config_class.__name__} field; fields: " + ", ".join(sorted(fields)))
        out[key] = _json_or_text(text)
    return out


def parse_spec_pairs(pairs: list[str] | None) -> dict:
    """``--spec key=value`` pairs -> system spec overrides (values parsed as JSON, else kept as text)."""
    out = {}
    for pair in pairs or []:
        key, sep, text = pair.partition("=")
        if not sep or not key.strip():
            raise ValueError(f"--spec expects section.key=value (e.g. reward.kind=upright_centered), got {pair!r}")
        out[key.strip()] = _json_or_text(text)
    return out


def _json_or_text(text: str):
    """A ``--set`` / ``--spec`` value: JSON where it parses, else the text itself."""
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def config_settings(args: argparse.Namespace) -> dict:
    """The config fields the command line set: ``--set`` pairs, then the field flags (which win)."""
    settings = parse_set_pairs(args.set, training_algorithms()[args.algorithm].config_class)
    settings.update({k[len(CONFIG_DEST):]: v for k, v in vars(args).items() if k.startswith(CONFIG_DEST)})
    return settings


# ------------------------------------------------------------------ parsers

def _unknown_flag_hint(algorithm: str, options: dict[str, set[str]]) -> Callable[[str], str | None]:
    """For ``algorithm``'s parser: "FLAG applies to X only" when another learner takes FLAG."""
    def hint(flag: str) -> str | None:
        takers = [name for name, known in options.items() if name != algorithm and flag in known]
        if not takers:
            return None
        text = f"{flag} applies to {', '.join(takers)} only"
        instead = INSTEAD.get((algorithm, flag))
        return f"{text}; {instead}" if instead else text
    return hint


def add_common_flags(parser: argparse.ArgumentParser, algorithm: str) -> set[str]:
    """The run flags every learner takes, plus ``--variant`` (ssac) and ``--init`` (ARS, the APG family);
    return their option strings."""
    run = parser.add_argument_group("run")
    actions = [
        run.add_argument("--out", metavar="DIR", help="run folder (default runs/train/ALGO-SYSTEM-sSEED; a new run beside an earlier one of the same settings gets -2, -3, ...; --resume and --overwrite take the newest)"),
        run.add_argument("--resume", action="store_true", help="continue from the run folder's newest checkpoint "
                         "(see 'Resuming' below)"),
        run.add_argument("--force", action="store_true",
                         help="with --resume: continue despite another algorithm or plant (spec values), changed "
                              "math settings, or a missing/damaged replay.pt or gate_data.pt (each is reported); "
                              "with --init: start from another env's checkpoint, or another plant's or reward's"),
        run.add_argument("--overwrite", action="store_true",
                         help="replace the run the --out folder holds (without it, or --resume, such a folder is "
                              "refused)"),
        run.add_argument("--eval-episodes", type=positive(int), metavar="N",
                         help="episodes in eval.json (default " + ("5" if algorithm == "ars" else "16, held-out starts"
                                                                 if algorithm in APG_METHODS else "100") + ")"),
        run.add_argument("--set", action="append", metavar="KEY=VALUE",
                         help="override a config field, e.g. --set polyak=0.9 (repeatable; value read as JSON)"),
    ]
    if algorithm in ("sac", "ssac"):
        actions.append(run.add_argument(
            "--spec", action="append", metavar="KEY=VALUE",
            help="override a system spec value for this run, e.g. --spec reward.kind=upright_centered or "
                 "--spec 'initial_state.low=[-1, -3.14159, 0, 0]' (repeatable; value read as JSON; recorded in "
                 "the checkpoint, which later loads with it)"))
    if algorithm == "ssac":
        actions.append(run.add_argument(
            "--variant", choices=SSAC_VARIANTS, default=None,
            help="SSAC settings: hybridctl's defaults, the thesis' throughout (paper), or the author's code "
                 "(author); field flags change the chosen preset (default: hybridctl; with --resume: the run's)"))
    if algorithm in APG_METHODS:
        actions.append(run.add_argument(
            "--preset", choices=APG_PRESETS, default=None,
            help="settings: the thesis' (Sec. 7.3.7) or 'reduced' (trains in minutes; see APGConfig.preset); "
                 "field flags change the chosen preset (default: thesis; with --resume: the run's)"))
    if training_algorithms()[algorithm].warm_starts:
        actions.append(run.add_argument(
            "--init", metavar="CHECKPOINT", help="start from this checkpoint's policy and normalisation; its "
            "counters go on, so the run's budget is the total" + INIT_NOTES.get(algorithm, "")))
    add_quiet_flag(run)
    add_debug_flag(run)
    options = {s for action in actions for s in action.option_strings}
    if training_algorithms()[algorithm].uses_backend:   # its rollouts or population members run on a backend
        add_ray_task_flags(parser)
        options |= {"--task-cpus", "--task-gpus", "--task-memory", "--runtime-env"}
    return options


def add_parser(sub) -> None:
    """Register ``train`` and its learners (every name of ``training_algorithms()``, read from the learner
    registry) on the top-level sub-parsers."""
    algorithms = training_algorithms()
    p = sub.add_parser("train", help=f"train a learner ({', '.join(algorithms)}): SAC / Switched SAC (thesis Ch. 3) "
                                     f"and the analytic policy gradients (Ch. 7) on a system, ARS (Ch. 4) on an env",
                       description="Train a learner; `hybridctl train ALGO --help` lists its flags.")
    add_debug_flag(p)
    learners = p.add_subparsers(dest="algorithm", required=True, metavar="{" + ",".join(algorithms) + "}",
                                parser_class=CommandParser)
    parsers, options = {}, {}
    for algorithm, learner in algorithms.items():
        config_name = learner.config_class.__name__
        title = learner_title(algorithm, learner)
        q = learners.add_parser(
            algorithm, help=title, description=title + ".",
            usage=f"%(prog)s SYSTEM [--FIELD VALUE ...] [--set KEY=VALUE ...] [--out DIR] [--resume] ...",
            epilog=f"Every {config_name} field is a flag.\n\n" + textwrap.fill(resume_help(algorithm), 100))
        add_system_argument(q, SYSTEM_HELP.get(algorithm, GYM_SYSTEM_HELP if learner.takes_gym_envs else None))
        options[algorithm] = add_common_flags(q, algorithm) | add_config_flags(q, algorithm)
        q.set_defaults(func=run_train)
        parsers[algorithm] = q
    for algorithm, q in parsers.items():
        q.unknown_flag_hint = _unknown_flag_hint(algorithm, options)


def resume_help(algorithm: str) -> str:
    """The resume policy of ``algorithm``, as ``hybridctl train ALGO --help`` prints it."""
    fields = {f.name for f in dataclasses.fields(training_algorithms()[algorithm].config_class)}
    applied = ", ".join(name for name in RESUME_APPLIED if name in fields)
    math_fields = "step_size, noise, n_directions, policy, postprocess, seed" if algorithm == "ars" else \
        "lr, gamma, network sizes, batch sizes, seed, num_envs" + (", the preset" if algorithm == "ssac" else "")
    bulky = "" if algorithm == "ars" else ", replay.pt" + (", gate_data.pt" if algorithm == "ssac" else "")
    text = (f"Resuming (--resume): the run continues from the newest of OUT/checkpoint and OUT/final, with the "
            f"checkpoint's settings. Given values of the run settings are applied: {applied}. Any other field "
            f"given with a value other than the recorded one ({math_fields}, ...) changes the algorithm's math: "
            f"the resume refuses, naming the field with its recorded and given value; --force applies it anyway. "
            f"A checkpoint of another algorithm or plant, or a missing or damaged file (model.pt, config.json, "
            f"normalization.json, progress.json{bulky}) is refused too, naming what differs or the file")
    text += "; --force continues without replay.pt" + (" / gate_data.pt" if algorithm == "ssac" else "") + \
        ", saying so." if bulky else "."
    return text + (" A new run refuses a folder that already holds a run unless --resume or --overwrite. A "
                   "checkpoint is written every checkpoint_every " + ("epochs" if algorithm == "ars" else "env steps")
                   + " and at least every checkpoint_minutes of wall time.")


@cli_errors
def run_train(args: argparse.Namespace) -> int:
    """Train, checkpoint, evaluate and print the evaluation (exit 3 when training diverged)."""
    settings = config_settings(args)
    if training_algorithms()[args.algorithm].uses_backend:
        backend = settings.get("backend", training_algorithms()[args.algorithm].config_class.backend)
        check_ray_task_flags(args, backend)
    with ray_options_for(args):   # --task-cpus/--task-gpus/--task-memory/--runtime-env (none: Ray's defaults)
        run = train_and_evaluate(args.algorithm, args.system, out=args.out, settings=settings,
                                 variant=getattr(args, "preset", None) or getattr(args, "variant", None),
                                 resume=args.resume,
                                 init=getattr(args, "init", None), eval_episodes=args.eval_episodes,
                                 progress=not args.quiet, command=args.command_line, force=args.force,
                                 overwrite=args.overwrite, spec=parse_spec_pairs(getattr(args, "spec", None)))
    result, out = run.evaluation, run.out
    if args.algorithm in APG_METHODS:
        print(f"return of the {result['which']} policy over {result['episodes']} held-out starts: "
              f"{result['mean_return']:.1f} +- {result['std_return']:.1f}; stabilised {result['success_rate']:.0%} "
              f"(pole upright {result['upright_rate']:.0%}); "
              f"{result['env_steps']} env steps; wrote {out}/final, progress.csv, eval.json")
        return 0
    if args.algorithm == "ars":
        dims = result["mean_dimensions"]
        print(f"return over {result['episodes']} episodes: {result['mean_return']:.1f} +- {result['std_return']:.1f}; "
              f"mesh dimension lower {dims['mesh_lower']}, upper {dims['mesh_upper']}; "
              f"wrote {out}/final, progress.csv, eval.json")
    else:   # SAC, SSAC and any other learner (EvalResult's keys; success None where the env has no success test)
        success = "no success test" if result.get("success_rate") is None else f"success {result['success_rate']:.0%}"
        print(f"deterministic return over {result['episodes']} episodes: {result['mean_return']:.2f} "
              f"+- {result['std_return']:.2f} (min {result['min_return']:.2f}), {success}")
        curves = ", training_curves.png" if (out / "training_curves.png").is_file() else ""
        print(f"wrote {out}/final (checkpoint), progress.csv{curves}, eval.json")
    return 0
