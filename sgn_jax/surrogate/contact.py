"""The contact-impulse surrogate (model kind "contact"): contact physics built in.

The SGN (:mod:`sgn_jax.surrogate.model`) maps raw displacement vectors, velocity histories and the jar's
global state through MLPs and must learn from data rotation invariance, Newton's third law,
that contacts repel, that the motion acts on the balls only through the walls they touch and
that dissipation adds up over contacts. This kind builds all of that in and learns only the
unknown part: the net contact impulse of one surrogate step as a function of a few invariant
scalars of each contact candidate (an edge of the same graph, :mod:`sgn_jax.surrogate.graph`).

One step (window ending at sample n, step ``dt``; N balls of mass m and radius R)::

    for each edge candidate c (ball-ball pair, or ball and its nearest wall):
        frame      unit normal n_c (ball-ball: along the centre line, from the receiver r to the
                   sender s; ball-wall: the SDF normal, from the ball towards the wall)
        inputs     invariant scalars (see ``edge_inputs``): surface gap at the last slots
                   (bounded transforms), the rate of change of the gap u = v_rel . n at the
                   last slots, the tangential relative speed |v_t|, for a wall the relative
                   acceleration along n; v_rel is the partner's velocity minus the ball's (for
                   a wall: the jar's velocity, which the motion gives exactly)
        outputs    du_n >= 0 (softplus, m/s: repulsive only), du_t = mu du_n tanh(.) (Coulomb
                   cone: |J_t| <= mu J_n), both zero unless contact is possible in this step
        impulse    J_r = m* (-du_n n + du_t t),  t = v_t / |v_t|  (m* = m/2 for a pair, m for a
                   wall); the sender ball gets -J_r (equal and opposite, exactly: each contact
                   is computed once, on the primary direction of its edge pair)
    v_{n+1} = v_n + sum_c J / m + g dt          (gravity exact, not learned)
    accel   = (v_{n+1} - v_n) / dt              (what the rollout integrates)

Dissipation is what the model's own impulses take out of the balls, with the midpoint
velocities ``vbar = (v_n + v_{n+1}) / 2`` of the integrator::

    D_pp = - sum over ball-ball contacts of J . (vbar_r - vbar_s)   (J on r, -J on s)
    D_pw =   sum over ball-wall edges of J_b . (u_wall - vbar_b)
    D_pp + D_pw = W_wall + W_grav - dKE       (exact identity; W_wall = sum J_b . u_wall,
                                               W_grav = sum m g . vbar dt)

so the surrogate's energy ledger closes by construction (tests/test_contact.py). Each term
belongs to one contact: a rollout with ``collisions=True`` gathers them into collision events
(:meth:`ContactNet.collision_terms`, :mod:`sgn_jax.surrogate.collisions`), whose energies add
up to ``D_pp + D_pw``. The paper's
target (normal + tangential damping, docs/conventions.md section 3) is reported as ``share_pp D_pp +
share_pw D_pw``; the two shares (the part of all losses that is damping, not slip or rolling) are
the only energy quantities fitted from data (``fit_dissipation_shares``), never a second energy.

Properties by construction (and tested): total ball-ball momentum conserved to rounding;
rotating the scene (positions, velocities, the jar and gravity) rotates the accelerations;
permuting the balls permutes them; normal impulses never attract; a ball resting on the floor
of a still jar or on another ball stays at rest once trained to (trained, not built in).

All computation in float32 on the raw graph (no normalisation statistics: the inputs are
scaled by fixed physical scales, so a deep overlap is a bounded input, not an out-of-range one).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import jraph
import numpy as np

from sgn_jax.dem.contact import head_on_impact, make_contact_law
from sgn_jax.errors import SGNJaxError
from sgn_jax.surrogate.collisions import contact_grid
from sgn_jax.surrogate.graph import SLOT_DIM, compact_edge_pairs, true_indices
from sgn_jax.surrogate.model import register_model

DTYPE = jnp.float32


class ContactModelError(SGNJaxError, ValueError):
    """The contact model's physics settings are inconsistent."""


# Fixed input scales (SI). A contact moves by at most a few m/s * dt = 0.1 mm per step.
GAP_SCALE_COARSE_M = 1.0e-4   # gap / 0.1 mm, clipped to [-1, 3]
GAP_SCALE_FINE_M = 5.0e-6     # tanh(gap / 5 um): resolves resting overlaps (0.5-5 um)
SPEED_SCALE_FINE = 1.0e-2     # tanh(u / 1 cm/s): resolves resting contacts (g dt = 1 mm/s)
IMPULSE_SCALE = 0.3           # du_n = IMPULSE_SCALE * softplus(out) (m/s)
TANGENT_EPS = 1.0e-4          # m/s: t = v_t / sqrt(|v_t|^2 + eps^2), smooth at |v_t| = 0
# A single rollout runs each MLP on a block of ceil(1.5 N) acting contacts per kind (see
# ContactNet.for_single_rollout; the standard case has at most 1.4 N).
SINGLE_ROLLOUT_ACTING_PER_BALL = 1.5
# ...and each step on a block of ceil(2 x 1.5 N) rows that may act, both kinds together
# (ContactNet.rollout_terms)
SINGLE_ROLLOUT_COMPACT_PER_BALL = 1.5


DAMPING_TARGETS: tuple[str, ...] = ("kind", "contact")
"""The dissipation targets of :class:`ContactPhysics` ``damping_target``."""

NO_REBOUND_RATE = -1.0e3      # m/s: the rebound rate of a contact the law rebound leaves alone
REBOUND_SWEEPS: tuple[str, ...] = ("off", "all", "free")
"""Which impacts past their contact time the overlap sweeps keep at the law's rebound with every
ball's other contacts acting (``ChargePhysics.rebound_sweeps``): none; all; or the ball-ball
impacts of two "free" balls, neither held by a contact closed over the whole window (resting
on, rolling on or pressed against the wall or another ball)."""
REBOUND_EXACT: tuple[str, ...] = ("off", "wall", "all", "fresh")
"""Where :class:`ContactPhysics` ``rebound_exact`` makes the law rebound the impulse's ceiling:
nowhere; at ball-wall contacts (a fresh impact ends at e v, a resting contact separates no
faster than e times the largest closing speed the ball's contacts saw in the window); at
every fresh impact; at every fresh impact and through it ("fresh": before its contact time
the step ends separating no faster than e times the largest closing speed its balls' acting
contacts saw in the window) (docs/contact.md, "One step", item 7)."""


def check_rebound_exact(rebound_exact: str, rebound_on: bool, rebound_name: str) -> None:
    """Refuse a ``rebound_exact`` not in :data:`REBOUND_EXACT`, or one other than "off"
    without the law rebound it makes exact (``rebound_name`` says how a kind turns it on)."""
    if rebound_exact not in REBOUND_EXACT:
        raise ContactModelError(f"rebound_exact must be one of {REBOUND_EXACT}, got "
                                f"{rebound_exact!r}")
    if rebound_exact != "off" and not rebound_on:
        raise ContactModelError(f"rebound_exact needs {rebound_name}")


