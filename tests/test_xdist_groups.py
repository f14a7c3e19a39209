"""``make test`` runs the suite on two processes with ``--dist loadgroup``: the tests marked
``xdist_group(NAME)`` must run on one process (one local Ray instance for the session, one run of a
module's expensive fixture). pytest 9.2 with pytest-xdist 3.8 silently stopped grouping; this checks
that the pinned pair groups."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

pytest.importorskip("xdist")


def test_tests_of_one_xdist_group_run_on_one_worker(tmp_path):
    (tmp_path / "test_grouped.py").write_text(textwrap.dedent("""
        import os
        import pytest

        pytestmark = pytest.mark.xdist_group("one")

        @pytest.mark.parametrize("i", range(8))
        def test_x(i, record_property):
            print("WORKER", os.environ["PYTEST_XDIST_WORKER"])
    """))
    out = subprocess.run([sys.executable, "-m", "pytest", "-n", "2", "--dist", "loadgroup", "-v", "-s",
                          "-p", "no:cacheprovider", "-o", "addopts=", str(tmp_path / "test_grouped.py")],
                         capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-2000:]
    workers = {line.split()[0] for line in out.stdout.splitlines() if line.startswith("[gw")}
    assert len(workers) == 1, out.stdout[-2000:]
