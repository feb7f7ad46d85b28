"""The DEM's collision ledger: every contact, from first touch to separation, as one event.

The energy ledger (:class:`sgn_jax.dem.engine.EnergyLedger`) says how much energy the contacts
dissipate; this ledger says how it arrives: in which contacts, at which impact speeds, in how
many events of which energy (docs/collisions.md). It is recorded inside the jitted step:

- every contact slot (a ball-ball slot of the pair list; a ball against the jar, whatever wall
  patches it touches) carries a :class:`ContactTrack`: whether it is touching, the step it
  began, its speeds at first touch, its deepest overlap and largest normal force so far and the
  energy it has dissipated, by kind (:data:`~sgn_jax.dem.contact.DISSIPATION_KINDS`, the kinds
  of the energy ledger);
- on the step a contact opens, its row goes into a fixed-capacity event buffer
  (:class:`CollisionBuffer`); the slot's values are restarted when its next contact begins. The
  buffer's ``count`` keeps counting past its capacity, so an overflow is seen (the host driver
  raises; nothing is dropped silently); the host empties the buffer after each chunk of steps.

Each step adds to a slot exactly the terms the energy ledger adds for that contact (its
normal and tangential damping, slip and rolling losses, and the energy its tangential spring
releases, see :func:`sgn_jax.dem.contact.contact_dissipation`), so the events' energies add up
to the energy ledger, kind by kind, up to float64 rounding.

Pure JAX; no config or file I/O. The host side (draining, the open events at the end of a run,
the table written with the run's record) is :mod:`sgn_jax.pipelines.dem_run`.
"""

from __future__ import annotations

from typing import Any

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from sgn_jax.dem.contact import DISSIPATION_KINDS

# --------------------------------------------------------------------------------------------
# The collision table: the one format of both ledgers' events (the DEM's here, the contact
# model's in sgn_jax.surrogate.collisions), of the records that store them and of the
# statistics that read them (docs/collisions.md).

COLLISION_PREFIX = "collision_"
"""The prefix of the event arrays in a record's ``.npz``."""

COLLISION_FIELDS: dict[str, tuple[str, str]] = {
    "ball": ("int32", "ball index i"),
    "partner": ("int32", "the other ball j > i (ball-ball) or the wall patch (ball-wall)"),
    "wall": ("bool", "True for a ball-wall event"),
    "start_s": ("float64", "s, motion time of the first touching step"),
    "duration_s": ("float64", "s, first touching step to the first step apart"),
    "impact_normal": ("float64", "m/s, normal approach speed at first touch (> 0 approaching)"),
    "impact_tangential": ("float64", "m/s, tangential speed of the contact point at first touch"),
    "max_overlap": ("float64", "m, deepest overlap (NaN where the ledger does not know it)"),
    "peak_force": ("float64", "N, largest normal force (NaN where unknown)"),
    "mass_eff": ("float64", "kg, reduced mass of the pair (the ball's mass for a wall)"),
    "energy": ("float64", "J dissipated, (E, 5) by the kinds of DISSIPATION_KINDS"),
    "flags": ("int8", "bit 0: began before the record; bit 1: still open at its end"),
}
"""Field -> (dtype, meaning) of the event table, stored as ``collision_<field>``; ``energy`` is
(E, 5), the others (E,)."""

FLAG_BEGAN_BEFORE = 1
"""Event flag bit: the contact began before the recorded window (its energy counts from its
start)."""
FLAG_OPEN_AT_END = 2
"""Event flag bit: the contact was still open when the record ended."""

# Columns of CollisionBuffer.floats (ContactTrack.values).
IMPACT_NORMAL, IMPACT_TANGENTIAL_SQ, MAX_OVERLAP, PEAK_FORCE = 0, 1, 2, 3
ENERGY0 = 4
N_FLOATS = ENERGY0 + len(DISSIPATION_KINDS)
# Columns of CollisionBuffer.ints.
BALL, PARTNER, WALL, START_STEP, END_STEP, FLAGS = range(6)
N_INTS = 6


