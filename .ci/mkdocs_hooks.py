"""MkDocs hooks of the docs site (mkdocs.yml ``hooks:``): the README and the changelog as pages.

The site's home page is README.md and its changelog page is CHANGELOG.md, both kept at the
repository root where GitHub and PyPI show them. This hook adds them to the site as generated
pages (``index.md``, ``changelog.md``) and rewrites the README's links to docs pages
(``docs/x.md`` -> ``x.md``), so that there is one copy of each text and ``mkdocs build --strict``
checks their links like any other page's.
"""

from __future__ import annotations

import re
from pathlib import Path

from mkdocs.structure.files import File

ROOT = Path(__file__).resolve().parent.parent
GENERATED = {"index.md": "README.md", "changelog.md": "CHANGELOG.md"}
_DOCS_LINK = re.compile(r"\]\(docs/")
_CHANGELOG_LINK = re.compile(r"\]\(CHANGELOG\.md")


def _page_text(source: str) -> str:
    text = (ROOT / source).read_text(encoding="utf-8")
    text = _DOCS_LINK.sub("](", text)
    return _CHANGELOG_LINK.sub("](changelog.md", text)


def on_files(files, config):
    for page, source in GENERATED.items():
        if files.get_file_from_path(page) is None:
            files.append(File.generated(config, page, content=_page_text(source)))
    return files
