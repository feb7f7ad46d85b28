"""Replace a benchmark's table in a Markdown file, between ``<!-- MARKER:begin -->`` and
``<!-- MARKER:end -->`` (the benchmark scripts' ``--markdown`` option)."""

from __future__ import annotations

from pathlib import Path


def replace_section(path: str | Path, marker: str, table: str) -> None:
    """Write ``table`` between the file's ``marker`` comments (SystemExit if they are
    missing)."""
    path = Path(path)
    text = path.read_text()
    begin, end = f"<!-- {marker}:begin -->", f"<!-- {marker}:end -->"
    if begin not in text or end not in text:
        raise SystemExit(f"{path} has no {begin} ... {end} markers")
    head, rest = text.split(begin, 1)
    _, tail = rest.split(end, 1)
    path.write_text(f"{head}{begin}\n{table}\n{end}{tail}")
