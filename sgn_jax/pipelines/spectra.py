"""Collision spectra from DEM and surrogate records: ``sgn-jax spectra`` and
``sj.collision_spectra`` (docs/collisions.md).

:func:`collision_spectra` reads the collision events of DEM trajectory records and/or rollout
prediction records (one record per packing), reduces each source to the ensemble mean and
standard error of every statistic of :mod:`sgn_jax.analysis.collisions`, and returns a
:class:`CollisionSpectra`: ``.table()`` (text), ``.to_json()`` (a JSON-ready dict),
``.plot(out_dir)`` (the figures of :mod:`sgn_jax.analysis.collision_plots`, DEM and surrogate
overlaid).
"""

from __future__ import annotations

import dataclasses
import glob
import math
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from sgn_jax.analysis.collisions import (
    DEFAULT_THRESHOLD_J,
    ENERGY_EDGES,
    KINDS,
    SPEED_EDGES,
    CollisionDataError,
    EnsembleStatistics,
    EventTable,
    decade_comparison,
    ensemble_statistics,
    events_from_record,
    load_events,
    record_source,
)
from sgn_jax.records.prediction import Prediction
from sgn_jax.records.trajectory import Trajectory

RecordInput = str | Path | EventTable | Trajectory | Prediction
"""What :func:`collision_spectra` takes per packing: a record path (globs allowed), a loaded
record, or an event table."""

_SCALAR_ROWS: tuple[tuple[str, str, str], ...] = (
    *((f"frequency_per_ball_hz[{k}]", f"collisions per ball per s, {k}", "1/s") for k in KINDS),
    *((f"power_W[{k}]", f"power dissipated, {k}", "W") for k in KINDS),
    ("specific_power_W_per_kg", "specific power", "W/kg"),
    *((f"mean_stress_energy_J[{k}]", f"mean stress energy, {k}", "J") for k in KINDS),
    *((f"normal_share[{k}]", f"normal share of dissipation, {k}", "-") for k in KINDS),
    ("impact_speed_mean_m_s[all]", "mean impact speed", "m/s"),
    ("impact_speed_median_m_s[all]", "median impact speed", "m/s"),
    ("impact_speed_q90_m_s", "90 % quantile of impact speed", "m/s"),
    ("power_above_W", "power at or above the threshold", "W"),
    ("share_above", "share of the power above the threshold", "-"),
)
"""(statistic, description, unit) of the rows of :meth:`CollisionSpectra.table`."""


def _is_glob(text: str) -> bool:
    return any(ch in text for ch in "*?[")


def expand_records(items: Iterable[RecordInput] | RecordInput | None, what: str
                   ) -> list[RecordInput]:
    """The inputs with every glob pattern expanded (sorted); paths checked to exist.

    Raises:
        CollisionDataError: a path that does not exist or a pattern that matches nothing,
            naming ``what`` (e.g. ``"--dem"``).
    """
    if items is None:
        return []
    if isinstance(items, (str, Path, EventTable, Trajectory, Prediction)):
        items = [items]
    out: list[RecordInput] = []
    for item in items:
        if isinstance(item, (EventTable, Trajectory, Prediction)):
            out.append(item)
            continue
        text = str(item)
        if _is_glob(text):
            matches = sorted(glob.glob(text))
            if not matches:
                raise CollisionDataError(f"{what} {text!r} matches no file; check the pattern")
            out.extend(matches)
        elif not Path(text).is_file():
            raise CollisionDataError(f"{what} {text!r}: no such file; check the path")
        else:
            out.append(text)
    return out


def _table_of(item: RecordInput, source: str, window: tuple[float, float] | None
              ) -> EventTable:
    if isinstance(item, EventTable):
        table = item
        if table.source != source:
            raise CollisionDataError(f"an event table of source {table.source!r} was passed "
                                     f"as {source}")
    elif isinstance(item, (Trajectory, Prediction)):
        table = events_from_record(item)
        if table.source != source:
            raise CollisionDataError(f"{item.path or 'a record'} is a {table.source} record, "
                                     f"passed as {source}")
    else:
        table = load_events(item, source)
    return table.window(*window) if window is not None else table