@dataclasses.dataclass(frozen=True)
class ContactPhysics:
    """The known physics of the contact model (static, hashable).

    Attributes:
        ball_radius: R (m). ball_mass: m (kg). dt: the surrogate step (s).
        gravity: (gx, gy, gz) m/s^2. friction: Coulomb coefficient mu of the impulse cone.
        window: W, slots of the graph's windows. history: slots used as inputs (<= W).
        gate_margin: m; an edge acts only if its gap now or at the end of a ballistic step is
            below this (contact possible within the step); elsewhere its impulse is exactly 0.
        wall_patches: the graphs' ``GraphSpec.wall_patches`` (from the same config), or None.
            Known, a model with ``rows_by_kind`` runs each contact kind's MLP only on its own
            rows (the graph's layout: the ball-ball contacts first, then at most N max(1, P)
            ball-wall contacts), half the work of running both MLPs on every row; None runs
            both on every row (correct for any graph; what a hand-built physics gets).
        rolling_friction: mu_r of the config's material (EDEM type A, as the DEM): with spin
            state, each contact brakes its balls' relative rotation by an angular impulse of
            at most mu_r R J_n (J_n its normal impulse), never reversing it. Unused without spin.
        overlap_limit: m; 0 = off. The rigid limit of the contact law (``[model]
            overlap_limit``): each acting contact's normal impulse is at least the one that
            keeps its overlap at the end of the step within this depth, computed ballistically
            for the contact alone (gap + (u + relative acceleration dt + du_n) dt >= -limit).
            A learned impulse that lets a contact sink deeper is raised to that floor, equal and
            opposite as every impulse, and its work is in the ledger like any other.
        overlap_law_factor: c >= 0 (``[model] overlap_law_factor``; 0 = off): the limit grows
            with the contact's approach speed v (the largest closing rate over the history
            slots) as c times the DEM contact law's own deepest overlap at that speed,
            ``limit = max(overlap_limit, c * peak * v^0.8)`` (m, v in m/s): fast impacts may go
            as deep as the DEM's (scaled), slow ones no deeper than ``overlap_limit``.
        overlap_peak_pp, overlap_peak_pw: m, the DEM law's deepest overlap of a head-on impact
            at 1 m/s, ball-ball and ball-wall (:func:`sgn_jax.dem.contact.head_on_peak_overlap`;
            ``physics_from_config`` sets them from the config's material).
        rebound_time_pp, rebound_time_pw, restitution: the law rebound (``[model]
            law_rebound``; 0 = off; needs ``overlap_law_factor``): the DEM law's
            ``v t_c(v) / peak(v)`` (its head-on contact time at speed v over its peak,
            :func:`sgn_jax.dem.contact.head_on_contact_time`; 3.4 for e = 0.74, 5.1 for 0.3)
            and its restitution e. A fresh impact (a contact whose gap was open at a slot of
            the window) that began more than ``t_c(v) = ratio * peak * v^0.8 / v`` before the
            end of the step is over in the DEM, its balls separating at e v: its normal impulse
            is at least the one that ends the step separating at e v (docs/contact.md, "One
            step", item 7).
        rebound_exact: where the law rebound is the impulse's ceiling too (``[model]
            law_rebound_exact``): "off"; "all": at every fresh impact past its contact time,
            whose normal impulse is then exactly that floor, the network's answer unused;
            "wall": the same at ball-wall impacts, and a ball-wall contact closed over the
            whole window separates no faster than e times the largest closing speed the
            ball's contacts (this one, its ball-ball ones) saw in the window; "fresh": as
            "all", and before its contact time a fresh impact (ball-ball or ball-wall) ends
            the step separating no faster than e times the largest closing speed its balls'
            acting contacts saw in the window, so that no impact gives back more than its
            material's restitution leaves (docs/contact.md, "One step", item 7).
        overlap_sweeps: 0 = off (``[model] overlap_sweeps``; needs ``overlap_limit`` > 0). The
            floor above is computed for each contact alone; in a chain (a ball struck while it
            rests on others, a bed compressed by an impact) the impulses of a ball's other
            contacts push it deeper into this one. After the impulses, this many Jacobi sweeps
            over ALL contacts with every ball's end-of-step velocity: each contact whose
            overlap would end deeper than its limit gets the normal impulse that removes the
            excess, shared among the violated contacts of its balls (relaxed by their number,
            as one sweep of a projected Jacobi contact solver; equal and opposite, repulsive,
            in the ledger as every impulse).
        friction_sweeps: 0 = off (``[model] friction_sweeps``; a model with spin only). The
            learned friction is one relaxed stick per contact from the step's start; a ball in
            a packed bed has several contacts whose sticks fight, so the bed creeps where the
            DEM's (whose tangential springs hold it) stays put. After the impulses (and the
            overlap sweeps), this many projected Jacobi sweeps of Coulomb sticking over all
            acting contacts with every ball's end-of-step velocity and spin: each contact
            gets the tangential impulse that stops its contact point's slip, shared among the
            acting contacts of its balls, its total tangential impulse kept inside the cone
            ``mu du_n`` (equal and opposite, with its torque on both balls, in the ledger).
        damping_target: how the dissipation target (the DEM's damping, the paper's target)
            comes from the model's own losses (``[model] damping_target``;
            :data:`DAMPING_TARGETS`). ``"kind"``: a share of all losses per contact kind,
            ``share_logit`` = the DEM's damping share of all its losses
            (:func:`sgn_jax.surrogate.contact_train.dissipation_shares`). ``"contact"``: per
            contact, its normal part whole (the DEM's normal losses are all damping), its
            rolling friction's none, the rest by the kind's tangential damping share,
            ``share_logit`` = the DEM's tangential damping against its Coulomb slip
            (:func:`sgn_jax.surrogate.contact_train.tangential_damping_shares`); the share then
            follows the contact's own split, higher where impacts dominate (docs/contact.md).
    """

    ball_radius: float = 0.005
    ball_mass: float = 4.0317e-3
    dt: float = 1.0e-4
    gravity: tuple[float, float, float] = (0.0, -9.81, 0.0)
    friction: float = 0.3
    window: int = 7
    history: int = 3
    gate_margin: float = 5.0e-5
    wall_patches: int | None = None
    rolling_friction: float = 0.0
    overlap_limit: float = 0.0
    overlap_law_factor: float = 0.0
    overlap_peak_pp: float = 4.53e-5
    overlap_peak_pw: float = 5.21e-5
    rebound_time_pp: float = 0.0
    rebound_time_pw: float = 0.0
    restitution: float = 0.0
    overlap_sweeps: int = 0
    friction_sweeps: int = 0
    damping_target: str = "kind"
    rebound_exact: str = "off"

    @property
    def inertia(self) -> float:
        """A ball's moment of inertia (2/5) m R^2 (kg m^2)."""
        return 0.4 * self.ball_mass * self.ball_radius ** 2

    def __post_init__(self) -> None:
        if not 1 <= self.history <= self.window:
            raise ContactModelError(f"history must be in 1..window={self.window}, got {self.history}")
        if not (self.overlap_limit >= 0 and self.overlap_law_factor >= 0):
            raise ContactModelError(f"overlap_limit (m) and overlap_law_factor must be >= 0, got "
                                    f"{self.overlap_limit} and {self.overlap_law_factor}")
        if self.overlap_law_factor > 0 and self.overlap_limit <= 0:
            raise ContactModelError(
                "overlap_law_factor needs overlap_limit > 0: the law's overlap vanishes for a "
                "contact at rest, and a limit of 0 there would lift every resting ball")
        if self.overlap_sweeps < 0 or (self.overlap_sweeps > 0 and self.overlap_limit <= 0):
            raise ContactModelError(f"overlap_sweeps must be >= 0 and needs overlap_limit > 0, "
                                    f"got {self.overlap_sweeps} and {self.overlap_limit}")
        if self.rebound_time_pp and self.overlap_law_factor <= 0:
            raise ContactModelError("the law rebound (rebound_time_pp/pw > 0) needs the law's "
                                    "limit (overlap_law_factor > 0)")
        if self.friction_sweeps < 0:
            raise ContactModelError(f"friction_sweeps must be >= 0, got {self.friction_sweeps}")
        check_rebound_exact(self.rebound_exact, self.rebound_time_pp > 0,
                            "the law rebound (rebound_time_pp/pw > 0)")
        if self.damping_target not in DAMPING_TARGETS:
            raise ContactModelError(f"damping_target must be one of {DAMPING_TARGETS}, got "
                                    f"{self.damping_target!r}")


def _slot(features: jax.Array, k: int, cols: slice) -> jax.Array:
    return features[:, SLOT_DIM * k + cols.start: SLOT_DIM * k + cols.stop]


def edge_kinematics(graph: jraph.GraphsTuple, window: int, dt: float, pp_reach: Any,
                    pw_reach: Any, primary_only: bool = False) -> dict[str, jax.Array]:
    """The kinematics of every edge that do not depend on the model's physics: frames, gaps,
    gap rates and slip (what :func:`edge_geometry` and the charge-conditioned model,
    :mod:`sgn_jax.surrogate.contact_charge`, both build on).

    Args:
        window: W, the graph's slots. dt: s, the step.
        pp_reach: m, the contact distance of a ball-ball edge, 2 R (a float) or r_r + r_s per
            row (E,). pw_reach: m, the receiver ball's radius R (a float) or per row (E,).
        primary_only: see :func:`edge_geometry`.

    Returns a dict: ``senders``, ``receivers`` (E,); ``is_pp``, ``is_pw`` (E,) edge kinds
    (only edges whose receiver is a ball; ball-wall the wall -> ball direction); ``vel``,
    ``jar_vel`` (W, n_node, 3) m/s, every node's velocity columns and the wall node's jar
    velocity per slot; ``v_rel`` (W, E, 3) m/s, the partner's velocity relative to the
    receiver; ``normal`` (E, 3); ``u`` (W, E) m/s, the gap rate; ``gap`` (W, E) m, the surface
    gap per slot (negative: overlap); ``v_t`` (E, 3) m/s, the tangential relative velocity of
    the centres at the newest slot, ``speed_t`` (E,) its size.
    """
    feats = jnp.asarray(graph.nodes["features"], DTYPE)
    w = window
    rows = slice(0, None, 2) if primary_only else slice(None)
    senders, receivers = graph.senders[rows], graph.receivers[rows]
    is_particle = graph.nodes["particle"]
    recv_ball = is_particle[receivers]
    is_pp = graph.edges["pp"][rows] & recv_ball
    is_pw = graph.edges["pw"][rows] & recv_ball  # wall -> ball direction only

    vel = jnp.stack([_slot(feats, k, slice(0, 3)) for k in range(w)])      # (W, n_node, 3)
    # The wall node's rows hold [offset, offset velocity, frequency] per slot: its "velocity"
    # columns 0..2 are the offset, 3..5 the jar velocity.
    jar_vel = jnp.stack([_slot(feats, k, slice(3, 6)) for k in range(w)])  # (W, n_node, 3)

    v_r = vel[:, receivers]                                                # (W, E, 3)
    # Partner velocity: the sender ball, or the jar (wall edges; the sender is the wall node).
    v_partner = jnp.where(is_pw[None, :, None], jar_vel[:, senders], vel[:, senders])
    v_rel = v_partner - v_r                                                # (W, E, 3)

    # Ball-ball frame: r = x_s - x_r at the newest slot (edge feature); older slots by
    # subtracting the relative displacements (x_j = x_{j-1} + v_j dt exactly).
    r_new = jnp.asarray(graph.edges["features"][rows, :3], DTYPE)
    disp_after = jnp.cumsum((v_rel * dt)[::-1], axis=0)[::-1]  # sum_{j >= k} v_rel_j dt
    # r at slot k = r_new - sum_{j > k} v_rel_j dt
    r_slots = r_new[None] - jnp.concatenate([disp_after[1:], jnp.zeros_like(disp_after[:1])])
    dist_slots = jnp.sqrt(jnp.sum(r_slots * r_slots, axis=-1) + 1e-20)    # (W, E)
    n_pp = r_new / dist_slots[-1][:, None]
    gap_pp = dist_slots - pp_reach                                         # (W, E)

    # Ball-wall frame: the edge's wall (the nearest wall, or its patch with
    # GraphSpec.wall_patches) from its feature phi n at the newest slot (phi < 0 inside the
    # cavity); older gaps by subtracting the approach along n, as for a pair.
    f_pw = r_new
    phi_pw = -jnp.sqrt(jnp.sum(f_pw * f_pw, axis=-1) + 1e-30)
    n_pw = f_pw / phi_pw[:, None]

    normal = jnp.where(is_pw[:, None], n_pw, n_pp)
    u = jnp.einsum("wec,ec->we", v_rel, normal)                            # (W, E) gap rate
    approach_after = jnp.concatenate([jnp.cumsum((u * dt)[::-1], axis=0)[::-1][1:],
                                      jnp.zeros_like(u[:1])])             # sum_{j > k} u_j dt
    gap_pw = (-phi_pw - pw_reach)[None] - approach_after                   # (W, E)
    gap = jnp.where(is_pw[None], gap_pw, gap_pp)
    v_t = v_rel[-1] - u[-1][:, None] * normal
    speed_t = _safe_norm(v_t)
    return {"senders": senders, "receivers": receivers, "is_pp": is_pp, "is_pw": is_pw,
            "vel": vel, "jar_vel": jar_vel, "v_rel": v_rel, "normal": normal, "u": u,
            "gap": gap, "v_t": v_t, "speed_t": speed_t}


