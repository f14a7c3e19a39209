"""The documentation site (`make docs`): its configuration, and the built site in headless Chromium.

The fast tests check mkdocs.yml: every notebook and every API page is in the navigation,
every module of the package is documented on some API page, the notebooks are executed
during the build, and nothing is fetched from the network. The slow test builds the site
(about a minute: the notebooks run) and opens its pages in headless Chromium: the
notebooks' figures are rendered as embedded PNGs, their printed results are there, and the
API pages carry the docstrings. Tests skip with the reason when the ``docs`` extra or
Chromium is missing (``HYBRIDCTL_REQUIRE_CHROMIUM=1`` makes a missing Chromium fail, as in
tests/test_viz.py).
"""

from __future__ import annotations

import base64
import html
import inspect
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "mkdocs.yml"
DOCS = ROOT / "docs"
NOTEBOOKS = sorted((ROOT / "notebooks").glob("*.ipynb"))
CHROMIUM = os.environ.get("HYBRIDCTL_CHROMIUM", "/usr/bin/chromium")
CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                  "--disable-component-update", "--no-first-run", "--disable-sync", "--window-size=1280,900",
                  "--virtual-time-budget=5000"]
# The rooms of ARCHITECTURE.md that must each have an API page (docs/api/<room>.md).
ROOMS = ["limits", "workers", "io", "parallel", "systems", "systems.control", "analysis", "viz", "drake", "envs", "learn", "learn.run",
         "experiments", "cli", "reproduce"]
# A line each executed notebook prints (the same lines tests/test_notebooks.py checks).
PRINTED = {
    "01_hybrid_control": "K matches thesis: True",
    "02_switched_sac": "save/load round trip: True",
    "03_trajectory_dimension": "same curve: True",
    "04_reachable_mesh_mfpt": "hopper record: results/ch5/hopper.json",
    "05_analytic_policy_gradients": "Ch. 7 record: results/ch7/table71.json",
    "06_fine_tuning": "Ch. 6 record: results/ch6/results.json",
}
# Figures (matplotlib PNGs) each notebook shows at least.
MIN_FIGURES = {"01_hybrid_control": 3, "02_switched_sac": 2, "03_trajectory_dimension": 3,
               "04_reachable_mesh_mfpt": 2, "05_analytic_policy_gradients": 3,
               "06_fine_tuning": 3}


def _config() -> dict:
    yaml = pytest.importorskip("yaml", reason="PyYAML is missing (install the docs extra: pip install -e '.[docs]')")
    return yaml.safe_load(CONFIG.read_text())


def _nav_pages(nav) -> list[str]:
    pages = []
    for item in nav:
        value = next(iter(item.values())) if isinstance(item, dict) else item
        pages += _nav_pages(value) if isinstance(value, list) else [value]
    return pages


def _plugin(config: dict, name: str) -> dict:
    for plugin in config["plugins"]:
        if plugin == name:
            return {}
        if isinstance(plugin, dict) and name in plugin:
            return plugin[name] or {}
    raise AssertionError(f"mkdocs.yml has no {name!r} plugin")


def _modules() -> list[str]:
    """Every public module of the room packages (``__main__`` and ``_private`` aside), dotted."""
    names = []
    for path in sorted((ROOT / "hybridctl").rglob("*.py")):
        parts = list(path.relative_to(ROOT).with_suffix("").parts)
        if parts[-1] == "__main__" or (parts[-1].startswith("_") and parts[-1] != "__init__") or len(parts) == 1 \
                or parts == ["hybridctl", "__init__"]:
            continue
        if parts[-1] == "__init__":
            parts = parts[:-1]
        names.append(".".join(parts))
    return names


def test_docs_config_lists_every_notebook_and_api_page():
    config = _config()
    assert config["docs_dir"] == "docs" and config["site_dir"] == "site"
    assert config["strict"] is True, "a broken page or reference must fail the build"
    assert config["use_directory_urls"] is False, "pages must open from file:// without a server"
    pages = _nav_pages(config["nav"])
    for page in pages:
        assert (DOCS / page).exists(), f"nav names {page}, which docs/ lacks"
    assert pages[0] == "index.md" and "architecture.md" in pages
    assert '--8<-- "README.md"' in (DOCS / "index.md").read_text(), "the home page is the README"
    assert '--8<-- "ARCHITECTURE.md"' in (DOCS / "architecture.md").read_text()
    assert (DOCS / "notebooks").resolve() == (ROOT / "notebooks").resolve(), "docs/notebooks links to notebooks/"
    assert [p for p in pages if p.endswith(".ipynb")] == [f"notebooks/{p.name}" for p in NOTEBOOKS]
    assert [p for p in pages if p.startswith("api/")] == [f"api/{room}.md" for room in ROOMS]

    # Every module has a `::: module` block on some API page.
    documented = {}
    for page in (DOCS / "api").glob("*.md"):
        for module in re.findall(r"^::: (\S+)$", page.read_text(), flags=re.M):
            documented[module] = page.name
    missing = [m for m in _modules() if m not in documented]
    assert not missing, f"modules without an API page: {missing}"
    unknown = [m for m in documented if m not in _modules()]
    assert not unknown, f"API pages name modules that do not exist: {unknown}"

    jupyter = _plugin(config, "mkdocs-jupyter")
    assert jupyter.get("execute") is True and jupyter.get("allow_errors") is False
    assert jupyter.get("cache") is False, "every build executes the notebooks of this checkout"
    assert jupyter.get("include") == ["*.ipynb"]
    assert _plugin(config, "mkdocstrings")["handlers"]["python"]["paths"] == ["."]
    assert config["theme"]["name"] == "material" and config["theme"]["font"] is False, "no Google Fonts"
    assert "hooks.py" in config["exclude_docs"]


