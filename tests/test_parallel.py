"""Scripts just work: the process backend names a missing ``if __name__ == "__main__":`` guard in one line."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

UNGUARDED = """\
from hybridctl.parallel import ProcessBackend

with ProcessBackend(workers=1) as backend:
    print(backend.map(abs, [-1, -2]))
"""

GUARDED = """\
from hybridctl.parallel import ProcessBackend


def main():
    with ProcessBackend(workers=1) as backend:
        print(backend.map(abs, [-1, -2]))


if __name__ == "__main__":
    main()
"""

UNGUARDED_BALANCE_MAP = """\
from hybridctl.experiments import balance_map

balance_map("pendulum", "energy", grid=2, duration=0.2, workers=2, progress=False)
"""


def run_script(tmp_path, source):
    script = tmp_path / "script.py"
    script.write_text(source)
    return subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300, cwd=tmp_path)


@pytest.mark.parametrize("source, line", [(UNGUARDED, 4), (UNGUARDED_BALANCE_MAP, 3)])
def test_an_unguarded_script_gets_one_line_naming_the_guard(tmp_path, source, line):
    out = run_script(tmp_path, source)
    assert out.returncode != 0
    message = [l for l in out.stderr.splitlines() if l.startswith("RuntimeError")]
    assert len(message) == 1, out.stderr
    assert f"script.py:{line} starts worker processes outside 'if __name__ == \"__main__\":'" in message[0]
    assert "workers died" not in out.stderr  # the cause, not the symptom


def test_a_guarded_script_runs_its_workers(tmp_path):
    out = run_script(tmp_path, GUARDED)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[1, 2]"


def test_no_check_outside_scripts():
    from hybridctl.parallel import unguarded_script_line

    assert unguarded_script_line() is None  # under pytest, whose entry point is guarded
    code = textwrap.dedent("""
        from hybridctl.parallel import unguarded_script_line
        print(unguarded_script_line())
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "None"  # python -c: no script file to re-import