def newest_gap_rate(graph: jraph.GraphsTuple, window: int, pp_reach: Any, pw_reach: Any
                    ) -> tuple[jax.Array, jax.Array]:
    """``(gap, u)`` (E / 2,) m and m/s of every primary row at the newest slot: what
    :func:`edge_kinematics` gives as ``gap[-1]`` and ``u[-1]`` (the same formulas), for the
    rows' gate without their history (:meth:`ContactNet._gate_candidates`). ``pp_reach``,
    ``pw_reach`` as :func:`edge_kinematics`'s, per primary row or scalars."""
    feats = jnp.asarray(graph.nodes["features"], DTYPE)
    senders, receivers = graph.senders[0::2], graph.receivers[0::2]
    is_pw = graph.edges["pw"][0::2] & graph.nodes["particle"][receivers]
    vel = _slot(feats, window - 1, slice(0, 3))
    jar_vel = _slot(feats, window - 1, slice(3, 6))
    v_rel = jnp.where(is_pw[:, None], jar_vel[senders], vel[senders]) - vel[receivers]
    r_new = jnp.asarray(graph.edges["features"][0::2, :3], DTYPE)
    dist = jnp.sqrt(jnp.sum(r_new * r_new, axis=-1) + 1e-20)
    phi = -jnp.sqrt(jnp.sum(r_new * r_new, axis=-1) + 1e-30)
    normal = jnp.where(is_pw[:, None], r_new / phi[:, None], r_new / dist[:, None])
    gap = jnp.where(is_pw, -phi - pw_reach, dist - pp_reach)
    return gap, jnp.sum(v_rel * normal, axis=-1)


@dataclasses.dataclass(frozen=True)
class InputScales:
    """The scales of a contact's kinematic inputs (m, m/s; scalars, or (E,) per contact):
    ``clip(gap / gap_coarse, -1, 3)``, ``tanh(gap / gap_fine)``,
    ``clip(u / speed_coarse, -speed_bound, speed_bound)``, ``tanh(u / speed_fine)``, and the
    tangential (slip) speeds alike, clipped to ``[0, speed_bound]``."""

    gap_coarse: Any
    gap_fine: Any
    speed_coarse: Any
    speed_fine: Any
    speed_bound: float


@dataclasses.dataclass(frozen=True)
class GateRule:
    """How a contact kind bounds overlaps and gates contacts (m; scalars or (E,)):
    ``limit_on`` (the kind's ``overlap_limit`` > 0), the base limit ``limit``, the law's
    ``law_factor`` L v^0.8 term with ``law_length`` L (m at ``speed_ref`` m/s), and the gate
    margin ``gate_margin``. ``rebound_time`` (None: off; needs the law term) and
    ``restitution``: the law's ``v t_c(v) / peak(v)`` (its contact time over its peak,
    :func:`sgn_jax.dem.contact.head_on_contact_time`) and restitution, for the law rebound of
    :func:`contact_rows`; ``rebound_exact``: where the rebound is also the impulse's ceiling
    (:data:`REBOUND_EXACT`)."""

    limit_on: bool
    limit: Any
    law_factor: float
    law_length: Any
    gate_margin: Any
    speed_ref: float = 1.0
    rebound_time: Any = None
    restitution: Any = None
    rebound_exact: str = "off"
    rebound_sweeps: str = "off"


def _largest_at_balls(values: jax.Array, receivers: jax.Array, senders: jax.Array,
                      is_pp: jax.Array, n_node: int) -> jax.Array:
    """(n_node,) the largest of ``values`` (E,) >= 0 over each ball's contact rows (a row
    counts at its receiver, a ball-ball row at its sender too); 0 for a ball without rows.
    Both ends in one scatter, as :func:`sum_at_both_ends`."""
    largest = jax.ops.segment_max(jnp.concatenate([values, jnp.where(is_pp, values, 0.0)]),
                                  jnp.concatenate([receivers, senders]), num_segments=n_node)
    return jnp.maximum(largest, 0.0)


def _scaled_inputs(gap: jax.Array, u: jax.Array, speed_t: jax.Array, acc_term: jax.Array,
                   slip_c: jax.Array | None, sc: InputScales, history: int) -> jax.Array:
    """(E, 4 history + 3 (+ 2 with ``slip_c``)) the kinematic inputs of :func:`contact_rows`:
    per slot of the newest ``history`` (oldest first) ``clip(gap / gap_coarse, -1, 3)``,
    ``tanh(gap / gap_fine)``, ``clip(u / speed_coarse, -bound, bound)``,
    ``tanh(u / speed_fine)``; then ``clip(speed_t / speed_coarse, 0, bound)``,
    ``tanh(speed_t / speed_fine)``, ``tanh(acc_term / speed_fine)`` and the slip speed's two
    columns as the tangential speed's.

    Scales per contact (arrays: the charge kind) give every column in one elementwise
    expression over the (E, C) raw values and scales: a small charge's step costs per XLA
    operation, and a column each is an operation each. Constant scales (floats) give each
    column alone, the division by a constant as XLA folds it (the contact kind's numbers)."""
    w = gap.shape[0]
    b = sc.speed_bound
    scales = (sc.gap_coarse, sc.gap_fine, sc.speed_coarse, sc.speed_fine)
    gc, gf, vc, vf = range(4)   # which of ``scales``
    # per column: (raw value, its scale's index, fine (tanh) or clipped to [low, high])
    cols: list[tuple] = []
    for k in range(w - history, w):  # the newest slots, oldest first
        cols += [(gap[k], gc, False, -1.0, 3.0), (gap[k], gf, True, 0, 0),
                 (u[k], vc, False, -b, b), (u[k], vf, True, 0, 0)]
    cols += [(speed_t, vc, False, 0.0, b), (speed_t, vf, True, 0, 0), (acc_term, vf, True, 0, 0)]
    if slip_c is not None:
        cols += [(slip_c, vc, False, 0.0, b), (slip_c, vf, True, 0, 0)]
    if all(isinstance(v, (int, float)) for v in scales):
        return jnp.stack([jnp.tanh(x / scales[i]) if fine else
                          jnp.clip(x / scales[i], low, high)
                          for x, i, fine, low, high in cols], axis=-1)
    # the raw columns and their scales: per slot [gap, gap, u, u] with the four scales in
    # order (as ``cols``), slot-major, then the speeds' columns
    g_h, u_h = gap[w - history:].T, u[w - history:].T                  # (E, history)
    tail = cols[4 * history:]
    raw = jnp.concatenate([jnp.stack([g_h, g_h, u_h, u_h], axis=-1).reshape(g_h.shape[0], -1),
                           jnp.stack([c[0] for c in tail], axis=-1)], axis=-1)
    four = jnp.stack([jnp.broadcast_to(jnp.asarray(v, raw.dtype), raw.shape[:1])
                      for v in scales], axis=-1)
    scale = jnp.concatenate([jnp.tile(four, (1, history)), four[:, [c[1] for c in tail]]],
                            axis=-1)
    fine = np.array([c[2] for c in cols])
    low = np.array([c[3] for c in cols], np.float32)
    high = np.array([c[4] for c in cols], np.float32)
    x = raw / scale
    return jnp.where(fine, jnp.tanh(x), jnp.minimum(high, jnp.maximum(low, x)))   # as jnp.clip


