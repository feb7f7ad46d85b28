"""The DEM engine: state pytree, jittable step, contact assembly and the energy ledger.

``make_dem_step(spec, wall_fn) -> step(params, state) -> state`` (JAX-MD style). ``spec``
(:class:`DEMSpec`) holds everything static (sizes, dt, dtype, pair mode); ``params``
(:class:`DEMParams`) every number that may be batched with ``jax.vmap`` (material, ball, gravity,
jar geometry, motion); ``state`` (:class:`DEMState`) the dynamic state.
The contact physics is the law in ``spec.contact_law`` (:mod:`sgn_jax.dem.laws`;
Hertz-Mindlin by default), whose parameters are ``params.pp`` / ``params.pw``.

Time integration: symplectic (semi-implicit) Euler,

    v_{n+1} = v_n + dt (F(x_n, v_n, w_n, d_t) / m + g),   w_{n+1} = w_n + dt tau / I,
    x_{n+1} = x_n + dt v_{n+1},

one force evaluation per step (the same integrator the surrogate uses,
docs/conventions.md section 5). The velocity dependent damping forces take the velocity of the start of the step. See
docs/dem.md for why.

Time is the integer ``state.step`` counting DEM steps since the start of motion (negative while
settling); t = step * dt_dem in float64, so 10 s of motion accumulate no rounding drift. For
step < 0 the jar rests at ``offset(motion, 0)`` with zero velocity; at step 0 its velocity jumps
to ``velocity(motion, 0)`` (docs/conventions.md section 2).

Energy ledger (cumulative, float64 whatever the state dtype): per contact type (pp, pw) the
dissipation by normal damping, tangential damping, Coulomb slip, rolling friction and the
tangential-stiffness term (see :mod:`sgn_jax.dem.contact`), plus the work done by the moving
wall on the balls. Each power uses the step's mean velocity, for which
dKE = sum F . v_mid dt holds exactly, so that

    work_wall = d(KE_trans + KE_rot + PE_grav + E_elastic) + sum of all dissipation

up to the time-integration error of the conservative springs alone.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import Any, NamedTuple

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from sgn_jax import motion as motion_mod
from sgn_jax.dem import collisions as coll
from sgn_jax.dem.cells import build_pairs_cells
from sgn_jax.dem.contact import DISSIPATION_KINDS  # noqa: F401  (re-exported: the ledger's kinds)
from sgn_jax.dem.laws import HERTZ_MINDLIN, ContactLawError, resolve_contact_law
from sgn_jax.errors import SGNJaxError

PAIR_MODES = ("auto", "nxn", "pairs", "neighbour")

WallFn = Callable[[Any, jnp.ndarray], tuple[jnp.ndarray, jnp.ndarray]]
MotionFn = Callable[[Any, jnp.ndarray], jnp.ndarray]


class DEMError(SGNJaxError, ValueError):
    """Bad DEM input (sizes, parameters), with a message that says how to fix it."""


# --------------------------------------------------------------------------------------------
# Static spec, parameters, state


@dataclasses.dataclass(frozen=True)
class DEMSpec:
    """Static DEM settings (hashable; changing one recompiles).

    Attributes:
        n_balls: N.
        n_patches: P, number of wall patches returned by ``wall_fn`` (each its own contact).
        dt_dem: solver step (s).
        dtype: "float64" or "float32" for positions, velocities and forces.
        clip_attractive: clip attractive normal forces to zero (off by default;
            docs/conventions.md section 3).
        pair_mode: how ball-ball contacts are formed:
            "nxn" (dense N x N arrays, every pair computed from both sides, per-ball sums by
            reductions; no gathers or scatters: the fast path for small N),
            "pairs" (static list of all N(N-1)/2 pairs i < j, gathers + one scatter-add),
            "neighbour" (Verlet list: the pairs whose surface gap is below ``neighbour_skin``,
            in a list of fixed capacity with a sticky overflow flag, rebuilt when a ball has
            moved more than half the skin since the last build; histories are carried over
            by pair key) or "auto" (= "neighbour").
        neighbour_capacity: capacity of the Verlet list in pairs per ball: the list holds
            ceil(neighbour_capacity * N / 2) pairs (at most all N(N-1)/2).
        neighbour_skin: m, surface gap within which a pair enters the Verlet list.
        contact_law: the contact law (:mod:`sgn_jax.dem.laws`), an object or a registered
            name (resolved here to the object); default Hertz-Mindlin. ``DEMParams.pp`` and
            ``pw`` must be this law's parameters (``make_params(..., contact_law=)``).
        collision_capacity: 0 (the default): no collision ledger. > 0: the state carries a
            collision ledger (:mod:`sgn_jax.dem.collisions`) whose buffer holds this many
            closed contacts between two emptyings by the host (pair modes "pairs" and
            "neighbour").
        cell_grid: None (the default): the Verlet list is rebuilt from all N(N-1)/2 pairs,
            the faster search below a few hundred balls. A :class:`sgn_jax.dem.cells.CellGrid`:
            from a cell list whose cost grows with N (the same list; neighbour mode only; a
            cell holding more balls than its capacity sets the list's overflow flag).
        cell_lower: m, (3,) jar-frame corner of the cell grid (it moves with the jar's offset).
    """

    n_balls: int
    n_patches: int
    dt_dem: float
    dtype: str = "float64"
    clip_attractive: bool = False
    pair_mode: str = "auto"
    neighbour_capacity: int = 8
    neighbour_skin: float = 0.001
    contact_law: Any = HERTZ_MINDLIN
    collision_capacity: int = 0
    cell_grid: Any = None
    cell_lower: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        try:
            object.__setattr__(self, "contact_law", resolve_contact_law(self.contact_law))
        except ContactLawError as exc:
            raise DEMError(str(exc)) from None
        if self.n_balls < 1:
            raise DEMError(f"n_balls must be >= 1, got {self.n_balls}")
        if self.n_patches < 1:
            raise DEMError(f"n_patches must be >= 1 (a wall function is required), got "
                           f"{self.n_patches}")
        if not self.dt_dem > 0:
            raise DEMError(f"dt_dem must be > 0, got {self.dt_dem}")
        if self.dtype not in ("float64", "float32"):
            raise DEMError(f"dtype must be 'float64' or 'float32', got {self.dtype!r}")
        if self.pair_mode not in PAIR_MODES:
            raise DEMError(f"pair_mode must be one of {PAIR_MODES}, got {self.pair_mode!r}")
        if self.neighbour_capacity < 1 or self.neighbour_skin < 0:
            raise DEMError("neighbour_capacity must be >= 1 and neighbour_skin >= 0")
        if self.collision_capacity < 0:
            raise DEMError(f"collision_capacity must be >= 0 (0: no collision ledger), got "
                           f"{self.collision_capacity}")
        if self.cell_grid is not None and self.resolved_pair_mode != "neighbour":
            raise DEMError(f"a cell grid serves pair_mode 'neighbour' (a Verlet list), not "
                           f"{self.pair_mode!r}")
        object.__setattr__(self, "cell_lower", tuple(float(x) for x in self.cell_lower))
        if self.collision_capacity and self.resolved_pair_mode == "nxn":
            raise DEMError("the collision ledger needs pair_mode 'neighbour' or 'pairs' (each "
                           "ball pair in one slot), not 'nxn'")

    @property
    def resolved_pair_mode(self) -> str:
        return "neighbour" if self.pair_mode == "auto" else self.pair_mode

    @property
    def n_pair_slots(self) -> int:
        """K, the number of ball-ball pair slots of the PairList (i < j)."""
        n = self.n_balls
        all_pairs = n * (n - 1) // 2
        if self.resolved_pair_mode in ("nxn", "pairs"):
            return all_pairs
        return max(1, min(all_pairs, math.ceil(self.neighbour_capacity * n / 2)))

    @property
    def jnp_dtype(self) -> Any:
        return jnp.dtype(self.dtype)


@flax.struct.dataclass
class DEMParams:
    """Everything numeric that a run depends on (vmappable).

    Two layouts (:mod:`sgn_jax.dem.charge` builds either from a charge):

    - identical balls (``ball_class`` None, the fast path): ``radius``, ``mass``, ``inertia``
      scalars, ``pp`` / ``pw`` the law's scalar parameters;
    - several ball classes (``ball_class`` (N,) int32): ``radius``, ``mass``, ``inertia`` (N,)
      per ball, every leaf of ``pp`` a (C, C) table over pairs of classes and of ``pw`` a
      (C,) table over classes, gathered per contact at every step.

    Attributes:
        radius: ball radius R (m).
        mass: ball mass m (kg).
        inertia: ball moment of inertia (2/5) m R^2 (kg m^2).
        pp: ball-ball contact-law parameters (for Hertz-Mindlin a ContactLaw).
        pw: ball-wall contact-law parameters.
        gravity: (3,) m/s^2.
        geometry: pytree given to ``wall_fn`` (JarParams, SDFGrid, test planes, ...).
        motion: pytree given to ``offset_fn`` / ``velocity_fn`` (a sgn_jax.motion Motion).
        ball_class: None, or (N,) int32 class of each ball (several classes).
    """

    radius: Any
    mass: Any
    inertia: Any
    pp: Any
    pw: Any
    gravity: Any
    geometry: Any
    motion: Any
    ball_class: Any = None

    @property
    def polydisperse(self) -> bool:
        """Several ball classes: per-ball radii and masses, per-class-pair contact tables."""
        return self.ball_class is not None


def _column(x: Any) -> Any:
    """A per-ball (N,) value as (N, 1), to broadcast against (N, 3) or (N, P); a scalar as is."""
    return x[:, None] if jnp.ndim(x) == 1 else x


def contact_law_per_slot(params: DEMParams, pairs: PairList | None) -> tuple[Any, Any]:
    """The contact law's parameters of every ball-ball slot and ball-wall contact: the scalar
    parameters themselves for identical balls, else gathered from the class-pair tables, (K,)
    per slot (``pairs`` None: the nxn layout, (N, N)) and (N, 1) per ball against the wall."""
    if not params.polydisperse:
        return params.pp, params.pw
    cls = params.ball_class
    if pairs is None:
        ci, cj = cls[:, None], cls[None, :]
    else:
        ci, cj = cls[pairs.i], cls[pairs.j]
    pp = jax.tree_util.tree_map(lambda t: jnp.asarray(t)[ci, cj], params.pp)
    pw = jax.tree_util.tree_map(lambda t: jnp.asarray(t)[cls][:, None], params.pw)
    return pp, pw


def make_params(
    radius: float,
    density: float,
    young: float,
    poisson: float,
    restitution: float,
    friction: float,
    rolling_friction: float,
    gravity: tuple[float, float, float],
    geometry: Any,
    motion: Any,
    contact_law: Any = HERTZ_MINDLIN,
) -> DEMParams:
    """DEMParams for identical balls of one material against walls of the same material.

    ``contact_law`` (an object or a registered name, default Hertz-Mindlin) builds ``pp`` and
    ``pw``; the DEMSpec the params are run with must name the same law.
    """
    try:
        law = resolve_contact_law(contact_law)
    except ContactLawError as exc:
        raise DEMError(str(exc)) from None
    mass = density * 4.0 / 3.0 * math.pi * radius**3
    common = dict(young=young, poisson=poisson, restitution=restitution, friction=friction,
                  rolling_friction=rolling_friction)
    return DEMParams(
        radius=float(radius),
        mass=float(mass),
        inertia=0.4 * mass * radius**2,
        pp=law.make_params(radius_1=radius, mass_1=mass, radius_2=radius, mass_2=mass, **common),
        pw=law.make_params(radius_1=radius, mass_1=mass, **common),
        gravity=jnp.asarray(gravity, dtype=jnp.float64),
        geometry=geometry,
        motion=motion,
    )


@flax.struct.dataclass
class EnergyLedger:
    """Cumulative energy bookkeeping (float64, J).

    Attributes:
        diss_pp: (5,) dissipated in ball-ball contacts, by kind ``DISSIPATION_KINDS``.
        diss_pw: (5,) the same for ball-wall contacts.
        work_wall: work done by the moving wall on the balls, sum F_wall_on_ball . d offset.
        spring_pp: tangential spring energy stored in ball-ball contacts now.
        spring_pw: the same in ball-wall contacts.
    """

    diss_pp: jnp.ndarray
    diss_pw: jnp.ndarray
    work_wall: jnp.ndarray
    spring_pp: jnp.ndarray
    spring_pw: jnp.ndarray


@flax.struct.dataclass
class PairList:
    """Ball-ball contact slots; each slot carries one tangential history.

    Attributes:
        i, j: (K,) int32 ball indices, i < j for a valid slot (0, 0 for an empty slot).
        valid: (K,) bool.
        ref_pos: (N,3) positions at the last rebuild (neighbour mode).
        overflow: () bool, sticky: more candidate pairs than slots at some rebuild, or a cell
            of the cell list fuller than its capacity (pairs were dropped: the run is
            invalid; raise ``neighbour_capacity``).
        rebuilds: () int32, number of rebuilds so far.
        max_candidates: () int32, the largest candidate count seen at a rebuild.
    """

    i: jnp.ndarray
    j: jnp.ndarray
    valid: jnp.ndarray
    ref_pos: jnp.ndarray
    overflow: jnp.ndarray
    rebuilds: jnp.ndarray
    max_candidates: jnp.ndarray


@flax.struct.dataclass
class DEMState:
    """Dynamic state of one DEM system.

    Attributes:
        pos, vel, omega: (N,3) m, m/s, rad/s (lab frame).
        pp_history: m, tangential displacement per ball-ball slot: (N,N,3) in "nxn" mode
            (entry [i,j] seen from ball i; [j,i] = -[i,j]), (K,3) otherwise.
        pw_history: (N,P,3) m tangential displacement per (ball, wall patch).
        offset: (3,) m, jar offset at the current step (float64).
        step: () int64, DEM steps since the start of motion (negative while settling).
        pairs: the ball-ball slots.
        ledger: the energy ledger.
        collisions: the collision ledger (:mod:`sgn_jax.dem.collisions`), None unless
            ``spec.collision_capacity`` > 0.
    """

    pos: jnp.ndarray
    vel: jnp.ndarray
    omega: jnp.ndarray
    pp_history: jnp.ndarray
    pw_history: jnp.ndarray
    offset: jnp.ndarray
    step: jnp.ndarray
    pairs: PairList
    ledger: EnergyLedger
    collisions: Any = None


def zero_ledger() -> EnergyLedger:
    z = jnp.zeros((), jnp.float64)
    return EnergyLedger(diss_pp=jnp.zeros(5, jnp.float64), diss_pw=jnp.zeros(5, jnp.float64),
                        work_wall=z, spring_pp=z, spring_pw=z)


def reset_ledger_totals(state: DEMState) -> DEMState:
    """Zero the cumulative dissipation and wall work (keeps the stored spring energies); the
    collision ledger, if any, starts its recorded window here too
    (:func:`sgn_jax.dem.collisions.restart_window`)."""
    led = state.ledger
    state = state.replace(ledger=led.replace(diss_pp=jnp.zeros_like(led.diss_pp),
                                             diss_pw=jnp.zeros_like(led.diss_pw),
                                             work_wall=jnp.zeros_like(led.work_wall)))
    if state.collisions is not None:
        state = state.replace(collisions=coll.restart_window(state.collisions))
    return state


def pp_history_shape(spec: DEMSpec) -> tuple[int, ...]:
    if spec.resolved_pair_mode == "nxn":
        return (spec.n_balls, spec.n_balls, 3)
    return (spec.n_pair_slots, 3)


def dense_pair_indices(n_balls: int) -> tuple[np.ndarray, np.ndarray]:
    """Static (i, j) index lists of all pairs i < j, each (N(N-1)/2,) int32."""
    i, j = np.triu_indices(n_balls, k=1)
    return i.astype(np.int32), j.astype(np.int32)


# --------------------------------------------------------------------------------------------
# Verlet list (fixed capacity, overflow flag)


def _build_verlet_list(spec: DEMSpec, radius: Any, pos: jnp.ndarray, offset: jnp.ndarray
                       ) -> tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray, jnp.ndarray,
                                  jnp.ndarray]:
    """Pairs i < j with surface gap < skin, in triangular order: (i, j, valid, count,
    cell_overflow); from the cell list of ``spec.cell_grid`` (its corner at the jar's
    ``offset`` + ``spec.cell_lower``) or from all pairs (``cell_overflow`` False)."""
    if spec.cell_grid is not None:
        origin = offset.astype(pos.dtype) + jnp.asarray(spec.cell_lower, pos.dtype)
        return build_pairs_cells(spec.cell_grid, spec.n_pair_slots, pos, radius,
                                 spec.neighbour_skin, origin)
    no_cell_overflow = jnp.zeros((), bool)
    iu, ju = dense_pair_indices(spec.n_balls)
    if len(iu) == 0:  # a single ball: one empty slot
        zero = jnp.zeros(spec.n_pair_slots, jnp.int32)
        return (zero, zero, jnp.zeros(spec.n_pair_slots, bool), jnp.zeros((), jnp.int32),
                no_cell_overflow)
    d = pos[ju] - pos[iu]
    dist_sq = jnp.sum(d * d, axis=-1)
    if jnp.ndim(radius) == 1:  # per-ball radii: the pair's own cutoff
        cutoff = radius[iu] + radius[ju] + spec.neighbour_skin
    else:
        cutoff = 2 * radius + spec.neighbour_skin
    candidate = dist_sq < cutoff * cutoff
    count = jnp.sum(candidate, dtype=jnp.int32)
    (slots,) = jnp.nonzero(candidate, size=spec.n_pair_slots, fill_value=0)
    valid = jnp.arange(spec.n_pair_slots) < count
    i = jnp.where(valid, jnp.asarray(iu)[slots], 0)
    j = jnp.where(valid, jnp.asarray(ju)[slots], 0)
    return i.astype(jnp.int32), j.astype(jnp.int32), valid, count, no_cell_overflow


def _pair_keys(spec: DEMSpec, i: jnp.ndarray, j: jnp.ndarray, valid: jnp.ndarray) -> jnp.ndarray:
    """i * N + j for valid slots, a sentinel larger than every key otherwise (sorted lists)."""
    n = spec.n_balls
    return jnp.where(valid, i.astype(jnp.int64) * n + j, n * n)


def _rebuild_pairs(spec: DEMSpec, radius: Any, pos: jnp.ndarray, offset: jnp.ndarray,
                   parts: tuple) -> tuple:
    """Rebuild the Verlet list and carry each surviving pair's history (and the event in
    progress of the collision ledger, if any) to its new slot.

    ``parts`` = ``(pairs, pp_history, pp_track)`` (``pp_track`` None without a ledger): only
    what a rebuild changes goes through its ``lax.cond``, whose operands XLA copies."""
    old, old_history, track = parts
    i, j, valid, count, cell_overflow = _build_verlet_list(spec, radius, pos, offset)
    # Both lists are sorted by key (triangular order, sentinels last): match by binary search.
    old_keys = _pair_keys(spec, old.i, old.j, old.valid)
    new_keys = _pair_keys(spec, i, j, valid)
    where = jnp.clip(jnp.searchsorted(old_keys, new_keys), 0, old_keys.shape[0] - 1)
    found = valid & (old_keys[where] == new_keys)
    history = jnp.where(found[:, None], old_history[where], 0.0)
    pairs = PairList(i=i, j=j, valid=valid, ref_pos=pos,
                     overflow=old.overflow | (count > spec.n_pair_slots) | cell_overflow,
                     rebuilds=old.rebuilds + 1,
                     max_candidates=jnp.maximum(old.max_candidates, count))
    if track is not None:
        track = coll.carry_pp_track(track, where, found)
    return pairs, history, track


def init_pairs(spec: DEMSpec, params: DEMParams, pos: jnp.ndarray, offset: jnp.ndarray
               ) -> PairList:
    """The initial pair list (nxn, pairs: all i < j; neighbour: Verlet list of ``pos``, the
    jar at ``offset``)."""
    n = spec.n_balls
    zero = jnp.zeros((), jnp.int32)
    if spec.resolved_pair_mode in ("nxn", "pairs"):
        i, j = dense_pair_indices(n)
        return PairList(i=jnp.asarray(i), j=jnp.asarray(j), valid=jnp.ones(len(i), bool),
                        ref_pos=pos, overflow=jnp.zeros((), bool), rebuilds=zero,
                        max_candidates=jnp.asarray(len(i), jnp.int32))
    i, j, valid, count, cell_overflow = _build_verlet_list(
        spec, jnp.asarray(params.radius, pos.dtype), pos, offset)
    return PairList(i=i, j=j, valid=valid, ref_pos=pos,
                    overflow=(count > spec.n_pair_slots) | cell_overflow,
                    rebuilds=zero, max_candidates=count)


_init_pairs_jit = jax.jit(init_pairs, static_argnums=0)


def init_state(
    spec: DEMSpec,
    params: DEMParams,
    pos: Any,
    vel: Any = None,
    omega: Any = None,
    step: int = 0,
    offset_fn: MotionFn | None = None,
) -> DEMState:
    """A fresh state (no contact histories) at DEM step ``step`` (negative: settling)."""
    if offset_fn is None:
        offset_fn = motion_mod.offset
    dtype = spec.jnp_dtype
    pos = jnp.asarray(pos, dtype=dtype)
    if pos.shape != (spec.n_balls, 3):
        raise DEMError(f"pos must have shape ({spec.n_balls}, 3), got {pos.shape}")
    vel = jnp.zeros_like(pos) if vel is None else jnp.asarray(vel, dtype=dtype)
    omega = jnp.zeros_like(pos) if omega is None else jnp.asarray(omega, dtype=dtype)
    # Jitted, as one program each: op by op, the pair list and the motion's offset cost ~60
    # small compilations (~2 s) at the start of every process that runs the DEM.
    t = max(step, 0) * spec.dt_dem
    offset = jnp.asarray(jax.jit(offset_fn)(params.motion, jnp.asarray(t, jnp.float64)),
                         jnp.float64)
    pairs = _init_pairs_jit(spec, params, pos, offset)
    return DEMState(
        pos=pos, vel=vel, omega=omega,
        pp_history=jnp.zeros(pp_history_shape(spec), dtype),
        pw_history=jnp.zeros((spec.n_balls, spec.n_patches, 3), dtype),
        offset=offset,
        step=jnp.asarray(step, jnp.int64),
        pairs=pairs,
        ledger=zero_ledger(),
        collisions=(coll.empty_ledger(spec.n_pair_slots, spec.n_balls, spec.collision_capacity)
                    if spec.collision_capacity else None),
    )


# --------------------------------------------------------------------------------------------
# Contact geometry


class _PairGeometry(NamedTuple):
    overlap: jnp.ndarray  # (K,)
    normal: jnp.ndarray  # (K,3) from i to j
    arm: jnp.ndarray  # (K,) distance from i's centre to the contact point
    arm_j: jnp.ndarray  # (K,) the same from j's centre (= arm for two equal balls)


def _pair_geometry(radius_i: Any, radius_j: Any, xi: jnp.ndarray, xj: jnp.ndarray,
                   valid: Any) -> _PairGeometry:
    """Overlap, unit normal i -> j and contact arms; xi, xj broadcast to (..., 3), the radii
    to their leading shape. The contact point is the middle of the overlap, R_i - d/2 from
    i's centre and R_j - d/2 from j's."""
    r = xj - xi
    dist_sq = jnp.sum(r * r, axis=-1)
    ok = dist_sq > 0
    dist = jnp.sqrt(jnp.where(ok, dist_sq, 1.0))
    normal = r / dist[..., None]
    overlap = jnp.where(ok & valid, radius_i + radius_j - dist, -1.0)
    half = 0.5 * jnp.maximum(overlap, 0.0)
    return _PairGeometry(overlap=overlap, normal=normal, arm=radius_i - half,
                         arm_j=radius_j - half)


def _slot_radii(radius: Any, pairs: PairList | None) -> tuple[Any, Any]:
    """(R_i, R_j) of every slot: per-ball radii gathered (pairs None: the nxn layout (N,1),
    (1,N)), a scalar radius as is."""
    if jnp.ndim(radius) == 0:
        return radius, radius
    if pairs is None:
        return radius[:, None], radius[None, :]
    return radius[pairs.i], radius[pairs.j]


def _wall_geometry(wall_fn: WallFn, geometry: Any, radius: Any, pos: jnp.ndarray,
                   offset: jnp.ndarray) -> _PairGeometry:
    x_jar = pos - offset.astype(pos.dtype)
    phi, normal = wall_fn(geometry, x_jar)
    radius = _column(radius)
    overlap = radius + phi.astype(pos.dtype)
    arm = radius - 0.5 * jnp.maximum(overlap, 0.0)
    return _PairGeometry(overlap=overlap, normal=normal.astype(pos.dtype), arm=arm, arm_j=arm)


def _default_motion_fns(offset_fn: MotionFn | None, velocity_fn: MotionFn | None
                        ) -> tuple[MotionFn, MotionFn]:
    return (offset_fn or motion_mod.offset), (velocity_fn or motion_mod.velocity)


# --------------------------------------------------------------------------------------------
# The step


def make_dem_step(
    spec: DEMSpec,
    wall_fn: WallFn,
    offset_fn: MotionFn | None = None,
    velocity_fn: MotionFn | None = None,
) -> Callable[[DEMParams, DEMState], DEMState]:
    """Build the jittable DEM step ``step(params, state) -> state`` (one dt_dem).

    Args:
        spec: static settings.
        wall_fn: ``wall_fn(params.geometry, x_jar (N,3)) -> (phi (N,P), normal (N,P,3))``, each
            patch its own SDF (negative inside the cavity) and unit normal towards the wall.
        offset_fn, velocity_fn: ``f(params.motion, t) -> (3,)``; default sgn_jax.motion.
    """
    offset_fn, velocity_fn = _default_motion_fns(offset_fn, velocity_fn)
    law = spec.contact_law
    n = spec.n_balls
    dt = spec.dt_dem
    dtype = spec.jnp_dtype
    mode = spec.resolved_pair_mode
    if mode == "nxn":
        off_diagonal = jnp.asarray(~np.eye(n, dtype=bool))
    # Every nxn pair is computed from both sides: its energies are counted twice.
    pair_weight = 0.5 if mode == "nxn" else 1.0

    def jar_kinematics(params: DEMParams, step: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
        """Jar offset at step+1 and jar velocity at step (zero while settling)."""
        t_now = jnp.maximum(step, 0).astype(jnp.float64) * dt
        t_next = jnp.maximum(step + 1, 0).astype(jnp.float64) * dt
        offset_next = offset_fn(params.motion, t_next).astype(jnp.float64)
        vel_now = jnp.where(step >= 0, velocity_fn(params.motion, t_now), 0.0)
        return offset_next, vel_now.astype(dtype)

    def pair_geometry(radius: Any, pos: jnp.ndarray, pairs: PairList) -> _PairGeometry:
        if mode == "nxn":
            r_i, r_j = _slot_radii(radius, None)
            return _pair_geometry(r_i, r_j, pos[:, None, :], pos[None, :, :], off_diagonal)
        r_i, r_j = _slot_radii(radius, pairs)
        return _pair_geometry(r_i, r_j, pos[pairs.i], pos[pairs.j], pairs.valid)

    def relative_kinematics(vel: jnp.ndarray, omega: jnp.ndarray, geo: _PairGeometry,
                            pairs: PairList, poly: bool) -> tuple[jnp.ndarray, jnp.ndarray]:
        """Contact-point velocity of i relative to j, and omega_i - omega_j, per slot."""
        if mode == "nxn":
            vi, vj, wi, wj = vel[:, None], vel[None, :], omega[:, None], omega[None, :]
        else:
            vi, vj, wi, wj = vel[pairs.i], vel[pairs.j], omega[pairs.i], omega[pairs.j]
        # The contact point is a_i n from i's centre and -a_j n from j's:
        # w_i x (a_i n) - w_j x (-a_j n) = (a_i w_i + a_j w_j) x n; for equal balls a_i = a_j.
        if poly:
            spin = geo.arm[..., None] * wi + geo.arm_j[..., None] * wj
            return vi - vj + jnp.cross(spin, geo.normal), wi - wj
        return vi - vj + jnp.cross(wi + wj, geo.arm[..., None] * geo.normal), wi - wj

    def per_ball(force: jnp.ndarray, torque_tangential: jnp.ndarray,
                 torque_rolling: jnp.ndarray, pairs: PairList, arm_ratio: Any = None
                 ) -> tuple[jnp.ndarray, jnp.ndarray]:
        """Per-ball force and torque from per-slot values on i (the reaction goes to j);
        ``arm_ratio`` (K,) a_j / a_i of unequal balls (None: equal)."""
        if mode == "nxn":  # slot [i, j] already holds the value on i
            return (jnp.sum(force, axis=1),
                    jnp.sum(torque_tangential + torque_rolling, axis=1))
        # One scatter-add for everything (three separate ones cost 4x as much on CPU). Ball j
        # gets -F, the tangential torque (a_j n) x F_t (its arm and force both flip, its arm
        # a_j long) and -tau_r.
        torque_j = (torque_tangential if arm_ratio is None
                    else arm_ratio[..., None] * torque_tangential)
        on_i = jnp.concatenate([force, torque_tangential + torque_rolling], axis=-1)
        on_j = jnp.concatenate([-force, torque_j - torque_rolling], axis=-1)
        index = jnp.concatenate([pairs.i, pairs.j])
        total = jnp.zeros((n, 6), force.dtype).at[index].add(jnp.concatenate([on_i, on_j]))
        return total[:, :3], total[:, 3:]

    def step(params: DEMParams, state: DEMState) -> DEMState:
        if mode == "neighbour":
            moved = jnp.max(jnp.sum((state.pos - state.pairs.ref_pos) ** 2, axis=-1))
            track = None if state.collisions is None else state.collisions.track
            pairs, history, track = jax.lax.cond(
                moved > (0.5 * spec.neighbour_skin) ** 2,
                lambda parts: _rebuild_pairs(spec, params.radius, state.pos, state.offset,
                                             parts),
                lambda parts: parts, (state.pairs, state.pp_history, track))
            state = state.replace(pairs=pairs, pp_history=history)
            if track is not None:
                state = state.replace(collisions=state.collisions.replace(track=track))
        pos, vel, omega = state.pos, state.vel, state.omega
        radius = jnp.asarray(params.radius, dtype)
        pairs = state.pairs
        poly = params.polydisperse
        law_pp, law_pw = contact_law_per_slot(params, None if mode == "nxn" else pairs)
        offset_next, v_wall = jar_kinematics(params, state.step)

        # Ball-ball contacts.
        pp = pair_geometry(radius, pos, pairs)
        v_rel, omega_rel = relative_kinematics(vel, omega, pp, pairs, poly)
        f_pp = law.forces(law_pp, pp.overlap, pp.normal, pp.arm, v_rel, omega_rel,
                          state.pp_history, dt, spec.clip_attractive)
        arm_ratio = None if not poly else pp.arm_j / pp.arm
        if poly and getattr(law, "rolling_uses_arm", True):
            # Unequal balls: the law's rolling torque used i's arm; the pair's rolling radius
            # is the harmonic mean of both arms (the arm itself for equal balls), so that the
            # torque is the same seen from either ball.
            f_pp = f_pp._replace(torque_rolling=f_pp.torque_rolling
                                 * (2.0 * arm_ratio / (1.0 + arm_ratio))[..., None])

        # Ball-wall contacts, one per (ball, patch).
        pw = _wall_geometry(wall_fn, params.geometry, radius, pos, state.offset)
        arm_w = pw.arm[..., None] * pw.normal
        v_rel_w = vel[:, None, :] + jnp.cross(omega[:, None, :], arm_w) - v_wall
        omega_rel_w = jnp.broadcast_to(omega[:, None, :], arm_w.shape)
        f_pw = law.forces(law_pw, pw.overlap, pw.normal, pw.arm, v_rel_w, omega_rel_w,
                          state.pw_history, dt, spec.clip_attractive)

        force, torque = per_ball(f_pp.force, f_pp.torque_tangential, f_pp.torque_rolling,
                                 pairs, arm_ratio)
        force = force + jnp.sum(f_pw.force, axis=1)
        torque = torque + jnp.sum(f_pw.torque_tangential + f_pw.torque_rolling, axis=1)

        gravity = jnp.asarray(params.gravity, dtype)
        mass = _column(jnp.asarray(params.mass, dtype))
        inertia = _column(jnp.asarray(params.inertia, dtype))
        vel_new = vel + dt * (force / mass + gravity)
        omega_new = omega + dt * (torque / inertia)
        pos_new = pos + dt * vel_new

        # Energy ledger, with the mean velocities of the step (see module docstring).
        vel_mid = 0.5 * (vel + vel_new)
        omega_mid = 0.5 * (omega + omega_new)
        d_offset = offset_next - state.offset
        v_wall_mid = (d_offset / dt).astype(dtype)
        v_rel_mid, omega_rel_mid = relative_kinematics(vel_mid, omega_mid, pp, pairs, poly)
        d_pp = law.dissipation(f_pp, pp.normal, v_rel_mid, omega_rel_mid, dt)
        v_rel_w_mid = vel_mid[:, None, :] + jnp.cross(omega_mid[:, None, :], arm_w) - v_wall_mid
        omega_rel_w_mid = jnp.broadcast_to(omega_mid[:, None, :], arm_w.shape)
        d_pw = law.dissipation(f_pw, pw.normal, v_rel_w_mid, omega_rel_w_mid, dt)

        led = state.ledger
        f64 = jnp.float64

        def total(x: jnp.ndarray, weight: float = 1.0) -> jnp.ndarray:
            return weight * jnp.sum(x, dtype=f64)

        w = pair_weight
        spring_pp = total(f_pp.spring_energy, w)
        spring_pw = total(f_pw.spring_energy)
        inc_pp = jnp.stack([total(d_pp.normal, w), total(d_pp.tangential, w),
                            total(d_pp.slip, w), total(d_pp.rolling, w),
                            led.spring_pp - total(f_pp.spring_energy_old_now, w)])
        inc_pw = jnp.stack([total(d_pw.normal), total(d_pw.tangential), total(d_pw.slip),
                            total(d_pw.rolling),
                            led.spring_pw - total(f_pw.spring_energy_old_now)])
        wall_force = jnp.sum(f_pw.force, axis=(0, 1)).astype(f64)
        ledger = EnergyLedger(
            diss_pp=led.diss_pp + inc_pp,
            diss_pw=led.diss_pw + inc_pw,
            work_wall=led.work_wall + jnp.dot(wall_force, d_offset),
            spring_pp=spring_pp,
            spring_pw=spring_pw,
        )
        collisions = state.collisions
        if collisions is not None:
            collisions = track_collisions(collisions, state.step, pairs, pp, f_pp, d_pp, v_rel,
                                          pw, f_pw, d_pw, v_rel_w)
        return state.replace(
            pos=pos_new, vel=vel_new, omega=omega_new,
            pp_history=f_pp.history, pw_history=f_pw.history,
            offset=offset_next, step=state.step + 1, ledger=ledger, collisions=collisions,
        )

    balls = jnp.arange(n)

    def track_collisions(collisions: Any, step_now: jnp.ndarray, pairs: PairList,
                         pp: _PairGeometry, f_pp: Any, d_pp: Any, v_rel: jnp.ndarray,
                         pw: _PairGeometry, f_pw: Any, d_pw: Any, v_rel_w: jnp.ndarray) -> Any:
        """The collision ledger after this step: each contact's terms of the energy ledger added
        to its event, the events of contacts that opened written to the buffer.

        A ball's contact with the jar is one event whatever wall patches it touches (a ball
        rolling across the seam of two patches stays in one contact): its terms are the sums
        over the patches, its overlap the deepest, its speeds and its patch (the event's
        ``partner``) those of the deepest patch."""
        def speeds(v: jnp.ndarray, normal: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
            v_n = jnp.sum(v * normal, axis=-1)
            return v_n, jnp.maximum(jnp.sum(v * v, axis=-1) - v_n * v_n, 0.0)

        v_n, v_t = speeds(v_rel, pp.normal)
        deepest_patch = jnp.argmax(pw.overlap, axis=1)                      # (N,)
        deepest = jax.nn.one_hot(deepest_patch, spec.n_patches, dtype=pw.overlap.dtype)
        v_n_w, v_t_w = speeds(v_rel_w, pw.normal)

        def both(x_pp: jnp.ndarray, x_pw: jnp.ndarray, reduce: Any = jnp.sum) -> jnp.ndarray:
            """(K + N,) the ball-ball slots' values, then each ball's over its wall patches."""
            return jnp.concatenate([x_pp, reduce(x_pw, axis=1)])

        track, started, ended = coll.update_track(
            collisions.track, step_now, both(f_pp.in_contact, f_pw.in_contact, jnp.any),
            both(pp.overlap, pw.overlap, jnp.max), both(f_pp.normal_total, f_pw.normal_total),
            both(v_n, deepest * v_n_w), both(v_t, deepest * v_t_w),
            tuple(both(getattr(d_pp, k), getattr(d_pw, k))
                  for k in ("normal", "tangential", "slip", "rolling")),
            both(f_pp.spring_energy_old_now, f_pw.spring_energy_old_now),
            both(f_pp.spring_energy, f_pw.spring_energy))
        n_pp = pairs.i.shape[0]
        patch = jnp.where(started[n_pp:], deepest_patch.astype(jnp.int32), collisions.wall_patch)
        ledger = coll.CollisionLedger(track=track, wall_patch=patch, buffer=collisions.buffer)

        def rows() -> tuple[jnp.ndarray, jnp.ndarray]:
            # From the new values only (a slot that ended this step kept its start and its
            # patch), so that the step needs no copy of the old ones.
            ints = jnp.concatenate([
                coll.event_ints(pairs.i, pairs.j, False, ledger.pp, step_now),
                coll.event_ints(balls, patch, True, ledger.pw, step_now)])
            return ints, track.values

        return ledger.replace(buffer=coll.write_events(collisions.buffer, (ended,), rows))

    return step


# --------------------------------------------------------------------------------------------
# Observables


class Contacts(NamedTuple):
    pp_overlap: jnp.ndarray  # (K,)
    pw_overlap: jnp.ndarray  # (N,P)


def contact_overlaps(spec: DEMSpec, wall_fn: WallFn, params: DEMParams, state: DEMState
                     ) -> Contacts:
    """Overlaps (m, > 0 in contact) of every ball-ball slot and every (ball, patch) now."""
    radius = jnp.asarray(params.radius, spec.jnp_dtype)
    pairs = state.pairs
    r_i, r_j = _slot_radii(radius, pairs)
    pp = _pair_geometry(r_i, r_j, state.pos[pairs.i], state.pos[pairs.j], pairs.valid)
    pw = _wall_geometry(wall_fn, params.geometry, radius, state.pos, state.offset)
    return Contacts(pp_overlap=pp.overlap, pw_overlap=pw.overlap)


def energies(spec: DEMSpec, wall_fn: WallFn, params: DEMParams, state: DEMState
             ) -> dict[str, jnp.ndarray]:
    """Energies of the state (J, float64): ke_trans, ke_rot, pe_grav, e_elastic.

    ``pe_grav = -sum m g . x`` (= m |g| y for g along -y); ``e_elastic`` is the normal spring
    energy of every overlap now (``spec.contact_law.elastic_energy``; Hertz by default) plus the
    tangential spring energy stored in the ledger.
    """
    f64 = jnp.float64
    vel = state.vel.astype(f64)
    omega = state.omega.astype(f64)
    pos = state.pos.astype(f64)
    height = pos @ jnp.asarray(params.gravity, f64)
    if params.polydisperse:
        mass = jnp.asarray(params.mass, f64)
        inertia = jnp.asarray(params.inertia, f64)
        ke_trans = 0.5 * jnp.sum(mass[:, None] * vel * vel)
        ke_rot = 0.5 * jnp.sum(inertia[:, None] * omega * omega)
        pe = -jnp.sum(mass * height)
    else:
        ke_trans = 0.5 * params.mass * jnp.sum(vel * vel)
        ke_rot = 0.5 * params.inertia * jnp.sum(omega * omega)
        pe = -params.mass * jnp.sum(height)
    ov = contact_overlaps(spec, wall_fn, params, state)
    law = spec.contact_law
    law_pp, law_pw = contact_law_per_slot(params, state.pairs)
    e_el = (jnp.sum(law.elastic_energy(law_pp, ov.pp_overlap.astype(f64)))
            + jnp.sum(law.elastic_energy(law_pw, ov.pw_overlap.astype(f64)))
            + state.ledger.spring_pp + state.ledger.spring_pw)
    return {"ke_trans": ke_trans, "ke_rot": ke_rot, "pe_grav": pe, "e_elastic": e_el}


def ledger_balance(spec: DEMSpec, wall_fn: WallFn, params: DEMParams, state: DEMState
                   ) -> jnp.ndarray:
    """KE + PE + E_elastic + cumulative dissipation - cumulative wall work (J).

    Constant up to the integration error; its change over a run is the ledger residual.
    """
    e = energies(spec, wall_fn, params, state)
    led = state.ledger
    return (e["ke_trans"] + e["ke_rot"] + e["pe_grav"] + e["e_elastic"]
            + jnp.sum(led.diss_pp) + jnp.sum(led.diss_pw) - led.work_wall)


def observe(
    spec: DEMSpec,
    wall_fn: WallFn,
    params: DEMParams,
    state: DEMState,
    pp_capacity: int,
    velocity_fn: MotionFn | None = None,
) -> dict[str, jnp.ndarray]:
    """One sample of the dataset (docs/conventions.md section 4) from a state; cumulative ledger
    values.

    Returns pos, vel, omega (N,3); offset, offset_vel (3,); energies; the cumulative
    ``diss_pp`` / ``diss_pw`` (5,) and ``work_wall``; ``pp_pairs`` (pp_capacity, 2) int32
    padded with -1; ``pw_contact`` (N,) bool; ``n_pp_contacts`` () and ``pp_overflow`` ().
    """
    _, velocity_fn = _default_motion_fns(None, velocity_fn)
    ov = contact_overlaps(spec, wall_fn, params, state)
    touching = ov.pp_overlap > 0
    n_pp = jnp.sum(touching)
    (slots,) = jnp.nonzero(touching, size=pp_capacity, fill_value=-1)
    have = slots >= 0
    pp_pairs = jnp.where(have[:, None],
                         jnp.stack([state.pairs.i[slots], state.pairs.j[slots]], axis=-1), -1)
    t = jnp.maximum(state.step, 0).astype(jnp.float64) * spec.dt_dem
    offset_vel = jnp.where(state.step >= 0, velocity_fn(params.motion, t), 0.0)
    out = {
        "pos": state.pos.astype(jnp.float64),
        "vel": state.vel.astype(jnp.float64),
        "omega": state.omega.astype(jnp.float64),
        "offset": state.offset,
        "offset_vel": offset_vel.astype(jnp.float64),
        "diss_pp": state.ledger.diss_pp,
        "diss_pw": state.ledger.diss_pw,
        "work_wall": state.ledger.work_wall,
        "pp_pairs": pp_pairs.astype(jnp.int32),
        "pw_contact": jnp.any(ov.pw_overlap > 0, axis=-1),
        "n_pp_contacts": n_pp.astype(jnp.int32),
        "pp_overflow": (n_pp > pp_capacity) | state.pairs.overflow,
    }
    out.update(energies(spec, wall_fn, params, state))
    return out


def make_sampler(
    spec: DEMSpec,
    wall_fn: WallFn,
    substeps: int,
    pp_capacity: int,
    offset_fn: MotionFn | None = None,
    velocity_fn: MotionFn | None = None,
) -> Callable[[DEMParams, DEMState, int], tuple[DEMState, dict[str, jnp.ndarray]]]:
    """``run(params, state, n_samples) -> (state, samples)``: n_samples x substeps DEM steps.

    A nested ``lax.scan`` (inner: ``substeps`` steps, outer: samples), jitted with
    ``n_samples`` static; ``samples`` holds :func:`observe` of the state after each inner loop
    (leading axis n_samples). No host synchronisation inside.
    """
    step = make_dem_step(spec, wall_fn, offset_fn, velocity_fn)

    def advance(params: DEMParams, state: DEMState, n_steps: int) -> DEMState:
        def body(s: DEMState, _: Any) -> tuple[DEMState, None]:
            return step(params, s), None

        return jax.lax.scan(body, state, None, length=n_steps)[0]

    def run(params: DEMParams, state: DEMState, n_samples: int
            ) -> tuple[DEMState, dict[str, jnp.ndarray]]:
        def outer(s: DEMState, _: Any) -> tuple[DEMState, dict[str, jnp.ndarray]]:
            s = advance(params, s, substeps)
            return s, observe(spec, wall_fn, params, s, pp_capacity, velocity_fn)

        return jax.lax.scan(outer, state, None, length=n_samples)

    return jax.jit(run, static_argnums=2)


def make_advance(
    spec: DEMSpec,
    wall_fn: WallFn,
    offset_fn: MotionFn | None = None,
    velocity_fn: MotionFn | None = None,
    unroll: int = 1,
) -> Callable[[DEMParams, DEMState, int], DEMState]:
    """``advance(params, state, n_steps) -> state``: a jitted ``lax.scan`` of n_steps steps."""
    step = make_dem_step(spec, wall_fn, offset_fn, velocity_fn)

    def advance(params: DEMParams, state: DEMState, n_steps: int) -> DEMState:
        def body(s: DEMState, _: Any) -> tuple[DEMState, None]:
            return step(params, s), None

        return jax.lax.scan(body, state, None, length=n_steps, unroll=unroll)[0]

    return jax.jit(advance, static_argnums=2)