@flax.struct.dataclass
class ContactTrack:
    """The event in progress in each contact slot (slots of any shape S).

    Every field has the slots' shape: separate arrays, the layout that measured cheapest per step
    on XLA:CPU (one packed (S, 9) array was slower).

    Attributes:
        active: bool, the slot was touching at the last step.
        start: int32, DEM step at which the contact began (its first touching step; a
            contact that began before the recorded window keeps its earlier start, which is
            how the host flags it).
        impact_normal: float64 m/s, the normal approach speed at first touch.
        impact_tangential: float64 m^2/s^2, the square of the tangential speed of the contact
            point at first touch (its root is taken on the host, off the step's path).
        max_overlap: float64 m, the deepest overlap so far.
        peak_force: float64 N, the largest normal force so far.
        energy: tuple of 5 float64 arrays, the energy dissipated so far by kind (J,
            :data:`~sgn_jax.dem.contact.DISSIPATION_KINDS`).
        spring: float64 J, the tangential spring energy stored after the last step (the
            stiffness term of the next step is measured against it).
    """

    active: jnp.ndarray
    start: jnp.ndarray
    impact_normal: jnp.ndarray
    impact_tangential: jnp.ndarray
    max_overlap: jnp.ndarray
    peak_force: jnp.ndarray
    energy: tuple
    spring: jnp.ndarray

    @property
    def values(self) -> jnp.ndarray:
        """(*S, N_FLOATS) the event columns of :attr:`CollisionBuffer.floats`."""
        return jnp.stack([self.impact_normal, self.impact_tangential, self.max_overlap,
                          self.peak_force, *self.energy], axis=-1)


@flax.struct.dataclass
class CollisionBuffer:
    """The events closed since the host last emptied the buffer (capacity C).

    Attributes:
        ints: (C, N_INTS) int64 per event: ball, partner (ball j > i, or the wall patch),
            wall (0/1), start step, end step (the first step apart), flags (0 here; the host
            sets :data:`FLAG_BEGAN_BEFORE` from the start step and the window's).
        floats: (C, N_FLOATS) float64 per event, the columns of :attr:`ContactTrack.values`.
        count: () int32, events closed since the last emptying; > C means the buffer
            overflowed (rows past C were not stored).
    """

    ints: jnp.ndarray
    floats: jnp.ndarray
    count: jnp.ndarray


@flax.struct.dataclass
class CollisionLedger:
    """The tracks of every contact slot, ``track`` (K + N slots: the K ball-ball slots of the
    pair list, then one per ball for its contact with the jar, whatever patches it touches;
    one track, so that each step updates all slots in one pass), the wall patch each ball-wall
    contact first touched (``wall_patch`` (N,) int32) and the event buffer. ``pp`` and ``pw``
    are the two kinds' slots."""

    track: ContactTrack
    wall_patch: jnp.ndarray
    buffer: CollisionBuffer

    @property
    def n_balls(self) -> int:
        return self.wall_patch.shape[0]

    @property
    def pp(self) -> ContactTrack:
        """The ball-ball slots (K,)."""
        n = self.n_balls
        return jax.tree_util.tree_map(lambda a: a[:a.shape[0] - n], self.track)

    @property
    def pw(self) -> ContactTrack:
        """The ball-wall slots (N,), one per ball."""
        n = self.n_balls
        return jax.tree_util.tree_map(lambda a: a[a.shape[0] - n:], self.track)


def empty_track(shape: tuple[int, ...]) -> ContactTrack:
    """A track of slots of ``shape`` with no contact in progress."""
    def zero() -> jnp.ndarray:
        return jnp.zeros(shape, jnp.float64)

    return ContactTrack(active=jnp.zeros(shape, bool), start=jnp.zeros(shape, jnp.int32),
                        impact_normal=zero(),
                        impact_tangential=zero(), max_overlap=zero(), peak_force=zero(),
                        energy=tuple(zero() for _ in DISSIPATION_KINDS), spring=zero())