def contact_rows(graph: jraph.GraphsTuple, kin: dict[str, jax.Array], v_slip: jax.Array,
                 slip_c: jax.Array, *, history: int, dt: float, gravity: Any,
                 scales: InputScales, gate_rule: GateRule, spin: bool,
                 constant_inputs: tuple = ()) -> dict[str, jax.Array]:
    """What every contact kind's :meth:`ContactNet._edge_geometry` builds from the edges'
    kinematics (:func:`edge_kinematics`) and their slip: the tangent, the wall's relative
    acceleration term, the inputs (the newest ``history`` slots' gap and gap rate, the
    tangential and, with ``spin``, slip speeds by ``scales``; then ``constant_inputs``, (E,)
    each), the overlap limit, the floor that keeps it, the gate (``gate_rule``), and with
    ``spin`` ``contacts_max``. Returns the keys of :func:`edge_geometry` but ``speed_c`` and
    the kind's extras."""
    senders, receivers, is_pp, is_pw = (kin[k] for k in ("senders", "receivers", "is_pp",
                                                         "is_pw"))
    jar_vel, normal, u, gap, speed_t = (kin[k] for k in ("jar_vel", "normal", "u", "gap",
                                                        "speed_t"))
    w = gap.shape[0]
    tangent = v_slip / jnp.sqrt(slip_c * slip_c + TANGENT_EPS ** 2)[:, None]

    g = jnp.asarray(gravity, DTYPE)
    # Relative acceleration of the partner along n over one step (m/s): for a wall the jar's
    # acceleration minus gravity (the ball falls, the jar is held); zero for a pair.
    jar_dv = jar_vel[-1, senders] - jar_vel[-2, senders]
    acc_term = jnp.where(is_pw, jnp.einsum("ec,ec->e", jar_dv - g * dt, normal), 0.0)

    inputs = _scaled_inputs(gap, u, speed_t, acc_term, slip_c if spin else None, scales,
                            history)
    if constant_inputs:
        inputs = jnp.concatenate([inputs, jnp.stack(constant_inputs, axis=-1)], axis=-1)

    rule = gate_rule
    gap_end = gap[-1] + u[-1] * dt
    # the contacts that act this step: the gate (and the "fresh" ceiling's acting rows)
    acting = (is_pp | is_pw) & (jnp.minimum(gap[-1], gap_end) < rule.gate_margin)
    ceiling = None
    sweep_rows = {}   # what the overlap sweeps read besides the limit (rebound_sweeps)
    if rule.limit_on:
        limit = rule.limit
        if rule.law_factor > 0:
            # the approach speed before the contact slowed it: the history's largest closing rate
            approach = jnp.maximum(-jnp.min(u[w - history:], axis=0), 0.0)
            limit = jnp.maximum(limit, rule.law_factor * rule.law_length
                                * jnp.power(approach / rule.speed_ref + 1e-12, 0.8))
        # The gap at the end of the step is gap + (u + acc_term + du_n) dt (semi-implicit Euler;
        # du_n raises the gap rate by itself: m* du_n on each ball of a pair of reduced mass m*).
        floor = jnp.maximum(-(gap[-1] + limit) / dt - u[-1] - acc_term, 0.0)
        if rule.rebound_time is not None:
            # Fresh impacts (the law's rebound, complete at the law's contact time). A contact
            # whose gap was open at some slot of the window began at a time the slots tell:
            # between the last open slot k and the next (or, open now, within this step). In
            # the DEM an impact at closing speed v lasts t_c(v) = ratio L v^0.8 / v and ends
            # with the pair separating at e v; when it began more than t_c before the end of
            # this step, the step ends with the pair moving apart at e v at least.
            apart = gap > 0                                                  # (W, E)
            fresh = jnp.any(apart, axis=0)
            k_a = w - 1 - jnp.argmax(apart[::-1], axis=0)                   # last open slot
            k_b = jnp.minimum(k_a + 1, w - 1)

            def at(x: jax.Array, k: jax.Array) -> jax.Array:
                return jnp.take_along_axis(x, k[None], axis=0)[0]

            gap_a, gap_b = at(gap, k_a), at(gap, k_b)
            closing = jnp.maximum(jnp.maximum(-at(u, k_a), -at(u, k_b)), 0.0)
            open_now = k_a == w - 1
            # the share of the interval after slot k_a before the first touch
            share = jnp.where(open_now, gap_a / jnp.maximum((closing + 1e-12) * dt, 1e-30),
                              gap_a / jnp.maximum(gap_a - gap_b, 1e-30))
            since_touch = (w - k_a - share) * dt               # s, at the end of this step
            t_contact = (rule.rebound_time * rule.law_length
                         * jnp.power(closing / rule.speed_ref + 1e-12, -0.2) / rule.speed_ref)
            over = fresh & (closing > 0) & (since_touch > t_contact)
            rebound = rule.restitution * closing - u[-1] - acc_term
            floor = jnp.where(over, jnp.maximum(floor, rebound), floor)
            if rule.rebound_sweeps != "off":
                # the gap rate each impact past its contact time ends the step with, for the
                # overlap sweeps to keep with every ball's other contacts (m/s; none elsewhere)
                swept = over
                if rule.rebound_sweeps == "free":
                    # A ball held by a contact closed over the window (in a bed, on the wall)
                    # shares an impact with what holds it: a collision of many bodies, more
                    # lossy than the pair's own rebound, left to the network and the step.
                    held = _largest_at_balls((acting & ~fresh).astype(gap.dtype), receivers,
                                             senders, is_pp, graph.nodes["features"].shape[0])
                    held_r, held_s = at_both_ends(held, receivers, senders)
                    swept = over & is_pp & (held_r == 0) & (held_s == 0)
                # The sweeps see a wall's velocity at the end of the step but not gravity's
                # g dt on the ball: a ball-wall target counts it here, once per step.
                gravity_n = jnp.where(is_pw, jnp.einsum("c,ec->e", g, normal) * dt, 0.0)
                sweep_rows["rebound_rate"] = jnp.where(
                    swept, rule.restitution * closing + gravity_n, NO_REBOUND_RATE)
            if rule.rebound_exact == "all":
                # ...and not faster: the contact's own impulse ends it at e v (or at what the
                # overlap limit needs), whatever the network would add
                ceiling = jnp.where(over, floor, jnp.inf)
            elif rule.rebound_exact == "wall":
                # The same at ball-wall impacts; and a ball-wall contact closed over the whole
                # window (a ball resting or pressed on the wall) does not push its ball off
                # faster than e times the largest closing speed the ball's contacts saw in the
                # window (this one's, or any ball-ball contact's of the ball, through which an
                # impact reaches a ball on the wall): a passive contact gives back at most what
                # the restitution leaves of what came in. Otherwise the balls of a slow bed
                # chatter on the wall, pushed off faster than they came (docs/contact.md,
                # item 7).
                closing_window = jnp.maximum(-jnp.min(u, axis=0), 0.0)          # (E,) m/s
                ball_in = _largest_at_balls(jnp.where(is_pp, closing_window, 0.0), receivers,
                                            senders, is_pp, graph.nodes["features"].shape[0])
                came_in = jnp.maximum(closing_window, ball_in[receivers])
                resting = jnp.maximum(floor, rule.restitution * came_in - u[-1] - acc_term)
                ceiling = jnp.where(is_pw & over, floor,
                                    jnp.where(is_pw & ~fresh, resting, jnp.inf))
            elif rule.rebound_exact == "fresh":
                # Every fresh impact, ball-ball and ball-wall, is passive from its first step:
                # past its contact time it ends at e v exactly (as "all"), and before that it
                # ends the step separating no faster than e times the largest closing speed
                # that its balls' acting contacts saw in the window (this one's, or another's
                # through which an impact reaches its balls). A network that pushes a pair
                # apart within its contact time can give back no more than the restitution
                # leaves, so a binary impact's restitution is its material's. Contacts closed
                # over the whole window (resting, rolling) keep the network's impulse. Only
                # acting (gated) rows count, so the compacted single-rollout step (which drops
                # rows that cannot act) gives the same ceilings.
                closing_window = jnp.where(acting, jnp.maximum(-jnp.min(u, axis=0), 0.0), 0.0)
                ball_in = _largest_at_balls(closing_window, receivers, senders, is_pp,
                                            graph.nodes["features"].shape[0])
                in_r, in_s = at_both_ends(ball_in, receivers, senders)
                came_in = jnp.maximum(jnp.maximum(closing_window, in_r),
                                      jnp.where(is_pp, in_s, 0.0))
                passive = jnp.maximum(floor, rule.restitution * came_in - u[-1] - acc_term)
                ceiling = jnp.where(over, floor, jnp.where(fresh, passive, jnp.inf))
    else:
        limit = jnp.zeros_like(gap_end)
        floor = jnp.zeros_like(gap_end)
    gate = acting.astype(DTYPE)
    extra = {}
    if spin:
        # Each contact's stick impulse is computed as if it were the ball's only one (a Jacobi
        # sweep); a ball in a bed has several, whose impulses add up and would overshoot (and
        # pump spin). Relaxed by the larger number of acting contacts of its two balls.
        n_node = graph.nodes["features"].shape[0]
        extra["contacts_max"] = _larger_ball_count(gate, receivers, senders, is_pp, n_node)
    return {
        "normal": normal, "tangent": tangent, "inputs": inputs, "gate": gate, "floor": floor,
        "is_pp": is_pp, "is_pw": is_pw, "senders": senders, "receivers": receivers,
        "gap": gap[-1], "limit": jnp.broadcast_to(limit, gap_end.shape),
        "u_wall": jnp.where(is_pw[:, None], jar_vel[-1, senders], 0.0),
        "jar_dv": jnp.where(is_pw[:, None], jar_dv, 0.0),
        "v_node": kin["vel"][-1], "u_n": u[-1], **extra,
        # the exact law rebound's ceiling, only where it is on (the step's hot path is
        # unchanged without it)
        **({} if ceiling is None else {"ceiling": ceiling}),
        **sweep_rows,
    }


def edge_geometry(graph: jraph.GraphsTuple, phys: ContactPhysics, primary_only: bool = False,
                  spin: bool = False):
    """Per directed edge (E rows; E / 2 with ``primary_only``): frame, inputs, which edges act.

    ``primary_only``: only the even edge slots, which in the layout of
    :func:`sgn_jax.surrogate.graph.build_graph` are one direction of every edge: ball-ball
    ``j -> i`` (slot 2r; its reverse ``i -> j`` is slot 2r + 1) and ball-wall ``wall -> ball``
    (the ``ball -> wall`` edge follows it); padding slots come in pairs too. The contact model
    computes each contact once there and gives the partner ball the opposite impulse.

    Returns a dict of float32 arrays:
        normal (E, 3): unit normal of the contact, from the receiver ball to its partner;
        tangent (E, 3): unit-ish tangential direction of the partner's relative velocity
            (``v_t / sqrt(|v_t|^2 + eps^2)``, 0 when there is no slip);
        inputs (E, 4 history + 3): the invariant scalars (per slot: coarse gap, fine gap, u,
            fine u; then |v_t|, fine |v_t| and the relative normal acceleration term);
        gate (E,): 1 where the edge acts (a real edge into a ball, contact possible in the step);
        floor (E,): m/s, the smallest du_n that keeps the contact's overlap at the end of a
            step within ``phys.overlap_limit`` (0 with the limit off, or where it is kept anyway);
        gap (E,): m, the surface gap at the newest slot (negative: overlap); limit (E,): m,
            the contact's overlap limit (0 with the limit off);
        is_pp (E,), is_pw (E,): edge kinds (only edges whose receiver is a ball);
        senders, receivers (E,): the edges' node indices;
        u_wall (E, 3): the jar's velocity (m/s) for ball-wall edges, 0 otherwise;
        jar_dv (E, 3): the jar's velocity change over the last step (m/s) for ball-wall
            edges (the estimate of its change over the next), 0 otherwise;
        v_node (n_node, 3): every node's velocity at the newest slot, v_n (m/s);
        u_n (E,): m/s, the gap rate v_rel . n at the newest slot (< 0: approaching);
        speed_c (E,): m/s, the tangential speed of the contact (of its contact point with
            ``spin``; of the centres without).

    With ``spin`` (the graph's ``nodes["spin"]``, the balls' angular velocities w at t_n) the
    tangent is that of the slip at the CONTACT POINT, v_rel - R (w_r + w_s) x n (a wall does
    not turn: its node's spin is 0), the inputs gain its speed (clipped and fine-scaled), and
    the dict gains ``w_node`` (n_node, 3) rad/s, ``w_rel`` (E, 3), w_r - w_s (w_r for a wall),
    ``arm`` (E,) m, the contact arm R - overlap / 2, ``slip`` (E,) m/s, |v_t,c|, and
    ``contacts_max`` (E,), the larger number of acting contacts of the edge's two balls (>= 1).
    """
    w, h, dt, radius = phys.window, phys.history, phys.dt, phys.ball_radius
    kin = edge_kinematics(graph, w, dt, 2.0 * radius, radius, primary_only)
    senders, receivers, is_pw = kin["senders"], kin["receivers"], kin["is_pw"]
    normal, gap, v_t, speed_t = kin["normal"], kin["gap"], kin["v_t"], kin["speed_t"]
    extra = {}
    if spin:
        if "spin" not in graph.nodes:
            raise ContactModelError("a contact model with spin needs the balls' spins in the "
                                    "graph: build it from a Window with spins (the rollout "
                                    "carries them; zeros for balls at rest)")
        w_node = jnp.asarray(graph.nodes["spin"], DTYPE)
        w_r, w_s = w_node[receivers], w_node[senders]      # the wall node's spin row is 0
        # The contact arm as the DEM's, R - overlap / 2: for a pair the contact point is the
        # midpoint of the centres, so the pair's angular momentum is conserved exactly.
        arm = radius - 0.5 * jnp.maximum(-gap[-1], 0.0)
        # contact point velocities: receiver v_r + w_r x (a n), partner v_s + w_s x (-a n)
        v_slip = v_t - arm[:, None] * jnp.cross(w_r + w_s, normal)  # (w x n): tangential
        slip_c = _safe_norm(v_slip)
        extra = {"w_node": w_node, "w_rel": w_r - w_s, "arm": arm, "slip": slip_c}
    else:
        v_slip, slip_c = v_t, speed_t
    peak = (jnp.where(is_pw, phys.overlap_peak_pw, phys.overlap_peak_pp)
            if phys.overlap_limit > 0 and phys.overlap_law_factor > 0 else 0.0)
    rows = contact_rows(
        graph, kin, v_slip, slip_c, history=h, dt=dt, gravity=phys.gravity,
        scales=InputScales(GAP_SCALE_COARSE_M, GAP_SCALE_FINE_M, 1.0, SPEED_SCALE_FINE, 10.0),
        gate_rule=GateRule(phys.overlap_limit > 0, phys.overlap_limit, phys.overlap_law_factor,
                           peak, phys.gate_margin,
                           rebound_time=(jnp.where(is_pw, phys.rebound_time_pw,
                                                   phys.rebound_time_pp)
                                         if phys.rebound_time_pp > 0 else None),
                           restitution=phys.restitution,
                           rebound_exact=phys.rebound_exact),
        spin=spin)
    return {**rows, "speed_c": slip_c, **extra}


