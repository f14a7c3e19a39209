"""Every `hybridctl ...` command in the code blocks of the README and of the documentation pages
parses with today's command line."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

from hybridctl.cli import build_parser

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
# The README and every page of docs/ written here (docs/api/ holds only ::: directives).
PAGES = [README, *sorted((ROOT / "docs").glob("*.md"))]


def page_commands(path: Path) -> list[str]:
    """The `hybridctl` lines of a page's bash blocks (continuation lines joined, comments cut)."""
    commands = []
    for block in re.findall(r"```bash\n(.*?)```", path.read_text(), re.S):
        text = block.replace("\\\n", " ")
        for line in text.splitlines():
            line = line.split("  #", 1)[0].split(" # ", 1)[0].strip()
            if line.startswith("hybridctl "):
                commands.append(line)
    return commands


COMMANDS = [(path.relative_to(ROOT).as_posix(), command) for path in PAGES for command in page_commands(path)]


def test_the_readme_and_the_pages_have_commands():
    assert len(page_commands(README)) >= 3, "the README's tour shows the command line"
    assert len(COMMANDS) >= 15, COMMANDS
    pages = {page for page, _ in COMMANDS}
    assert {"docs/systems.md", "docs/ch3_switched_sac.md", "docs/ch7_apg.md"} <= pages, pages


@pytest.fixture(scope="module")
def parser():
    """The command line's parser, built once for the module (about 0.08 s a build; parsing leaves it as it was)."""
    return build_parser()


@pytest.mark.parametrize("page, command", COMMANDS, ids=[f"{p}: {c}" for p, c in COMMANDS])
def test_documented_command_parses(page, command, parser):
    words = shlex.split(command)[1:]
    if "--help" in words:
        pytest.skip("prints help")
    parser.parse_args(words)  # a flag that no longer exists is a usage error (SystemExit)