def test_docs_config_loads_in_mkdocs():
    """mkdocs itself validates the file (plugins, theme, extensions): needs the docs extra."""
    pytest.importorskip("mkdocs", reason="the docs extra is not installed (pip install -e '.[docs]')")
    for name in ("material", "mkdocstrings", "mkdocs_jupyter", "mkdocstrings_handlers.python"):
        pytest.importorskip(name, reason=f"{name} is missing: install the docs extra (pip install -e '.[docs]')")
    from mkdocs.config import load_config

    cwd = os.getcwd()
    os.chdir(ROOT)  # the snippets' base path and the hooks are relative to the repository
    try:
        config = load_config(str(CONFIG))
    finally:
        os.chdir(cwd)
    assert config.site_name == "hybridctl"
    assert {"mkdocs-jupyter", "mkdocstrings"} <= set(config.plugins), set(config.plugins)
    assert any(name.endswith("search") for name in config.plugins), set(config.plugins)


def test_doctest_lines_render_as_code():
    """docs/hooks.py fences ``>>>`` runs of the docstrings and drops Sphinx roles."""
    markdown = pytest.importorskip("markdown", reason="the docs extra is not installed")
    pytest.importorskip("mkdocs", reason="the docs extra is not installed")
    import importlib.util

    spec = importlib.util.spec_from_file_location("hybridctl_docs_hooks", DOCS / "hooks.py")
    hooks = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(hooks)
    text = ("Run it (:func:`simulate`):\n\n>>> result = run_demo()\n>>> result[\"simulation\"][\"balanced\"]\nTrue\n\n"
            "After.\n\n```python\n>>> inside a fence\n```\n")
    out = markdown.markdown(text, extensions=[hooks.DoctestFences(), "fenced_code"])
    assert "<code>simulate</code>" in out and ":func:" not in out
    assert out.count("<pre>") == 2
    assert html.escape('>>> result["simulation"]["balanced"]') in out, out
    assert "<p>After.</p>" in out


# --- the built site -----------------------------------------------------------------------

def _dump_dom(page: Path, tmp_path: Path) -> str:
    profile = tmp_path / f"profile-{page.stem}"
    cmd = [CHROMIUM, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", "--dump-dom", page.as_uri()]
    result = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0 and "<body" in result.stdout, \
        f"chromium could not open {page} (rc {result.returncode}):\n{result.stderr[-2000:]}"
    return result.stdout


def _text(dom: str) -> str:
    """The visible text of a DOM, whitespace collapsed."""
    dom = re.sub(r"<(script|style)\b.*?</\1>", " ", dom, flags=re.S)
    return " ".join(html.unescape(re.sub(r"<[^>]+>", " ", dom)).split())


def _images(dom: str, page: Path) -> list[bytes]:
    """The bytes of every <img> of the page: embedded data: URIs decoded, files read."""
    images = []
    for src in re.findall(r"<img\b[^>]*?\bsrc=\"([^\"]*)\"", dom):
        src = html.unescape(src)
        assert src, f"{page.name}: an <img> without src"
        if src.startswith("data:"):
            header, _, data = src.partition(",")
            assert ";base64" in header and data, f"{page.name}: an empty data: image"
            images.append(base64.b64decode(data))
        else:
            assert not src.startswith(("http:", "https:", "//")), f"{page.name}: remote image {src}"
            path = (page.parent / src.split("#")[0]).resolve()
            assert path.is_file(), f"{page.name}: <img src={src}> does not exist"
            images.append(path.read_bytes())
    return images


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """The site, built once into a temporary folder (the notebooks execute)."""
    pytest.importorskip("mkdocs", reason="the docs extra is not installed (pip install -e '.[docs]')")
    for name in ("material", "mkdocstrings", "mkdocs_jupyter", "mkdocstrings_handlers.python"):
        pytest.importorskip(name, reason=f"{name} is missing: install the docs extra (pip install -e '.[docs]')")
    out = tmp_path_factory.mktemp("docs") / "site"
    sources = {p: p.read_bytes() for p in NOTEBOOKS}
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    env.pop("HYBRIDCTL_LIVE_MESHCAT", None)  # never the paced live run
    start = time.perf_counter()
    result = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--site-dir", str(out)], cwd=ROOT, env=env,
                            capture_output=True, text=True, timeout=600)
    elapsed = time.perf_counter() - start
    print(f"mkdocs build: {elapsed:.1f} s")
    assert result.returncode == 0, f"mkdocs build failed:\n{result.stdout[-3000:]}\n{result.stderr[-6000:]}"
    changed = [p.name for p, data in sources.items() if p.read_bytes() != data]
    assert not changed, f"the build wrote into the stored notebooks {changed}: they must stay without outputs"
    return out


