"""The Python blocks of the README and of the documentation's tour pages run as printed.

Each page's ```python blocks run in order, as one script, in one fresh interpreter
(``sys.executable``): a later block may use what an earlier one defined, as a reader who
pastes them one after another would. The working folder is a temporary one that links the
repository's ``models/`` and ``systems/``, so the pages' relative paths
(``models/policies/ssac-acrobot``) resolve as from the repository's root, while what the blocks
write (``runs/...``, ``replay.html``) lands in the temporary folder. A block whose fence reads
```python title="not run: REASON" is skipped and counted; keep those few.

The blocks run under a small driver that guards itself with ``if __name__ == "__main__":``,
so the worker processes a block spawns (balance maps, meshes) re-import the driver, not the
blocks. Tracebacks name the page and its line.

Also here, cheap checks of the same pages: the README stays short, its links and the pages'
links resolve, and the text carries no issue numbers.
"""

from __future__ import annotations

import importlib.util
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
README = ROOT / "README.md"
# The pages whose Python blocks are a tour to run (docs/your_robot.md is not among them).
TOUR_PAGES = [README, DOCS / "systems.md", DOCS / "ch3_switched_sac.md", DOCS / "ch4_trajectory_dimension.md",
              DOCS / "ch5_meshes_mfpt.md", DOCS / "ch6_finetuning.md", DOCS / "ch7_apg.md", DOCS / "performance.md"]
# Optional extras a page's blocks need: the page skips (with the reason) without them.
EXTRAS = {"ch4_trajectory_dimension.md": ["mujoco"], "ch5_meshes_mfpt.md": ["mujoco"]}
NOT_RUN = re.compile(r'title="not run: ([^"]+)"')
MAX_NOT_RUN = 3
LINKED = ["systems", "ch3_switched_sac", "ch4_trajectory_dimension", "ch5_meshes_mfpt", "ch6_finetuning",
          "ch7_apg", "performance", "your_robot"]

_FENCE = re.compile(r"^(?P<indent>[ \t]*)```(?P<info>[^\n`]*)$")

DRIVER = '''\
import builtins, json, sys, traceback

if __name__ == "__main__":
    blocks = json.load(open(sys.argv[1]))
    namespace = {"__name__": "__main__", "__builtins__": builtins}
    for block in blocks:
        # blank lines in front: a traceback names the page's own line
        code = compile("\\n" * (block["line"] - 1) + block["code"], block["page"], "exec")
        print(f"--- {block['page']}:{block['line']}", flush=True)
        try:
            exec(code, namespace)
        except BaseException:
            traceback.print_exc()
            print(f"FAILED: the block at {block['page']}:{block['line']}", flush=True)
            sys.exit(1)
    print("ALL BLOCKS RAN", flush=True)
'''


def fenced_blocks(path: Path) -> list[dict]:
    """Every fenced block of a Markdown file: language, info string, first code line (1-based), code."""
    lines = path.read_text().splitlines()
    blocks, i = [], 0
    while i < len(lines):
        match = _FENCE.match(lines[i])
        if match is None:
            i += 1
            continue
        indent, info = match.group("indent"), match.group("info").strip()
        start, body = i + 1, []
        i += 1
        while i < len(lines) and lines[i].strip() != "```":
            line = lines[i]
            body.append(line[len(indent):] if line.startswith(indent) else line.lstrip())
            i += 1
        assert i < len(lines), f"{path.name}:{start}: a fence that is never closed"
        language = info.split()[0] if info else ""
        blocks.append({"language": language, "info": info, "line": start + 1, "code": "\n".join(body) + "\n"})
        i += 1
    return blocks


def python_blocks(path: Path) -> tuple[list[dict], list[str]]:
    """(blocks to run, reasons of the blocks marked not to run) of a page."""
    run, skipped = [], []
    for block in fenced_blocks(path):
        if block["language"] != "python":
            continue
        reason = NOT_RUN.search(block["info"])
        if reason:
            skipped.append(f"{path.name}:{block['line']}: {reason.group(1)}")
        else:
            run.append(block)
    return run, skipped


def _label(path: Path) -> str:
    return str(path.relative_to(ROOT))


def test_the_pages_have_python_blocks_and_few_are_skipped():
    counts = {_label(p): len(python_blocks(p)[0]) for p in TOUR_PAGES}
    assert counts["README.md"] >= 3, counts
    assert sum(counts.values()) >= 15, counts
    skipped = [reason for p in TOUR_PAGES for reason in python_blocks(p)[1]]
    assert len(skipped) <= MAX_NOT_RUN, f"too many blocks marked not to run: {skipped}"


