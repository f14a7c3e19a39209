"""A user's install: the wheel carries the specs, robot models and pretrained checkpoints.

The wheel is built from this checkout and installed into a fresh virtual environment outside
it. The environment borrows the third-party packages (drake, torch, ...) of the running one
through a ``.pth`` line, which adds their folder without running its ``.pth`` files, so the
editable install of this checkout stays invisible: hybridctl comes from the wheel alone.
"""

from __future__ import annotations

import os
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# one xdist worker runs the module, so the wheel is built and installed once, not once per worker
pytestmark = pytest.mark.xdist_group("install")


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """(python, hybridctl script, working folder) of a fresh venv with the built wheel installed."""
    pytest.importorskip("setuptools", reason="building the wheel needs setuptools")
    tmp = tmp_path_factory.mktemp("install")
    wheels = tmp / "wheels"
    subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation",
                    "-w", str(wheels), str(ROOT)], check=True, capture_output=True)
    (wheel,) = wheels.glob("hybridctl-*.whl")
    venv = tmp / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    python = venv / "bin" / "python"
    purelib = subprocess.run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                             check=True, capture_output=True, text=True).stdout.strip()
    borrowed = sysconfig.get_paths()["purelib"]
    Path(purelib, "borrowed_dependencies.pth").write_text(borrowed + "\n")
    subprocess.run([sys.executable, "-m", "pip", "--python", str(python), "install", "-q", "--no-deps",
                    "--no-index", str(wheel)], check=True, capture_output=True)
    work = tmp / "elsewhere"
    work.mkdir()
    return python, venv / "bin" / "hybridctl", work


def run(command, work, **env):
    environment = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "HYBRIDCTL_SYSTEMS")}
    environment.update(env)
    return subprocess.run([str(c) for c in command], cwd=work, capture_output=True, text=True, env=environment,
                          timeout=300)


def test_the_installed_package_is_the_wheel_not_the_checkout(installed):
    python, _, work = installed
    out = run([python, "-c", "import hybridctl; print(hybridctl.__file__)"], work)
    assert out.returncode == 0, out.stderr
    assert str(ROOT) not in out.stdout and "site-packages" in out.stdout


@pytest.mark.slow   # one more interpreter start of the installed wheel; the simulate test covers the shipped data
def test_installed_hybridctl_lists_the_shipped_systems(installed):
    _, hybridctl, work = installed
    out = run([hybridctl, "systems"], work)
    assert out.returncode == 0, out.stderr
    for name in ("acrobot", "cartpole", "double_cartpole", "pendulum"):
        assert name in out.stdout


def test_installed_hybridctl_simulates_with_the_shipped_models_and_checkpoint(installed):
    _, hybridctl, work = installed
    out = run([hybridctl, "simulate", "cartpole", "--controller", "lqr", "--x0=0,0.05,0,0", "--duration", "0.5",
               "--out", "sim", "--no-html"], work)  # the cart-pole plant is built from the shipped SDF
    assert out.returncode == 0, out.stderr
    assert (work / "sim" / "summary.json").is_file()
    python = installed[0]
    code = ("from hybridctl.experiments import PRETRAINED_ACROBOT; from hybridctl.learn import load_controller; "
            "from hybridctl import systems; load_controller(PRETRAINED_ACROBOT, systems.load('acrobot')); "
            "print(PRETRAINED_ACROBOT)")
    out = run([python, "-c", code], work)
    assert out.returncode == 0, out.stderr
    assert "site-packages" in out.stdout


@pytest.mark.slow   # two more interpreter starts of the installed wheel (~25-40 s)
def test_user_specs_come_from_HYBRIDCTL_SYSTEMS(installed, tmp_path):
    _, hybridctl, work = installed
    spec = (ROOT / "hybridctl" / "data" / "systems" / "pendulum.toml").read_text()
    (tmp_path / "my_pendulum.toml").write_text(spec.replace('name = "pendulum"', 'name = "my_pendulum"'))
    out = run([hybridctl, "systems"], work, HYBRIDCTL_SYSTEMS=str(tmp_path))
    assert out.returncode == 0, out.stderr
    assert "my_pendulum" in out.stdout and "acrobot" in out.stdout
    out = run([hybridctl, "systems"], work, HYBRIDCTL_SYSTEMS=str(tmp_path / "missing"))
    assert out.returncode == 2 and "HYBRIDCTL_SYSTEMS" in out.stderr and "Traceback" not in out.stderr


# not pinned on purpose: this checkout itself and the installer's own tools
UNPINNED = {"hybridctl", "pip", "setuptools", "wheel"}


def _canonical(name: str) -> str:
    import re
    return re.sub(r"[-_.]+", "-", name).lower()


def test_every_installed_distribution_is_pinned_in_constraints():
    """What `make test` installed (the extras of TEST_EXTRAS and everything they pull in) is pinned exactly in
    constraints.txt, so a fresh machine gets the versions the suite was checked with."""
    import importlib.metadata

    pins = {}
    for line in (ROOT / "constraints.txt").read_text().splitlines():
        requirement = line.split("#")[0].strip()
        if "==" in requirement:
            name, version = requirement.split("==", 1)
            pins[_canonical(name)] = version.strip()
    unpinned = {}
    # what pip installed lies directly in site-packages; copies a package bundles and puts on sys.path
    # (setuptools/_vendor, Ray's thirdparty_files once ray is imported) are not installs of their own
    site_packages = {Path(sysconfig.get_paths()[key]).resolve() for key in ("purelib", "platlib")}
    for dist in importlib.metadata.distributions():
        if Path(str(getattr(dist, "_path", ""))).resolve().parent not in site_packages:
            continue
        name = _canonical(dist.metadata["Name"])
        # a local version label (torch's "+cpu") is the build, not the version
        if name not in UNPINNED and pins.get(name) != dist.version.split("+")[0]:
            unpinned[name] = (dist.version, pins.get(name))
    assert not unpinned, f"installed (version, pin): {unpinned}"


def test_make_test_requires_every_extra_it_installs():
    """The Makefile's TEST_EXTRAS are extras of pyproject.toml and each has modules that conftest checks, so
    `make test` fails at the start instead of skipping their tests when one is missing."""
    import tomllib

    import conftest

    makefile = (ROOT / "Makefile").read_text()
    (line,) = [row for row in makefile.splitlines() if row.startswith("TEST_EXTRAS :=")]
    extras = line.split(":=")[1].strip().split(",")
    declared = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    assert set(extras) <= set(declared) and set(extras) <= set(conftest.EXTRA_MODULES)
    assert {"sb3", "mujoco", "ray"} <= set(extras)
    assert "HYBRIDCTL_REQUIRE_EXTRAS=$(TEST_EXTRAS)" in makefile and "--dist loadgroup" in makefile