def _number(value: Any) -> Any:
    """JSON-ready: NaN -> None, numpy -> Python, arrays -> lists."""
    if isinstance(value, dict):
        return {str(k): _number(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_number(v) for v in value]
    if isinstance(value, np.ndarray):
        return [_number(v) for v in value.tolist()]
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    return value


def _relative(value: float, reference: float) -> float:
    if not (math.isfinite(value) and math.isfinite(reference)) or reference == 0:
        return math.nan
    return (value - reference) / reference


@dataclasses.dataclass(frozen=True)
class CollisionSpectra:
    """The collision statistics of the DEM's and/or the surrogate's records.

    Attributes:
        dem, surrogate: the ensemble statistics of each source (None where not given).
        threshold: J, the energy threshold of the power above it; threshold_by: whether it
            bounds each event's ``"dissipated"`` or ``"stress"`` energy.
        window: (start, end) s of motion time the events were taken from, or None (each
            record whole).
    """

    dem: EnsembleStatistics | None
    surrogate: EnsembleStatistics | None
    threshold: float
    threshold_by: str
    window: tuple[float, float] | None = None

    @property
    def ensembles(self) -> list[EnsembleStatistics]:
        """The sources present, DEM first."""
        return [e for e in (self.dem, self.surrogate) if e is not None]

    def decades(self, spectrum: str = "dissipation", min_share: float = 0.05
                ) -> list[dict[str, Any]]:
        """The surrogate's spectrum against the DEM's, per decade
        (:func:`sgn_jax.analysis.collisions.decade_comparison`); both sources needed."""
        if self.dem is None or self.surrogate is None:
            raise CollisionDataError("a per-decade comparison needs both DEM and surrogate "
                                     "records")
        return decade_comparison(self.dem, self.surrogate, spectrum=spectrum,
                                 min_share=min_share)

    def table(self) -> str:
        """The scalar statistics as a text table: mean +- SE per source, and the surrogate's
        relative difference from the DEM where both are given."""
        both = self.dem is not None and self.surrogate is not None
        header = f"{'statistic':<52} {'unit':<5}"
        for e in self.ensembles:
            header += f" {(e.source + f' (n={e.n_records})'):>24}"
        if both:
            header += f" {'surr vs DEM':>12}"
        lines = [header, "-" * len(header)]
        for key, description, unit in _SCALAR_ROWS:
            label = description
            if key.startswith("power_above") or key == "share_above":
                label = f"{description} ({self.threshold:g} J)"
            line = f"{label:<52} {unit:<5}"
            for e in self.ensembles:
                mean, se = e.mean[key], e.se[key]
                cell = f"{mean:.4g}" + (f" +- {se:.2g}" if math.isfinite(se) else "")
                line += f" {cell:>24}"
            if both:
                rel = _relative(self.surrogate.mean[key], self.dem.mean[key])
                line += f" {100 * rel:>+11.1f}%" if math.isfinite(rel) else f" {'-':>12}"
            lines.append(line)
        return "\n".join(lines)

    def to_json(self) -> dict[str, Any]:
        """A JSON-ready dict: the settings, the bins, each source's mean and SE of every
        statistic and its records, and (both sources) the per-decade comparison. NaN -> null."""
        out: dict[str, Any] = {
            "threshold_J": self.threshold, "threshold_by": self.threshold_by,
            "window_s": list(self.window) if self.window is not None else None,
            "energy_edges_J": (self.ensembles[0].edges if self.ensembles else ENERGY_EDGES),
            "speed_edges_m_s": (self.ensembles[0].speed_edges if self.ensembles
                                else SPEED_EDGES),
        }
        for e in self.ensembles:
            out[e.source] = {
                "n_records": e.n_records, "records": list(e.paths),
                "n_events": list(e.n_events), "duration_s": list(e.duration_s),
                "mean": e.mean, "se": e.se,
            }
        if self.dem is not None and self.surrogate is not None:
            out["decades"] = {"dissipation": self.decades("dissipation"),
                              "stress": self.decades("stress")}
        return _number(out)

    def plot(self, out_dir: str | Path) -> dict[str, Path]:
        """Write one figure per statistic into ``out_dir`` (DEM and surrogate overlaid, SE
        error bars); returns {name: path}
        (:func:`sgn_jax.analysis.collision_plots.plot_collision_figures`)."""
        # deferred: matplotlib is loaded only by the call that draws
        from sgn_jax.analysis.collision_plots import plot_collision_figures

        return plot_collision_figures(self.ensembles, out_dir)


def collision_spectra(dem: Sequence[RecordInput] | RecordInput | None = None,
                      surrogate: Sequence[RecordInput] | RecordInput | None = None, *,
                      threshold: float = DEFAULT_THRESHOLD_J, threshold_by: str = "dissipated",
                      window: tuple[float, float] | None = None) -> CollisionSpectra:
    """The collision statistics of DEM and/or surrogate records, one record per packing.

    Args:
        dem: DEM trajectory records (``.npz`` paths, glob patterns, loaded
            ``Trajectory`` objects or event tables) written with the collision ledger.
        surrogate: rollout prediction records, likewise.
        threshold: J, > 0: the energy above which :func:`power_above` counts an event (default
            1e-4 J, docs/collisions.md).
        threshold_by: ``"dissipated"`` (each event's dissipated energy) or ``"stress"``
            (its stress energy).
        window: (start, end) s of motion time: only events that begin in it count, and its
            length is the time base (e.g. the same stretch for the DEM and the surrogate).

    Raises:
        CollisionDataError: no records, a missing file, a record without collision events or
            of the other kind, a window outside a record, a bad threshold or window.
    """
    if not (isinstance(threshold, (int, float)) and not isinstance(threshold, bool)
            and math.isfinite(threshold) and threshold > 0):
        raise CollisionDataError(f"threshold must be an energy > 0 J, got {threshold!r} "
                         f"(default {DEFAULT_THRESHOLD_J:g} J)")
    if threshold_by not in ("dissipated", "stress"):
        raise CollisionDataError(f"threshold_by={threshold_by!r}: use 'dissipated' or 'stress'")
    if window is not None:
        window = (float(window[0]), float(window[1]))
        if not window[1] > window[0]:
            raise CollisionDataError(f"window {window} s: the end must be after the start")
    dem_items = expand_records(dem, "dem record")
    surrogate_items = expand_records(surrogate, "surrogate record")
    if not dem_items and not surrogate_items:
        raise CollisionDataError("no records given: pass DEM trajectory records and/or rollout "
                                 "prediction records written with the collision ledger")
    for source, items in (("dem", dem_items), ("surrogate", surrogate_items)):
        for item in items:  # every file's kind and events, before any is loaded
            if isinstance(item, str):
                record_source(item, source)
    ensembles = {}
    for source, items in (("dem", dem_items), ("surrogate", surrogate_items)):
        if items:
            tables = [_table_of(item, source, window) for item in items]
            ensembles[source] = ensemble_statistics(tables, threshold=threshold,
                                                    threshold_by=threshold_by)
    return CollisionSpectra(dem=ensembles.get("dem"), surrogate=ensembles.get("surrogate"),
                            threshold=float(threshold), threshold_by=threshold_by,
                            window=window)


__all__ = ["CollisionSpectra", "RecordInput", "collision_spectra", "expand_records"]
