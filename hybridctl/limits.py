"""Every upper limit hybridctl puts on a size, count or duration, stated once.

The bottom room, beside ``io`` and ``parallel``: it imports nothing from the package.
A limit is checked before any work starts, with a one-line error that names the argument
(a flag, or a file and its key) and the limit. Limits derived from the machine read its
memory and cores when they are asked for; the others are stated caps, chosen so that the
largest run a user may want passes and a typo (``--duration 1e9``) does not start a run
that cannot end. Where a user may truly want more, the command has ``--force`` (the Python
API: ``force=True``), which lifts the caps but never the machine-derived memory limits.
"""

from __future__ import annotations

import math
import os

__all__ = ["LimitError", "memory_bytes", "cpu_count", "memory_budget", "check_at_most", "check_fits_memory",
           "MAX_SIMULATION_STEPS", "MAX_TOTAL_STEPS", "MAX_GRID", "MAX_DISTURBANCES", "MAX_REFINED_DISTURBANCES",
           "MAX_MONTE_CARLO",
           "MAX_HIDDEN_UNITS", "MAX_NUM_ENVS", "MAX_ZIP_ENTRY_BYTES", "MAX_ZIP_ENTRIES", "MAX_JSON_BYTES",
           "MAX_SPEC_BYTES", "MAX_MODEL_CACHE_BYTES", "MAX_MODEL_CACHE_DEPTH",
           "MAX_MODEL_BODIES", "MAX_FIT_BUDGET_MINUTES", "MAX_FIT_EQUILIBRIUM_CANDIDATES", "MAX_NAME_CHARS", "MAX_CACHE_INTEGER", "MIN_DT", "MEMORY_FRACTION"]


class LimitError(ValueError):
    """A size, count or duration above its limit (a ValueError: the CLI prints it as one line, exit 2)."""


# --------------------------------------------------------------------------- stated caps
MAX_SIMULATION_STEPS = 10_000_000
"""Time steps of one simulated trajectory (``--duration`` / the spec's ``dt``): 1e7 steps of the
acrobot's 4 states and 1 input are 0.4 GB recorded; at dt = 0.01 s it is 27 hours of motion."""
MAX_FIT_BUDGET_MINUTES = 7 * 24 * 60
"""``hybridctl fit --budget``: a week; a typo (``--budget 1e9``) is refused."""
MAX_FIT_EQUILIBRIUM_CANDIDATES = 4096
"""0/pi combinations ``fit`` tries for the equilibria (12 revolute coordinates, the multibody family's most)."""
MAX_TOTAL_STEPS = 10_000_000_000
"""Time steps of all simulations of one command together (a balance map: grid^2 x steps):
about an hour of the torch engine on one core (measured order: 3e6 steps/s)."""
MAX_GRID = 1001
"""Points per axis of a balance map (``--grid``): 1e6 initial states."""
MAX_DISTURBANCES = 100_000
"""Disturbance samples per state of a reachable-state mesh (``--disturbances``)."""
MAX_REFINED_DISTURBANCES = 1537
"""Points a mesh's disturbance grid may be refined to (25 doubled six times: 25, 49, ..., 1537);
the rimless wheel's MFPT settles to 1 % by 193. The successor table's memory is checked too."""
MAX_MONTE_CARLO = 10_000_000
"""Monte Carlo runs of a first-passage estimate (``--monte-carlo``)."""
MAX_HIDDEN_UNITS = 65_536
"""Units of one hidden layer of a learner's network (``--hidden-size``); memory is checked too."""
MAX_NUM_ENVS = 1_000_000
"""Environments of one batched torch env (``--num-envs``); memory is checked too."""
MAX_UPDATES = 10_000_000
"""Updates, epochs or iterations of one training run (``--epochs``, ``--updates``, ``apg_iterations``):
the thesis' longest runs take thousands (ARS on Hopper: 1e3 to 1e4 epochs)."""
MAX_EVAL_EPISODES = 1_000_000
"""Episodes of one evaluation (``--eval-episodes``); the thesis evaluates on 100 to 1,000."""
MAX_CONFIG_INTEGER = 2 ** 53
"""Any other integer setting of a learner's config (buffer sizes, batch sizes, cadences): the largest
integer a float64 (JSON, a checkpoint) holds exactly; above it a value is a typo, not a setting."""
MIN_DT = 1e-6
"""The smallest time step a spec may set (``dt``, ``control.period``): one microsecond."""