@pytest.mark.slow
def test_built_site_is_complete_and_offline(site):
    config = _config()
    for page in _nav_pages(config["nav"]):
        built = site / Path(page).with_suffix(".html")
        assert built.is_file(), f"{page} was not built ({built})"
    assert (site / "search" / "search_index.json").is_file()
    remote = []
    for page in site.rglob("*.html"):
        text = page.read_text(errors="replace")
        remote += [f"{page.name}: {m}" for m in re.findall(
            r"<(?:script|img|iframe)\b[^>]*\bsrc=\"(?:https?:)?//[^\"]*\"|<link\b[^>]*\bhref=\"(?:https?:)?//[^\"]*\"",
            text)]
    assert not remote, f"pages load from the network: {remote[:5]}"
    for css in (site / "assets").rglob("*.css"):
        assert not re.search(r"@import\s+url\(\s*['\"]?(?:https?:)?//", css.read_text(errors="replace")), css


@pytest.mark.slow
@pytest.mark.skipif(not os.path.exists(CHROMIUM) and not os.environ.get("HYBRIDCTL_REQUIRE_CHROMIUM"),
                    reason=f"{CHROMIUM} not installed (apt package chromium)")
@pytest.mark.parametrize("notebook", [p.stem for p in NOTEBOOKS])
def test_notebook_pages_show_figures_and_results(site, notebook, tmp_path):
    page = site / "notebooks" / f"{notebook}.html"
    dom = _dump_dom(page, tmp_path)
    images = _images(dom, page)
    pngs = [data for data in images if data.startswith(b"\x89PNG\r\n\x1a\n")]
    assert len(pngs) >= MIN_FIGURES[notebook], f"{page.name}: {len(pngs)} PNG figures, expected {MIN_FIGURES[notebook]}"
    assert all(len(data) > 5_000 for data in pngs), [len(d) for d in pngs]
    text = _text(dom)
    assert PRINTED[notebook] in text, f"{page.name} does not show the executed output {PRINTED[notebook]!r}"
    assert "Traceback (most recent call last)" not in text, f"{page.name} shows a traceback"


@pytest.mark.slow
@pytest.mark.skipif(not os.path.exists(CHROMIUM) and not os.environ.get("HYBRIDCTL_REQUIRE_CHROMIUM"),
                    reason=f"{CHROMIUM} not installed (apt package chromium)")
def test_api_pages_show_the_docstrings(site, tmp_path):
    from hybridctl.systems import control
    from hybridctl.viz import plots

    def plain(doc: str) -> str:
        return " ".join(doc.replace("``", "").split())

    checks = {
        "systems.control": [("hybridctl.systems.control.lqr_command", control.lqr_command),
                            ("hybridctl.systems.control.wrap_angles", control.wrap_angles)],
        "viz": [("hybridctl.viz.plots.plot_balance_map", plots.plot_balance_map)],
    }
    for room, functions in checks.items():
        page = site / "api" / f"{room}.html"
        dom = _dump_dom(page, tmp_path)
        text = _text(dom)
        for anchor, function in functions:
            assert f'id="{anchor}"' in dom, f"{page.name} has no entry {anchor}"
            first = plain(inspect.getdoc(function).split("\n\n")[0])
            assert first in text, f"{page.name} lacks the docstring of {anchor}: {first!r}"
    # Every room's page names its modules.
    for room in ROOMS:
        text = _text((site / "api" / f"{room}.html").read_text())
        assert f"hybridctl.{room}" in text, f"api/{room}.html does not document hybridctl.{room}"
    home = _text(_dump_dom(site / "index.html", tmp_path))
    assert "Quick start" in home and "make docs" in home, "the home page is the README"


def test_notebooks_use_only_the_installed_package():
    """A reader runs the notebooks with hybridctl installed: no imports from tests/, no stale promises."""
    import json

    for path in NOTEBOOKS:
        cells = json.loads(path.read_text())["cells"]
        code = "\n".join("".join(c["source"]) for c in cells if c["cell_type"] == "code")
        text = "\n".join("".join(c["source"]) for c in cells)
        assert "toy_envs" not in code and '"tests"' not in code, f"{path.name} imports from tests/"
        for stale in ("a later issue", "once recorded", "later step of this project"):
            assert stale not in text, f"{path.name} still says {stale!r}"
