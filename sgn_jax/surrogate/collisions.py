"""The contact surrogate's collision ledger: one event per contact, recorded inside the rollout.

An event is a run of consecutive surrogate steps in which one contact touches: its impulse
acts (the gate) with a normal force of at least :data:`EVENT_FORCE_FRACTION` of its reduced
mass's weight; a ball pair (i < j) or a ball and the wall (the jar: all its wall patches
together). The contact
model (:mod:`sgn_jax.surrogate.contact`) reports per step, for every pair, a
:class:`ContactGrid` (dense: (N, N + 1), column N the wall); :func:`update_events` keeps one
accumulator per pair in the rollout's carry (:class:`CollisionCarry`) and writes each event
into a table of fixed capacity when its contact stops touching. All of it runs in the jitted
``lax.scan``; nothing is dropped silently: more events than the capacity in one jitted call
set ``count`` above it, and :func:`collision_arrays` (the host) raises
:class:`CollisionCapacityError` naming the capacity and how to raise it.

What an event holds (the collision table of the records, ``collision_<key>`` arrays,
:func:`collision_arrays`; E events):

| key | shape, dtype | meaning |
|---|---|---|
| ball | (E,) int32 | ball index i |
| partner | (E,) int32 | the other ball j > i; 0 for the wall |
| wall | (E,) bool | True = ball-wall event |
| start_s | (E,) float64 | s since the start of motion, the start of the event's first step |
| duration_s | (E,) float64 | s, steps in which the impulse acted times dt |
| impact_normal | (E,) float64 | m/s, approach speed along the normal at the start of the first step (> 0: approaching) |
| impact_tangential | (E,) float64 | m/s, tangential speed of the contact point there (of the centres for a model without spin) |
| max_overlap | (E,) float64 | m, the deepest overlap at the start of the event's steps (0: the balls never overlapped at a step boundary) |
| peak_force | (E,) float64 | N, the largest normal impulse of a step over dt (the step's mean force) |
| mass_eff | (E,) float64 | kg, the reduced mass m* of the model's impulse (m / 2 for a pair, m for the wall) |
| energy | (E, 5) float64 | J: the event's share of the model's own dissipation, normal-impulse part (col 0) and tangential part, with the rotational work of the contact's torques (col 1); cols 2-4 (slip, rolling, stiffness) 0 |
| flags | (E,) int8 | bit 0: the pair overlapped at the start of the rollout (began before it); bit 1: still acting at its end (flushed) |

The energies are the model's own ledger, ``D_pp + D_pw`` of :mod:`sgn_jax.surrogate.contact`
(what its impulses take out of the balls, all losses), not the damping-share report
``share_pp D_pp + share_pw D_pw`` (``dE``): the events of a rollout add up to
``sum(diss_pp + diss_pw)`` of its steps to float32 rounding.
"""

from __future__ import annotations

from typing import Any

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from sgn_jax.dem.collisions import (
    COLLISION_FIELDS,
    COLLISION_PREFIX,
    FLAG_BEGAN_BEFORE,
    FLAG_OPEN_AT_END,
)
from sgn_jax.dem.contact import DISSIPATION_KINDS
from sgn_jax.errors import SGNJaxError

F64 = jnp.float64
I32 = jnp.int32

# Columns of ContactGrid.values and of the accumulators / table floats.
GRID_FIELDS = ("impact_normal", "impact_tangential", "max_overlap", "peak_force", "mass_eff",
               "energy_normal", "energy_tangential")
_N_FLOAT = len(GRID_FIELDS)
_LARGEST = np.array([f in ("max_overlap", "peak_force") for f in GRID_FIELDS])
_SUMMED = np.array([f.startswith("energy") for f in GRID_FIELDS])
# Integer columns of the table: ball, partner, wall, start step, steps, flags.
_N_INT = 6
EVENT_FORCE_FRACTION = 0.1
"""A contact is touching in a step when its normal force (impulse / dt) is at least this
fraction of the weight of its reduced mass, ``EVENT_FORCE_FRACTION * m* * STANDARD_GRAVITY``
(docs/collisions.md). The gate lets a contact act whenever the balls come within
``gate_margin`` (50 um) of touching, and the model's impulse there is small but not zero: a
pair rattling at a few um, which the DEM sees as several contacts, would otherwise be one
event. The fraction is fitted on training packings of training motions (docs/collisions.md),
never on the held-out ones."""
STANDARD_GRAVITY = 9.80665
DEFAULT_CAPACITY = 20000
"""Events per jitted call (per chunk of ``[rollout] chunk_steps`` in ``run_rollout``): the
standard case (24 balls, 300 rpm) closes about 8,000 events per second of rollout (1.6 per
step of 0.2 ms), about 3,300 in a chunk of 2,000 steps."""