# --------------------------------------------------------------------------- Ray and trajopt
RAY_CONNECT_TIMEOUT_S = 10.0
"""Seconds to find the Ray cluster named by ``--address`` / ``RAY_ADDRESS`` before joining it: the
host's DNS lookup, a TCP connect and the gRPC greeting of its head together (a head on the same
network answers in milliseconds; Ray itself waited 70 s on a closed port, and forever at times)."""
MAX_TASK_CPUS = 10_000
"""CPUs one Ray task may ask for (``--task-cpus``); the cluster's largest node is checked too."""
MAX_TASK_GPUS = 1_000
"""GPUs one Ray task may ask for (``--task-gpus``); the cluster's largest node is checked too."""
MAX_TASK_MEMORY_BYTES = 1 << 46
"""Bytes one Ray task may reserve (``--task-memory``, 64 TiB: above the largest single machines);
the cluster's largest node is checked too."""
MAX_TRAJOPT_KNOTS = 2_000
"""Knots of one collocation swing-up (``TrajoptSettings.knots``; 41 solve every benchmark system)."""
MAX_TRAJOPT_ROWS = 1_000_000
"""Rows of one trajopt tracking table (duration / period + 1; 801 for 8 s at 0.01 s), also as read
from a cache file: the double cart-pole's rows are 14 floats, 0.1 GB at the limit."""

__all__ += ["RAY_CONNECT_TIMEOUT_S", "MAX_TASK_CPUS", "MAX_TASK_GPUS", "MAX_TASK_MEMORY_BYTES", "MAX_TRAJOPT_KNOTS",
            "MAX_TRAJOPT_ROWS"]

# --------------------------------------------------------------------------- files we read
MAX_ZIP_ENTRY_BYTES = 1 << 30
"""Decompressed bytes of one entry of a zip we read (an SB3 ``model.zip``); read in chunks and
stopped at the limit, so a zip bomb never inflates past it."""
MAX_ZIP_ENTRIES = 1_000
"""Entries of one zip we read."""
MAX_JSON_BYTES = 64 << 20
"""Bytes of one JSON file or zip entry parsed as JSON (``config.json``, an SB3 ``data`` entry)."""
MAX_SPEC_BYTES = 1 << 20
"""Bytes of one spec file (``systems/NAME.toml``, ``--spec FILE``)."""
MAX_MODEL_BYTES = 16 << 20
"""Bytes of one robot model file (URDF, SDF, MJCF, and each file it includes): far above any model of
an underactuated robot; a larger file is refused before it is parsed."""
MAX_MESH_BYTES = 32 << 20
"""Bytes of one file a model names (a mesh, its material library, a texture, a glTF buffer): a replay
page embeds it, so it is read only when it is a regular file in the model's folder of at most this."""
MAX_MODEL_FILES = 1_000
"""File references (meshes, textures, includes) of one model with its includes expanded as the parser
expands them (a file included twice counts twice)."""
MAX_INCLUDE_DEPTH = 8
"""How deep MJCF / SDF ``<include>``s may nest; a file that includes itself is refused at any depth."""
MAX_BODIES = 100
"""Bodies (links) of one model with its includes expanded, counted in the file before Drake parses it:
the generated models have at most 12 joints; deriving one with 100 welded links took 0.7 s, with 300
19 s (measured on a 2-core machine, 2026-12-07), so 20,000 would not end."""
MAX_MODEL_LENGTH = 1e3
"""|x| of any offset in a model (joint origins, frames, in m): a kilometre. Products of lengths, masses
and inertias appear squared in the generated code; past this a typo (1e300) becomes inf there."""
MAX_MODEL_MASS = 1e6
"""Mass of one body of a model, in kg (a thousand tonnes)."""
MAX_MODEL_INERTIA = 1e6
"""Principal moment of inertia of one body of a model, in kg m^2."""
MAX_DERIVE_SECONDS = 300.0
"""Wall time of one symbolic derivation of a model's equations (checked as it goes): a planar chain
of 4 joints took 1.8 s, of 5 joints 14 s, of 6 joints more than 2 minutes (measured on a 2-core machine, 2026-12-07); past
this a model is too large to generate code for."""

__all__ += ["MAX_MODEL_BYTES", "MAX_MESH_BYTES", "MAX_MODEL_FILES", "MAX_INCLUDE_DEPTH", "MAX_BODIES",
            "MAX_MODEL_LENGTH", "MAX_MODEL_MASS", "MAX_MODEL_INERTIA", "MAX_DERIVE_SECONDS"]

MAX_MODEL_CACHE_BYTES = 16 << 20
"""Bytes of one generated-model cache file (``$HYBRIDCTL_CACHE/multibody/KEY.json``): a model at
``systems.multibody.MAX_TERMS`` (20,000 terms of 48 exponents) writes about 3 MB; the acrobot's 5 kB."""
MAX_MODEL_CACHE_DEPTH = 8
"""Nesting of lists and objects in one generated-model cache file (a model record nests 5 deep),
checked on the bytes before they are parsed."""
MAX_MODEL_BODIES = 256
"""Moving bodies of one generated model (its drawing's points), as read from a cache file."""
MAX_NAME_CHARS = 255
"""Characters of one joint, actuator or body name read from a generated-model cache file."""
MAX_CACHE_INTEGER = 1 << 53
"""Largest magnitude of an integer read from a cache file as a number: every integer up to it is
a float exactly (a larger one could overflow, or round)."""