def empty_ledger(n_pair_slots: int, n_balls: int, capacity: int) -> CollisionLedger:
    """A collision ledger with nothing in progress and an empty buffer of ``capacity`` events."""
    return CollisionLedger(
        track=empty_track((n_pair_slots + n_balls,)),
        wall_patch=jnp.zeros((n_balls,), jnp.int32),
        buffer=CollisionBuffer(ints=jnp.zeros((capacity, N_INTS), jnp.int64),
                               floats=jnp.zeros((capacity, N_FLOATS), jnp.float64),
                               count=jnp.zeros((), jnp.int32)))


def carry_pp_track(track: ContactTrack, where: jnp.ndarray, found: jnp.ndarray) -> ContactTrack:
    """The tracks (K + N slots, :class:`CollisionLedger`) after a pair-list rebuild: new
    ball-ball slot k takes old slot ``where[k]`` when ``found[k]`` (the same pair), else starts
    empty; the ball-wall slots stay. A pair in contact is always in the new list (its gap is
    below the skin), so no event in progress is lost."""
    k = where.shape[0]
    n = track.active.shape[0] - k
    where = jnp.concatenate([where, k + jnp.arange(n, dtype=where.dtype)])
    found = jnp.concatenate([found, jnp.ones((n,), bool)])

    def take(a: jnp.ndarray) -> jnp.ndarray:
        mask = found.reshape(found.shape + (1,) * (a.ndim - 1))
        return jnp.where(mask, a[where], jnp.zeros_like(a))

    return jax.tree_util.tree_map(take, track)


def update_track(track: ContactTrack, step: jnp.ndarray, in_contact: jnp.ndarray,
                 overlap: jnp.ndarray, normal_force: jnp.ndarray, approach_speed: jnp.ndarray,
                 tangential_speed_sq: jnp.ndarray, energy: tuple, spring_old_now: jnp.ndarray,
                 spring_new: jnp.ndarray) -> tuple[ContactTrack, jnp.ndarray, jnp.ndarray]:
    """Advance the tracks by one step; returns ``(track, started, ended)``.

    Args (all over the slots' shape S):
        step: () int64, the DEM step being taken (a contact touching now began at ``step``).
        in_contact: bool, overlap > 0 at the start of the step.
        overlap: m; normal_force: N (the applied normal force, spring + damping).
        approach_speed: m/s, tangential_speed_sq: m^2/s^2, at the start of the step (kept at
            first touch).
        energy: 4 arrays, J dissipated this step: normal, tangential, slip, rolling.
        spring_old_now, spring_new: J, the tangential spring energy of the old displacement at the
            current stiffness, and the energy stored after the step (ContactForces fields).

    ``started`` marks the slots whose contact began this step, ``ended`` those whose contact
    opened this step; the new track holds their
    values including this step's terms (the energy the spring releases as it opens): a slot
    out of contact keeps the values of its last event until its next one begins.
    """
    f64 = jnp.float64
    started = in_contact & ~track.active
    ended = track.active & ~in_contact
    # Every term is 0 for a slot that is neither touching nor just opened (the forces are
    # masked out of contact, and such a slot stores no spring energy), so the sums need no
    # mask; a slot's values are reset when its next contact begins, not when one ends.
    stiffness = track.spring - spring_old_now.astype(f64)
    increments = (*energy, stiffness)
    new = ContactTrack(
        active=in_contact,
        start=jnp.where(started, step.astype(jnp.int32), track.start),
        impact_normal=jnp.where(started, approach_speed.astype(f64), track.impact_normal),
        impact_tangential=jnp.where(started, tangential_speed_sq.astype(f64),
                                    track.impact_tangential),
        max_overlap=jnp.maximum(jnp.where(started, 0.0, track.max_overlap), overlap.astype(f64)),
        peak_force=jnp.maximum(jnp.where(started, 0.0, track.peak_force),
                               normal_force.astype(f64)),
        energy=tuple(jnp.where(started, 0.0, e) + inc.astype(f64)
                     for e, inc in zip(track.energy, increments, strict=True)),
        spring=spring_new.astype(f64),
    )
    return new, started, ended