class CollisionCapacityError(SGNJaxError, RuntimeError):
    """More collision events in one jitted rollout call than the table holds."""


@flax.struct.dataclass
class ContactGrid:
    """One step's contacts per pair (N balls): ``acting`` (N, N + 1) bool, whether the pair's
    impulse acts in the step (row i, column j > i a ball pair, column N ball i and the wall);
    ``values`` (N, N + 1, 7) float32 in the order of :data:`GRID_FIELDS`: approach speed
    (m/s), tangential speed (m/s), overlap (m) at the step's start, normal impulse / dt (N),
    m* (kg), the normal and tangential parts of the contact's dissipation in the step (J).
    Several wall patches of one ball add their energies and take the largest of the rest."""

    acting: jax.Array
    values: jax.Array


@flax.struct.dataclass
class CollisionCarry:
    """The collision ledger in the rollout's carry (N balls, capacity C).

    Attributes:
        open: (N, N + 1) bool, the pair's impulse acted in the last step (an event is open).
        acc: (N, N + 1, 7) float64, the open events' fields (:data:`GRID_FIELDS`; impact
            speeds and m* of the first step, the largest overlap and force, the summed energies).
        start: (N, N + 1) int32, the rollout step at which the open event began.
        began: (N, N + 1) bool, the open event's pair overlapped at the rollout's first step.
        floats: (C, 8) float64, the closed events' :data:`GRID_FIELDS` and start time (s).
        ints: (C, 6) int32, their ball, partner, wall, start step, steps and flags.
        count: () int32, events closed in this call (the table holds the first min(count, C)).
        t0, dt: () float64 s, the rollout's start time and step.
        pending: (N, N + 1, 2) float64 J, the dissipation of a pair's gated steps below the
            force floor while no event of it is open: added to its next event (so the events
            still add up to the model's ledger); what is left at the end is reported apart.
        min_force_per_kg: () float64 N/kg, the force floor per kg of m*
            (:data:`EVENT_FORCE_FRACTION` of standard gravity by default).
    """

    open: jax.Array
    acc: jax.Array
    start: jax.Array
    began: jax.Array
    floats: jax.Array
    ints: jax.Array
    count: jax.Array
    t0: jax.Array
    dt: jax.Array
    pending: jax.Array
    min_force_per_kg: jax.Array

    @property
    def capacity(self) -> int:
        """C, the events the table holds per jitted call."""
        return int(self.floats.shape[-2])


def init_collisions(n_balls: int, capacity: int, t0: Any, dt: float,
                    force_fraction: float = EVENT_FORCE_FRACTION) -> CollisionCarry:
    """An empty ledger of ``n_balls`` balls and a table of ``capacity`` events; a contact
    touches in a step when its force is at least ``force_fraction`` of its m*'s weight."""
    capacity = check_capacity(capacity)
    if not force_fraction >= 0:
        raise CollisionCapacityError(f"force_fraction must be >= 0, got {force_fraction!r}")
    shape = (n_balls, n_balls + 1)
    return CollisionCarry(open=jnp.zeros(shape, bool), acc=jnp.zeros(shape + (_N_FLOAT,), F64),
                          start=jnp.zeros(shape, I32), began=jnp.zeros(shape, bool),
                          floats=jnp.zeros((capacity, _N_FLOAT + 1), F64),
                          ints=jnp.zeros((capacity, _N_INT), I32), count=jnp.zeros((), I32),
                          t0=jnp.asarray(t0, F64), dt=jnp.asarray(dt, F64),
                          pending=jnp.zeros(shape + (2,), F64),
                          min_force_per_kg=jnp.asarray(force_fraction * STANDARD_GRAVITY, F64))


def check_capacity(capacity: Any) -> int:
    """``capacity`` as an int >= 1, or a CollisionCapacityError naming the value."""
    if isinstance(capacity, bool) or not isinstance(capacity, (int, np.integer)) or capacity < 1:
        raise CollisionCapacityError(f"collision_capacity must be an integer >= 1 (events per "
                                     f"jitted rollout call), got {capacity!r}")
    return int(capacity)


