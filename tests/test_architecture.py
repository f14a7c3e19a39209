"""The layer rule of ARCHITECTURE.md, checked on the source: no module imports from a room above its own.

Rooms, bottom to top (one level per line; rooms on one level never import each other):

    limits
    io, parallel
    systems
    analysis
    viz
    drake, envs
    learn
    experiments
    cli, reproduce

Every ``import`` and ``from ... import`` is checked, also those inside functions (a lazy
import hides a cycle, it does not remove it).
"""

from __future__ import annotations

import ast
import importlib
import re
import subprocess
import sys
from pathlib import Path

import pytest

import hybridctl

PACKAGE_DIR = Path(hybridctl.__file__).resolve().parent
LEVELS = {"limits": -1, "io": 0, "parallel": 0, "workers": -1, "systems": 1, "analysis": 2, "viz": 3, "drake": 4, "envs": 4, "learn": 5,
          "experiments": 6, "cli": 7, "reproduce": 7}


def module_name(path: Path) -> str:
    """'hybridctl.envs.single' for .../hybridctl/envs/single.py (packages without '__init__')."""
    parts = list(path.relative_to(PACKAGE_DIR.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def imported_modules(source: str, module: str, is_package: bool) -> list[tuple[int, str]]:
    """(line, absolute module) for every import in ``source``, relative ones resolved.

    ``from X import name`` yields ``X.name`` (the name may be a submodule) and the room
    is decided by the first component after ``hybridctl``, so both forms count.
    """
    package = module if is_package else module.rpartition(".")[0]
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            found += [(node.lineno, f"{target}.{alias.name}") for alias in node.names]
    return found


def room(module: str) -> str | None:
    """The room of a hybridctl module ('hybridctl.learn.sac' -> 'learn'); None outside hybridctl
    or for the package root itself (which holds only ``__version__``)."""
    parts = module.split(".")
    if parts[0] != "hybridctl" or len(parts) < 2 or parts[1] not in LEVELS:
        return None
    return parts[1]


def violations(source: str, module: str, is_package: bool = False) -> list[str]:
    """Imports in ``source`` (the module ``module``) that go up or sideways between rooms."""
    own = room(module)
    if own is None:
        return []
    bad = []
    for line, target in imported_modules(source, module, is_package):
        other = room(target)
        if other is None or other == own:
            continue
        if LEVELS[other] >= LEVELS[own]:
            direction = "sideways" if LEVELS[other] == LEVELS[own] else "up"
            bad.append(f"{module}:{line} imports {target} ({own} -> {other}, {direction})")
    return bad


def all_modules() -> list[Path]:
    return sorted(PACKAGE_DIR.rglob("*.py"))


def test_every_module_belongs_to_a_room():
    homeless = [module_name(p) for p in all_modules()
                if module_name(p) != "hybridctl" and room(module_name(p)) is None]
    assert not homeless, f"modules outside the rooms of ARCHITECTURE.md: {homeless}"


def test_no_module_imports_from_a_room_above_its_own():
    bad = []
    for path in all_modules():
        bad += violations(path.read_text(), module_name(path), path.name == "__init__.py")
    assert not bad, "imports against the layer rule:\n" + "\n".join(bad)


@pytest.mark.parametrize("source, module, expected", [
    ("from ..learn import SAC\n", "hybridctl.drake.diagram", "drake -> learn, up"),
    ("def f():\n    from ..learn import load_controller\n", "hybridctl.drake.diagram", "drake -> learn, up"),
    ("import hybridctl.drake\n", "hybridctl.envs.single", "envs -> drake, sideways"),
    ("from .. import experiments\n", "hybridctl.analysis.mesh", "analysis -> experiments, up"),
    ("from ..systems import System\n", "hybridctl.drake", None),
    ("from hybridctl.reproduce import table51\n", "hybridctl.cli.train", "cli -> reproduce, sideways"),
    ("from ..experiments import apg_study\n", "hybridctl.reproduce.fig71", None),
])
def test_the_checker_finds_upward_lazy_and_sideways_imports(source, module, expected):
    found = violations(source, module, is_package=module.count(".") == 1)
    if expected is None:
        assert found == []
    else:
        assert len(found) == 1 and expected in found[0]


@pytest.mark.parametrize("module, forbidden", [
    ("hybridctl.envs", "pydrake"),
    ("hybridctl.systems", "pydrake"),
    ("hybridctl.analysis.poincare", "scipy.sparse"),
])
def test_light_rooms_do_not_load_heavy_dependencies(module, forbidden):
    code = f"import sys, {module}; print({forbidden!r} in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False", f"import {module} loaded {forbidden}"


def test_no_spec_string_look_ups_outside_systems():
    """Outside ``systems`` a spec value is read from its typed section (``system.gate.on``), not by string."""
    offenders = [f"{module_name(p)}:{i}" for p in all_modules() if room(module_name(p)) != "systems"
                 for i, line in enumerate(p.read_text().splitlines(), 1)
                 if "spec.get(" in line or "spec.has(" in line]
    assert not offenders, offenders


@pytest.mark.parametrize("module, forbidden", [
    ("hybridctl.learn", "pydrake"),
    ("hybridctl.viz.training", "pydrake"),
])
def test_learners_and_their_plots_do_not_need_drake(module, forbidden):
    code = (f"import sys, {module}; import hybridctl.learn as L; L.plot_training_curves; "
            f"print({forbidden!r} in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False", f"import {module} loaded {forbidden}"


REPRODUCE = PACKAGE_DIR / "reproduce"


@pytest.mark.parametrize("path", sorted(p for p in REPRODUCE.glob("*.py") if p.stem not in ("__init__", "common")),
                         ids=lambda p: p.stem)
def test_every_reproduction_driver_imports_and_runs_as_a_module(path):
    """``python -m hybridctl.reproduce.NAME``: each driver imports as a module, has ``main(argv=None)`` and
    the ``__main__`` guard, and the package docstring names it."""
    module = importlib.import_module(f"hybridctl.reproduce.{path.stem}")
    assert callable(getattr(module, "main", None)), f"{path.stem} has no main()"
    assert "argv" in module.main.__code__.co_varnames[:1], f"{path.stem}.main does not take argv"
    assert 'if __name__ == "__main__":' in path.read_text(), f"{path.stem} does not run as python -m"
    assert f"hybridctl.reproduce.{path.stem}" in (REPRODUCE / "__init__.py").read_text(), \
        f"hybridctl/reproduce/__init__.py does not list {path.stem}"


def _path_hacks(source: str) -> list[tuple[int, str]]:
    """``sys.path.insert`` / ``sys.path.append`` calls and ``spec_from_file_location`` loads in ``source``."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if not isinstance(node, ast.Call):
            continue
        name = ast.unparse(node.func)
        if name in ("sys.path.insert", "sys.path.append") or name.endswith("spec_from_file_location"):
            found.append((node.lineno, ast.unparse(node)[:100]))
    return found


# Loads by file path that are not drivers: the docs build's hook module (it lives in docs/, not in the package).
PATH_LOADS_ALLOWED = {("tests/test_docs.py", "hooks.py")}


def test_no_module_or_test_edits_sys_path_or_loads_a_script_by_its_path():
    """Drivers are imported as hybridctl.reproduce modules: nothing under hybridctl/ or tests/ edits
    ``sys.path`` or loads a file with ``spec_from_file_location`` (the docs hook aside)."""
    root = PACKAGE_DIR.parent
    bad = []
    for path in sorted(PACKAGE_DIR.rglob("*.py")) + sorted((root / "tests").rglob("*.py")):
        rel = str(path.relative_to(root))
        for line, call in _path_hacks(path.read_text()):
            if not any(rel == name and marker in call for name, marker in PATH_LOADS_ALLOWED):
                bad.append(f"{rel}:{line}: {call}")
    assert not bad, "path edits or loads by file path:\n" + "\n".join(bad)


def test_the_path_check_finds_them():
    assert len(_path_hacks("import sys\nsys.path.insert(0, 'x')\nsys.path.append('y')\n")) == 2
    assert len(_path_hacks("import importlib.util\nimportlib.util.spec_from_file_location('t', 'a/t.py')\n")) == 1
    assert _path_hacks("from hybridctl.reproduce import table51\n") == []


# ============================================================================ import cycles

def import_graph(modules: dict[str, str]) -> dict[str, set[str]]:
    """module -> the hybridctl modules it imports, from ``modules`` (name -> source). Every import
    counts, also those inside functions and under ``TYPE_CHECKING``: a cycle a type checker needs
    is still two modules that cannot be read or moved one without the other. ``from X import name``
    is an edge to ``X.name`` where that is a module, else to ``X``."""
    graph = {}
    for name, source in modules.items():
        edges = set()
        for _, target in imported_modules(source, name, name in PACKAGES):
            while target and target not in modules:
                target = target.rpartition(".")[0]
            if target and target != name:
                edges.add(target)
        graph[name] = edges
    return graph


def import_cycles(graph: dict[str, set[str]]) -> list[frozenset[str]]:
    """The strongly connected groups of more than one module (Tarjan's algorithm, iterative)."""
    index, low, on_stack, stack, found, counter = {}, {}, set(), [], [], 0
    for start in sorted(graph):
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = counter = counter + 1
        stack.append(start)
        on_stack.add(start)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = counter = counter + 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                group = set()
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    group.add(member)
                    if member == node:
                        break
                if len(group) > 1:
                    found.append(frozenset(group))
    return found


PACKAGES = {module_name(p) for p in all_modules() if p.name == "__init__.py"}


def test_no_two_modules_import_each_other():
    """No module imports another that imports it back, directly or around a longer cycle. A module that only
    names another's class in annotations writes a plain alias (``System = Any`` in ``systems/control.py``)."""
    modules = {module_name(p): p.read_text() for p in all_modules()}
    cycles = [sorted(c) for c in import_cycles(import_graph(modules))]
    assert not cycles, "modules that import each other (directly or through a cycle):\n" + "\n".join(map(str, cycles))


def test_the_cycle_check_finds_them():
    modules = {
        "hybridctl.learn": "",
        "hybridctl.learn.base": "from .run import Run\n",
        "hybridctl.learn.run": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from .base import Learner\n",
        "hybridctl.learn.a": "def f():\n    from . import b\n",
        "hybridctl.learn.b": "from .c import x\n",
        "hybridctl.learn.c": "from hybridctl.learn.a import f\n",
        "hybridctl.learn.d": "from .run import Run\nfrom . import base\n",
    }
    cycles = import_cycles(import_graph(modules))
    assert sorted(map(sorted, cycles)) == [["hybridctl.learn.a", "hybridctl.learn.b", "hybridctl.learn.c"],
                                           ["hybridctl.learn.base", "hybridctl.learn.run"]]


# ============================================================================ module size

MAX_MODULE_LINES = 600
"""A module longer than this mixes concerns; split it along one."""

# Modules still over the limit, each with why; the list may only shrink (one that got under it fails too).
OVER_THE_LIMIT: dict[str, str] = {}


def test_no_module_is_over_600_lines():
    sizes = {str(p.relative_to(PACKAGE_DIR)): len(p.read_text().splitlines()) for p in all_modules()}
    over = {name: n for name, n in sizes.items() if n > MAX_MODULE_LINES}
    new = {name: n for name, n in over.items() if name not in OVER_THE_LIMIT}
    assert not new, f"modules over {MAX_MODULE_LINES} lines (split them along a concern): {new}"
    fixed = [name for name in OVER_THE_LIMIT if name not in over]
    assert not fixed, f"now at most {MAX_MODULE_LINES} lines; remove them from OVER_THE_LIMIT: {fixed}"


# ============================================================================ tracker numbers

# Where the code, the specs and the docs live (CHANGELOG.md is history and keeps its issue numbers; systems/ and
# models/ are links into hybridctl/data, read there).
TEXT_ROOTS = ["hybridctl", "docs", "results", "notebooks", "benchmarks", "README.md", "ARCHITECTURE.md"]
TEXT_SUFFIXES = {".py", ".toml", ".md", ".ipynb"}
TRACKER_NUMBER = re.compile(r"\bissues? #?\d+", re.IGNORECASE)

# Files that still point at a tracker number, each with why; the list may only shrink (one without a hit fails too).
TRACKER_NUMBERS_LEFT: dict[str, str] = {}


def tracker_numbers(text: str) -> list[str]:
    """Each 'issue N' / 'issues N' / 'issue #N' in ``text`` (any case)."""
    return [m.group(0) for m in TRACKER_NUMBER.finditer(text)]


def text_files() -> list[Path]:
    root = PACKAGE_DIR.parent
    found = []
    for name in TEXT_ROOTS:
        path = root / name
        found += [path] if path.is_file() else sorted(p for p in path.rglob("*") if p.suffix in TEXT_SUFFIXES
                                                       and p.is_file() and not p.is_symlink())
    return found


def test_code_specs_and_docs_state_reasons_not_tracker_numbers():
    """A comment, a spec's source or a doc says why ("the Python loop the C++ PortSwitch replaced"), not
    where it was discussed ("before issue 15"): a reader of the repository has no tracker."""
    root = PACKAGE_DIR.parent
    hits = {}
    for path in text_files():
        rel = path.relative_to(root).as_posix()
        for i, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
            for found in tracker_numbers(line):
                hits.setdefault(rel, []).append(f"{rel}:{i}: {found}")
    new = [h for rel, lines in hits.items() if rel not in TRACKER_NUMBERS_LEFT for h in lines]
    assert not new, "tracker numbers instead of reasons:\n" + "\n".join(new)
    fixed = [rel for rel in TRACKER_NUMBERS_LEFT if rel not in hits]
    assert not fixed, f"no tracker numbers left; remove them from TRACKER_NUMBERS_LEFT: {fixed}"


def test_the_tracker_number_check_finds_them():
    assert tracker_numbers("measured (issue 16): 7 %; Issues 15 and 16; issue #3") == ["issue 16", "Issues 15",
                                                                                        "issue #3"]
    assert tracker_numbers("no issue here, 15 issues, tissue 3") == []