@pytest.mark.parametrize("page", [p for p in TOUR_PAGES if python_blocks(p)[0]], ids=_label)
def test_page_python_blocks_run_as_printed(page, tmp_path):
    for module in EXTRAS.get(page.name, []):
        if importlib.util.find_spec(module) is None:
            pytest.skip(f"{page.name} needs the {module} extra (pip install -e '.[{module}]')")
    work = tmp_path / "work"
    work.mkdir()
    for name in ("models", "systems"):
        (work / name).symlink_to(ROOT / name)
    blocks = [{"page": _label(page), "line": b["line"], "code": b["code"]} for b in python_blocks(page)[0]]
    (tmp_path / "blocks.json").write_text(json.dumps(blocks))
    driver = tmp_path / "run_blocks.py"
    driver.write_text(DRIVER)
    # one torch thread, as in every test (tests/conftest.py): the blocks' torch balance maps and rollouts
    # otherwise take both cores' threads while the other test process runs, and ran 2-3x slower
    env = {**os.environ, "MPLBACKEND": "Agg", "TQDM_DISABLE": "1", "OMP_NUM_THREADS": "1"}
    env.pop("HYBRIDCTL_LIVE_MESHCAT", None)
    start = time.perf_counter()
    result = subprocess.run([sys.executable, str(driver), str(tmp_path / "blocks.json")], cwd=work, env=env,
                            capture_output=True, text=True, timeout=300)
    print(f"{_label(page)}: {len(blocks)} blocks in {time.perf_counter() - start:.1f} s")
    output = result.stdout + result.stderr
    assert result.returncode == 0 and "ALL BLOCKS RAN" in result.stdout, \
        f"{_label(page)}: a Python block does not run as printed:\n{output[-6000:]}"


# --- cheap checks of the same pages ----------------------------------------------------------

def test_the_readme_is_short():
    lines = README.read_text().splitlines()
    assert len(lines) <= 200, f"README.md has {len(lines)} lines: move detail to a docs page"
    assert "## Quick start" in README.read_text() and "make docs" in README.read_text()


_LINK = re.compile(r"\]\(([^)\s]+)\)")


def _site_figures() -> set[str]:
    """docs/hooks.py's RESULT_FIGURES (read as text: the hooks import MkDocs, a docs extra)."""
    found = re.search(r"RESULT_FIGURES = \(([^)]*)\)", (DOCS / "hooks.py").read_text())
    return set(re.findall(r'"([^"]+)"', found.group(1))) if found else set()


@pytest.mark.parametrize("page", [README, *sorted(p for p in DOCS.glob("*.md"))], ids=_label)
def test_relative_links_resolve(page):
    """Links to files resolve from the page's folder (the README's from the repository's root;
    docs/hooks.py points them at the site's pages); a figure the hooks add to the site
    (RESULT_FIGURES) resolves from the repository's root."""
    text = re.sub(r"```.*?```", "", page.read_text(), flags=re.S)
    broken = []
    figures = _site_figures()
    for target in _LINK.findall(text):
        if re.match(r"[a-z]+:", target) or target.startswith("#"):
            continue
        if page.parent == DOCS and target in figures:
            path = ROOT / target
            if not path.exists():
                broken.append(target)
            continue
        path = (page.parent / target.split("#")[0]).resolve()
        if not path.exists():
            broken.append(target)
    assert not broken, f"{_label(page)}: links to missing files {broken}"


def test_the_readme_links_every_page():
    text = README.read_text()
    for name in LINKED:
        assert f"](docs/{name}.md)" in text, f"README.md does not link docs/{name}.md"
    for notebook in sorted((ROOT / "notebooks").glob("*.ipynb")):
        assert f"](notebooks/{notebook.name})" in text, f"README.md does not link notebooks/{notebook.name}"


@pytest.mark.parametrize("page", [*TOUR_PAGES, ROOT / "CHANGELOG.md", ROOT / "ARCHITECTURE.md"], ids=_label)
def test_no_issue_numbers_in_the_product(page):
    found = re.findall(r"\bissues? \d+", page.read_text(), flags=re.I)
    assert not found, f"{_label(page)} names issues {found}: say what was done, not which issue asked"