def at_both_ends(node_values: jax.Array, receivers: jax.Array, senders: jax.Array
                 ) -> tuple[jax.Array, jax.Array]:
    """``(node_values[receivers], node_values[senders])``, each (E, ...), by one gather: a step
    of a small charge costs per XLA operation, not per row (docs/contact.md)."""
    both = node_values[jnp.concatenate([receivers, senders])]
    return both[:receivers.shape[0]], both[receivers.shape[0]:]


def sum_at_both_ends(on_receiver: jax.Array, on_sender: jax.Array, receivers: jax.Array,
                     senders: jax.Array, n_node: int) -> jax.Array:
    """(n_node, ...) the per-edge values ``on_receiver`` summed at each edge's receiver plus
    ``on_sender`` at its sender, by one scatter-add (one XLA operation instead of two)."""
    return jax.ops.segment_sum(jnp.concatenate([on_receiver, on_sender]),
                               jnp.concatenate([receivers, senders]), num_segments=n_node)


def _larger_ball_count(flags: jax.Array, receivers: jax.Array, senders: jax.Array,
                       is_pp: jax.Array, n_node: int) -> jax.Array:
    """(E,) the larger number of flagged contacts (``flags`` (E,) 0/1) of each edge's two balls
    (its receiver's alone for a wall edge), at least 1: the relaxation of a Jacobi sweep, whose
    per-contact corrections on a ball with several contacts add up."""
    per_node = sum_at_both_ends(flags, flags * is_pp, receivers, senders, n_node)
    at_recv, at_send = at_both_ends(per_node, receivers, senders)
    return jnp.maximum(jnp.maximum(at_recv, jnp.where(is_pp, at_send, 0.0)), 1.0)


def _safe_norm(v: jax.Array) -> jax.Array:
    """|v| over the last axis with a finite derivative at v = 0 (a head-on or padded contact):
    sqrt's derivative is infinite there, which made the horizon estimator's gradients NaN; the
    value is unchanged."""
    speed_sq = jnp.sum(v * v, axis=-1)
    positive = speed_sq > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, speed_sq, 1.0)), 0.0)


class ImpulseMLP(nn.Module):
    """``layers`` dense layers with SiLU between them (smooth), 2 outputs; the output layer
    starts at zero, so an untrained model gives the same small impulse to every contact."""

    hidden: int
    layers: int

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        for i in range(self.layers - 1):
            x = nn.silu(nn.Dense(self.hidden, dtype=DTYPE, param_dtype=DTYPE, name=f"dense_{i}")(x))
        return nn.Dense(2, dtype=DTYPE, param_dtype=DTYPE, kernel_init=nn.initializers.zeros,
                        name=f"dense_{self.layers - 1}")(x)


