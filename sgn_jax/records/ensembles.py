"""Ensembles files: which DEM runs (config x seeds) make up each case of an experiment.

An ensembles file (``experiments/ensembles.toml``, ``experiments/envelope/ensembles.toml``) has
one ``[cases.NAME]`` table per case::

    [cases.standard]
    config = "emax_300rpm"       # a .toml path (relative to the file) or a config name
    duration = 10.0              # seconds of motion after settling
    seeds = [0, 1, 2, 3, 4, 5]   # DEM placement seeds (packings)
    train_seeds = [0, 1]         # the packings the SGN may train on (a subset of seeds)
    description = "..."

A config name is looked up in ``<the file's folder>/configs/NAME.toml``, then among the
package's built-in configs. :func:`load_ensembles` checks the whole file and names the case and
the key of every problem (:class:`EnsembleError`); :func:`select_cases` picks cases by name.
The experiment scripts (``experiments/tools/generate_data.py``, ``run_experiments.py`` and
``evaluate_contact.py`` there, ``experiments/reproduce/mse_floor/mse_baseline.py``,
``experiments/reproduce/envelope_heldout/evaluate_model.py``) read their ensembles through this
module.
"""

from __future__ import annotations

import dataclasses
import math
import re
from pathlib import Path
from typing import Any

from sgn_jax.config import ConfigError, builtin_config_path, read_toml
from sgn_jax.errors import SGNJaxError

_CASE_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_-]*$")
_CASE_KEYS = {"config", "duration", "seeds", "train_seeds", "description"}


class EnsembleError(SGNJaxError, ValueError):
    """The ensembles file or an argument is wrong; the message says what and how to fix it."""


@dataclasses.dataclass(frozen=True)
class Case:
    """One case of the ensembles file: a config run from several seeds (packings).

    ``duration`` is seconds of motion after settling; ``train_seeds`` is a subset of ``seeds``
    (the packings the SGN may train on); the other seeds are held-out evaluation packings.
    """

    name: str
    config: str
    config_path: Path
    duration: float
    seeds: tuple[int, ...]
    train_seeds: tuple[int, ...]
    description: str = ""

    @property
    def eval_seeds(self) -> tuple[int, ...]:
        return tuple(s for s in self.seeds if s not in self.train_seeds)

    def split_of(self, seed: int) -> str:
        return "train" if seed in self.train_seeds else "eval"


def _resolve_config(value: str, base: Path) -> Path:
    """A config named in the ensembles file: a ``.toml`` path (relative to the file's folder)
    or a name looked up in ``<folder>/configs/NAME.toml``, then in the package's configs."""
    if value.endswith(".toml") or "/" in value:
        path = Path(value)
        return path if path.is_absolute() else base / path
    local = base / "configs" / f"{value}.toml"
    if local.is_file():
        return local
    try:
        return builtin_config_path(value)
    except ConfigError as exc:
        raise EnsembleError(f"config {value!r}: not in {base / 'configs'} and {exc}") from None


def _seed_list(value: Any, where: str) -> tuple[int, ...]:
    if not isinstance(value, list) or not all(
            isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in value):
        raise EnsembleError(f"{where} must be a list of integers >= 0, got {value!r}")
    duplicates = sorted({s for s in value if value.count(s) > 1})
    if duplicates:
        raise EnsembleError(f"{where} lists seed(s) {duplicates} more than once")
    return tuple(value)


def load_ensembles(path: str | Path) -> dict[str, Case]:
    """Read and check an ensembles file (see experiments/ensembles.toml for the format).

    Returns:
        {case name: Case}, in file order.
    Raises:
        EnsembleError naming the file, the case and the problem.
    """
    path = Path(path)
    data = read_toml(path, EnsembleError, "ensembles file")
    tables = data.get("cases")
    unknown_top = sorted(set(data) - {"cases"})
    if unknown_top:
        raise EnsembleError(f"{path}: unknown top-level key(s) {unknown_top}; cases go in "
                            "[cases.NAME] tables")
    if not isinstance(tables, dict) or not tables:
        raise EnsembleError(f"{path}: no cases; add [cases.NAME] tables with config, duration, "
                            "seeds and train_seeds")
    cases: dict[str, Case] = {}
    for name, table in tables.items():
        where = f"{path}: [cases.{name}]"
        if not _CASE_NAME.match(name):
            raise EnsembleError(f"{where}: a case name may hold only letters, digits, '_' and "
                                "'-' (it names the data files)")
        if not isinstance(table, dict):
            raise EnsembleError(f"{where} must be a table")
        unknown = sorted(set(table) - _CASE_KEYS)
        missing = sorted({"config", "duration", "seeds"} - set(table))
        if unknown or missing:
            raise EnsembleError(f"{where}: unknown key(s) {unknown}, missing key(s) {missing}; "
                                f"allowed: {sorted(_CASE_KEYS)}")
        config = table["config"]
        if not isinstance(config, str) or not config:
            raise EnsembleError(f"{where}: config must be a config name or a .toml path")
        config_path = _resolve_config(config, path.parent)
        if not config_path.is_file():
            raise EnsembleError(f"{where}: config file {config_path} does not exist")
        duration = table["duration"]
        if isinstance(duration, bool) or not isinstance(duration, (int, float)) \
                or not duration > 0 or not math.isfinite(duration):
            raise EnsembleError(f"{where}: duration must be a number of seconds > 0, got "
                                f"{duration!r}")
        seeds = _seed_list(table["seeds"], f"{where} seeds")
        if not seeds:
            raise EnsembleError(f"{where}: seeds is empty")
        train = _seed_list(table.get("train_seeds", []), f"{where} train_seeds")
        stray = [s for s in train if s not in seeds]
        if stray:
            raise EnsembleError(f"{where}: train_seeds {stray} are not in seeds {list(seeds)}; "
                                "every training seed must also be listed in seeds")
        description = table.get("description", "")
        if not isinstance(description, str):
            raise EnsembleError(f"{where}: description must be a string")
        cases[name] = Case(name=name, config=config, config_path=config_path,
                           duration=float(duration), seeds=seeds, train_seeds=train,
                           description=description)
    return cases


def select_cases(cases: dict[str, Case], names: str | None) -> list[Case]:
    """The cases named in a comma-separated list (all if None), in the file's order."""
    if not names:
        return list(cases.values())
    wanted = [n.strip() for n in names.split(",") if n.strip()]
    unknown = [n for n in wanted if n not in cases]
    if unknown or not wanted:
        raise EnsembleError(f"--cases {names!r}: unknown case(s) {unknown}; the ensembles file "
                            f"has {list(cases)}")
    return [case for name, case in cases.items() if name in wanted]


__all__ = ["Case", "EnsembleError", "load_ensembles", "select_cases"]
