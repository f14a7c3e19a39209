"""Every `hybridctl ...` command in the README's code blocks parses with today's command line."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

from hybridctl.cli import build_parser

README = Path(__file__).resolve().parents[1] / "README.md"


def readme_commands() -> list[str]:
    """The `hybridctl` lines of the README's bash blocks (continuation lines joined, comments cut)."""
    commands = []
    for block in re.findall(r"```bash\n(.*?)```", README.read_text(), re.S):
        text = block.replace("\\\n", " ")
        for line in text.splitlines():
            line = line.split("  #", 1)[0].split(" # ", 1)[0].strip()
            if line.startswith("hybridctl "):
                commands.append(line)
    return commands


COMMANDS = readme_commands()


def test_the_readme_has_commands():
    assert len(COMMANDS) >= 15


@pytest.mark.parametrize("command", COMMANDS)
def test_readme_command_parses(command):
    words = shlex.split(command)[1:]
    if "--help" in words:
        pytest.skip("prints help")
    build_parser().parse_args(words)  # a flag that no longer exists is a usage error (SystemExit)