class ContactNet(nn.Module):
    """The contact-impulse surrogate. ``__call__(raw_graph) -> (accel (n_node, 3) m/s^2,
    dE_target (n_graph,) J)``; :meth:`step_terms` gives the impulses and the energy split.

    Takes the RAW graph of :func:`sgn_jax.surrogate.graph.build_graph` (``takes_raw_graph``): its inputs
    are scaled by fixed physical scales, not by normalisation statistics.

    Every contact's impulse is a function of its own invariants alone (one pass per contact);
    the overlap and friction sweeps of :class:`ContactPhysics` then couple the contacts of a
    ball.

    ``spin`` (``[model] spin = true``): the balls' angular velocities are rollout state (the
    window's ``spins``, the graph's ``nodes["spin"]``). The tangential impulse then acts along
    the slip of the contact POINT and turns both balls (dw = R n x J / I, the same on both
    balls of a pair: angular momentum about the contact is conserved), the rolling friction of
    the config's material brakes their relative rotation (at most mu_r R J_n, never reversing
    it), and the outputs are (n_node, 6): linear and angular accelerations. A ball that rolls
    along a wall, which a spinless model can only let slide or stick, is then representable
    (docs/contact.md).

    ``rows_by_kind`` and ``acting_per_ball`` change where the MLPs run, not what they give
    (:meth:`for_single_rollout` sets both; :meth:`_per_kind`): each MLP on its own kind's rows,
    and only on its kind's acting contacts, a block of ceil(acting_per_ball N) rows (0 = off).
    ``compact_per_ball`` changes which rows a rollout step computes at all, not what it gives
    (:meth:`rollout_terms`; 0 = off).
    """

    physics: ContactPhysics = ContactPhysics()
    hidden: int = 64
    mlp_layers: int = 3
    rows_by_kind: bool = False
    spin: bool = False
    acting_per_ball: float = 0.0
    compact_per_ball: float = 0.0
    takes_raw_graph = True

    def for_single_rollout(self) -> ContactNet:
        """This model in the form that runs fastest as one rollout (no vmap): each MLP on its
        own kind's rows (``rows_by_kind``; with the config's ``wall_patches``), and no
        pair-capacity tiers (``capacity_tiers_help``). Vmapped over packings (ensembles,
        design studies, training) the per-packing row offset turns the slices into a gather
        and a scatter and the plain model is the faster one (docs/benchmarks.md), so only the
        single-rollout drivers ask for this
        (:func:`sgn_jax.surrogate.rollout.single_rollout_model`).

        Each MLP also runs only on its kind's ACTING contacts (``acting_per_ball``: a block of
        ceil(1.5 N) rows per kind, the others are gated off; a step with more runs on all the
        kind's rows): the standard case at 300-900 rpm has 12-21 acting ball-ball and 21-26
        ball-wall contacts on average, at most 33 (N = 24: blocks of 36 rows against 96 of
        each kind). The numbers are the same to float32 rounding.

        And a rollout step computes only the rows that may act (``compact_per_ball``,
        :meth:`rollout_terms`): the graph's candidate edges within the skins are 8 N contact
        rows with 4 wall patches, of which 1-3 N act; the geometry, the impulses, the sweeps
        and the ledger of the others are exact zeros. Not with the exact law rebound at the
        wall, whose resting ceiling reads every ball-ball row's closing speed.

        A model already in this form (``rows_by_kind``) is returned as it is, so that a caller
        may hand the drivers a form of its own (e.g. ``compact_per_ball=0``: every step on the
        whole graph, what ``benchmarks/bench_charge_ratio.py --full-rows`` times)."""
        if self.rows_by_kind:
            return self
        compact = (SINGLE_ROLLOUT_COMPACT_PER_BALL
                   if getattr(self.physics, "rebound_exact", "off") != "wall" else 0.0)
        return self.clone(rows_by_kind=True, acting_per_ball=SINGLE_ROLLOUT_ACTING_PER_BALL,
                          compact_per_ball=compact)

    # Pair-capacity tiers (make_rollout's pp_capacity_tiers) switch between graphs of several
    # capacities every step: they speed up the SGN's single rollout, not this model's.
    capacity_tiers_help = False

    def setup(self):
        self.pp_net = ImpulseMLP(self.hidden, self.mlp_layers)
        self.pw_net = ImpulseMLP(self.hidden, self.mlp_layers)
        # Damping share of all losses per contact kind, as logits (fitted after training).
        self.share_logit = self.param("share_logit", nn.initializers.constant(2.0), (2,),
                                      DTYPE)

    def _per_kind(self, pp_net: nn.Module, pw_net: nn.Module, geo: dict[str, jax.Array],
                  x: jax.Array, n_balls: int) -> jax.Array:
        """(R, 2) outputs: ``pw_net`` on the ball-wall rows, ``pp_net`` on the others.

        With ``acting_per_ball`` f > 0 each MLP runs only on its kind's ACTING rows (gate 1,
        at most K = ceil(f N) of each kind; the others are gated off, so their outputs
        are never used and are 0 here), or, in a step with more than K of a kind, on the rows
        of :meth:`_rows_of_kind` (``nn.cond``: one branch runs, except under vmap, where both
        do: only single rollouts ask for it).
        """
        if self.acting_per_ball > 0:
            block = max(1, math.ceil(self.acting_per_ball * n_balls))
            acting = geo["gate"] > 0
            fits = ((jnp.sum(acting & geo["is_pp"]) <= block)
                    & (jnp.sum(acting & geo["is_pw"]) <= block))
            return nn.cond(fits, lambda mdl: mdl._acting_only(pp_net, pw_net, geo, x, block),
                           lambda mdl: mdl._rows_of_kind(pp_net, pw_net, geo, x, n_balls), self)
        return self._rows_of_kind(pp_net, pw_net, geo, x, n_balls)

    def _acting_only(self, pp_net: nn.Module, pw_net: nn.Module, geo: dict[str, jax.Array],
                     x: jax.Array, block: int) -> jax.Array:
        """(R, 2): each MLP on the (at most ``block``) acting rows of its kind, gathered into
        a block of ``block`` rows (the unused ones repeat the last row) and scattered back; 0
        on the other rows."""
        rows = x.shape[0]
        acting = geo["gate"] > 0
        # both kinds' acting rows at once, (2 block,): the ball-ball ones, then the ball-wall
        # ones, each in order and then ``rows`` (no row); one gather, one scatter back
        index = true_indices(jnp.stack([acting & geo["is_pp"], acting & geo["is_pw"]]), block,
                             rows).reshape(-1)
        picked = x[jnp.minimum(index, rows - 1)]
        outputs = jnp.concatenate([pp_net(picked[:block]), pw_net(picked[block:])])
        return jnp.zeros((rows, 2), x.dtype).at[index].set(outputs, mode="drop")

    def _rows_of_kind(self, pp_net: nn.Module, pw_net: nn.Module, geo: dict[str, jax.Array],
                      x: jax.Array, n_balls: int) -> jax.Array:
        """(R, 2): ``pw_net`` on the ball-wall rows, ``pp_net`` on the others.

        The primary rows of :func:`sgn_jax.surrogate.graph.build_graph` hold the kept ball-ball
        contacts at ``[0, kept)``, the ball-wall ones right after them (at most N max(1, P)),
        then padding. With ``physics.wall_patches`` known, ``pp_net`` runs on the first
        R - N max(1, P) rows (the ball-ball capacity) and ``pw_net`` on the N max(1, P) rows
        from ``kept`` on: each row gets the same output as from running both everywhere
        (padding rows, gated off, may differ), at half the cost."""
        is_pw = geo["is_pw"][:, None]
        rows = x.shape[0]
        patches = self.physics.wall_patches
        wall_rows = n_balls * max(1, patches or 0)
        pair_rows = rows - wall_rows
        if not self.rows_by_kind or patches is None or pair_rows < 1:
            return jnp.where(is_pw, pw_net(x), pp_net(x))
        kept = jnp.sum(geo["is_pp"], dtype=jnp.int32)   # ball-ball rows come first
        pp_out = jnp.concatenate([pp_net(x[:pair_rows]),
                                  jnp.zeros((wall_rows, 2), x.dtype)])
        pw_out = jax.lax.dynamic_update_slice_in_dim(
            jnp.zeros((rows, 2), x.dtype),
            pw_net(jax.lax.dynamic_slice_in_dim(x, kept, wall_rows)), kept, axis=0)
        return jnp.where(is_pw, pw_out, pp_out)

    def _edge_geometry(self, graph: jraph.GraphsTuple) -> dict[str, jax.Array]:
        """:func:`edge_geometry` of the primary rows (a kind conditioned on more, such as
        :mod:`sgn_jax.surrogate.contact_charge`, builds its own)."""
        return edge_geometry(graph, self.physics, primary_only=True, spin=self.spin)

    def _learned_normal(self, geo: dict[str, jax.Array], logits: jax.Array) -> jax.Array:
        """(E,) m/s, the learned normal impulse over m* before the floor and the gate."""
        del geo
        return IMPULSE_SCALE * nn.softplus(logits[:, 0])

    def _dissipation_target(self, parts: dict[str, jax.Array],
                            seg: Any) -> jax.Array:
        """(n_graph,) J, the paper's target from the step's dissipation: ``share_pp D_pp +
        share_pw D_pw`` (``damping_target = "kind"``) or the sum of
        :func:`per_contact_damping` (``"contact"``). ``parts``: ``d_pp``, ``d_pw``
        (n_graph,) and per contact row the terms :meth:`_terms_and_contacts` has (``geo``,
        ``impulse``, ``angular``, ``wbar_node``, ``edge_pp``, ``edge_pw``, ``edge_normal``);
        ``seg`` sums rows per graph."""
        share = jax.nn.sigmoid(jax.lax.stop_gradient(self.share_logit))
        if self.physics.damping_target == "contact":
            return seg(per_contact_damping(parts, share, self.spin))
        return share[0] * parts["d_pp"] + share[1] * parts["d_pw"]

    def _normal_impulse(self, geo: dict[str, jax.Array], logits: jax.Array) -> jax.Array:
        """(E,) m/s, each contact's du_n: the learned one, at least the floor (the rigid
        limit, the law rebound), at most the exact law rebound's ceiling where it is on, 0
        where the gate is shut."""
        du_n = jnp.maximum(self._learned_normal(geo, logits), geo["floor"])
        if "ceiling" in geo:   # the exact law rebound
            du_n = jnp.minimum(du_n, geo["ceiling"])
        return du_n * geo["gate"]

    def _reduced_mass(self, geo: dict[str, jax.Array]) -> jax.Array:
        """(E,) kg: m* of each contact, m / 2 for a pair of equal balls, m against a wall."""
        mass = self.physics.ball_mass
        return jnp.where(geo["is_pw"], mass, 0.5 * mass)

    def _impulses(self, geo: dict[str, jax.Array], logits: jax.Array):
        """Impulse (E, 3) N s on each contact's receiver ball from the logits (E, 2):
        ``du_n >= 0`` (softplus: repulsive only), ``|du_t| <= mu du_n`` (Coulomb cone).

        Without spin ``du_t = mu du_n tanh(out_1)``: the network learns the friction outright.
        With spin, Coulomb friction with sticking is built in: the impulse that stops the
        contact point's slip within the step is ``|v_t,c| / k`` (k = 1 + m a^2 / I, 7/2 for
        a = R: the slip falls by k du_t, through both the balls' velocities and their spins);
        relaxed by the larger number n of acting contacts of the two balls (a Jacobi sweep,
        whose impulses on a ball in a bed add up), ``stick = s |v_t,c| / (k n)``, and
        ``du_t = c tanh(stick / c)`` with the cone ``c = mu du_n``: the stick
        impulse where the cone allows it (rolling), the cone where it does not (sliding). The
        network learns only ``s = 2 sigmoid(out_1)``, the share of the slip stopped in one step
        (1 at initialisation: full sticking; the DEM's tangential spring lets a contact creep).

        With ``physics.overlap_limit`` the normal impulse is at least ``geo["floor"]`` (the
        rigid limit; see :class:`ContactPhysics`)."""
        phys = self.physics
        du_n = self._normal_impulse(geo, logits)
        if self.spin:
            cone = phys.friction * du_n
            k = 1.0 + phys.ball_mass * geo["arm"] ** 2 / phys.inertia
            stick = (2.0 * jax.nn.sigmoid(logits[:, 1]) * geo["slip"]
                     / (k * geo["contacts_max"]))
            du_t = cone * jnp.tanh(stick / (cone + 1e-12))
        else:
            du_t = phys.friction * du_n * jnp.tanh(logits[:, 1])
        m_star = self._reduced_mass(geo)
        impulse = ((m_star * (-du_n))[:, None] * geo["normal"]
                   + (m_star * du_t)[:, None] * geo["tangent"])
        return impulse, du_n, du_t

    def _angular_impulses(self, geo: dict[str, jax.Array], impulse: jax.Array, du_n: jax.Array
                          ) -> tuple[jax.Array, jax.Array]:
        """(E, 3) N m s each: the angular impulse on each contact's receiver ball and on its
        sender ball (0 for a wall). The contact force acts at R n from the receiver's centre
        and (as -J) at -R n from the sender's: both get R n x J (R: the arm, R - overlap / 2,
        as the DEM's). Rolling friction (EDEM type A, as the DEM):
        -min(mu_r R J_n, I_eff |w_rel|) w_rel / |w_rel| on the receiver and the opposite on the
        sender, I_eff = I / 2 for a pair (both balls brake), I for a wall; the cap keeps one
        step from reversing the relative rotation."""
        phys = self.physics
        arm, inertia = geo["arm"], phys.inertia
        a_contact = arm[:, None] * jnp.cross(geo["normal"], impulse)
        m_star = self._reduced_mass(geo)
        w_rel = geo["w_rel"]
        w_norm = _safe_norm(w_rel)
        i_eff = jnp.where(geo["is_pw"], inertia, 0.5 * inertia)
        roll = jnp.minimum(phys.rolling_friction * arm * m_star * du_n, i_eff * w_norm)
        roll_dir = w_rel / jnp.where(w_norm > 0, w_norm, 1.0)[:, None]
        l_roll = -roll[:, None] * roll_dir
        return a_contact + l_roll, (a_contact - l_roll) * geo["is_pp"][:, None]

    def _spin_change(self, geo: dict[str, jax.Array], a_recv: jax.Array, a_send: jax.Array,
                     n_node: int, is_particle: jax.Array) -> jax.Array:
        """(n_node, 3) rad/s: the angular impulses summed per ball over I; 0 for the wall."""
        total = sum_at_both_ends(a_recv, a_send, geo["receivers"], geo["senders"], n_node)
        return jnp.where(is_particle[:, None], total / self.physics.inertia, 0.0)

    def _velocity_change(self, geo: dict[str, jax.Array], impulse: jax.Array, n_node: int,
                         is_particle: jax.Array) -> jax.Array:
        """(n_node, 3) m/s: the impulses (a ball-ball contact gives its sender ball the
        opposite impulse, equal and opposite by construction; a wall takes its reaction itself)
        plus gravity (exact, not learned); 0 for the wall node."""
        g = jnp.asarray(self.physics.gravity, DTYPE)
        return (self._impulse_velocity_change(geo, impulse, n_node, is_particle)
                + jnp.where(is_particle[:, None], g * self.physics.dt, 0.0))

    def _impulse_velocity_change(self, geo: dict[str, jax.Array], impulse: jax.Array,
                                 n_node: int, is_particle: jax.Array) -> jax.Array:
        """(n_node, 3) m/s: the impulses alone (a pair's sender gets the opposite one)."""
        receivers, senders = geo["receivers"], geo["senders"]
        total = sum_at_both_ends(impulse, -impulse * geo["is_pp"][:, None], receivers, senders,
                                 n_node)
        return jnp.where(is_particle[:, None], total / self.physics.ball_mass, 0.0)

    def _project_overlaps(self, geo: dict[str, jax.Array], impulse: jax.Array, du_n: jax.Array,
                          dv: jax.Array, n_node: int, is_particle: jax.Array
                          ) -> tuple[jax.Array, jax.Array, jax.Array]:
        """``physics.overlap_sweeps`` Jacobi sweeps of the overlap limit over all contacts
        (:class:`ContactPhysics`): ``(impulse, du_n, dv)`` with the extra normal impulses.

        Each sweep: every acting contact's end-of-step gap with the balls' velocities
        ``v_n + dv`` (a wall's at the end of the step from its last change), the closing
        speed too many, ``need = max(0, -(gap_end + limit) / dt)``, shared by the larger
        number of violated contacts of its two balls, added as a normal impulse
        ``m* need / n`` (it raises that contact's gap rate by ``need / n``, m* its reduced
        mass). A normal impulse has no torque, so the spins are unchanged. With the geometry's
        ``rebound_rate`` (the charge kind's ``rebound_sweeps``) a contact also needs
        ``rebound_rate - u_end``: an impact past its contact time ends the step parting at its
        law's rebound with the balls' other contacts acting, not only by itself."""
        phys = self.physics
        if phys.overlap_sweeps == 0:
            return impulse, du_n, dv
        receivers, senders, normal = geo["receivers"], geo["senders"], geo["normal"]
        is_pp, gate = geo["is_pp"], geo["gate"]
        m_star = self._reduced_mass(geo)
        wall_end = geo["u_wall"] + geo["jar_dv"]
        for _ in range(phys.overlap_sweeps):
            v_end = geo["v_node"] + dv
            v_recv, v_send = at_both_ends(v_end, receivers, senders)
            partner = jnp.where(geo["is_pw"][:, None], wall_end, v_send)
            u_end = jnp.einsum("ec,ec->e", partner - v_recv, normal)
            gap_end = geo["gap"] + u_end * phys.dt
            need = -(gap_end + geo["limit"]) / phys.dt
            if "rebound_rate" in geo:   # and each impact past its contact time ends at e v
                need = jnp.maximum(need, geo["rebound_rate"] - u_end)
            need = jnp.maximum(need, 0.0) * gate
            violated = (need > 0).astype(need.dtype)
            extra = need / _larger_ball_count(violated, receivers, senders, is_pp, n_node)
            extra_impulse = (m_star * (-extra))[:, None] * normal
            impulse = impulse + extra_impulse
            du_n = du_n + extra
            dv = dv + self._impulse_velocity_change(geo, extra_impulse, n_node, is_particle)
        return impulse, du_n, dv

    def _project_friction(self, geo: dict[str, jax.Array], impulse: jax.Array, du_n: jax.Array,
                          dv: jax.Array, dw: jax.Array, angular: tuple[jax.Array, jax.Array],
                          n_node: int, is_particle: jax.Array):
        """``physics.friction_sweeps`` projected Jacobi sweeps of Coulomb sticking over all
        acting contacts (:class:`ContactPhysics`): ``(impulse, du_t, dv, dw, angular)`` with
        the extra tangential impulses and their torques, ``du_t`` (E,) m/s the size of each
        contact's total tangential impulse over m* (<= mu du_n).

        Each sweep: every acting contact's end-of-step contact-point slip s' (with ``v_n + dv``
        and ``w_n + dw``; a wall's velocity at the end of the step from its last change); the
        tangential impulse that stops it, ``m* s' / k`` (k = 1 + m a^2 / I: the slip falls by
        k du_t through the velocities and the spins), over the larger number of acting
        contacts of its two balls; the contact's total tangential impulse (learned plus
        sweeps) projected back into the cone ``mu m* du_n``. The torque ``a n x J`` acts on
        both balls of a pair, so the pair's linear and angular momentum are kept."""
        phys = self.physics   # called with spin and friction_sweeps > 0 (step_terms)
        receivers, senders, normal = geo["receivers"], geo["senders"], geo["normal"]
        gate, arm = geo["gate"], geo["arm"]
        m_star = self._reduced_mass(geo)
        k = 1.0 + phys.ball_mass * arm ** 2 / phys.inertia
        count = _larger_ball_count(gate, receivers, senders, geo["is_pp"], n_node)
        cone = phys.friction * m_star * du_n                              # N s, per contact
        wall_end = geo["u_wall"] + geo["jar_dv"]
        tangential = impulse - jnp.einsum("ec,ec->e", impulse, normal)[:, None] * normal
        a_recv, a_send = angular
        is_pp = geo["is_pp"][:, None]
        mass_inertia = jnp.asarray([phys.ball_mass] * 3 + [phys.inertia] * 3, DTYPE)
        for _ in range(phys.friction_sweeps):
            # one gather of both contact ends and one scatter-add onto both per sweep: the
            # balls' velocities and spins side by side, (n_node, 6)
            state = jnp.concatenate([geo["v_node"] + dv, geo["w_node"] + dw], axis=-1)
            at_recv, at_send = at_both_ends(state, receivers, senders)
            partner = jnp.where(geo["is_pw"][:, None], wall_end, at_send[:, :3])
            v_rel = partner - at_recv[:, :3]
            v_t = v_rel - jnp.einsum("ec,ec->e", v_rel, normal)[:, None] * normal
            slip = v_t - arm[:, None] * jnp.cross(at_recv[:, 3:] + at_send[:, 3:], normal)
            wanted = tangential + (m_star * gate / (k * count))[:, None] * slip
            size = _safe_norm(wanted)
            scale = jnp.minimum(1.0, cone / jnp.maximum(size, 1e-30))
            extra = wanted * scale[:, None] - tangential
            tangential = tangential + extra
            impulse = impulse + extra
            torque = arm[:, None] * jnp.cross(normal, extra)
            a_recv, a_send = a_recv + torque, a_send + torque
            # the receiver gets (J, torque), a pair's sender (-J, torque); the wall node none
            on_balls = sum_at_both_ends(jnp.concatenate([extra, torque], axis=-1),
                                        jnp.concatenate([-extra * is_pp, torque], axis=-1),
                                        receivers, senders, n_node)
            change = jnp.where(is_particle[:, None], on_balls / mass_inertia, 0.0)
            dv, dw = dv + change[:, :3], dw + change[:, 3:]
        return impulse, _safe_norm(tangential) / m_star, dv, dw, (a_recv, a_send)

    def step_terms(self, graph: jraph.GraphsTuple) -> dict[str, jax.Array]:
        """Everything of one step: per-node velocity change and per-graph energies (J)."""
        return self._terms_and_contacts(graph)[0]

    def _terms_and_contacts(self, graph: jraph.GraphsTuple
                            ) -> tuple[dict[str, jax.Array], dict[str, Any]]:
        """``(step_terms, contacts)``; ``contacts``: the edge geometry ``geo``
        (:func:`edge_geometry`) and per contact row (E,) its dissipation ``diss`` (J, its term
        of ``diss_pp + diss_pw``) and that dissipation's normal-impulse part ``diss_normal``."""
        # One row per contact (the primary direction of each edge, half the slots): the MLPs run
        # once per contact and the partner gets exactly the opposite impulse.
        geo = self._edge_geometry(graph)
        n_node = graph.nodes["features"].shape[0]
        is_particle = graph.nodes["particle"]

        def kinematics(logits):
            impulse, du_n, du_t = self._impulses(geo, logits)
            dv = self._velocity_change(geo, impulse, n_node, is_particle)
            if not self.spin:
                return impulse, du_n, du_t, dv, None, None
            a_recv, a_send = self._angular_impulses(geo, impulse, du_n)
            dw = self._spin_change(geo, a_recv, a_send, n_node, is_particle)
            return impulse, du_n, du_t, dv, dw, (a_recv, a_send)

        logits = self._per_kind(self.pp_net, self.pw_net, geo, geo["inputs"], n_node - 2)
        impulse, du_n, du_t, dv, dw, angular = kinematics(logits)
        impulse, du_n, dv = self._project_overlaps(geo, impulse, du_n, dv, n_node, is_particle)
        if self.spin and self.physics.friction_sweeps > 0:
            impulse, du_t, dv, dw, angular = self._project_friction(
                geo, impulse, du_n, dv, dw, angular, n_node, is_particle)

        receivers, senders = geo["receivers"], geo["senders"]
        vbar_node = geo["v_node"] + 0.5 * dv
        vbar = vbar_node[receivers]
        # a pair: J on the receiver, -J on the sender
        per_edge_pp = -jnp.sum(impulse * (vbar - vbar_node[senders]), axis=-1) * geo["is_pp"]
        per_edge_pw = jnp.sum(impulse * (geo["u_wall"] - vbar), axis=-1) * geo["is_pw"]
        wbar_node = None
        if self.spin:
            # the work of the angular impulses on the midpoint spins (I dw . wbar = d KE_rot)
            wbar_node = geo["w_node"] + 0.5 * dw
            a_recv, a_send = angular
            rot_work = (jnp.sum(a_recv * wbar_node[receivers], axis=-1)
                        + jnp.sum(a_send * wbar_node[senders], axis=-1))
            per_edge_pp = per_edge_pp - rot_work * geo["is_pp"]
            per_edge_pw = per_edge_pw - rot_work * geo["is_pw"]
        # The normal-impulse part of each contact's dissipation, (J . n)(n . (vbar_partner -
        # vbar_r)); the rest (tangential impulse, torques) is its tangential part.
        vbar_partner = jnp.where(geo["is_pw"][:, None], geo["u_wall"], vbar_node[senders])
        per_edge_normal = (jnp.sum(impulse * geo["normal"], axis=-1)
                           * jnp.sum(geo["normal"] * (vbar_partner - vbar), axis=-1)
                           * (geo["is_pp"] | geo["is_pw"]))
        work_wall_e = jnp.sum(impulse * geo["u_wall"], axis=-1) * geo["is_pw"]
        n_graph = graph.n_node.shape[0]
        edge_graph = _edge_graph_index(graph)[0::2]
        seg = lambda x: jax.ops.segment_sum(x, edge_graph, num_segments=n_graph)  # noqa: E731
        d_pp, d_pw = seg(per_edge_pp), seg(per_edge_pw)
        target = self._dissipation_target(
            {"d_pp": d_pp, "d_pw": d_pw, "geo": geo, "impulse": impulse, "angular": angular,
             "wbar_node": wbar_node, "edge_pp": per_edge_pp, "edge_pw": per_edge_pw,
             "edge_normal": per_edge_normal}, seg)
        terms = {"dv": dv, "diss_pp": d_pp, "diss_pw": d_pw, "work_wall": seg(work_wall_e),
                 "dE_target": target, "du_n": du_n, "du_t": du_t,
                 "gate": geo["gate"],
                 # where the rigid limit set the normal impulse (the learned one was below it)
                 "at_floor": (geo["floor"] > self._learned_normal(geo, logits)) * geo["gate"]}
        if self.spin:
            terms["dw"] = dw
        contacts = {"geo": geo, "diss": per_edge_pp + per_edge_pw, "diss_normal": per_edge_normal}
        return terms, contacts

    def _accelerations(self, terms: dict[str, jax.Array]) -> jax.Array:
        """(n_node, 3) m/s^2, or with spin (n_node, 6): then the angular ones (rad/s^2)."""
        dt = self.physics.dt
        if self.spin:
            return jnp.concatenate([terms["dv"], terms["dw"]], axis=-1) / dt
        return terms["dv"] / dt

    def rollout_terms(self, graph: jraph.GraphsTuple):
        """``(accel (n_node, 3), dE_target (n_graph,), ledger (n_graph, 3))`` with ledger
        ``(diss_pp, diss_pw, work_wall)`` J (what :func:`sgn_jax.surrogate.rollout.model_predictor`
        uses, so a rollout records the model's own energy ledger).

        With ``compact_per_ball`` f > 0 (one graph, not vmapped: ``nn.cond`` runs one branch)
        the step runs on the graph of the edge pairs that may act
        (:meth:`_gate_candidates`, :func:`sgn_jax.surrogate.graph.compact_edge_pairs`, a
        block of ceil(2 f N) rows), or on the whole graph in a step with more. A row that
        does not act gives exact zeros (impulse, torques, sweeps, energies), so both give the
        same numbers to float32 rounding (the sums' order)."""
        n_balls = graph.nodes["features"].shape[0] - 2
        rows = graph.senders.shape[0] // 2
        block = math.ceil(2.0 * self.compact_per_ball * n_balls)
        if self.compact_per_ball <= 0 or block >= rows or graph.n_node.shape[0] != 2:
            return self._rollout_outputs(graph)
        keep = self._gate_candidates(graph)
        return nn.cond(
            jnp.sum(keep) <= block,
            lambda mdl, g: mdl._rollout_outputs(compact_edge_pairs(g, keep, block)),
            lambda mdl, g: mdl._rollout_outputs(g), self, graph)

    def _rollout_outputs(self, graph: jraph.GraphsTuple):
        terms = self.step_terms(graph)
        ledger = jnp.stack([terms["diss_pp"], terms["diss_pw"], terms["work_wall"]], axis=-1)
        return self._accelerations(terms), terms["dE_target"], ledger

    # A candidate row's margin over the gate's: the gate's own gap and rate come from the
    # longer computation of the geometry, whose rounding may differ in the last bits
    CANDIDATE_MARGIN_FACTOR = 1.5
    CANDIDATE_MARGIN_SLACK_M = 1.0e-7

    def _gate_candidates(self, graph: jraph.GraphsTuple) -> jax.Array:
        """(E / 2,) bool per primary row: True wherever the gate of :meth:`_edge_geometry`
        may be on (a real edge into a ball whose gap now or at the end of a ballistic step
        is below the kind's gate margin, here with a margin 1.5 times as wide), from the
        newest slot alone (:func:`newest_gap_rate`). A superset of the gate."""
        receivers, senders = graph.receivers[0::2], graph.senders[0::2]
        recv_ball = graph.nodes["particle"][receivers]
        is_pp = graph.edges["pp"][0::2] & recv_ball
        is_pw = graph.edges["pw"][0::2] & recv_ball
        pp_reach, pw_reach, margin = self._reach_and_margin(graph, receivers, senders, is_pp)
        gap, u = newest_gap_rate(graph, self.physics.window, pp_reach, pw_reach)
        reach_gap = jnp.minimum(gap, gap + u * self.physics.dt)
        return (is_pp | is_pw) & (reach_gap < self.CANDIDATE_MARGIN_FACTOR * margin
                                  + self.CANDIDATE_MARGIN_SLACK_M)

    def _reach_and_margin(self, graph: jraph.GraphsTuple, receivers: jax.Array,
                          senders: jax.Array, is_pp: jax.Array) -> tuple[Any, Any, Any]:
        """``(pp_reach, pw_reach, gate_margin)`` m of the primary rows, as
        :meth:`_edge_geometry` uses them (scalars for this kind: one ball radius)."""
        del graph, receivers, senders, is_pp
        radius = self.physics.ball_radius
        return 2.0 * radius, radius, self.physics.gate_margin

    def collision_terms(self, graph: jraph.GraphsTuple):
        """``(accel, dE_target, ledger, grid)``: :meth:`rollout_terms` and the step's contacts
        per pair, a :class:`sgn_jax.surrogate.collisions.ContactGrid` (what a rollout with
        ``collisions=True`` records events from). A contact acts where its gate is on (its
        impulse is nonzero only there); its approach speed ``-u`` and tangential speed are
        those of the inputs (the velocities at the step's start), its overlap ``-gap`` at the
        step's start, its force ``m* du_n / dt`` (the step's mean normal force), its energies
        the two parts of its term of ``diss_pp + diss_pw``."""
        terms, contacts = self._terms_and_contacts(graph)
        geo = contacts["geo"]
        ledger = jnp.stack([terms["diss_pp"], terms["diss_pw"], terms["work_wall"]], axis=-1)
        m_star = self._reduced_mass(geo)
        normal_part = contacts["diss_normal"]
        values = jnp.stack([-geo["u_n"], geo["speed_c"], jnp.maximum(-geo["gap"], 0.0),
                            m_star * terms["du_n"] / self.physics.dt, m_star, normal_part,
                            contacts["diss"] - normal_part], axis=-1)
        n_balls = graph.nodes["features"].shape[0] - 2   # balls, the wall node, padding
        grid = contact_grid(n_balls, geo["receivers"], geo["senders"], geo["gate"] > 0,
                            values.astype(DTYPE))
        return self._accelerations(terms), terms["dE_target"], ledger, grid

    def __call__(self, graph: jraph.GraphsTuple, stats: Any = None):
        del stats
        terms = self.step_terms(graph)
        return self._accelerations(terms), terms["dE_target"]


