"""The docs site's navigation (mkdocs.yml) and its API reference pages are complete and current.

``mkdocs build --strict`` (run by .ci/run after the tests, with the ``docs`` extra) checks this
and more; these checks run in the default test suite without mkdocs, so that a page added to
docs/ without a nav entry, or a reference page naming a module that no longer exists, fails
here first.
"""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs"

# Pages the build makes from files at the repository root (.ci/mkdocs_hooks.py, GENERATED).
GENERATED = {"index.md": "README.md", "changelog.md": "CHANGELOG.md"}

# A nav entry: "- page.md" or "- Title: page.md" (mkdocs.yml's nav is a YAML list).
_NAV_ENTRY = re.compile(r"^\s*-\s+(?:[^:\n]+:\s+)?([\w./-]+\.md)\s*$", re.MULTILINE)
_REFERENCE = re.compile(r"^:::\s+([\w.]+)\s*$", re.MULTILINE)


def nav_pages() -> list[str]:
    """The pages of mkdocs.yml's nav, as paths relative to docs/."""
    text = (ROOT / "mkdocs.yml").read_text(encoding="utf-8")
    nav = text[text.index("\nnav:"):]
    return _NAV_ENTRY.findall(nav)


def test_the_nav_parser_reads_the_entries():
    pages = nav_pages()
    assert "conventions.md" in pages and "index.md" in pages, pages
    assert len(pages) == len(set(pages)), "a page is listed twice in the nav"


def test_every_docs_page_is_in_the_nav():
    pages = {p.relative_to(DOCS).as_posix() for p in DOCS.rglob("*.md")}
    missing = sorted(pages - set(nav_pages()))
    assert not missing, f"docs pages missing from mkdocs.yml's nav: {missing}"


def test_every_nav_page_exists():
    absent = [page for page in nav_pages()
              if not (DOCS / page).is_file()
              and not (page in GENERATED and (ROOT / GENERATED[page]).is_file())]
    assert not absent, f"mkdocs.yml's nav names pages that do not exist: {absent}"


def test_reference_pages_name_existing_modules():
    pages = sorted((DOCS / "reference").glob("*.md"))
    assert pages, "no API reference pages under docs/reference/"
    for page in pages:
        modules = _REFERENCE.findall(page.read_text(encoding="utf-8"))
        assert modules, f"{page.relative_to(ROOT)} has no '::: module' directive"
        for module in modules:
            assert importlib.util.find_spec(module) is not None, (
                f"{page.relative_to(ROOT)} documents {module}, which does not exist")
