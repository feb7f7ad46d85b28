"""The config reference page (``docs/config.md``), generated from :mod:`sgn_jax.config`.

Every TOML section is a field of :class:`sgn_jax.config.Config` and every key a field of that
section's dataclass; a key's type and default come from the dataclass, its description from the
``Attributes:`` section of the dataclass's docstring (one ``name: unit, meaning`` entry per
field). Regenerate the page after changing a config dataclass::

    python -m sgn_jax.config_reference --out docs/config.md

``tests/test_config_reference.py`` fails when the page is out of date or a field is undocumented.
"""

from __future__ import annotations

import argparse
import dataclasses
import inspect
import json
import re
import sys
import typing
from typing import Any, NamedTuple

from sgn_jax import config as config_module
from sgn_jax.config import Config, MotionConfig
from sgn_jax.records.io_utils import atomic_write

REGENERATE_COMMAND = "python -m sgn_jax.config_reference --out docs/config.md"

# A complete, minimal config: the required sections and keys only (every other key defaults).
EXAMPLE_TOML = """\
[case]
name = "my_case"

[jar]
kind = "emax"            # the parametric Emax-like cavity, default dimensions

[motion]
kind = "circle"
rpm = 300.0
amplitude = 0.017        # m

[balls]
count = 24
radius = 0.005           # m
density = 7700.0         # kg/m^3

[material]
young = 2.05e9           # Pa
poisson = 0.235
restitution = 0.3
friction = 0.3
rolling_friction = 0.045

# Optional sections: [dem], [sdf], [graph], [model], [train], [rollout].
[dem]
duration = 2.0           # s
"""

STL_EXAMPLE_TOML = """\
[jar]
kind = "stl"
stl_path = "jars/my_jar.stl"   # relative to the working directory
stl_units = "mm"               # the file's coordinates are in mm
"""

_KIND_MARK = re.compile(r'\(kind "(\w+)"\)\.?$')


class KeyDoc(NamedTuple):
    """One key of a section: name, type, default (TOML text or "required"), description."""

    name: str
    type: str
    default: str
    description: str


class SectionDoc(NamedTuple):
    """One TOML section: its table name, dataclass, whether it is required, and its keys."""

    name: str
    cls: type
    required: bool
    description: str
    keys: tuple[KeyDoc, ...]
    array: bool = False  # an array of tables ([[name]]), each one of ``cls``

    @property
    def heading(self) -> str:
        return f"[[{self.name}]]" if self.array else f"[{self.name}]"


def table_class(tp: Any) -> type | None:
    """The dataclass of an array of tables (``tuple[SomeConfig, ...]``), else None."""
    args = typing.get_args(tp)
    if (typing.get_origin(tp) is tuple and len(args) == 2 and args[1] is Ellipsis
            and dataclasses.is_dataclass(args[0])):
        return args[0]
    return None


def parse_attributes(doc: str | None) -> dict[str, str]:
    """The ``Attributes:`` entries of a Google-style docstring as ``{name: description}``.

    An entry is ``name: text`` one level deeper than ``Attributes:``; deeper-indented lines
    continue the previous entry. The section ends at a blank line or a dedent.
    """
    lines = inspect.cleandoc(doc or "").splitlines()
    out: dict[str, str] = {}
    start = next((i for i, line in enumerate(lines) if line.strip() == "Attributes:"), None)
    if start is None:
        return out
    base = len(lines[start]) - len(lines[start].lstrip())
    entry_indent: int | None = None
    current: str | None = None
    for line in lines[start + 1:]:
        if not line.strip():
            break
        indent = len(line) - len(line.lstrip())
        if indent <= base:
            break
        if entry_indent is None:
            entry_indent = indent
        if indent == entry_indent:
            name, sep, text = line.strip().partition(":")
            if not sep:
                raise ValueError(f"malformed Attributes entry (no 'name: text'): {line.strip()!r}")
            current = name.strip()
            out[current] = text.strip()
        elif current is not None:
            out[current] = f"{out[current]} {line.strip()}".strip()
    return out


