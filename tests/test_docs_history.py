"""What a user reads describes the software as it is, not how it came to be.

The README, the docs pages, every ``--help`` text of ``sgn-jax`` and the package's code, configs
and tests must not speak of work periods ("session 7"), issue numbers ("issue 19", "#19"),
dates (``2026-11-27``), the development reference ("SPEC 4": the conventions are
docs/conventions.md, cited by section) or model generations that are not shipped
(``contact_t21``, ``contact_dt2k``, ...; the shipped models are ``contact``, ``emax_300rpm`` and
``envelope``). History belongs in CHANGELOG.md (dated, newest first) and in git; CHANGELOG.md is
the one page these rules do not apply to.

Excluded: the shipped checkpoints and their provenance records under ``sgn_jax/data/models/``
(data written by the training runs, not prose), this file (its patterns name what they find)
and the result files under ``experiments/`` and ``benchmarks/`` (JSON, JSON lines and CSV
written by the runs: their commands, commits and dates are the record of the run). The scripts,
READMEs, configs and expected tables there are prose and are scanned.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

HISTORY_PATTERNS: dict[str, re.Pattern[str]] = {
    "a work period": re.compile(r"\bsessions?[\s_-]?\d+\b", re.IGNORECASE),
    "an issue number": re.compile(r"\bissues?[\s_-]?#?\d+\b|(?<![\w&/])#\d+\b", re.IGNORECASE),
    "a date": re.compile(r"\b20\d\d-[01]\d-[0-3]\d\b"),
    "the development reference SPEC": re.compile(r"\bSPEC\b"),
    "a model generation that is not shipped": re.compile(
        r"\bcontact_(?:t\d+|dt\d+[a-z]?|s\d+[a-z]?|k\d+|q\d+)\w*"),
}

TEXT_SUFFIXES = {".py", ".toml", ".md", ".txt", ".cfg", ".ini", ".json", ".yml", ".yaml"}
EXCLUDED = (ROOT / "sgn_jax" / "data" / "models", Path(__file__).resolve())


def history_mentions(text: str) -> list[tuple[int, str, str]]:
    """(line number, what, the matched text) of every history mention in ``text``."""
    found = []
    for what, pattern in HISTORY_PATTERNS.items():
        for match in pattern.finditer(text):
            line = text.count("\n", 0, match.start()) + 1
            found.append((line, what, " ".join(match.group(0).split())))
    return sorted(found)


def _files(folder: Path, suffixes: set[str]) -> list[Path]:
    return sorted(p for p in folder.rglob("*")
                  if p.is_file() and p.suffix in suffixes and "__pycache__" not in p.parts
                  and not any(p == e or e in p.parents for e in EXCLUDED))


def _report(sources: dict[str, str]) -> list[str]:
    return [f"{name}:{line}: {what}: {text!r}"
            for name, source in sources.items()
            for line, what, text in history_mentions(source)]


def _read(paths: list[Path]) -> dict[str, str]:
    return {str(p.relative_to(ROOT)): p.read_text(encoding="utf-8") for p in paths}


def _help_texts() -> dict[str, str]:
    """``sgn-jax --help`` and ``sgn-jax COMMAND --help``, from the parser (no command runs)."""
    from sgn_jax.cli import build_parser

    parser = build_parser()
    texts = {"sgn-jax --help": parser.format_help()}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                texts[f"sgn-jax {name} --help"] = sub.format_help()
    return texts


# ---------------------------------------------------------------------------------------------
# The detector itself: it finds what it is meant to find, and only that.


@pytest.mark.parametrize("text", [
    "measured in session 8", "Session7's run", "(issue 19)", "issues 11 and 14", "issue #20",
    "fixed in #12", "the issue-10 arms", "(2026-11-27)", "SPEC section 4", "a SPEC-4 file",
    "contact_k3", "contact_dt2k", "contact_t21's rows", "contact_s1c_unseen.json",
])
def test_the_detector_finds_history(text):
    assert history_mentions(text), text


@pytest.mark.parametrize("text", [
    "the contact model", "`contact`", "contact_forces(law, ...)", "contact_train.py",
    "GRAPH_SPEC = GraphSpec(...)", "docs/conventions.md section 4", "a test session's cache",
    "issue a warning", "emax_300rpm", "step 2e-4 s", "&#8217;", "10-20 s", "see CHANGELOG.md",
])
def test_the_detector_leaves_present_tense_text_alone(text):
    assert not history_mentions(text), text


# ---------------------------------------------------------------------------------------------
# What a user reads


def test_readme_has_no_history():
    problems = _report(_read([ROOT / "README.md"]))
    assert not problems, "history in the README (it goes to CHANGELOG.md):\n" + "\n".join(problems)


def test_docs_pages_have_no_history():
    pages = [p for p in _files(ROOT / "docs", {".md"}) if p.name != "changelog.md"]
    assert pages, "no docs pages found"
    problems = _report(_read(pages))
    assert not problems, ("history in the docs pages (it goes to CHANGELOG.md):\n"
                          + "\n".join(problems))


def test_help_texts_have_no_history():
    texts = _help_texts()
    assert len(texts) > 5, sorted(texts)  # the top level and every subcommand
    problems = _report(texts)
    assert not problems, "history in --help texts:\n" + "\n".join(problems)


# ---------------------------------------------------------------------------------------------
# Code, configs and tests


def test_package_code_and_configs_have_no_history():
    problems = _report(_read(_files(ROOT / "sgn_jax", TEXT_SUFFIXES)))
    assert not problems, "history in sgn_jax/:\n" + "\n".join(problems)


def test_project_files_have_no_history():
    files = [ROOT / "pyproject.toml", ROOT / "mkdocs.yml",
             *_files(ROOT / ".ci", TEXT_SUFFIXES | {""})]  # .ci/run has no suffix
    problems = _report(_read([p for p in files if p.is_file()]))
    assert not problems, "history in the project files:\n" + "\n".join(problems)


def test_tests_have_no_history():
    problems = _report(_read(_files(ROOT / "tests", TEXT_SUFFIXES)))
    assert not problems, "history in tests/:\n" + "\n".join(problems)


# The experiments' and benchmarks' prose: scripts, shell commands, READMEs, configs, expected
# tables; not the result files the runs write (RESULT_SUFFIXES).
EXPERIMENT_SUFFIXES = (TEXT_SUFFIXES | {".sh"}) - {".json"}
RESULT_SUFFIXES = {".json", ".jsonl", ".csv"}


@pytest.mark.parametrize("folder", ["experiments", "benchmarks"])
def test_experiments_and_benchmarks_prose_has_no_history(folder):
    files = _files(ROOT / folder, EXPERIMENT_SUFFIXES)
    assert files, f"nothing to scan under {folder}/"
    assert not any(p.suffix in RESULT_SUFFIXES for p in files)
    problems = _report(_read(files))
    assert not problems, f"history in {folder}/:\n" + "\n".join(problems)