def per_contact_damping(parts: dict[str, Any], share: jax.Array, spin: bool) -> jax.Array:
    """(E,) J per contact row, the DEM's damping in it from the model's own losses: the
    normal part whole (the Hertz spring stores, the normal damper dissipates: the DEM's normal
    losses are all damping), the rolling friction's none (the DEM's rolling losses), the rest
    (the tangential impulse and its torques) by the kind's tangential damping share
    ``share`` (2,) = (ball-ball, ball-wall), the DEM's tangential damping against its Coulomb
    slip. ``parts``: the rows' ``geo`` (with ``arm``, ``normal``, ``receivers``, ``senders``,
    ``is_pp``, ``is_pw``), ``impulse``, ``angular`` (the final angular impulses), ``wbar_node``
    (the midpoint spins), ``edge_pp``, ``edge_pw`` and ``edge_normal`` (the rows' losses)."""
    geo = parts["geo"]
    total = parts["edge_pp"] + parts["edge_pw"]
    normal = parts["edge_normal"]
    rolling = jnp.zeros_like(total)
    if spin:
        # the rolling impulse from the final angular impulses: a_recv = a_r n x J + l_roll
        # (the sweeps add only torques of J, the normal sweeps none)
        a_recv = parts["angular"][0]
        l_roll = a_recv - geo["arm"][:, None] * jnp.cross(geo["normal"], parts["impulse"])
        wbar = parts["wbar_node"]
        w_rel_bar = wbar[geo["receivers"]] - jnp.where(geo["is_pp"][:, None],
                                                       wbar[geo["senders"]], 0.0)
        rolling = -jnp.sum(l_roll * w_rel_bar, axis=-1) * (geo["is_pp"] | geo["is_pw"])
    tangential = total - normal - rolling
    return normal + jnp.where(geo["is_pw"], share[1], share[0]) * tangential