def docstring_prose(doc: str | None) -> str:
    """The docstring without its ``Attributes:`` section, rst literals turned into Markdown."""
    lines = inspect.cleandoc(doc or "").splitlines()
    cut = next((i for i, line in enumerate(lines) if line.strip() == "Attributes:"), len(lines))
    text = "\n".join(lines[:cut]).strip()
    return text.replace("``", "`")


def type_name(tp: Any) -> str:
    """A field's annotation as TOML-flavoured text: str, float, int, bool, list[...]."""
    if typing.get_origin(tp) is tuple:
        args = typing.get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            return f"list[{type_name(args[0])}]"
        return f"list[{', '.join(type_name(a) for a in args)}]"
    return getattr(tp, "__name__", str(tp))


def toml_value(value: Any) -> str:
    """A default value as inline TOML text."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, (tuple, list)):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    raise TypeError(f"no TOML form for default {value!r}")


def _default_text(f: dataclasses.Field) -> str:
    if f.default is not dataclasses.MISSING:
        return toml_value(f.default)
    if f.default_factory is not dataclasses.MISSING:
        return toml_value(f.default_factory())
    return "required"


def _section_doc(section: dataclasses.Field, hints: dict[str, Any]) -> SectionDoc:
    cls = table_class(hints[section.name]) or hints[section.name]
    field_hints = typing.get_type_hints(cls, vars(config_module))
    attrs = parse_attributes(cls.__doc__)
    keys = tuple(KeyDoc(f.name, type_name(field_hints[f.name]), _default_text(f),
                        attrs.get(f.name, ""))
                 for f in dataclasses.fields(cls))
    required = (section.default is dataclasses.MISSING
                and section.default_factory is dataclasses.MISSING)
    return SectionDoc(section.name, cls, required, docstring_prose(cls.__doc__), keys,
                      array=table_class(hints[section.name]) is not None)


def config_sections() -> tuple[SectionDoc, ...]:
    """The sections of :class:`Config` in declaration order, with their keys documented."""
    hints = typing.get_type_hints(Config, vars(config_module))
    return tuple(_section_doc(s, hints) for s in dataclasses.fields(Config))


def documentation_problems() -> list[str]:
    """Fields without a description and ``Attributes:`` entries that name no field."""
    problems = []
    section_attrs = parse_attributes(Config.__doc__)
    for section in config_sections():
        if not section_attrs.get(section.name):
            problems.append(f"Config.{section.name} has no description in Config's Attributes")
        names = {k.name for k in section.keys}
        for key in section.keys:
            if not key.description:
                problems.append(f"[{section.name}] {key.name} ({section.cls.__name__}) has no "
                                "description in the docstring's Attributes section")
        for extra in sorted(set(parse_attributes(section.cls.__doc__)) - names):
            problems.append(f"{section.cls.__name__}'s Attributes documents {extra!r}, "
                            "which is not a field")
    return problems


def _cell(text: str) -> str:
    return text.replace("``", "`").replace("|", "\\|").replace("\n", " ")


def _keys_by_kind_table(kinds: dict[str, list[str]]) -> list[str]:
    lines = ["| kind | keys |", "|---|---|"]
    for kind, keys in kinds.items():
        lines.append(f"| `\"{kind}\"` | {', '.join(f'`{k}`' for k in keys)} |")
    return lines


def _jar_keys_by_kind(section: SectionDoc) -> dict[str, list[str]]:
    kinds: dict[str, list[str]] = {}
    for key in section.keys:
        m = _KIND_MARK.search(key.description)
        if m:
            kinds.setdefault(m.group(1), []).append(key.name)
    return kinds


def _section_markdown(section: SectionDoc) -> list[str]:
    if section.array:
        status = "Optional array of tables (none by default), each table"
    else:
        status = ("Required section" if section.required
                  else "Optional section (every key has a default)")
    lines = [f"## `{section.heading}`", "",
             f"{status}; `sgn_jax.config.{section.cls.__name__}`.", "",
             section.description, "",
             "| key | type | default | description |", "|---|---|---|---|"]
    for key in section.keys:
        lines.append(f"| `{key.name}` | `{_cell(key.type)}` | "
                     f"{'required' if key.default == 'required' else f'`{_cell(key.default)}`'} | "
                     f"{_cell(key.description)} |")
    lines.append("")
    if section.cls is MotionConfig:
        order = [k.name for k in section.keys]
        kinds = {kind: sorted(keys, key=order.index)
                 for kind, keys in MotionConfig._KEYS_BY_KIND.items()}
        lines += ["Keys by motion kind (`kind` plus these; a key of another kind is an error, and "
                  "the saved config keeps only its kind's keys):", ""]
        lines += _keys_by_kind_table(kinds) + [""]
    section_hints = typing.get_type_hints(section.cls, vars(config_module))
    for key in section.keys:  # arrays of tables inside the section ([[train.stages]], ...)
        inner = table_class(section_hints[key.name])
        if inner is None:
            continue
        inner_hints = typing.get_type_hints(inner, vars(config_module))
        inner_attrs = parse_attributes(inner.__doc__)
        lines += [f"### `[[{section.name}.{key.name}]]`", "",
                  f"`sgn_jax.config.{inner.__name__}`. {_cell(docstring_prose(inner.__doc__))}",
                  "", "| key | type | default | description |", "|---|---|---|---|"]
        for f in dataclasses.fields(inner):
            default = _default_text(f)
            lines.append(f"| `{f.name}` | `{_cell(type_name(inner_hints[f.name]))}` | "
                         f"{'required' if default == 'required' else f'`{_cell(default)}`'} | "
                         f"{_cell(inner_attrs.get(f.name, ''))} |")
        lines.append("")
    if section.name == "jar":
        lines += ["Keys by jar kind (`kind` plus these; the other kind's keys are not used):",
                  ""]
        lines += _keys_by_kind_table(_jar_keys_by_kind(section)) + [""]
        lines += ["An STL jar (`sgn_jax.pipelines.configure.load_stl`): the file is the closed "
                  "**cavity** (where the balls are) in jar-frame coordinates, floor centre at the "
                  "origin and y up; it must be watertight and consistently wound, and is read in "
                  "`stl_units` and scaled to m (docs/geometry.md):", "",
                  "```toml", STL_EXAMPLE_TOML.rstrip("\n"), "```", ""]
    return lines


def config_reference_markdown() -> str:
    """The whole reference page as Markdown (ends with one newline)."""
    problems = [p for p in documentation_problems() if "which is not a field" in p]
    if problems:
        raise ValueError("; ".join(problems))
    section_attrs = parse_attributes(Config.__doc__)
    sections = config_sections()
    lines = [
        "# Config reference",
        "",
        f"<!-- Generated by sgn_jax/config_reference.py from sgn_jax/config.py; do not edit. "
        f"Regenerate with: {REGENERATE_COMMAND} -->",
        "",
        "An experiment is one TOML file with a table per section, loaded by "
        "`sgn_jax.config.load_config` into frozen dataclasses. Rules:",
        "",
        "- an unknown key (a typo) is an error that names it and lists the allowed keys;",
        "- a key whose default is \"required\" must be given;",
        "- values are SI units (m, s, kg, Pa) unless the key or its description says otherwise;",
        "- every artifact is saved with its resolved config (defaults written out).",
        "",
        "A complete config with only the required keys (the built-in cases, "
        "`sgn_jax/configs/*.toml`, are complete examples; `--config NAME` loads one by name):",
        "",
        "```toml",
        EXAMPLE_TOML.rstrip("\n"),
        "```",
        "",
        "Sections:",
        "",
    ]
    for s in sections:
        lines.append(f"- [`{s.heading}`](#{s.name}): {section_attrs.get(s.name, '')}"
                     f"{'' if s.required else ' (optional)'}")
    lines.append("")
    for s in sections:
        lines += _section_markdown(s)
    return "\n".join(lines).rstrip("\n") + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m sgn_jax.config_reference",
        description="Write the config reference (Markdown) generated from sgn_jax.config.")
    parser.add_argument("--out", default=None,
                        help="file to write atomically (default: standard output)")
    args = parser.parse_args(argv)
    text = config_reference_markdown()
    if args.out is None:
        sys.stdout.write(text)
    else:
        with atomic_write(args.out, "w") as fh:
            fh.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