def contact_grid(n_balls: int, receivers: jax.Array, senders: jax.Array, acting: jax.Array,
                 values: jax.Array) -> ContactGrid:
    """Scatter per-contact rows into the dense pair grid.

    Args:
        n_balls: N. receivers, senders: (E,) node indices of each contact (balls 0..N-1, the
            wall node N: a wall contact's sender). acting: (E,) whether its impulse acts.
        values: (E, 7) float32, the fields of :data:`GRID_FIELDS` per contact.
    """
    a, b = jnp.minimum(receivers, senders), jnp.maximum(receivers, senders)
    size = n_balls * (n_balls + 1)
    flat = jnp.where(acting, a * (n_balls + 1) + b, size)   # out of range: dropped
    # energies add over a ball's wall patches; the other fields take the largest (a pair that
    # acts has m* > 0, so its largest m* is finite: no scatter of its own for ``acting``)
    summed = jnp.zeros((size, 2), values.dtype).at[flat].add(values[:, 5:], mode="drop")
    largest = jnp.full((size, 5), -jnp.inf, values.dtype).at[flat].max(values[:, :5], mode="drop")
    on = largest[:, 4] > -jnp.inf
    grid = jnp.concatenate([jnp.where(on[:, None], largest, 0.0), summed], axis=-1)
    shape = (n_balls, n_balls + 1)
    return ContactGrid(acting=on.reshape(shape), values=grid.reshape(shape + (_N_FLOAT,)))


def _pair_ids(n_balls: int) -> tuple[jax.Array, jax.Array, jax.Array]:
    ball = jnp.broadcast_to(jnp.arange(n_balls, dtype=I32)[:, None], (n_balls, n_balls + 1))
    column = jnp.broadcast_to(jnp.arange(n_balls + 1, dtype=I32)[None, :], ball.shape)
    wall = column == n_balls
    return ball, jnp.where(wall, 0, column), wall


def update_events(carry: CollisionCarry, grid: ContactGrid, step: jax.Array) -> CollisionCarry:
    """One rollout step (``step``: its index since the rollout's start): close the events
    whose contact stopped touching (written to the table), open the new ones, accumulate.

    A pair touches in a step when its impulse acts (the gate) with a normal force of at least
    ``min_force_per_kg * m*``. The dissipation of a gated step below that floor belongs to the
    pair's event that closes in it, else waits in ``pending`` for the pair's next event: every
    joule of the model's ledger lands in an event or, at the end, in the pending total."""
    n = carry.open.shape[0]
    capacity = carry.floats.shape[0]
    fresh = grid.values.astype(F64)
    touching = grid.acting & (fresh[..., 3] >= carry.min_force_per_kg * fresh[..., 4])
    below = grid.acting & ~touching
    close_grid = carry.open & ~touching
    close = close_grid.reshape(-1)
    n_close = jnp.sum(close, dtype=I32)
    energy = fresh[..., 5:7]

    def emit(tables):
        table_f, table_i = tables
        rank = jnp.cumsum(close, dtype=I32) - 1
        row = jnp.where(close, carry.count + rank, capacity)   # past the table: dropped
        ball, partner, wall = _pair_ids(n)
        flags = jnp.where(carry.began, FLAG_BEGAN_BEFORE, 0).astype(I32)
        ints = jnp.stack([ball, partner, wall.astype(I32), carry.start, step - carry.start,
                          flags], axis=-1).reshape(-1, _N_INT)
        start_s = carry.t0 + carry.start.astype(F64) * carry.dt
        # a closing event takes the energy of its last, below-floor step
        acc = carry.acc.at[..., 5:7].add(jnp.where(below[..., None], energy, 0.0))
        floats = jnp.concatenate([acc, start_s[..., None]], axis=-1).reshape(-1, _N_FLOAT + 1)
        return (table_f.at[row].set(floats, mode="drop"),
                table_i.at[row].set(ints, mode="drop"))

    # most steps close no event: skip the write there
    table_f, table_i = jax.lax.cond(n_close > 0, emit, lambda tables: tables,
                                    (carry.floats, carry.ints))
    count = carry.count + n_close

    new = touching & ~carry.open
    # continuing: first-step fields kept, the largest overlap and force, the energies summed
    # (one elementwise pass over the columns, by column masks); a new event takes the pair's
    # pending energy
    old = carry.acc
    cont = jnp.where(_LARGEST, jnp.maximum(old, fresh), jnp.where(_SUMMED, old + fresh, old))
    first = fresh.at[..., 5:7].add(carry.pending)
    acc = jnp.where(new[..., None], first, cont)
    pending = jnp.where(new[..., None], 0.0,
                        carry.pending + jnp.where((below & ~carry.open)[..., None], energy, 0.0))
    began = jnp.where(new, (step == 0) & (fresh[..., 2] > 0), carry.began)
    return carry.replace(open=touching, acc=acc, start=jnp.where(new, step, carry.start),
                         began=began, floats=table_f, ints=table_i, count=count,
                         pending=pending)


