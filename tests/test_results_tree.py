"""The records tree (results/): no record holds an absolute path of the machine that made it, no record
names the old tree, and results/INDEX.md lists every work folder that holds checkpoints."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "results"
BINARY = (".pt", ".npz", ".zip", ".png", ".pkl")
CHECKPOINTS = (".pt", ".zip", ".npz")
# an absolute path of a machine: a home folder, the scratch folder, a checkout under /work, a mount
MACHINE_PATH = re.compile(r"(?<![\w.~$/-])/(home|Users|root|tmp|work|mnt|private/var)/")


def tracked() -> list[Path]:
    """The files under results/ that git tracks (all files there without git)."""
    try:
        out = subprocess.run(["git", "ls-files", "-z", "results"], cwd=ROOT, capture_output=True, text=True,
                             check=True).stdout
        files = [ROOT / name for name in out.split("\0") if name]
    except (OSError, subprocess.CalledProcessError):
        files = [p for p in RESULTS.rglob("*") if p.is_file()]
    if not files:
        pytest.skip("no results/ tree in this checkout")
    return [p for p in files if p.is_file()]


def test_no_record_holds_an_absolute_machine_path():
    offenders = []
    for path in tracked():
        if path.suffix in BINARY:
            continue
        for i, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
            if MACHINE_PATH.search(line):
                offenders.append(f"{path.relative_to(ROOT)}:{i}: {line.strip()[:120]}")
    assert not offenders, "records with absolute paths (write them relative to the repository root):\n" + \
        "\n".join(offenders[:20])


def test_the_pattern_finds_machine_paths_only():
    assert MACHINE_PATH.search('"policy": "/work/main/models/policies/ars-hopper"')
    assert MACHINE_PATH.search("--out /tmp/he.json") and MACHINE_PATH.search("File \"/home/me/x.py\"")
    assert not MACHINE_PATH.search("results/ch5/hopper.json") and not MACHINE_PATH.search("/usr/bin/time")
    assert not MACHINE_PATH.search("$TMPDIR/t51a.json") and not MACHINE_PATH.search("~/.pyenv/versions")


# hybridctl/learn/apg.py is being rewritten beside this change; its one mention goes with that rewrite
NOT_YET: set[str] = set()


def test_no_file_names_the_old_records_tree():
    old = "notebooks" + "/data"
    offenders = [str(p.relative_to(ROOT)) for p in tracked() if p.suffix not in BINARY and old in p.read_text(errors="replace")]
    for folder in ("hybridctl", "tests", "docs", "notebooks", "benchmarks"):
        offenders += [str(p.relative_to(ROOT)) for p in (ROOT / folder).rglob("*")
                      if p.is_file() and p.suffix in (".py", ".md", ".ipynb", ".toml", ".json")
                      and str(p.relative_to(ROOT)) not in NOT_YET and old in p.read_text(errors="replace")]
    offenders += [name for name in ("README.md", "ARCHITECTURE.md", "mkdocs.yml", "Makefile")
                  if (ROOT / name).is_file() and old in (ROOT / name).read_text()]
    assert not offenders, f"files that still point at {old}/ (now results/): {offenders}"


def test_the_index_lists_every_work_folder_with_checkpoints():
    index = (RESULTS / "INDEX.md").read_text()
    folders = re.findall(r"^\| `([^`]+/)`", index, flags=re.M)
    assert folders, "results/INDEX.md has no table of work folders"
    missing = [f for f in folders if not (RESULTS / f).is_dir()]
    assert not missing, f"results/INDEX.md lists folders that do not exist: {missing}"
    unlisted = sorted({str(p.parent.relative_to(RESULTS)) for p in tracked() if p.suffix in CHECKPOINTS
                       and not any(str(p.relative_to(RESULTS)).startswith(f) for f in folders)})
    assert not unlisted, f"checkpoints in folders results/INDEX.md does not list: {unlisted}"


# ------------------------------------------------------------------ the tree holds records, not run state
# (ARCHITECTURE.md, "Records and run state")

MAX_TRACKED_BYTES = 20_000_000
"""The most the tracked results/ may hold: records and one checkpoint per run that something reads."""
SMALL_BYTES = 1024
"""Files below this may be equal by content alone (identity normalisation statistics, one-line logs)."""
EQUAL_BY_RESULT = {
    r"ch5/table51_runs/s\d+/(fractal|mesh-lower)/final/model\.pt":
        "two post-processors that left a seed's continuation at the same weights (two runs, one outcome)",
    r"your_robot/balance_map_furuta_(drake|torch)/balance_map\.png": "the Drake and torch engines draw the same map",
    r"(matrix/maps|trajopt/maps)/[\w-]+/balance_map\.png":
        "the same controller's map measured by the matrix and by the trajopt study (their JSON differ in timings)",
    r"matrix/finetune/[\w-]+/before\.json": "one starting policy measured before two fine-tunings",
    r"ch6/walker2d-ppo/(pretrained|finetuned)/vecnormalize\.npz": "fine-tuning keeps the normaliser frozen",
}
"""Groups of byte-identical records whose equality is itself a result, with the reason."""


def _sizes_and_digests(files: list[Path]) -> tuple[int, dict[str, list[str]]]:
    import hashlib

    total, groups = 0, {}
    for path in files:
        data = path.read_bytes()
        total += len(data)
        if len(data) >= SMALL_BYTES:
            groups.setdefault(hashlib.sha256(data).hexdigest(), []).append(str(path.relative_to(RESULTS)))
    return total, groups


def byte_copies(groups: dict[str, list[str]]) -> list[list[str]]:
    """The groups of two or more equal files that no :data:`EQUAL_BY_RESULT` pattern explains."""
    return [sorted(g) for g in groups.values() if len(g) > 1
            and not any(all(re.fullmatch(pattern, p) for p in g) for pattern in EQUAL_BY_RESULT)]


def run_state_twins(names: list[str]) -> list[str]:
    """Runs holding checkpoint state twice: a ``final/`` beside a ``checkpoint*/`` of the same run folder."""
    kinds: dict[str, set[str]] = {}
    for name in names:
        parts = name.split("/")
        for i, part in enumerate(parts[:-1]):
            if part == "final" or part.startswith("checkpoint"):
                kinds.setdefault("/".join(parts[:i]), set()).add(part)
                break
    return sorted(run for run, found in kinds.items() if len(found) > 1)


def test_the_tracked_tree_is_records_not_run_state():
    files = tracked()
    total, groups = _sizes_and_digests(files)
    assert total <= MAX_TRACKED_BYTES, (f"tracked results/ holds {total / 1e6:.1f} MB, over {MAX_TRACKED_BYTES / 1e6:.0f} "
                                        "MB: resumable state belongs in runs/ (ARCHITECTURE.md, 'Records and run state')")
    copies = byte_copies(groups)
    assert not copies, f"byte-identical copies under results/ (keep the one the code reads): {copies[:5]}"
    twins = run_state_twins([str(p.relative_to(RESULTS)) for p in files])
    assert not twins, f"runs with checkpoint state in both final/ and checkpoint*/ (keep final/): {twins[:5]}"


def test_the_checks_find_copies_and_twins():
    groups = {"a": ["s1/run/final/model.pt", "s1/run/checkpoint/model.pt"], "b": ["x.json"],
              "c": ["your_robot/balance_map_furuta_drake/balance_map.png",
                    "your_robot/balance_map_furuta_torch/balance_map.png"]}
    assert byte_copies(groups) == [["s1/run/checkpoint/model.pt", "s1/run/final/model.pt"]]
    assert run_state_twins(["a/r/final/model.pt", "a/r/checkpoint/model.pt", "b/final/model.pt",
                            "c/run/checkpoint-3/x", "c/run/final/x"]) == ["a/r", "c/run"]
