"""Collision statistics: what a milling engineer reads from the collisions of a run.

Both collision ledgers (the DEM's, written with a trajectory record, and the surrogate's, written
with a prediction record) produce the same **event table**: one row per contact, from first
touch to separation, stored as ``collision_<field>`` arrays in the record's ``.npz``
(:data:`EVENT_FIELDS`; docs/collisions.md). :func:`load_events` reads one record into an
:class:`EventTable`; the functions below compute one statistic each from a table, and
:func:`ensemble_statistics` gives the mean and standard error of all of them over an ensemble of
packings (one table per packing).

Conventions (docs/collisions.md):

- **pair kind**: ``"ball-ball"``, ``"ball-wall"`` or ``"all"`` (:data:`PAIR_KINDS`; a charge
  with several ball classes adds kinds).
- **new events**: events whose first touch lies inside the record (flag bit 0 clear). Counts,
  frequencies, stress energies and impact speeds use only these (an event that was already in
  contact when the record began has no impact to measure). Dissipated energies and powers use
  every event, so the summed power is the ledger's power.
- **stress energy** of an event: ``0.5 * mass_eff * impact_normal**2`` (J), the kinetic energy
  of the normal approach at first touch (Kwade's stress energy); 0 where the bodies were not
  approaching (``impact_normal <= 0``).
- **dissipated energy** of an event: ``energy.sum(axis=1)`` (J).
- **energy bins**: fixed, decade-aligned log bins (:data:`ENERGY_EDGES`: 4 per decade,
  1e-10 .. 1e-1 J), the same for every record, so the DEM's and the surrogate's spectra overlay.
  A bin is ``[lo, hi)``; energies below the first edge (including 0) and at or above the last
  are counted in ``below`` and ``above``, so nothing is dropped.

Everything here is numpy on the host; nothing is jitted.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from sgn_jax.dem.collisions import COLLISION_FIELDS as EVENT_FIELDS
from sgn_jax.dem.collisions import COLLISION_PREFIX as PREFIX
from sgn_jax.dem.collisions import FLAG_BEGAN_BEFORE, FLAG_OPEN_AT_END
from sgn_jax.dem.contact import DISSIPATION_KINDS
from sgn_jax.errors import SGNJaxError
from sgn_jax.records.prediction import Prediction, load_prediction
from sgn_jax.records.trajectory import Trajectory, load_trajectory


class CollisionDataError(SGNJaxError, ValueError):
    """A record holds no collision events, or malformed ones; the message says how to fix it."""


PAIR_KINDS: tuple[str, ...] = ("ball-ball", "ball-wall")
"""The pair kinds of the event table (by its ``wall`` column)."""

KINDS: tuple[str, ...] = ("all", *PAIR_KINDS)
"""What a ``kind`` argument accepts: every event, or one pair kind."""

SOURCES: tuple[str, ...] = ("dem", "surrogate")
"""Which ledger wrote a table: the DEM's (trajectory record) or the surrogate's (prediction)."""

ENERGY_COLUMNS: tuple[str, ...] = tuple(DISSIPATION_KINDS)
"""The columns of ``energy`` (E, 5): the DEM's dissipation kinds. Column 0 is the normal
(impact) part; the others (tangential damping, Coulomb slip, rolling friction, stiffness) are
the tangential (shear) part."""

def log_edges(lo: float = 1e-10, hi: float = 1e-1, per_decade: int = 4) -> np.ndarray:
    """Decade-aligned logarithmic bin edges from ``lo`` to ``hi``, ``per_decade`` bins a decade.

    ``lo`` and ``hi`` must be powers of ten; the edges at whole decades are exact (``1e-4``
    is the literal 1e-4), so a value on a decade lands in the bin that starts there.

    Returns:
        (B + 1,) edges, B = per_decade * log10(hi / lo).
    """
    lo_exp, hi_exp = math.log10(lo), math.log10(hi)
    if (lo <= 0 or hi <= lo or abs(lo_exp - round(lo_exp)) > 1e-9
            or abs(hi_exp - round(hi_exp)) > 1e-9):
        raise ValueError(f"log_edges needs powers of ten lo < hi, got lo={lo!r}, hi={hi!r} "
                         "(e.g. lo=1e-10, hi=1e-1)")
    if isinstance(per_decade, bool) or not isinstance(per_decade, int) or per_decade < 1:
        raise ValueError(f"per_decade must be an integer >= 1, got {per_decade!r}")
    lo_k, hi_k = round(lo_exp) * per_decade, round(hi_exp) * per_decade
    edges = []
    for k in range(lo_k, hi_k + 1):
        # whole decades from their decimal literal (exact), the others from the power
        edges.append(float(f"1e{k // per_decade}") if k % per_decade == 0
                     else 10.0 ** (k / per_decade))
    return np.asarray(edges, dtype=np.float64)


ENERGY_EDGES: np.ndarray = log_edges(1e-10, 1e-1, 4)
"""(37,) J: the energy bins every spectrum shares (4 per decade, 1e-10 .. 1e-1 J)."""

SPEED_EDGES: np.ndarray = log_edges(1e-4, 1e1, 4)
"""(21,) m/s: the impact-speed bins (4 per decade, 1e-4 .. 10 m/s; stress energy goes with the
speed squared, so log bins keep the soft contacts and the impacts apart)."""

DEFAULT_THRESHOLD_J = 1e-4
"""J: the default energy threshold of :func:`power_above`. For the standard charge (10 mm steel
balls, 4.0 g) it is the normal kinetic energy of a ball-ball pair approaching at 0.32 m/s, about
60 % of the jar's speed at 300 rpm (0.53 m/s): events above it are impacts driven by the jar's
motion, events below it the soft contacts of the bed. It is a decade edge of
:data:`ENERGY_EDGES`, so the power above it is a sum of whole spectrum bins."""

QUANTILES: tuple[float, ...] = (0.1, 0.25, 0.5, 0.75, 0.9)
"""The quantiles of the impact-speed distribution."""


# --------------------------------------------------------------------------------------------
# The event table


def _as_read_only(value: Any, dtype: str) -> np.ndarray:
    array = np.array(value, dtype=dtype)
    array.flags.writeable = False
    return array


@dataclasses.dataclass(frozen=True, eq=False)
class EventTable:
    """The collision events of one record (E events), read-only, with what the statistics need.

    Attributes:
        ball, partner: (E,) int32, see :data:`EVENT_FIELDS`.
        wall: (E,) bool, True for a ball-wall event.
        start_s, duration_s: (E,) float64 s.
        impact_normal, impact_tangential: (E,) float64 m/s.
        max_overlap: (E,) float64 m; peak_force: (E,) float64 N (NaN where unknown).
        mass_eff: (E,) float64 kg.
        energy: (E, 5) float64 J, columns :data:`ENERGY_COLUMNS`.
        flags: (E,) int8, :data:`FLAG_BEGAN_BEFORE` | :data:`FLAG_OPEN_AT_END`.
        record_duration_s: s, the time the record spans (the statistics' time base).
        record_start_s: s, motion time at which the record begins.
        n_balls: N, balls in the charge.
        total_mass_kg: kg, the mass of all balls (specific power).
        source: ``"dem"`` or ``"surrogate"``.
        path: the record file, or None.
        ball_class: None (one ball class), or (N,) int the class of each ball of a charge of
            several (docs/charge.md): the table then also has the kinds of
            :attr:`class_kinds`, ``"ball-ball a-b"`` (a <= b) and ``"ball-wall a"``.
    """

    ball: np.ndarray
    partner: np.ndarray
    wall: np.ndarray
    start_s: np.ndarray
    duration_s: np.ndarray
    impact_normal: np.ndarray
    impact_tangential: np.ndarray
    max_overlap: np.ndarray
    peak_force: np.ndarray
    mass_eff: np.ndarray
    energy: np.ndarray
    flags: np.ndarray
    record_duration_s: float
    record_start_s: float
    n_balls: int
    total_mass_kg: float
    source: str
    path: str | None = None
    ball_class: np.ndarray | None = None

    def __post_init__(self) -> None:
        where = self.path or "event table"
        if self.ball_class is not None:
            object.__setattr__(self, "ball_class", _as_read_only(self.ball_class, "int32"))
            if self.ball_class.shape != (int(self.n_balls),):
                raise CollisionDataError(f"{where}: ball_class has shape "
                                         f"{self.ball_class.shape}, expected ({self.n_balls},)")
        for name, (dtype, _) in EVENT_FIELDS.items():
            object.__setattr__(self, name, _as_read_only(getattr(self, name), dtype))
        n_events = self.ball.shape[0] if self.ball.ndim == 1 else -1
        for name in EVENT_FIELDS:
            value = getattr(self, name)
            expected = (n_events, len(ENERGY_COLUMNS)) if name == "energy" else (n_events,)
            if value.shape != expected:
                raise CollisionDataError(
                    f"{where}: collision field {name!r} has shape {value.shape}, expected "
                    f"{expected} (one row per event, E = {n_events} from 'ball'); the ledger "
                    "wrote inconsistent arrays: rerun the simulation that produced them")
        if not (math.isfinite(self.record_duration_s) and self.record_duration_s > 0):
            raise CollisionDataError(f"{where}: record_duration_s must be > 0 s, got "
                                     f"{self.record_duration_s!r} (a record of one sample)")
        if isinstance(self.n_balls, bool) or int(self.n_balls) < 1:
            raise CollisionDataError(f"{where}: n_balls must be >= 1, got {self.n_balls!r}")
        if not (math.isfinite(self.total_mass_kg) and self.total_mass_kg > 0):
            raise CollisionDataError(f"{where}: total_mass_kg must be > 0, got "
                                     f"{self.total_mass_kg!r}")
        if self.source not in SOURCES:
            raise CollisionDataError(f"{where}: source must be one of {list(SOURCES)}, got "
                                     f"{self.source!r}")
        object.__setattr__(self, "record_duration_s", float(self.record_duration_s))
        object.__setattr__(self, "record_start_s", float(self.record_start_s))
        object.__setattr__(self, "n_balls", int(self.n_balls))
        object.__setattr__(self, "total_mass_kg", float(self.total_mass_kg))

    @property
    def n_events(self) -> int:
        """E, the number of events (new or not)."""
        return int(self.ball.shape[0])

    @property
    def stress_energy(self) -> np.ndarray:
        """(E,) J, ``0.5 * mass_eff * max(impact_normal, 0)**2``: the impact's normal kinetic
        energy (0 for a contact whose bodies were not approaching at first touch)."""
        return 0.5 * self.mass_eff * np.maximum(self.impact_normal, 0.0)**2

    @property
    def dissipated(self) -> np.ndarray:
        """(E,) J, the energy each event dissipated (all columns summed)."""
        return self.energy.sum(axis=1)

    @property
    def new(self) -> np.ndarray:
        """(E,) bool, events whose first touch lies inside the record."""
        return (self.flags & FLAG_BEGAN_BEFORE) == 0

    @property
    def class_kinds(self) -> tuple[str, ...]:
        """The kinds by ball class of a charge of several classes (empty for one):
        ``"ball-ball a-b"`` for every pair of classes a <= b, then ``"ball-wall a"``."""
        if self.ball_class is None:
            return ()
        n = int(self.ball_class.max()) + 1 if self.ball_class.size else 0
        if n < 2:
            return ()
        pairs = tuple(f"ball-ball {a}-{b}" for a in range(n) for b in range(a, n))
        return pairs + tuple(f"ball-wall {a}" for a in range(n))

    @property
    def kinds(self) -> tuple[str, ...]:
        """Every kind a ``kind`` argument takes for this table: :data:`KINDS`, then
        :attr:`class_kinds`."""
        return KINDS + self.class_kinds

    def kind_mask(self, kind: str = "all") -> np.ndarray:
        """(E,) bool, the events of a kind (:attr:`kinds`)."""
        if kind in self.class_kinds:
            cls = self.ball_class
            own = cls[self.ball]
            if kind.startswith("ball-wall "):
                return self.wall & (own == int(kind.split()[1]))
            a, b = (int(x) for x in kind.split()[1].split("-"))
            other = cls[np.where(self.wall, 0, self.partner)]
            lo, hi = np.minimum(own, other), np.maximum(own, other)
            return ~self.wall & (lo == a) & (hi == b)
        check_kind(kind, self.kinds)
        if kind == "all":
            return np.ones(self.n_events, dtype=bool)
        return self.wall if kind == "ball-wall" else ~self.wall

    def window(self, start_s: float, end_s: float) -> EventTable:
        """The events whose first touch lies in ``[start_s, end_s)`` (s, motion time), with the
        window's length as the time base.

        An event that began before ``start_s`` is left out whole, one open at ``end_s`` is kept
        whole: at a few events per window edge against thousands inside, the bias is small.

        Raises:
            CollisionDataError: the window is empty or reaches outside the record.
        """
        start_s, end_s = float(start_s), float(end_s)
        begin, finish = self.record_start_s, self.record_start_s + self.record_duration_s
        # a window edge may sit a rounding off the record's own edge
        slack = 1e-9 * max(1.0, abs(finish))
        if not (end_s > start_s and start_s >= begin - slack and end_s <= finish + slack):
            raise CollisionDataError(
                f"{self.path or 'event table'}: window [{start_s:g}, {end_s:g}) s must be "
                f"non-empty and inside the record, [{begin:g}, {finish:g}] s")
        keep = (self.start_s >= start_s) & (self.start_s < end_s)
        fields = {name: getattr(self, name)[keep] for name in EVENT_FIELDS}
        return dataclasses.replace(self, **fields, record_duration_s=end_s - start_s,
                                   record_start_s=start_s)

    def merge_recontacts(self, gap_s: float) -> EventTable:
        """The events seen at a coarser time resolution: a contact of a pair (two balls, or a
        ball and the jar) that begins less than ``gap_s`` (s) after the pair's previous contact
        ended joins it as one event.

        A diagnostic, for comparing ledgers of different time resolution: the DEM resolves a
        pair that touches, parts for 0.1 ms and touches again as two events, where the
        surrogate, whose step is 0.2 ms, can only see one. The merged event keeps the first
        contact's start, impact speeds, flags' began-before bit, partner and m*; it lasts from
        the first start to the last end; its deepest overlap and largest force are the largest
        of its parts, its energies their sums (so the power is unchanged) and its open-at-end
        bit the last part's. ``gap_s = 0`` merges nothing but contacts that touch end to start.

        Raises:
            ValueError: ``gap_s`` is negative or not finite.
        """
        if not (math.isfinite(gap_s) and gap_s >= 0):
            raise ValueError(f"gap_s must be a finite time >= 0 s, got {gap_s!r}")
        if self.n_events == 0:
            return self
        pair = np.where(self.wall, -1, self.partner).astype(np.int64)
        order = np.lexsort((self.start_s, pair, self.ball))
        ball, pair, start = self.ball[order], pair[order], self.start_s[order]
        end = start + self.duration_s[order]
        same = (ball[1:] == ball[:-1]) & (pair[1:] == pair[:-1])
        # a part joins the group of the part before it (the same pair's previous contact, which
        # ended before it began) when it begins within gap_s of that one's end
        first = np.ones(order.size, dtype=bool)
        first[1:] = ~(same & (start[1:] - end[:-1] < gap_s))
        group = np.cumsum(first) - 1
        lead = order[first]
        n = int(first.sum())

        def largest(values: np.ndarray) -> np.ndarray:
            out = np.full(n, -np.inf)
            np.maximum.at(out, group, np.nan_to_num(values[order], nan=-np.inf))
            return np.where(np.isneginf(out), np.nan, out)

        energy = np.zeros((n, self.energy.shape[1]))
        np.add.at(energy, group, self.energy[order])
        last = np.flatnonzero(np.r_[first[1:], True])       # the last part of each group
        flags = ((self.flags[lead] & FLAG_BEGAN_BEFORE)
                 | (self.flags[order][last] & FLAG_OPEN_AT_END)).astype(self.flags.dtype)
        fields = {name: getattr(self, name)[lead] for name in EVENT_FIELDS}
        fields.update(duration_s=end[last] - self.start_s[lead], energy=energy, flags=flags,
                      max_overlap=largest(self.max_overlap), peak_force=largest(self.peak_force))
        return dataclasses.replace(self, **fields)


def check_kind(kind: str, kinds: tuple[str, ...] = KINDS) -> None:
    """Raise ValueError unless ``kind`` is one of ``kinds`` (:data:`KINDS`, or a table's
    :attr:`EventTable.kinds`)."""
    if kind not in kinds:
        raise ValueError(f"kind={kind!r}: use one of {list(kinds)}")


# --------------------------------------------------------------------------------------------
# Loading


_DEM_HINT = ("rerun the DEM with its collision ledger on (`sgn-jax dem --config CONFIG --out "
             "FILE.npz` with [dem] collisions = true, the default; docs/collisions.md)")
_SURROGATE_HINT = ("rerun the rollout with its collision ledger on (`sgn-jax rollout --init "
                   "DEM.npz --duration S --out FILE.npz --collisions`, a contact model; "
                   "docs/collisions.md)")


def _ball_mass(meta: Mapping[str, Any], where: str) -> float:
    """kg, the mass of one ball: meta['ball_mass'], else from the config's [balls]."""
    if isinstance(meta.get("ball_mass"), (int, float)) and meta["ball_mass"] > 0:
        return float(meta["ball_mass"])
    balls = meta.get("config", {}).get("balls") if isinstance(meta.get("config"), Mapping) \
        else None
    try:
        radius, density = float(balls["radius"]), float(balls["density"])
    except (TypeError, KeyError, ValueError):
        raise CollisionDataError(
            f"{where}: meta has neither 'ball_mass' nor a config with [balls] radius and "
            "density, so the balls' mass (specific power) is unknown; the record was not "
            "written by sgn-jax's writers") from None
    return 4.0 / 3.0 * math.pi * radius**3 * density


def events_from_arrays(arrays: Mapping[str, Any], meta: Mapping[str, Any], *, source: str,
                       path: str | Path | None = None) -> EventTable:
    """The event table of one record from its arrays and meta.

    Args:
        arrays: the record's arrays: the ``collision_*`` fields, and ``t`` (T,) s and ``pos``
            (T, N, 3) for a DEM trajectory, or ``t_step`` (S,) s and ``pos`` (P, N, 3) for a
            surrogate prediction.
        meta: the record's meta: ``dt`` (s; a prediction's step) and the ball mass
            (``ball_mass`` kg, or ``config['balls']`` radius m and density kg/m^3).
        source: ``"dem"`` (the record spans ``t[0] .. t[-1]``) or ``"surrogate"`` (it spans
            ``t_step[0] - dt .. t_step[-1]``).
        path: named in errors and kept on the table.

    Raises:
        CollisionDataError: no ``collision_*`` arrays (saying how to produce them), some
            missing, or inconsistent shapes.
    """
    where = str(path) if path is not None else f"{source} record"
    if source not in SOURCES:
        raise CollisionDataError(f"{where}: source must be one of {list(SOURCES)}, got "
                                 f"{source!r}")
    present = [name for name in EVENT_FIELDS if PREFIX + name in arrays]
    if not present:
        hint = _DEM_HINT if source == "dem" else _SURROGATE_HINT
        raise CollisionDataError(f"{where} holds no collision events (no '{PREFIX}*' "
                                 f"arrays); {hint}")
    missing = [PREFIX + name for name in EVENT_FIELDS if PREFIX + name not in arrays]
    if missing:
        raise CollisionDataError(f"{where}: collision arrays {missing} are missing (it has "
                                 f"{[PREFIX + n for n in present]}); the ledger that wrote it "
                                 "is incomplete: rerun the simulation")
    try:
        if source == "dem":
            t = np.asarray(arrays["t"], dtype=np.float64)
            record_start, record_end = float(t[0]), float(t[-1])
        else:
            t_step = np.asarray(arrays["t_step"], dtype=np.float64)
            record_start = float(t_step[0]) - float(meta["dt"])
            record_end = float(t_step[-1])
        n_balls = int(np.shape(arrays["pos"])[1])
    except (KeyError, IndexError, TypeError, ValueError) as exc:
        raise CollisionDataError(f"{where}: not a {source} record ({type(exc).__name__}: "
                                 f"{exc}); pass DEM trajectories as DEM and rollout "
                                 "predictions as surrogate") from None
    return EventTable(
        **{name: np.asarray(arrays[PREFIX + name]) for name in EVENT_FIELDS},
        record_duration_s=record_end - record_start, record_start_s=record_start,
        n_balls=n_balls, total_mass_kg=n_balls * _ball_mass(meta, where), source=source,
        path=None if path is None else str(path), ball_class=_ball_classes(meta, n_balls))


def _ball_classes(meta: Mapping[str, Any], n_balls: int) -> np.ndarray | None:
    """(N,) the class of each ball from the record's config (``[balls]`` count, then each
    ``[[balls.mix]]`` count), or None for a charge of one class."""
    config = meta.get("config")
    balls = config.get("balls") if isinstance(config, Mapping) else None
    mix = balls.get("mix") if isinstance(balls, Mapping) else None
    if not mix:
        return None
    counts = [int(balls["count"])] + [int(m["count"]) for m in mix]
    if sum(counts) != n_balls:
        return None
    return np.repeat(np.arange(len(counts), dtype=np.int32), counts)


def events_from_record(record: Trajectory | Prediction) -> EventTable:
    """The event table of a loaded DEM trajectory (source ``"dem"``) or rollout prediction
    (``"surrogate"``); see :func:`events_from_arrays`."""
    if isinstance(record, Trajectory):
        source = "dem"
    elif isinstance(record, Prediction):
        source = "surrogate"
    else:
        raise TypeError(f"expected a Trajectory or a Prediction, got {type(record).__name__}")
    return events_from_arrays(record.arrays, record.meta, source=source, path=record.path)


def record_source(path: str | Path, source: str | None = None) -> str:
    """``"dem"`` or ``"surrogate"``: which kind of record the ``.npz`` at ``path`` is, by its
    array names (a prediction has ``t_step``, a trajectory ``pp_pairs``), checked to hold
    collision events. Reads only the archive's directory, so every input can be checked before
    any is loaded.

    Args:
        source: ``"dem"`` or ``"surrogate"`` to insist on a kind; None to accept either.

    Raises:
        CollisionDataError: the file is missing, not an ``.npz`` archive, neither kind (or not
            the kind asked for), or has no ``collision_*`` arrays (saying how to produce them).
    """
    path = Path(path)
    if not path.is_file():
        raise CollisionDataError(f"record {str(path)!r} not found; check the path")
    try:
        with np.load(path, allow_pickle=False) as npz:
            names = set(npz.files)
    except (OSError, ValueError, AttributeError) as exc:
        raise CollisionDataError(f"{path} is not an .npz record ({type(exc).__name__}: "
                                 f"{exc})") from None
    if "t_step" in names:
        found = "surrogate"
    elif "pp_pairs" in names and "t" in names:
        found = "dem"
    else:
        raise CollisionDataError(f"{path} is neither a DEM trajectory (`sgn-jax dem`) nor a "
                                 "rollout prediction (`sgn-jax rollout`)")
    if source is not None and found != source:
        what = {"dem": "a DEM trajectory", "surrogate": "a rollout prediction"}
        raise CollisionDataError(f"{path} is {what[found]}, not {what[source]}; pass it as "
                                 f"{'a DEM' if found == 'dem' else 'a surrogate'} record "
                                 f"(--{'dem' if found == 'dem' else 'surrogate'})")
    if not any(name.startswith(PREFIX) for name in names):
        hint = _DEM_HINT if found == "dem" else _SURROGATE_HINT
        raise CollisionDataError(f"{path} holds no collision events (no '{PREFIX}*' "
                                 f"arrays); {hint}")
    return found


def load_events(path: str | Path, source: str | None = None) -> EventTable:
    """Read and validate a record (DEM trajectory or rollout prediction) and return its events.

    Args:
        path: the ``.npz`` record.
        source: ``"dem"`` or ``"surrogate"`` to insist on a kind; None to tell by its arrays.

    Raises:
        CollisionDataError: a record of the other kind, or one without collision events;
        DatasetError / PredictionError: a malformed record.
    """
    found = record_source(path, source)
    record = load_trajectory(path) if found == "dem" else load_prediction(path)
    return events_from_record(record)


# --------------------------------------------------------------------------------------------
# One statistic each


def collision_frequency(table: EventTable, kind: str = "all") -> float:
    """Collisions per ball per second (1/s): new events of ``kind`` / (N * record duration).

    A ball-ball event involves two balls, so a ball is hit by another ball twice as often as
    the ball-ball value; the kinds add up to ``"all"``.
    """
    count = int(np.count_nonzero(table.kind_mask(kind) & table.new))
    return count / (table.n_balls * table.record_duration_s)


def dissipated_power(table: EventTable, kind: str = "all") -> float:
    """W, the energy the events of ``kind`` dissipated / record duration (every event)."""
    return float(table.dissipated[table.kind_mask(kind)].sum()) / table.record_duration_s


def specific_power(table: EventTable, kind: str = "all") -> float:
    """W per kg of balls: :func:`dissipated_power` / the balls' total mass."""
    return dissipated_power(table, kind) / table.total_mass_kg


def mean_stress_energy(table: EventTable, kind: str = "all") -> float:
    """J, the mean stress energy (``0.5 m* v_n^2``) of the new events of ``kind``; NaN if none.

    With the collision frequency this is Kwade's pair of stress energy and stress number.
    """
    select = table.kind_mask(kind) & table.new
    return float(table.stress_energy[select].mean()) if select.any() else math.nan


@dataclasses.dataclass(frozen=True)
class Spectrum:
    """Events binned by an energy (J) on log bins: how many per second and how much power.

    Attributes:
        quantity: ``"dissipated"`` (each event's dissipated energy) or ``"stress"`` (its
            stress energy).
        edges: (B + 1,) J, the bin edges; bin b is ``[edges[b], edges[b + 1])``.
        rate: (B,) events per second in each bin.
        power: (B,) W, the energy the bin's events dissipated per second (for both quantities:
            which impacts the dissipated power comes from).
        rate_below, power_below: events/s and W under ``edges[0]`` (energy 0 included).
        rate_above, power_above: events/s and W at or above ``edges[-1]``.
    """

    quantity: str
    edges: np.ndarray
    rate: np.ndarray
    power: np.ndarray
    rate_below: float
    power_below: float
    rate_above: float
    power_above: float

    @property
    def total_power(self) -> float:
        """W, the power of every event counted (in and out of the bins)."""
        return float(self.power.sum()) + self.power_below + self.power_above


def _bin_index(values: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """(E,) bin of each value: -1 below edges[0], B at or above edges[-1]; NaN -> -1."""
    index = np.searchsorted(edges, values, side="right") - 1
    index = np.where(np.isnan(values), -1, index)
    return np.minimum(index, edges.size - 1)


def _spectrum(table: EventTable, quantity: str, kind: str, edges: Any) -> Spectrum:
    edges = np.asarray(edges, dtype=np.float64)
    if edges.ndim != 1 or edges.size < 2 or np.any(np.diff(edges) <= 0):
        raise ValueError(f"edges must be increasing (B + 1,) J with B >= 1, got {edges!r}")
    select = table.kind_mask(kind)
    if quantity == "stress":
        select = select & table.new
        values = table.stress_energy[select]
    else:
        values = table.dissipated[select]
    dissipated = table.dissipated[select]
    n_bins = edges.size - 1
    index = _bin_index(values, edges) + 1  # 0: below, 1..B: bins, B + 1: above
    counts = np.bincount(index, minlength=n_bins + 2).astype(np.float64)
    energy = np.bincount(index, weights=dissipated, minlength=n_bins + 2)
    per_s = 1.0 / table.record_duration_s
    return Spectrum(quantity=quantity, edges=edges, rate=counts[1:-1] * per_s,
                    power=energy[1:-1] * per_s, rate_below=float(counts[0] * per_s),
                    power_below=float(energy[0] * per_s), rate_above=float(counts[-1] * per_s),
                    power_above=float(energy[-1] * per_s))


def dissipation_spectrum(table: EventTable, kind: str = "all", edges: Any = ENERGY_EDGES
                         ) -> Spectrum:
    """Events binned by the energy each dissipated (J): events/s and W per bin (every event,
    so ``total_power`` is :func:`dissipated_power`)."""
    return _spectrum(table, "dissipated", kind, edges)


def stress_spectrum(table: EventTable, kind: str = "all", edges: Any = ENERGY_EDGES
                    ) -> Spectrum:
    """New events binned by their stress energy ``0.5 m* v_n^2`` (J): events/s per bin (the
    stress-energy distribution of Kwade's model) and the power the bin's events dissipated (W)."""
    return _spectrum(table, "stress", kind, edges)


def _threshold_quantity(table: EventTable, by: str) -> tuple[np.ndarray, np.ndarray]:
    """(values J, select) for a threshold on ``by``."""
    if by == "dissipated":
        return table.dissipated, np.ones(table.n_events, dtype=bool)
    if by == "stress":
        return table.stress_energy, table.new
    raise ValueError(f"by={by!r}: use 'dissipated' (each event's dissipated energy) or "
                     "'stress' (its stress energy)")


def power_above(table: EventTable, threshold: float = DEFAULT_THRESHOLD_J, *,
                by: str = "dissipated", kind: str = "all") -> float:
    """W dissipated by the events of ``kind`` whose energy is at or above ``threshold`` (J).

    Args:
        by: ``"dissipated"`` (each event's dissipated energy) or ``"stress"`` (its stress
            energy; new events only).
    """
    values, select = _threshold_quantity(table, by)
    select = select & table.kind_mask(kind) & (values >= threshold)
    return float(table.dissipated[select].sum()) / table.record_duration_s


def power_share_above(table: EventTable, thresholds: Any = ENERGY_EDGES, *,
                      by: str = "dissipated", kind: str = "all") -> np.ndarray:
    """The cumulative share of the power: for each threshold (J), the fraction of the power
    dissipated by ``kind``'s events (:func:`dissipated_power`) that comes from events at or
    above it (see :func:`power_above`).

    Returns:
        same shape as ``thresholds``, in [0, 1], non-increasing in the threshold; NaN where
        nothing was dissipated.
    """
    thresholds = np.asarray(thresholds, dtype=np.float64)
    values, select = _threshold_quantity(table, by)
    select = select & table.kind_mask(kind)
    total = float(table.dissipated[table.kind_mask(kind)].sum())
    order = np.argsort(values[select])
    sorted_values = values[select][order]
    # energy from the events at or above each threshold: a reversed cumulative sum
    tail = np.concatenate([np.cumsum(table.dissipated[select][order][::-1])[::-1], [0.0]])
    above = tail[np.searchsorted(sorted_values, thresholds, side="left")]
    return above / total if total > 0 else np.full(thresholds.shape, math.nan)


@dataclasses.dataclass(frozen=True)
class SpeedDistribution:
    """The distribution of the impact speeds (m/s) of the new events of one kind.

    Attributes:
        component: ``"normal"`` (approach speed) or ``"tangential"``.
        edges: (B + 1,) m/s; rate: (B,) events per second in each bin (speeds outside the
            edges are not binned but count in the moments).
        mean, median: m/s (NaN without events).
        quantiles: {q: speed m/s} for :data:`QUANTILES`.
    """

    component: str
    edges: np.ndarray
    rate: np.ndarray
    mean: float
    median: float
    quantiles: dict[float, float]


def impact_speed_distribution(table: EventTable, kind: str = "all", *,
                              component: str = "normal", edges: Any = SPEED_EDGES
                              ) -> SpeedDistribution:
    """Histogram (events/s per bin), mean, median and :data:`QUANTILES` of the impact speed
    (m/s) of the new events of ``kind``: the normal approach speed or the tangential speed at
    first touch."""
    if component not in ("normal", "tangential"):
        raise ValueError(f"component={component!r}: use 'normal' or 'tangential'")
    edges = np.asarray(edges, dtype=np.float64)
    speeds = (table.impact_normal if component == "normal"
              else table.impact_tangential)[table.kind_mask(kind) & table.new]
    counts, _ = np.histogram(speeds, bins=edges)
    if speeds.size:
        quantiles = {q: float(v) for q, v in zip(QUANTILES, np.quantile(speeds, QUANTILES),
                                                   strict=True)}
        mean, median = float(speeds.mean()), float(np.median(speeds))
    else:
        quantiles = dict.fromkeys(QUANTILES, math.nan)
        mean = median = math.nan
    return SpeedDistribution(component=component, edges=edges,
                             rate=counts / table.record_duration_s, mean=mean, median=median,
                             quantiles=quantiles)


def dissipation_split(table: EventTable, kind: str = "all") -> dict[str, Any]:
    """Shares (in [0, 1]) of the dissipated energy of ``kind``'s events: ``"normal"`` (column 0,
    normal damping: the impact), ``"tangential"`` (every other column: the shear), and
    ``"columns"``, {column: share} for each of :data:`ENERGY_COLUMNS`; NaN where nothing was
    dissipated."""
    by_column = table.energy[table.kind_mask(kind)].sum(axis=0)
    total = float(by_column.sum())
    if total <= 0:
        return {"normal": math.nan, "tangential": math.nan,
                "columns": dict.fromkeys(ENERGY_COLUMNS, math.nan)}
    return {"normal": float(by_column[0]) / total,
            "tangential": float(by_column[1:].sum()) / total,
            "columns": {name: float(v) / total
                        for name, v in zip(ENERGY_COLUMNS, by_column, strict=True)}}


# --------------------------------------------------------------------------------------------
# All statistics of a table, and their ensemble


def collision_statistics(table: EventTable, *, threshold: float = DEFAULT_THRESHOLD_J,
                         threshold_by: str = "dissipated", edges: Any = ENERGY_EDGES,
                         speed_edges: Any = SPEED_EDGES) -> dict[str, float | np.ndarray]:
    """Every statistic of one table, by name (units in :data:`STATISTIC_UNITS`).

    Names ending in ``[kind]`` are given for each of the table's kinds (:data:`KINDS`, and for a
    charge of several ball classes each pair of classes, :attr:`EventTable.class_kinds`; every
    frequency is per ball of the whole charge, so that the kinds add up); the spectra and the
    cumulative share are arrays on ``edges`` (the spectra (B,), the share (B + 1,) at each
    edge), the speed histogram on ``speed_edges``.
    """
    stats: dict[str, float | np.ndarray] = {}
    for kind in table.kinds:
        stats[f"frequency_per_ball_hz[{kind}]"] = collision_frequency(table, kind)
        stats[f"power_W[{kind}]"] = dissipated_power(table, kind)
        stats[f"mean_stress_energy_J[{kind}]"] = mean_stress_energy(table, kind)
        split = dissipation_split(table, kind)
        stats[f"normal_share[{kind}]"] = split["normal"]
        stats[f"tangential_share[{kind}]"] = split["tangential"]
        speeds = impact_speed_distribution(table, kind, edges=speed_edges)
        stats[f"impact_speed_mean_m_s[{kind}]"] = speeds.mean
        stats[f"impact_speed_median_m_s[{kind}]"] = speeds.median
    speeds = impact_speed_distribution(table, edges=speed_edges)
    for q, value in speeds.quantiles.items():
        stats[f"impact_speed_q{round(100 * q):02d}_m_s"] = value
    stats["specific_power_W_per_kg"] = specific_power(table)
    stats["power_above_W"] = power_above(table, threshold, by=threshold_by)
    total = stats["power_W[all]"]
    stats["share_above"] = stats["power_above_W"] / total if total > 0 else math.nan
    dissipation = dissipation_spectrum(table, edges=edges)
    stress = stress_spectrum(table, edges=edges)
    stats["dissipation_rate_hz"] = dissipation.rate
    stats["dissipation_power_W"] = dissipation.power
    stats["stress_rate_hz"] = stress.rate
    stats["stress_power_W"] = stress.power
    stats["share_above_curve"] = power_share_above(table, edges, by=threshold_by)
    stats["impact_speed_rate_hz"] = speeds.rate
    return stats


STATISTIC_UNITS: dict[str, str] = {
    "frequency_per_ball_hz": "collisions per ball per second (1/s)",
    "power_W": "W dissipated by the events",
    "mean_stress_energy_J": "J, mean 0.5 m* v_n^2 of a collision",
    "normal_share": "fraction of the dissipated energy in normal damping",
    "tangential_share": "fraction in tangential damping, slip, rolling and stiffness",
    "impact_speed_mean_m_s": "m/s, mean normal approach speed at first touch",
    "impact_speed_median_m_s": "m/s, median normal approach speed",
    "impact_speed_q": "m/s, quantile of the normal approach speed (q10 = 10 %)",
    "specific_power_W_per_kg": "W per kg of balls",
    "power_above_W": "W dissipated by events at or above the threshold",
    "share_above": "fraction of the power from events at or above the threshold",
    "dissipation_rate_hz": "events/s per dissipated-energy bin",
    "dissipation_power_W": "W per dissipated-energy bin",
    "stress_rate_hz": "events/s per stress-energy bin",
    "stress_power_W": "W dissipated per stress-energy bin",
    "share_above_curve": "share of the power at or above each bin edge",
    "impact_speed_rate_hz": "events/s per impact-speed bin",
}
"""What each statistic of :func:`collision_statistics` is, by the name before any ``[kind]``."""


def mean_and_se(values: Any) -> tuple[np.ndarray, np.ndarray]:
    """Mean and standard error over the first axis, ignoring NaN (a packing without events of
    a kind has no mean stress energy).

    SE = std(ddof=1) / sqrt(n), n the finite values of each entry; NaN where n < 2 (one
    packing gives no scatter), and the mean NaN where n = 0.

    Args:
        values: (n, ...) one row per packing.
    Returns:
        (mean, se), each of shape ``values.shape[1:]``.
    """
    values = np.asarray(values, dtype=np.float64)
    if values.ndim < 1 or values.shape[0] < 1:
        raise ValueError(f"mean_and_se needs (n, ...) values with n >= 1, got shape "
                         f"{values.shape}")
    finite = np.isfinite(values)
    n = finite.sum(axis=0)
    zeroed = np.where(finite, values, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(n > 0, zeroed.sum(axis=0) / np.maximum(n, 1), np.nan)
        squares = np.where(finite, (values - mean) ** 2, 0.0).sum(axis=0)
        se = np.where(n >= 2, np.sqrt(squares / np.maximum(n - 1, 1)) / np.sqrt(n), np.nan)
    return mean, se


@dataclasses.dataclass(frozen=True)
class EnsembleStatistics:
    """The statistics of an ensemble of records (one per packing) of one source.

    Attributes:
        source: ``"dem"`` or ``"surrogate"``.
        paths: the records (None for tables built in memory).
        mean, se: {name: float or array} over the records (:func:`mean_and_se`), names as in
            :func:`collision_statistics`.
        per_record: one :func:`collision_statistics` dict per record.
        n_events: new events per record; duration_s: record durations (s).
        edges, speed_edges: the bins (J, m/s); threshold: J; threshold_by: what it bounds.
    """

    source: str
    paths: tuple[str | None, ...]
    mean: dict[str, Any]
    se: dict[str, Any]
    per_record: tuple[dict[str, Any], ...]
    n_events: tuple[int, ...]
    duration_s: tuple[float, ...]
    edges: np.ndarray
    speed_edges: np.ndarray
    threshold: float
    threshold_by: str

    @property
    def n_records(self) -> int:
        """The number of records (packings)."""
        return len(self.per_record)


def ensemble_statistics(tables: Sequence[EventTable] | Iterable[EventTable], *,
                        threshold: float = DEFAULT_THRESHOLD_J, threshold_by: str = "dissipated",
                        edges: Any = ENERGY_EDGES, speed_edges: Any = SPEED_EDGES
                        ) -> EnsembleStatistics:
    """Mean and standard error of every :func:`collision_statistics` entry over ``tables``
    (one per packing, all of one source), per bin for the spectra.

    Raises:
        CollisionDataError: no tables, or tables of both sources (reduce each separately).
    """
    tables = list(tables)
    if not tables:
        raise CollisionDataError("ensemble_statistics needs at least one event table")
    sources = sorted({t.source for t in tables})
    if len(sources) > 1:
        raise CollisionDataError(f"ensemble_statistics got tables of sources {sources}; "
                                 "reduce the DEM's and the surrogate's separately")
    edges = np.asarray(edges, dtype=np.float64)
    speed_edges = np.asarray(speed_edges, dtype=np.float64)
    per_record = [collision_statistics(t, threshold=threshold, threshold_by=threshold_by,
                                       edges=edges, speed_edges=speed_edges) for t in tables]
    mean, se = {}, {}
    for name, first in per_record[0].items():
        m, s = mean_and_se(np.stack([np.asarray(r[name], dtype=np.float64)
                                     for r in per_record]))
        scalar = np.ndim(first) == 0
        mean[name] = float(m) if scalar else m
        se[name] = float(s) if scalar else s
    return EnsembleStatistics(
        source=sources[0], paths=tuple(t.path for t in tables), mean=mean, se=se,
        per_record=tuple(per_record), n_events=tuple(int(t.new.sum()) for t in tables),
        duration_s=tuple(t.record_duration_s for t in tables), edges=edges,
        speed_edges=speed_edges, threshold=float(threshold), threshold_by=threshold_by)


def decade_comparison(reference: EnsembleStatistics, other: EnsembleStatistics, *,
                      spectrum: str = "dissipation", min_share: float = 0.05
                      ) -> list[dict[str, Any]]:
    """The two ensembles' spectra summed per decade, with the relative difference of the power
    and of the event rate in each decade that holds at least ``min_share`` of the reference's
    power in the bins.

    Args:
        spectrum: ``"dissipation"`` or ``"stress"``.
    Returns:
        one dict per decade: ``lo_J``, ``hi_J``, ``reference_share``, ``power_W`` and
        ``rate_hz`` ({"reference", "other"}), ``power_relative_difference`` and
        ``rate_relative_difference`` ((other - reference) / reference; None for a decade below
        ``min_share``), ``power_se_W`` ({"reference", "other"}: the standard error over the
        packings of the decade's power, NaN for an ensemble of one) and
        ``power_relative_difference_se`` (first-order propagation of the two SEs,
        (other / reference) sqrt((se_o / other)^2 + (se_r / reference)^2); None below
        ``min_share``). The SE says how far a decade's difference can be trusted: a decade of
        few, energetic collisions per packing scatters far more between packings than the
        mean power does.
    """
    if spectrum not in ("dissipation", "stress"):
        raise ValueError(f"spectrum={spectrum!r}: use 'dissipation' or 'stress'")
    edges = reference.edges
    if not np.array_equal(edges, other.edges):
        raise CollisionDataError("the two ensembles use different energy bins; compute both "
                                 "with the same edges")
    exponents = np.log10(edges)
    whole = np.flatnonzero(np.abs(exponents - np.round(exponents)) < 1e-9)
    if whole.size < 2:
        raise CollisionDataError("the energy bins span less than one decade")
    ref_power = np.asarray(reference.mean[f"{spectrum}_power_W"])
    ref_total = float(np.nansum(ref_power))
    rows = []
    for lo, hi in zip(whole[:-1], whole[1:], strict=True):
        power = {name: float(np.nansum(e.mean[f"{spectrum}_power_W"][lo:hi]))
                 for name, e in (("reference", reference), ("other", other))}
        rate = {name: float(np.nansum(e.mean[f"{spectrum}_rate_hz"][lo:hi]))
                for name, e in (("reference", reference), ("other", other))}
        power_se = {name: float(mean_and_se(np.asarray(
                        [np.nansum(np.asarray(r[f"{spectrum}_power_W"])[lo:hi])
                         for r in e.per_record], dtype=np.float64))[1])
                    for name, e in (("reference", reference), ("other", other))}
        share = power["reference"] / ref_total if ref_total > 0 else math.nan
        counted = share >= min_share
        ratio = power["other"] / power["reference"] if power["reference"] > 0 else math.nan
        ratio_se = ratio * math.hypot(
            power_se["other"] / power["other"] if power["other"] > 0 else math.nan,
            power_se["reference"] / power["reference"] if power["reference"] > 0 else math.nan)
        rows.append({
            "lo_J": float(edges[lo]), "hi_J": float(edges[hi]), "reference_share": share,
            "power_W": power, "rate_hz": rate, "power_se_W": power_se,
            "power_relative_difference_se": ratio_se if counted else None,
            "power_relative_difference": (power["other"] - power["reference"])
            / power["reference"] if counted else None,
            "rate_relative_difference": (rate["other"] - rate["reference"]) / rate["reference"]
            if counted and rate["reference"] > 0 else None,
        })
    return rows


__all__ = [
    "DEFAULT_THRESHOLD_J",
    "ENERGY_COLUMNS",
    "ENERGY_EDGES",
    "EVENT_FIELDS",
    "FLAG_BEGAN_BEFORE",
    "FLAG_OPEN_AT_END",
    "KINDS",
    "PAIR_KINDS",
    "PREFIX",
    "QUANTILES",
    "SOURCES",
    "SPEED_EDGES",
    "STATISTIC_UNITS",
    "CollisionDataError",
    "EnsembleStatistics",
    "EventTable",
    "Spectrum",
    "SpeedDistribution",
    "check_kind",
    "collision_frequency",
    "collision_statistics",
    "decade_comparison",
    "dissipated_power",
    "dissipation_spectrum",
    "dissipation_split",
    "ensemble_statistics",
    "events_from_arrays",
    "events_from_record",
    "impact_speed_distribution",
    "load_events",
    "log_edges",
    "mean_and_se",
    "mean_stress_energy",
    "power_above",
    "power_share_above",
    "record_source",
    "specific_power",
    "stress_spectrum",
]