def collision_arrays(carry: CollisionCarry, final_step: Any | None = None,
                     chunk_hint: str = "") -> dict[str, np.ndarray]:
    """The closed events of one jitted call as the ``collision_*`` arrays (host numpy; module
    docstring), and with ``final_step`` (the rollout's step count at its end) the events still
    open there, flushed with flags bit 1. Raises :class:`CollisionCapacityError` when the call
    closed more events than the table holds (``chunk_hint``: where the call's length is set)."""
    carry = jax.device_get(carry)
    count, capacity = int(carry.count), int(np.shape(carry.floats)[0])
    if count > capacity:
        raise CollisionCapacityError(
            f"the rollout closed {count} collision events in one jitted call, more than its "
            f"collision_capacity = {capacity}; raise it (collision_capacity={2 * count} in "
            f"sgn_jax, --collision-capacity {2 * count} in `sgn-jax rollout`){chunk_hint}")
    floats = np.asarray(carry.floats[:count], np.float64)
    ints = np.asarray(carry.ints[:count], np.int64)
    if final_step is not None:
        is_open = np.asarray(carry.open)
        ball, col = np.nonzero(is_open)
        n = is_open.shape[0]
        start = np.asarray(carry.start)[ball, col].astype(np.int64)
        dt, t0 = float(carry.dt), float(carry.t0)
        open_f = np.concatenate([np.asarray(carry.acc)[ball, col], (t0 + start * dt)[:, None]],
                                axis=1)
        flags = (np.where(np.asarray(carry.began)[ball, col], FLAG_BEGAN_BEFORE, 0)
                 | FLAG_OPEN_AT_END).astype(np.int64)
        open_i = np.stack([ball, np.where(col == n, 0, col), (col == n).astype(np.int64), start,
                           int(final_step) - start, flags], axis=1)
        floats = np.concatenate([floats, open_f.reshape(-1, _N_FLOAT + 1)])
        ints = np.concatenate([ints, open_i.reshape(-1, _N_INT)])
    return event_table(floats, ints, float(carry.dt))


def pending_energy(carry: CollisionCarry) -> np.ndarray:
    """(2,) J, host: the dissipation (normal part, tangential part) of below-floor steps that
    no event has taken yet (:func:`update_events`); the events plus this add up to the model's
    ledger."""
    return np.asarray(jax.device_get(carry.pending), np.float64).reshape(-1, 2).sum(axis=0)


def event_table(floats: np.ndarray, ints: np.ndarray, dt: float) -> dict[str, np.ndarray]:
    """The ``collision_*`` arrays of table rows (floats (E, 8), ints (E, 6)), sorted by start
    time, then ball, wall and partner."""
    order = np.lexsort((ints[:, 1], ints[:, 2], ints[:, 0], ints[:, 3]))
    f, i = floats[order], ints[order]
    energy = np.zeros((len(f), len(DISSIPATION_KINDS)))
    energy[:, :2] = f[:, 5:7]
    columns = {"ball": i[:, 0], "partner": i[:, 1], "wall": i[:, 2], "start_s": f[:, 7],
               "duration_s": i[:, 4] * float(dt), "impact_normal": f[:, 0],
               "impact_tangential": f[:, 1], "max_overlap": f[:, 2], "peak_force": f[:, 3],
               "mass_eff": f[:, 4], "energy": energy, "flags": i[:, 5]}
    return {COLLISION_PREFIX + key: np.array(columns[key], dtype=dtype)
            for key, (dtype, _) in COLLISION_FIELDS.items()}


def concat_tables(tables: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """The ``collision_*`` arrays of several jitted calls of one rollout, in order."""
    keys = tables[0].keys()
    merged = {k: np.concatenate([t[k] for t in tables]) for k in keys}
    order = np.lexsort((merged["collision_partner"], merged["collision_wall"],
                        merged["collision_ball"], merged["collision_start_s"]))
    return {k: v[order] for k, v in merged.items()}


__all__ = [
    "DEFAULT_CAPACITY",
    "GRID_FIELDS",
    "CollisionCapacityError",
    "CollisionCarry",
    "ContactGrid",
    "collision_arrays",
    "concat_tables",
    "contact_grid",
    "event_table",
    "init_collisions",
    "pending_energy",
    "update_events",
]