MAX_CHECKPOINT_FILE_BYTES = 4 << 30
"""Bytes of one file a checkpoint names or holds (``model.pt``, ``replay.pt``, a file a field points to):
SSAC's replay buffer at its default size is about 0.5 GB; the file must also be a regular file."""
MAX_NETWORK_PARAMETERS = 1 << 30
"""Parameters of one network a checkpoint describes (widths x depths, summed over its layers): 4 GiB of
float32; the memory budget is checked too."""
MAX_CHECKPOINT_STRING = 4096
"""Characters of one string a checkpoint records (a name, a path, a setting)."""
MAX_SPEC_FILES = 1_000
"""Spec files read from one ``$HYBRIDCTL_SYSTEMS`` folder."""

MEMORY_FRACTION = 0.5
"""The share of the machine's memory one allocation we can size in advance may take."""


# --------------------------------------------------------------------------- the machine
def memory_bytes() -> int:
    """The machine's physical memory in bytes (from ``os.sysconf``; 8 GiB where it cannot be read)."""
    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):  # pragma: no cover - platforms without sysconf
        return 8 << 30


def cpu_count() -> int:
    """The cores this process may run on (its affinity where the OS tells it, else ``os.cpu_count()``)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # pragma: no cover - macOS, Windows
        return max(1, os.cpu_count() or 1)


def memory_budget() -> int:
    """Bytes one allocation sized in advance may take: :data:`MEMORY_FRACTION` of the memory."""
    return int(memory_bytes() * MEMORY_FRACTION)


def _shown(value: float) -> str:
    return f"{value:,}" if isinstance(value, int) else f"{value:g}"


def check_at_most(name: str, value: float, limit: float, force: bool = False, why: str = "",
                  force_flag: str | None = "--force") -> None:
    """Raise :class:`LimitError` if ``value`` > ``limit`` (or is not finite) unless ``force``.

    ``name`` is the argument as the user wrote it (``"--duration"``, ``"config.json: num_envs"``);
    ``why`` says what the limit protects (``"steps of one trajectory"``). ``force_flag`` names the
    escape in the message (None: there is none, ``force`` is ignored).
    """
    if isinstance(value, float) and not math.isfinite(value):
        raise LimitError(f"{name} must be finite, got {value}")
    if value <= limit or (force and force_flag is not None):
        return
    what = f" ({why})" if why else ""
    escape = f"; pass {force_flag} to allow more" if force_flag is not None else ""
    raise LimitError(f"{name} is {_shown(value)}, above its limit of {_shown(limit)}{what}{escape}")


def check_fits_memory(name: str, nbytes: float, what: str) -> None:
    """Raise :class:`LimitError` if ``nbytes`` (what ``name`` asks to allocate) exceeds :func:`memory_budget`.

    No ``--force`` lifts it: past the machine's memory a run is killed, it does not finish.
    """
    budget = memory_budget()
    if not math.isfinite(nbytes) or nbytes > budget:
        raise LimitError(f"{name} needs {nbytes / 2**30:.3g} GiB for {what}, more than "
                         f"{MEMORY_FRACTION:.0%} of this machine's {memory_bytes() / 2**30:.3g} GiB")


MAX_SWEEP_MONTE_CARLO_STEPS = 100_000_000
"""Expected simulated steps (runs x the mesh's MFPT) of one Monte Carlo estimate in an MFPT-vs-roughness
sweep (``hybridctl mesh MAP --slope-std A B ...``); above it that sigma's Monte Carlo is skipped with the
reason recorded. Measured on one core of the development machine: the rimless wheel's 2,000 runs at
sigma 2 degrees (6.4e7 steps) take 13-25 s, so 1e8 is under a minute."""
__all__ += ["MAX_SWEEP_MONTE_CARLO_STEPS"]


MAX_SECTION_STEP_SECONDS = 5.0
"""Wall time one step of a Drake section map (``hybridctl.drake.sections``: the rimless wheel, the compass
gait) may take; past it the step stops and counts as a fall (the map's ``last_failure`` and ``guard_trips``
say so). A normal compass-gait step takes about 15 ms here; a falling one whose legs chatter on the ground
(heel strikes in a Zeno sequence) ran on for minutes before the guard."""
MAX_SECTION_INTEGRATOR_STEPS = 50_000
"""Integrator steps one step of a Drake section map may take before it counts as a fall (deterministic,
unlike the wall-time guard: about 13 s of simulated time at the 1e-3 s largest step; a normal compass-gait
step takes under 1,000)."""
__all__ += ["MAX_SECTION_STEP_SECONDS", "MAX_SECTION_INTEGRATOR_STEPS"]
