"""MkDocs hooks of the docs site (mkdocs.yml ``hooks:``).

- The README and the changelog as pages: the site's home page is README.md and its changelog
  page is CHANGELOG.md, both kept at the repository root where GitHub and PyPI show them. They
  are added as generated pages (``index.md``, ``changelog.md``), with the README's links to docs
  pages rewritten (``docs/x.md`` -> ``x.md``), so that there is one copy of each text and
  ``mkdocs build --strict`` checks their links like any other page's.
- The docstrings' Sphinx roles (``:func:`name```, ``:class:``, ...) render as plain code in the
  API reference instead of showing the role's name.
"""

from __future__ import annotations

import re
from pathlib import Path

from mkdocs.structure.files import File

ROOT = Path(__file__).resolve().parent.parent
GENERATED = {"index.md": "README.md", "changelog.md": "CHANGELOG.md"}
_DOCS_LINK = re.compile(r"\]\(docs/")
_CHANGELOG_LINK = re.compile(r"\]\(CHANGELOG\.md")
_SPHINX_ROLE = re.compile(r":(?:func|class|mod|meth|attr|data|exc|obj):(?=<code>)")


def _page_text(source: str) -> str:
    text = (ROOT / source).read_text(encoding="utf-8")
    text = _DOCS_LINK.sub("](", text)
    return _CHANGELOG_LINK.sub("](changelog.md", text)


def on_files(files, config):
    for page, source in GENERATED.items():
        if files.get_file_from_path(page) is None:
            files.append(File.generated(config, page, content=_page_text(source)))
    return files


def on_page_content(html, page, config, files):
    if page.file.src_uri.startswith("reference/"):
        html = _SPHINX_ROLE.sub("", html)
    return html