def write_events(buffer: CollisionBuffer, ended_parts: tuple,
                 make_rows: Any) -> CollisionBuffer:
    """Append the rows ``make_rows() -> (ints (S, N_INTS), floats (S, N_FLOATS))`` where
    ``ended`` (S,), the concatenation of ``ended_parts``, to the buffer; rows past its capacity
    are not stored but still counted. The rows are built and scattered only on steps where a
    contact opens (most steps have none)."""
    capacity = buffer.ints.shape[0]

    def write(b: CollisionBuffer) -> CollisionBuffer:
        ended = jnp.concatenate(ended_parts)
        ints, floats = make_rows()
        rank = jnp.cumsum(ended.astype(jnp.int32)) - 1
        index = jnp.where(ended, b.count + rank, capacity)  # capacity: out of range, dropped
        return CollisionBuffer(ints=b.ints.at[index].set(ints, mode="drop"),
                               floats=b.floats.at[index].set(floats, mode="drop"),
                               count=b.count + jnp.sum(ended, dtype=jnp.int32))

    any_ended = jnp.any(jnp.stack([jnp.any(part) for part in ended_parts]))
    return jax.lax.cond(any_ended, write, lambda b: b, buffer)


def event_ints(ball: jnp.ndarray, partner: jnp.ndarray, wall: bool, track: ContactTrack,
               end_step: jnp.ndarray) -> jnp.ndarray:
    """(S, N_INTS) integer columns of the events of S slots (flattened)."""
    s = ball.shape[0]
    return jnp.stack([ball.astype(jnp.int64), partner.astype(jnp.int64),
                      jnp.full((s,), int(wall), jnp.int64), track.start.reshape(s),
                      jnp.broadcast_to(end_step, (s,)).astype(jnp.int64),
                      jnp.zeros((s,), jnp.int64)], axis=-1)


def restart_window(ledger: CollisionLedger) -> CollisionLedger:
    """The ledger at the start of a recorded window (when the energy ledger's totals are reset):
    contacts in progress keep their first-touch values and their start (before the window) but
    count energy from now on; the buffer is emptied."""
    def restart(track: ContactTrack) -> ContactTrack:
        return track.replace(energy=tuple(jnp.zeros_like(e) for e in track.energy))

    return ledger.replace(track=restart(ledger.track),
                          buffer=ledger.buffer.replace(count=jnp.zeros((), jnp.int32)))


def empty_buffer(ledger: CollisionLedger) -> CollisionLedger:
    """The ledger with its buffer emptied (after the host has read it)."""
    return ledger.replace(buffer=ledger.buffer.replace(count=jnp.zeros((), jnp.int32)))


def buffer_rows(ledger: CollisionLedger) -> tuple[np.ndarray, np.ndarray]:
    """Host side: the stored events ``(ints (E, N_INTS), floats (E, N_FLOATS))`` of the buffer
    (E = min(count, capacity); the caller checks ``count`` against the capacity first)."""
    count = int(ledger.buffer.count)
    e = min(count, ledger.buffer.ints.shape[0])
    return np.asarray(ledger.buffer.ints[:e]), np.asarray(ledger.buffer.floats[:e])


def open_rows(ledger: CollisionLedger, pair_i: Any, pair_j: Any, step: int
              ) -> tuple[np.ndarray, np.ndarray]:
    """Host side: the contacts still in progress as event rows (flag :data:`FLAG_OPEN_AT_END`),
    ended at ``step``; ``pair_i``, ``pair_j`` (K,) are the ball-ball slots' balls."""
    rows_i, rows_f = [], []
    for wall, track in ((False, ledger.pp), (True, ledger.pw)):
        active = np.asarray(track.active)
        if wall:
            (ball,) = np.nonzero(active)
            partner = np.asarray(ledger.wall_patch)[ball]
        else:
            (slot,) = np.nonzero(active)
            ball, partner = np.asarray(pair_i)[slot], np.asarray(pair_j)[slot]
        ints = np.stack([ball, partner, np.full(ball.shape, int(wall)),
                         np.asarray(track.start)[active], np.full(ball.shape, step),
                         np.full(ball.shape, FLAG_OPEN_AT_END)], axis=-1).astype(np.int64)
        rows_i.append(ints.reshape(-1, N_INTS))
        rows_f.append(np.asarray(track.values)[active].reshape(-1, N_FLOATS))
    return np.concatenate(rows_i), np.concatenate(rows_f)
