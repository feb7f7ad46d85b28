"""Tests of sgn_jax.config_reference: every config key documented, docs/config.md up to date."""

import dataclasses
import re
import tomllib
import typing
from pathlib import Path

from sgn_jax import config as config_module
from sgn_jax.config import BallClassConfig, Config, MotionConfig, TrainStage, config_from_dict
from sgn_jax.config_reference import (
    EXAMPLE_TOML,
    REGENERATE_COMMAND,
    STL_EXAMPLE_TOML,
    config_reference_markdown,
    documentation_problems,
    main,
    parse_attributes,
    table_class,
)

DOC = Path(__file__).resolve().parents[1] / "docs" / "config.md"


def _section_classes() -> dict[str, type]:
    hints = typing.get_type_hints(Config, vars(config_module))
    return {f.name: table_class(hints[f.name]) or hints[f.name]
            for f in dataclasses.fields(Config)}


def _markdown_rows(markdown: str) -> dict[str, dict[str, list[str]]]:
    """``{section: {key: [type, default, description]}}`` from the key tables of the page."""
    rows: dict[str, dict[str, list[str]]] = {}
    section = None
    for line in markdown.splitlines():
        m = re.fullmatch(r"## `\[\[?(\w+)\]\]?`", line) or re.fullmatch(
            r"### `\[\[(\w+\.\w+)\]\]`", line)
        if m:
            section = m.group(1)
            rows[section] = {}
            continue
        m = re.fullmatch(r"\| `(\w+)` \| (.*) \|", line)
        if section is not None and m and not line.startswith('| `"'):
            cells = [c.strip() for c in re.split(r"(?<!\\)\|", m.group(2))]
            rows[section][m.group(1)] = cells
    return rows


def test_every_field_of_every_section_is_documented():
    assert documentation_problems() == []
    rows = _markdown_rows(config_reference_markdown())
    sections = _section_classes()
    # The arrays of tables inside sections.
    for name, cls in (("train.stages", TrainStage), ("balls.mix", BallClassConfig)):
        inner_keys = rows.pop(name)
        assert list(inner_keys) == [f.name for f in dataclasses.fields(cls)]
        assert all(cells[2] for cells in inner_keys.values()), f"a {name} key has no description"
    assert list(rows) == list(sections)
    for name, cls in sections.items():
        fields = [f.name for f in dataclasses.fields(cls)]
        assert list(rows[name]) == fields, f"[{name}] table keys differ from {cls.__name__}"
        for f in dataclasses.fields(cls):
            type_, default, description = rows[name][f.name]
            assert type_ and default, f"[{name}] {f.name}: empty type or default"
            assert description, (f"[{name}] {f.name} has no description: add a line "
                                 f"'{f.name}: unit, meaning' to the Attributes section of "
                                 f"{cls.__name__}'s docstring")
            required = (f.default is dataclasses.MISSING
                        and f.default_factory is dataclasses.MISSING)
            assert (default == "required") == required, f"[{name}] {f.name}: default {default}"


def test_config_md_is_up_to_date():
    expected = config_reference_markdown()
    actual = DOC.read_text(encoding="utf-8") if DOC.is_file() else None
    assert actual == expected, (f"docs/config.md is out of date with sgn_jax/config.py; "
                                f"regenerate it with: {REGENERATE_COMMAND}")


def test_page_lists_motion_kinds_and_stl_keys():
    markdown = config_reference_markdown()
    for kind, keys in MotionConfig._KEYS_BY_KIND.items():
        row = next(line for line in markdown.splitlines() if line.startswith(f'| `"{kind}"` |'))
        assert all(f"`{k}`" in row for k in keys), row
    stl_row = next(line for line in markdown.splitlines() if line.startswith('| `"stl"` |'))
    assert "`stl_path`" in stl_row and "`stl_units`" in stl_row


def test_examples_are_valid_configs():
    cfg = config_from_dict(tomllib.loads(EXAMPLE_TOML))
    assert cfg.jar.kind == "emax" and cfg.dem.duration == 2.0
    data = tomllib.loads(EXAMPLE_TOML)
    data.update(tomllib.loads(STL_EXAMPLE_TOML))
    cfg = config_from_dict(data)
    assert (cfg.jar.kind, cfg.jar.stl_units) == ("stl", "mm")


def test_parse_attributes_continuation_and_end():
    doc = """Summary.

    Attributes:
        a: first line
            continued.
        b: m, second.

    Trailing prose: not an attribute.
    """
    assert parse_attributes(doc) == {"a": "first line continued.", "b": "m, second."}
    assert parse_attributes("No section.") == {}


def test_main_writes_the_page(tmp_path, capsys):
    out = tmp_path / "config.md"
    assert main(["--out", str(out)]) == 0
    assert out.read_text(encoding="utf-8") == config_reference_markdown()
    assert main([]) == 0
    assert capsys.readouterr().out == config_reference_markdown()