def _edge_graph_index(graph: jraph.GraphsTuple) -> jax.Array:
    n_edge_total = graph.senders.shape[0]
    n_graph = graph.n_edge.shape[0]
    return jnp.repeat(jnp.arange(n_graph), graph.n_edge, total_repeat_length=n_edge_total)


def physics_from_config(cfg: Any) -> ContactPhysics:
    """The :class:`ContactPhysics` of an experiment config (read by attribute: ``balls``,
    ``material.friction``, ``dem.dt`` and ``gravity``, ``graph.window`` and ``wall_patches``;
    no config import). The config's graphs have the same ``wall_patches``
    (``graph_spec_from_config``), so each contact kind's MLP runs on its own rows only."""
    radius = float(cfg.balls.radius)
    mass = float(cfg.balls.density) * 4.0 / 3.0 * math.pi * radius ** 3
    factor = float(getattr(cfg.model, "overlap_law_factor", 0.0))
    peaks = {}
    if factor > 0:   # the DEM law's deepest overlap at 1 m/s (a ms of host numpy)
        mat = cfg.material
        for kind, partner in (("pp", {"radius_2": radius, "mass_2": mass}), ("pw", {})):
            law = make_contact_law(mat.young, mat.poisson, mat.restitution, mat.friction,
                                   mat.rolling_friction, radius, mass, **partner)
            peak, duration = head_on_impact(law)
            peaks[f"overlap_peak_{kind}"] = peak
            if getattr(cfg.model, "law_rebound", False):
                peaks[f"rebound_time_{kind}"] = duration / peak
                peaks["restitution"] = float(mat.restitution)
    return ContactPhysics(ball_radius=radius, ball_mass=mass, dt=float(cfg.dem.dt),
                          gravity=tuple(float(g) for g in cfg.dem.gravity),
                          friction=float(cfg.material.friction), window=int(cfg.graph.window),
                          wall_patches=int(cfg.graph.wall_patches),
                          rolling_friction=float(cfg.material.rolling_friction),
                          overlap_limit=float(getattr(cfg.model, "overlap_limit", 0.0)),
                          overlap_law_factor=factor,
                          overlap_sweeps=int(getattr(cfg.model, "overlap_sweeps", 0)),
                          friction_sweeps=int(getattr(cfg.model, "friction_sweeps", 0)),
                          damping_target=str(getattr(cfg.model, "damping_target", "kind")),
                          rebound_exact=str(getattr(cfg.model, "law_rebound_exact", "off")),
                          **peaks)


def make_contact_net(cfg: Any) -> ContactNet:
    """The factory of kind "contact": a :class:`ContactNet` of a whole experiment config
    (``[model] hidden`` and ``mlp_layers`` size its impulse MLPs; ``spin`` makes the balls'
    angular velocities rollout state; the other keys it reads are the overlap limit's and the
    sweeps', :func:`physics_from_config`)."""
    return ContactNet(physics=physics_from_config(cfg), hidden=int(cfg.model.hidden),
                      mlp_layers=int(cfg.model.mlp_layers), spin=bool(cfg.model.spin))


register_model("contact", make_contact_net, builds_from="config", node_walls=False,
               description="contact-impulse model: invariant edge inputs, equal and opposite "
                           "impulses, dissipation from its own impulses")
