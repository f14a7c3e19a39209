"""MkDocs hooks of the hybridctl site (mkdocs.yml ``hooks:``).

The docstrings show usage as doctest lines (``>>> call(...)``) without a Markdown fence.
Rendered as Markdown they would run together into one paragraph (and ``x["a"]`` would read
as a reference link), so a small Markdown preprocessor fences every run of ``>>>`` lines
(with their ``...`` continuations and printed results) as Python code before the docstrings
and pages are converted. It also drops Sphinx roles (``:func:`name``` -> ``name``), which
Markdown would print literally.

The home page includes README.md, whose links are written for the repository
(``docs/systems.md``, ``ARCHITECTURE.md``, ``CHANGELOG.md``); a second preprocessor, after the
snippets are included, points them at the site's pages (``systems.md``, ``architecture.md``,
``changelog.md``), so the README's links work on GitHub and on the site alike.
"""

from __future__ import annotations

import re

from markdown import Extension
from markdown.preprocessors import Preprocessor
from mkdocs.plugins import event_priority

_PROMPT = re.compile(r"^(\s*)>>> ?")
_ROLE = re.compile(r":(?:py:)?(?:func|class|mod|meth|attr|data|obj|exc|const):(?=`)")


class _DoctestFences(Preprocessor):
    def run(self, lines: list[str]) -> list[str]:
        out, i, fenced = [], 0, False
        while i < len(lines):
            line = lines[i]
            if line.lstrip().startswith(("```", "~~~")):
                fenced = not fenced
            match = None if fenced else _PROMPT.match(line)
            if match is None:
                out.append(line if fenced else _ROLE.sub("", line))
                i += 1
                continue
            indent = match.group(1)
            block = []
            while i < len(lines) and lines[i].strip() and lines[i].startswith(indent):
                block.append(lines[i][len(indent):])
                i += 1
            if out and out[-1].strip():
                out.append("")
            out += [f"{indent}```python", *[indent + b for b in block], f"{indent}```", ""]
        return out


class DoctestFences(Extension):
    """Fence doctest runs (``>>>`` lines) as Python code blocks."""

    def extendMarkdown(self, md):  # noqa: N802 (Markdown's API name)
        md.preprocessors.register(_DoctestFences(md), "hybridctl_doctest_fences", 40)


# Repository paths of the README's links -> the site's pages (docs/X.md -> X.md).
_REPO_LINK = re.compile(r"\]\((?:docs/([^)#\s]+)|(ARCHITECTURE|CHANGELOG)\.md)(#[^)\s]*)?\)")


def site_links(line: str) -> str:
    """``](docs/x.md)`` -> ``](x.md)``; ``](ARCHITECTURE.md)`` -> ``](architecture.md)`` (and CHANGELOG)."""
    def repl(match: re.Match) -> str:
        target = match.group(1) or f"{match.group(2).lower()}.md"
        return f"]({target}{match.group(3) or ''})"
    return _REPO_LINK.sub(repl, line)


class _SiteLinks(Preprocessor):
    def run(self, lines: list[str]) -> list[str]:
        return [site_links(line) for line in lines]


class SiteLinks(Extension):
    """Point the included README's repository links at the site's pages."""

    def extendMarkdown(self, md):  # noqa: N802 (Markdown's API name)
        md.preprocessors.register(_SiteLinks(md), "hybridctl_site_links", 31)  # after snippets (32)


@event_priority(100)  # before mkdocstrings reads the Markdown extensions
def on_config(config):
    """Add the doctest fences and the README link rewriting to the site's Markdown extensions."""
    config.markdown_extensions.append(DoctestFences())
    config.markdown_extensions.append(SiteLinks())
    return config


# Figures of the results tree that pages show (a page links them as ``results/...png``): added to the
# site's files from the repository root, so the records stay in one place and the build fails on a
# missing one (strict mode checks every link).
RESULT_FIGURES = ("results/matrix/matrix.png", "results/ch5/mfpt_vs_roughness/mfpt_vs_roughness.png")


def on_files(files, config):
    """Add :data:`RESULT_FIGURES` to the site, at their repository paths."""
    from pathlib import Path

    from mkdocs.structure.files import File

    root = Path(config.config_file_path).parent
    for figure in RESULT_FIGURES:
        files.append(File(figure, src_dir=str(root), dest_dir=config.site_dir, use_directory_urls=False))
    return files
