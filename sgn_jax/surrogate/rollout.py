"""The surrogate rollout: one jitted, differentiable ``lax.scan`` over SGN steps (paper 2.2.3).

One step (time indexing as in :mod:`sgn_jax.surrogate.graph`; the window ends at sample n,
time t_n)::

    graph      = build_graph(window_n)                  same featurizer as in training
    a_n, dE_n  = predictor(params, stats, graph, step)  de-normalised (m/s^2, J)
    v_n        = (x_n - x_{n-1}) / dt                   from the window
    v_{n+1}    = v_n + a_n dt                           semi-implicit Euler
    x_{n+1}    = x_n + v_{n+1} dt
    offset, offset velocity at t_{n+1} = t0 + (step + 1) dt    (motion module, float64)
    snap-back: phi(x_{n+1}) >= phi_sb -> x_{n+1} -= (phi - phi_sb) n      (optional)
    window_{n+1} = slide(window_n, x_{n+1}, jar state at t_{n+1});  E += dE_n

Positions, time and the energy sum are float64; the network runs in float32. Time is an integer
step count ``step`` (0 at the rollout's start) and ``t = t0 + step * dt`` is formed in float64,
so the jar phase does not drift over long rollouts.

Snap-back (paper step 7; docs/rollout.md): a ball with ``phi >= phi_sb`` is moved once along
``-n`` to ``phi = phi_sb`` (exactly for a planar wall; to first order elsewhere). Its velocity
is left unchanged, as in the paper's code, where velocity is a state variable. Here the velocity
is the finite difference of the window's positions, so "unchanged" means that the ball's whole
window history (all W + 1 positions) is translated with it: every velocity feature and the next
integration step see the same velocities as without the snap, and only the phi/normal features
move. ``snap_velocity="position"`` moves only the newest position instead, so the
finite-difference velocity loses the snapped distance / dt (a position-based wall). The snap
must be switched off to replay a DEM trajectory: DEM balls in wall contact have phi > -R and in
hard impacts reach phi >= -0.0049 m (0.1 mm overlap); they would be moved.

Memory of a differentiated rollout: the steps are grouped into frames of ``save_every`` steps
and the frames into chunks of ``checkpoint_steps``; each chunk is a ``jax.checkpoint``-ed scan,
so reverse mode stores one carry per chunk plus the residuals of one chunk (O(S / c + c) for S
steps and chunks of c), not of every step. A run of one chunk is not checkpointed (nothing to
save: it would only recompute the chunk in the backward pass).

Public API:

- :func:`make_rollout` -> ``rollout(params, stats, window0, motion, sdf, t0) -> RolloutResult``
  (jitted; ``jax.grad`` and ``jax.vmap`` apply to it);
- :func:`make_rollout_advance` -> ``advance(params, stats, state, motion, sdf, t0)`` continues
  a :class:`RolloutState` (the host-level chunked run uses it);
- predictors: :func:`model_predictor` (the SGN), :func:`replay_predictor` (given accelerations
  and dissipation, the "cheating model"); :func:`analytic_jar_query` (exact jar SDF, e.g. for
  gradients w.r.t. jar parameters);
- :func:`run_rollout`: a trained model + a dataset -> prediction file (``sgn-jax rollout``).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import Any, NamedTuple

import flax.linen as nn
import flax.struct
import jax
import jax.numpy as jnp
import jraph
import numpy as np

from sgn_jax.errors import SGNJaxError
from sgn_jax.motion import Motion, frequency_hz, offset, velocity
from sgn_jax.scene import SDFQuery, analytic_jar_query, grid_query
from sgn_jax.surrogate.collisions import (
    DEFAULT_CAPACITY,
    check_capacity,
    collision_arrays,
    init_collisions,
    pending_energy,
    update_events,
)
from sgn_jax.surrogate.graph import (
    GraphSpec,
    Window,
    build_graph,
    neighbour_pairs,
    slide_window,
    with_spins,
)
from sgn_jax.surrogate.model import make_predict

F64 = jnp.float64
I32 = jnp.int32

Predictor = Callable[[Any, Any, jraph.GraphsTuple, jax.Array], tuple[jax.Array, jax.Array]]
"""``predictor(params, stats, raw_graph, step) -> (accel (>= N, 3) m/s^2, dE () J)``.

``step`` is the int32 step index since the rollout's start; rows beyond the N balls of
``accel`` are ignored. A kind that carries spin as state returns ``accel`` (>= N, 6): the
linear accelerations (m/s^2) and then the angular ones (rad/s^2), which the rollout integrates
into the window's ``spins``."""


class RolloutError(SGNJaxError, ValueError):
    """Bad rollout input (shapes, step counts, start index) or a diverged rollout."""


# --------------------------------------------------------------------------------------------
# Pytrees


@flax.struct.dataclass
class RolloutState:
    """The scan carry: the window, the step count and the dissipation sum.

    Attributes:
        window: :class:`sgn_jax.surrogate.graph.Window` ending at the current sample
            (positions f64).
        step: () int32, steps taken since the rollout's start (time t0 + step * dt).
        energy: () float64 J, cumulative predicted dissipation since the start.
        collisions: the collision ledger (:class:`sgn_jax.surrogate.collisions.CollisionCarry`:
            the open events and the table of the closed ones) of a rollout with
            ``collisions=True``; None otherwise.
        neighbours: a :class:`NeighbourList` (:func:`empty_neighbour_list`): each step's
            ball-ball candidates come from it instead of all N (N - 1) / 2 pairs, the same
            graph; None (the default): all pairs.
    """

    window: Window
    step: jax.Array
    energy: jax.Array
    collisions: Any = None
    neighbours: Any = None


@flax.struct.dataclass
class NeighbourList:
    """The ball pairs a rollout step tests for ball-ball edges, carried from step to step.

    A Verlet list (as the DEM's, docs/dem.md): every pair within the graph's reach plus
    ``skin`` at the positions ``reference`` (:func:`sgn_jax.surrogate.graph.neighbour_pairs`),
    rebuilt at the start of a step in which some ball has moved more than ``skin`` / 2 from
    its reference position. Until then no pair outside the list can come within the graph's
    reach, so the graph is the one of all pairs, edge for edge, at the cost of C rows a step
    instead of N (N - 1) / 2 (and one all-pairs build every few steps).

    Attributes:
        pairs: (C, 2) int32 (i, j), i < j, unused rows (N, N).
        reference: (N, 3) m, the newest positions at the last build.
        overflow: () bool, True once a build found more than C pairs (sticky: the host refuses
            the run, :func:`check_neighbours`).
        skin: m, the list's margin over the graph's reach (static).
    """

    pairs: jax.Array
    reference: jax.Array
    overflow: jax.Array
    skin: float = flax.struct.field(pytree_node=False, default=1e-3)


def empty_neighbour_list(window: Window, capacity: int, skin: float) -> NeighbourList:
    """A list of ``capacity`` pairs and margin ``skin`` (m) that the rollout's first step
    builds (its reference lies 1 m from every ball)."""
    if capacity < 1 or not skin > 0:
        raise RolloutError(f"a neighbour list needs capacity >= 1 and skin > 0 m, got "
                           f"{capacity} and {skin}")
    x = jnp.asarray(window.positions[-1], F64)
    n = x.shape[0]
    return NeighbourList(pairs=jnp.full((capacity, 2), n, I32), reference=x + 1.0,
                         overflow=jnp.zeros((), bool), skin=float(skin))


def _refresh_neighbours(nl: NeighbourList, window: Window, spec: GraphSpec) -> NeighbourList:
    """``nl`` rebuilt at the window's newest positions when a ball has moved more than half
    the skin since the last build (``lax.cond``: a step that keeps it pays N distances)."""
    x = jnp.asarray(window.positions[-1], F64)
    moved2 = jnp.max(jnp.sum((x - nl.reference) ** 2, axis=-1))

    def rebuild(old: NeighbourList) -> NeighbourList:
        pairs, found = neighbour_pairs(x, spec, window.charge, old.skin, old.pairs.shape[0])
        return old.replace(pairs=pairs, reference=x,
                           overflow=old.overflow | (found > old.pairs.shape[0]))

    return jax.lax.cond(moved2 > (0.5 * nl.skin) ** 2, rebuild, lambda old: old, nl)


def check_neighbours(state: RolloutState) -> None:
    """Refuse (host side) a rollout whose neighbour list overflowed: its graphs may have
    missed ball-ball contacts."""
    nl = state.neighbours
    if nl is not None and bool(nl.overflow):
        raise RolloutError(
            f"the rollout's neighbour list of {nl.pairs.shape[0]} ball pairs overflowed (more "
            f"pairs within the graph's reach + {nl.skin:g} m); give it a larger capacity "
            "(sgn_jax.pipelines.rollout_run.NEIGHBOUR_PAIRS_PER_BALL)")


@flax.struct.dataclass
class StepRecord:
    """Per-step outputs (each (S,) once stacked; int32 counts).

    ``n_pp_edges``, ``n_pw_edges`` and ``overflow`` describe the graph the step's prediction was
    made from (directed edges; overflow = ball-ball edges dropped by the capacity);
    ``n_outside`` (phi > 0) and ``n_snapped`` the balls after the step.

    The model's own energy ledger (J per step; NaN for a kind that does not report it, such as
    the SGN, whose dE is learned apart from its motion): ``diss_pp`` and ``diss_pw``, what its
    ball-ball and ball-wall impulses take out of the balls, and ``work_wall``, the work of its
    ball-wall impulses at the jar's velocity (:mod:`sgn_jax.surrogate.contact`).
    """

    dE: jax.Array
    energy_cum: jax.Array
    n_pp_edges: jax.Array
    n_pw_edges: jax.Array
    overflow: jax.Array
    n_outside: jax.Array
    n_snapped: jax.Array
    diss_pp: jax.Array
    diss_pw: jax.Array
    work_wall: jax.Array


@flax.struct.dataclass
class RolloutResult:
    """What a rollout returns (S steps, P frames, N balls; leading batch axis under vmap).

    Attributes:
        t_step: (S,) f64 s, time at the END of each step.
        steps: :class:`StepRecord` of (S,) arrays: dE (J), energy_cum (J), edge and ball counts.
        t_pos: (P,) f64 s, times of the saved frames.
        positions: (P, N, 3) f64 m, ball positions at t_pos.
        offsets: (P, 3) f64 m, jar offset at t_pos.
        final: the :class:`RolloutState` after the last step (to continue the rollout).
        spins: (P, N, 3) f64 rad/s, the balls' angular velocities at t_pos (0 throughout for a
            kind without spin state).
    """

    t_step: jax.Array
    steps: StepRecord
    t_pos: jax.Array
    positions: jax.Array
    offsets: jax.Array
    final: RolloutState
    spins: jax.Array

    @property
    def energy(self) -> jax.Array:
        """Cumulative dissipation after the last step (J)."""
        return self.steps.energy_cum[..., -1]

    def collision_arrays(self, flush: bool = True, packing: int | None = None
                         ) -> dict[str, np.ndarray]:
        """The collision events of this result's call, the ``collision_*`` arrays of
        :mod:`sgn_jax.surrogate.collisions`; ``flush``: with the events still open at its end
        (flags bit 1); ``packing``: for a batched result (an ensemble), its packing k. Needs a
        rollout with ``collisions=True``; raises
        :class:`sgn_jax.surrogate.collisions.CollisionCapacityError` when the call closed more
        events than ``collision_capacity``."""
        final = self.final
        if final.collisions is None:
            raise RolloutError("this rollout recorded no collision events: run it with "
                               "collisions=True (a contact model; RolloutOptions)")
        batched = np.ndim(final.step) > 0
        if batched != (packing is not None):
            raise RolloutError(
                f"this result has {np.shape(final.step)[0] if batched else 'no'} packings: "
                + ("pass packing=k" if batched else "call it without packing"))
        if batched:
            final = jax.tree_util.tree_map(lambda a: a[packing], final)
        return collision_arrays(final.collisions, int(final.step) if flush else None)

    def collision_pending(self, packing: int | None = None) -> np.ndarray:
        """(2,) J: the dissipation of below-floor contact steps that no event has taken at the
        end of this call (:func:`sgn_jax.surrogate.collisions.pending_energy`); the events of
        :meth:`collision_arrays` plus this add up to the model's ledger."""
        final = self.final
        if final.collisions is None:
            raise RolloutError("this rollout recorded no collision events: run it with "
                               "collisions=True (a contact model; RolloutOptions)")
        carry = final.collisions
        if packing is not None:
            carry = jax.tree_util.tree_map(lambda a: a[packing], carry)
        return pending_energy(carry)

    def prediction_arrays(self) -> dict[str, np.ndarray]:
        """The arrays of :func:`sgn_jax.records.prediction.save_prediction` (unbatched result)."""
        s = self.steps
        return {
            "t_step": np.asarray(self.t_step, np.float64),
            "dE": np.asarray(s.dE, np.float64),
            "energy_cum": np.asarray(s.energy_cum, np.float64),
            "n_pp_edges": np.asarray(s.n_pp_edges, np.int64),
            "n_pw_edges": np.asarray(s.n_pw_edges, np.int64),
            "overflow": np.asarray(s.overflow, np.int64),
            "n_outside": np.asarray(s.n_outside, np.int64),
            "n_snapped": np.asarray(s.n_snapped, np.int64),
            "t_pos": np.asarray(self.t_pos, np.float64),
            "pos": np.asarray(self.positions, np.float64),
            "offset": np.asarray(self.offsets, np.float64),
            **self.ledger_arrays(),
        }

    def ledger_arrays(self) -> dict[str, np.ndarray]:
        """The model's own energy ledger per step (J), for a kind that reports one (extra
        arrays of the prediction file: ``diss_pp_model``, ``diss_pw_model``, ``work_wall_model``,
        and the spins of the frames ``omega_model`` (P, N, 3) rad/s, whose rotational energy
        the ledger counts); empty otherwise."""
        s = self.steps
        if np.all(np.isnan(np.asarray(s.diss_pp))):
            return {}
        return {"diss_pp_model": np.asarray(s.diss_pp, np.float64),
                "diss_pw_model": np.asarray(s.diss_pw, np.float64),
                "work_wall_model": np.asarray(s.work_wall, np.float64),
                "omega_model": np.asarray(self.spins, np.float64)}


@flax.struct.dataclass
class ReplayTable:
    """Parameters of :func:`replay_predictor`: per-step accelerations (S, N, 3) and dE (S,)."""

    accel: jax.Array
    dE: jax.Array


# --------------------------------------------------------------------------------------------
# Predictors and SDF queries


def model_predictor(model_or_predict: Any, collisions: bool = False) -> Predictor:
    """Predictor of an SGN: a flax ``SGN`` module or a ``predict(params, stats, raw_graph)``
    from :func:`sgn_jax.surrogate.model.make_predict`. Returns the N ball rows and dE of graph 0.

    ``collisions``: the predictor also returns the step's contacts per pair (a
    :class:`sgn_jax.surrogate.collisions.ContactGrid`, what a rollout with ``collisions=True``
    records events from); only a kind with ``collision_terms`` (the contact model) has them."""
    if collisions:
        method = getattr(model_or_predict, "collision_terms", None)
        if not isinstance(model_or_predict, nn.Module) or method is None:
            raise RolloutError(
                f"collisions=True needs a model that reports its contacts' impulses (model kind "
                f"'contact'), got {type(model_or_predict).__name__}; run this one with "
                "collisions=False")

        def collision_predictor(params: Any, stats: Any, graph: jraph.GraphsTuple,
                                step: jax.Array):
            del stats, step
            accel, de, ledger, grid = model_or_predict.apply({"params": params}, graph,
                                                             method=method)
            return accel, de[0], ledger[0], grid

        return collision_predictor
    if isinstance(model_or_predict, nn.Module):
        predict = make_predict(model_or_predict)
    elif callable(model_or_predict):
        predict = model_or_predict
    else:
        raise TypeError(f"model_predictor needs an SGN module or a predict function, got "
                        f"{type(model_or_predict).__name__}")

    terms = getattr(model_or_predict, "rollout_terms", None)
    if isinstance(model_or_predict, nn.Module) and terms is not None:
        # A kind that reports its own energy ledger (the contact model): (accel, dE, ledger).
        def ledger_predictor(params: Any, stats: Any, graph: jraph.GraphsTuple, step: jax.Array):
            del stats, step
            accel, de, ledger = model_or_predict.apply({"params": params}, graph,
                                                       method=terms)
            return accel, de[0], ledger[0]

        return ledger_predictor

    def predictor(params: Any, stats: Any, graph: jraph.GraphsTuple, step: jax.Array):
        del step
        accel, de = predict(params, stats, graph)
        return accel, de[0]

    return predictor


def single_rollout_model(model: Any) -> tuple[Any, bool]:
    """``(module, tiers)`` for ONE rollout, not vmapped over packings: the model kind's
    single-rollout form where it has one (``for_single_rollout()``; the contact kind runs each
    MLP on its own rows there) and whether pair-capacity tiers speed it up
    (``capacity_tiers_help``, default True). The single-rollout drivers (``run_rollout``, the
    demo, ``benchmarks/bench_ratio.py``) decide by this, one place for both rules."""
    tiers = bool(getattr(model, "capacity_tiers_help", True))
    single = getattr(model, "for_single_rollout", None)
    return (single() if single is not None else model), tiers


NO_LEDGER = (float("nan"),) * 3


def _with_ledger(out: tuple) -> tuple[jax.Array, jax.Array, jax.Array, Any]:
    """A predictor's ``(accel, dE)``, ``(accel, dE, ledger (3,))`` or ``(accel, dE, ledger,
    grid)`` as the latter (ledger = ``(diss_pp, diss_pw, work_wall)`` J, NaN when the predictor
    does not report one; grid: the contacts per pair, None when it does not report them)."""
    ledger = out[2] if len(out) >= 3 else jnp.asarray(NO_LEDGER, F64)
    grid = out[3] if len(out) == 4 else None
    return out[0], out[1], jnp.asarray(ledger).astype(F64).reshape(3), grid


def replay_predictor() -> Predictor:
    """The "cheating model": ``params`` is a :class:`ReplayTable`; step s returns its row s.

    Fed the finite-difference accelerations ``(x_{n+1} - 2 x_n + x_{n-1}) / dt^2`` and the DEM
    dissipation of ``(t_n, t_{n+1}]`` (:func:`sgn_jax.surrogate.graph.targets_from_arrays`) for
    n = start + s, the rollout reproduces the trajectory to rounding (snap-back off).
    """

    def predictor(table: ReplayTable, stats: Any, graph: jraph.GraphsTuple, step: jax.Array):
        del stats, graph
        return table.accel[step], table.dE[step]

    return predictor


def _default_query() -> SDFQuery:
    return grid_query


# --------------------------------------------------------------------------------------------
# The step


def jar_state_window(window: Window, motion: Motion, t0: jax.Array, dt: float) -> Window:
    """``window`` with its jar state (offsets, velocities at the slot times
    ``t0 - (W-1) dt .. t0``, rotational frequency) recomputed from ``motion`` (float64), and
    its spins as float64 (zeros, balls not turning, where the window has none: the rollout's
    carry always holds them)."""
    w = jnp.shape(window.offsets)[0]
    times = jnp.asarray(t0, F64) + dt * jnp.arange(-(w - 1), 1, dtype=F64)
    return with_spins(window).replace(
        positions=jnp.asarray(window.positions, F64),
        offsets=jnp.asarray(offset(motion, times), F64),
        offset_velocities=jnp.asarray(velocity(motion, times), F64),
        frequency_hz=jnp.asarray(frequency_hz(motion), F64),
        charge=None if window.charge is None else _as_f64(window.charge),
    )


def init_state(window0: Window, motion: Motion, t0: float | jax.Array, dt: float,
               collision_capacity: int = 0) -> RolloutState:
    """The rollout's initial carry: ``window0``'s positions, the jar state of ``motion``;
    with ``collision_capacity`` > 0 an empty collision ledger whose table holds that many
    events per jitted call (:mod:`sgn_jax.surrogate.collisions`; static)."""
    collisions = None
    if collision_capacity:
        n_balls = int(jnp.shape(window0.positions)[1])
        collisions = init_collisions(n_balls, collision_capacity, t0, dt)
    return RolloutState(window=jar_state_window(window0, motion, t0, dt),
                        step=jnp.zeros((), I32), energy=jnp.zeros((), F64),
                        collisions=collisions)


@dataclasses.dataclass(frozen=True)
class SnapBack:
    """Static snap-back settings (see the module docstring)."""

    enabled: bool = True
    phi_sb: float = -0.0049
    keep_velocity: bool = True
    pp_max_overlap: float | None = None  # m; None: no ball-ball separation


def snap_back_shift(phi: jax.Array, normal: jax.Array, phi_sb: float | jax.Array
                    ) -> tuple[jax.Array, jax.Array]:
    """The snap-back (module docstring): the shift (N, 3) m that moves every ball with
    ``phi >= phi_sb`` along ``-normal`` to ``phi_sb``, and which balls it moves (N,) bool.
    ``phi_sb`` is one threshold (m) or each ball's (N,) (a charge of several sizes:
    :func:`charge_snap_threshold`). A zero normal (vanishing gradient) gives no direction:
    such a ball is not moved."""
    snapped = (phi >= phi_sb) & (jnp.sum(normal * normal, axis=-1) > 0)
    return jnp.where(snapped[:, None], -(phi - phi_sb)[:, None] * normal, 0.0), snapped


def charge_snap_threshold(phi_sb: float, ball_radius: float, radius: jax.Array) -> jax.Array:
    """Each ball's snap-back threshold (N,) m for a window with a charge: ``phi_sb`` is set for
    a ball of ``ball_radius`` (the config's, e.g. -4.9 mm for 5 mm: 0.1 mm into the wall), so
    a ball of radius r_i is snapped from the same depth into the wall,
    ``phi_sb + ball_radius - r_i``. With one threshold for all, every ball smaller than
    ``ball_radius`` that touches the wall would be pushed off it at every step."""
    return phi_sb + ball_radius - jnp.asarray(radius, F64)


def separate_pairs(positions: jax.Array, radius: float | jax.Array, max_overlap: float
                   ) -> tuple[jax.Array, jax.Array]:
    """Ball-ball analogue of the snap-back: the shift that reduces every overlap beyond
    ``max_overlap`` back to it.

    For each pair with overlap o = r_i + r_j - |x_j - x_i| > ``max_overlap`` both balls move apart
    along the pair's normal by (o - max_overlap) / 2 (one Jacobi pass: a ball in several deep
    overlaps gets the sum of its shifts). Coincident balls (|x_j - x_i| = 0) have no normal and
    are not moved.

    Args:
        positions: (N, 3) m; radius: R (m), or each ball's (N,); max_overlap: m.
    Returns:
        ``(shift (N, 3) m, n_pairs ())``: the shift to add and the number of pairs separated.
    """
    diff = positions[None, :, :] - positions[:, None, :]  # x_j - x_i at [i, j]
    dist2 = jnp.sum(diff * diff, axis=-1)
    n = positions.shape[0]
    valid = (dist2 > 0) & ~jnp.eye(n, dtype=bool)
    dist = jnp.sqrt(jnp.where(valid, dist2, 1.0))
    r = jnp.broadcast_to(jnp.asarray(radius, positions.dtype), (n,))
    excess = jnp.where(valid, r[:, None] + r[None, :] - dist - max_overlap, 0.0)
    deep = excess > 0
    push = jnp.where(deep, 0.5 * excess / dist, 0.0)  # per unit of (x_j - x_i)
    shift = -jnp.sum(push[:, :, None] * diff, axis=1)
    return shift, jnp.sum(deep, dtype=I32) // 2


def check_tiers(spec: GraphSpec, tiers: Any) -> tuple[int, ...]:
    """Validated ball-pair capacity tiers: increasing, each below ``spec.pp_pair_capacity``."""
    tiers = tuple(int(t) for t in (tiers or ()))
    if any(t < 1 for t in tiers) or list(tiers) != sorted(set(tiers)) \
            or (tiers and tiers[-1] >= spec.pp_pair_capacity):
        raise RolloutError(f"pp_capacity_tiers must be increasing pair counts in [1, "
                           f"{spec.pp_pair_capacity}) (the graph's pp_pair_capacity), got {tiers}")
    return tiers


def _predict_tiered(spec: GraphSpec, tiers: tuple[int, ...], predictor: Predictor,
                    query: SDFQuery, params: Any, stats: Any, sdf: Any, window: Window,
                    step: jax.Array, candidates: jax.Array | None = None):
    """Build the graph with the smallest capacity tier that holds all ball pairs and predict.

    Padding edges are masked in the network, so every tier gives the same prediction (up to
    float rounding); a smaller tier only costs fewer edge-MLP rows. The smallest tier's graph
    is built first (its counts are exact whatever the capacity); ``lax.switch`` runs one branch
    (under ``vmap`` all branches run: use no tiers there).
    """
    specs = [dataclasses.replace(spec, pp_pair_capacity=t) for t in tiers] + [spec]
    graph0, counts0 = build_graph(window, sdf, specs[0], query, candidates)
    n_pairs = counts0.n_pp // 2
    dropped = 2 * jnp.maximum(n_pairs - spec.pp_pair_capacity, 0)
    counts = counts0._replace(pp_dropped=dropped.astype(counts0.pp_dropped.dtype))
    if not tiers:
        return _with_ledger(predictor(params, stats, graph0, step)), counts
    index = jnp.sum(n_pairs > jnp.asarray(tiers), dtype=I32)

    def branch(k: int):
        def run(_: Any):
            graph = graph0 if k == 0 else build_graph(window, sdf, specs[k], query, candidates)[0]
            accel, de, ledger, grid = _with_ledger(predictor(params, stats, graph, step))
            n = spec.n_particles
            return (jnp.asarray(accel)[:n].astype(F64), jnp.asarray(de).astype(F64).reshape(()),
                    ledger, grid)
        return run

    return jax.lax.switch(index, [branch(k) for k in range(len(specs))], None), counts


def _present_only(window: Window, phi: jax.Array) -> jax.Array:
    """``phi`` (N,) with the absent balls of a padded charge (parked outside the jar, not
    particles) at -inf: never snapped, never counted outside."""
    if window.charge is None:
        return phi
    return jnp.where(window.charge.present, phi, -jnp.inf)


def _make_step(spec: GraphSpec, predictor: Predictor, query: SDFQuery, snap: SnapBack,
               params: Any, stats: Any, motion: Motion, sdf: Any, t0: jax.Array,
               tiers: tuple[int, ...] = (), collisions: bool = False):
    n, dt = spec.n_particles, spec.dt

    def step_fn(state: RolloutState, _: Any) -> tuple[RolloutState, StepRecord]:
        window = state.window
        neighbours, candidates = state.neighbours, None
        if neighbours is not None:
            neighbours = _refresh_neighbours(neighbours, window, spec)
            candidates = neighbours.pairs
        (accel, de, ledger, grid), counts = _predict_tiered(spec, tiers, predictor, query, params,
                                                            stats, sdf, window, state.step,
                                                            candidates)
        ledger_carry = state.collisions
        if collisions:
            if grid is None:
                raise RolloutError("collisions=True needs a predictor that reports its contacts "
                                   "(model_predictor(model, collisions=True) of a contact model)")
            if ledger_carry is None:
                raise RolloutError("collisions=True needs a state with a collision ledger: "
                                   "init_state(..., collision_capacity=C)")
            ledger_carry = update_events(ledger_carry, grid, state.step)
        accel = jnp.asarray(accel)[:n].astype(F64)
        de = jnp.asarray(de).astype(F64).reshape(())
        spins = window.spins
        if accel.shape[-1] == 6:  # a kind with spin state: linear, then angular acceleration
            if spins is None:
                raise RolloutError("this model carries the balls' spins as state: start the "
                                   "rollout from init_state/jar_state_window (zero spins), or "
                                   "give the window spins")
            spins = spins + accel[:, 3:] * dt
            accel = accel[:, :3]

        x_n = window.positions[-1]
        v_n = (x_n - window.positions[-2]) / dt
        v_next = v_n + accel * dt
        x_next = x_n + v_next * dt
        t_next = t0 + (state.step + 1).astype(F64) * dt
        jar_offset = jnp.asarray(offset(motion, t_next), F64)
        jar_velocity = jnp.asarray(velocity(motion, t_next), F64)
        window = slide_window(window, x_next, jar_offset, jar_velocity).replace(spins=spins)

        if snap.pp_max_overlap is not None:  # before the wall snap, so that walls win
            radius = spec.ball_radius if window.charge is None else window.charge.radius
            shift, _ = separate_pairs(window.positions[-1], radius, snap.pp_max_overlap)
            if snap.keep_velocity:
                positions = window.positions + shift[None]
            else:
                positions = window.positions.at[-1].add(shift)
            window = window.replace(positions=positions)

        # The balls' wall distances at the step's new positions and (with the separation on)
        # after the separation; the wall normals only in a step that snaps a ball (lax.cond:
        # a step without one pays one phi query, two with the separation). The snap-back
        # reads the step's new positions x_next and moves the separated ones.
        def wall_distance(x: jax.Array) -> jax.Array:
            return _present_only(window, jnp.asarray(query(sdf, x, jar_offset)[0], F64))

        phi_next = wall_distance(x_next)
        phi_new = phi_next if snap.pp_max_overlap is None else wall_distance(
            window.positions[-1])
        if snap.enabled:
            phi_sb = (snap.phi_sb if window.charge is None else
                      charge_snap_threshold(snap.phi_sb, spec.ball_radius, window.charge.radius))

            def snap_back(positions: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
                phi, normal = query(sdf, x_next, jar_offset)
                phi, normal = jnp.asarray(phi, F64), jnp.asarray(normal, F64)
                shift, snapped = snap_back_shift(_present_only(window, phi), normal, phi_sb)
                if snap.keep_velocity:  # translate the whole history: velocities unchanged
                    positions = positions + shift[None]
                else:  # only the newest position: the FD velocity follows the move
                    positions = positions.at[-1].add(shift)
                return positions, jnp.sum(snapped, dtype=I32), wall_distance(positions[-1])

            positions, n_snapped, phi_after = jax.lax.cond(
                jnp.any(phi_next >= phi_sb), snap_back,
                lambda positions: (positions, jnp.zeros((), I32), phi_new), window.positions)
            window = window.replace(positions=positions)
        else:
            n_snapped, phi_after = jnp.zeros((), I32), phi_new
        energy = state.energy + de
        record = StepRecord(dE=de, energy_cum=energy, n_pp_edges=counts.n_pp.astype(I32),
                            n_pw_edges=counts.n_pw.astype(I32),
                            overflow=counts.pp_dropped.astype(I32),
                            n_outside=jnp.sum(phi_after > 0, dtype=I32), n_snapped=n_snapped,
                            diss_pp=ledger[0], diss_pw=ledger[1], work_wall=ledger[2])
        return RolloutState(window=window, step=state.step + 1, energy=energy,
                            collisions=ledger_carry, neighbours=neighbours), record

    return step_fn


# --------------------------------------------------------------------------------------------
# Factories


def _jit_canonical(fn: Callable[..., RolloutResult], state_arg: bool) -> Callable[..., RolloutResult]:
    """``jax.jit(fn)`` behind a wrapper that casts the window (or state) leaves and ``t0`` to
    float64 arrays first, so that a Python float and a float64 array (weakly and strongly typed
    to jit) do not compile twice. The wrapper has the jitted function's ``lower``,
    ``_cache_size`` and ``jitted``."""
    jitted = jax.jit(fn)

    def canonical(args: tuple) -> tuple:
        params, stats, window_or_state, motion, sdf, t0 = args
        if state_arg:
            window_or_state = window_or_state.replace(window=_as_f64(window_or_state.window))
        else:
            window_or_state = _as_f64(window_or_state)
        return params, stats, window_or_state, motion, sdf, jnp.asarray(t0, F64)

    @functools.wraps(fn)
    def wrapper(*args: Any) -> RolloutResult:
        return jitted(*canonical(args))

    wrapper.lower = lambda *args: jitted.lower(*canonical(args))  # type: ignore[attr-defined]
    wrapper._cache_size = jitted._cache_size  # type: ignore[attr-defined]
    wrapper.jitted = jitted  # type: ignore[attr-defined]
    return wrapper


def _as_f64(window: Any) -> Any:
    """``window`` (or any pytree) with its floating arrays as float64; integer and boolean ones (a charge's
    ball classes and presence) keep their dtype."""
    def cast(a: Any) -> jax.Array:
        a = jnp.asarray(a)
        return a.astype(F64) if jnp.issubdtype(a.dtype, jnp.floating) else a
    return jax.tree_util.tree_map(cast, window)


def _check_counts(n_steps: int, save_every: int, checkpoint_steps: int | None) -> int:
    for name, value in (("n_steps", n_steps), ("save_every", save_every)):
        if not isinstance(value, (int, np.integer)) or value < 1:
            raise RolloutError(f"{name} must be an integer >= 1, got {value!r}")
    if n_steps % save_every:
        raise RolloutError(f"n_steps = {n_steps} must be a multiple of save_every = {save_every} "
                           "(a position frame is saved after every save_every steps)")
    checkpoint_steps = checkpoint_steps or min(n_steps, 100 * save_every)
    if checkpoint_steps < 1 or checkpoint_steps % save_every:
        raise RolloutError(f"checkpoint_steps = {checkpoint_steps} must be a positive multiple of "
                           f"save_every = {save_every}")
    return checkpoint_steps


def _as_predictor(predictor: Any, collisions: bool = False) -> Predictor:
    if isinstance(predictor, nn.Module):
        return model_predictor(predictor, collisions)
    return predictor


@dataclasses.dataclass(frozen=True)
class RolloutOptions:
    """How a rollout steps (the keyword options of every rollout factory).

    Attributes:
        checkpoint_steps: steps per ``jax.checkpoint`` chunk (a multiple of save_every;
            default min(S, 100 save_every)); only matters under reverse-mode differentiation.
        snap_back, phi_sb, snap_velocity: the snap-back (module docstring); off for replays.
        query: ``query(sdf, points, offset) -> (phi, normal)`` (:data:`sgn_jax.scene.SDFQuery`);
            default the SDF grid (:data:`sgn_jax.scene.grid_query`);
            :data:`sgn_jax.scene.analytic_jar_query` for JarParams.
        unroll: ``lax.scan`` unroll factor of the inner step loop (speed only).
        pp_capacity_tiers: smaller ball-pair capacities (increasing, below
            ``spec.pp_pair_capacity``); each step runs the network on the smallest tier that
            holds its pairs (``lax.switch``), the same prediction on fewer padded edge rows.
            Speed only, for single rollouts: under ``vmap`` every tier runs.
        pp_max_overlap: ball-ball separation (:func:`separate_pairs`, not in the paper): after
            each step, pairs overlapping by more than this (m) are moved apart to it, with the
            velocity rule of ``snap_velocity``; None (default) = off, as in the paper.
        collisions: record the collision ledger (:mod:`sgn_jax.surrogate.collisions`; a
            contact model only): the carry's ``collisions`` gathers one event per contact,
            read with :meth:`RolloutResult.collision_arrays`. Off by default.
        collision_capacity: events the ledger's table holds per jitted call (more raise
            :class:`sgn_jax.surrogate.collisions.CollisionCapacityError` on the host).
    """

    checkpoint_steps: int | None = None
    snap_back: bool = True
    phi_sb: float = -0.0049
    snap_velocity: str = "keep"
    query: SDFQuery | None = None
    unroll: int = 1
    pp_capacity_tiers: Any = ()
    pp_max_overlap: float | None = None
    collisions: bool = False
    collision_capacity: int = DEFAULT_CAPACITY


class _Stepping(NamedTuple):
    predictor: Predictor
    query: SDFQuery
    snap: SnapBack
    tiers: tuple[int, ...]
    collisions: bool


def _stepping(spec: GraphSpec, predictor: Any, options: RolloutOptions) -> _Stepping:
    """Check the options and resolve the predictor, the query, the snap rules and the tiers."""
    o = options
    if o.snap_velocity not in ("keep", "position"):
        raise RolloutError(f"snap_velocity must be 'keep' or 'position', got {o.snap_velocity!r}")
    if o.pp_max_overlap is not None and o.pp_max_overlap < 0:
        raise RolloutError(f"pp_max_overlap must be >= 0 m or None, got {o.pp_max_overlap}")
    snap = SnapBack(bool(o.snap_back), float(o.phi_sb), o.snap_velocity == "keep",
                    None if o.pp_max_overlap is None else float(o.pp_max_overlap))
    if o.collisions:
        check_capacity(o.collision_capacity)
    return _Stepping(_as_predictor(predictor, bool(o.collisions)),
                     _default_query() if o.query is None else o.query,
                     snap, check_tiers(spec, o.pp_capacity_tiers), bool(o.collisions))


def make_rollout_step(spec: GraphSpec, predictor: Any, **options: Any) -> Callable[..., Any]:
    """The rollout's ``step`` of the ``init``/``step`` pair (``init`` is :func:`init_state`).

    ``step(params, stats, state, motion, sdf, t0) -> (state, StepRecord)`` advances a
    :class:`RolloutState` by one surrogate step of ``spec.dt`` (``t0``: the rollout's start
    time, so the step's time is ``t0 + (state.step + 1) dt``). Pure and jittable; the scan of
    :func:`make_rollout` is this step. ``options``: :class:`RolloutOptions` (``unroll`` and
    ``checkpoint_steps`` do not apply to one step).
    """
    s = _stepping(spec, predictor, RolloutOptions(**options))

    def step(params: Any, stats: Any, state: RolloutState, motion: Motion, sdf: Any,
             t0: Any) -> tuple[RolloutState, StepRecord]:
        return _make_step(spec, s.predictor, s.query, s.snap, params, stats, motion, sdf,
                          jnp.asarray(t0, F64), s.tiers, s.collisions)(state, None)

    return step


def make_rollout_advance(spec: GraphSpec, predictor: Any, n_steps: int, save_every: int = 1, *,
                         jit: bool = True, **options: Any) -> Callable[..., RolloutResult]:
    """``advance(params, stats, state, motion, sdf, t0) -> RolloutResult`` of ``n_steps`` steps.

    Continues ``state`` (a :class:`RolloutState`, e.g. ``result.final``); frames are saved after
    every ``save_every`` steps (P = n_steps / save_every, no frame of the initial state). ``t0``
    is the rollout's start time (step 0), not the time of ``state``. Arguments as in
    :func:`make_rollout`; ``options``: :class:`RolloutOptions`.
    """
    opts = RolloutOptions(**options)
    s = _stepping(spec, predictor, opts)
    predictor, query, snap, tiers, unroll = s.predictor, s.query, s.snap, s.tiers, opts.unroll
    checkpoint_steps = _check_counts(n_steps, save_every, opts.checkpoint_steps)
    n_frames = n_steps // save_every
    frames_per_chunk = min(checkpoint_steps // save_every, n_frames)
    n_chunks, rest = divmod(n_frames, frames_per_chunk)
    # A run of one chunk is not checkpointed: reverse mode would store that chunk's residuals
    # either way, and jax.checkpoint would only add a second forward pass of it to the backward
    # pass (a design study's gradient horizons are one chunk: ~25 % less to compile and run).
    remat = jax.checkpoint if n_chunks + bool(rest) > 1 else (lambda f: f)

    def advance(params: Any, stats: Any, state: RolloutState, motion: Motion, sdf: Any,
                t0: Any) -> RolloutResult:
        t0 = jnp.asarray(t0, F64)
        if s.collisions and state.collisions is None:   # a state from init_state without one
            state = state.replace(collisions=init_collisions(
                spec.n_particles, opts.collision_capacity, t0, spec.dt))
        step_fn = _make_step(spec, predictor, query, snap, params, stats, motion, sdf, t0,
                             tiers, s.collisions)

        def frame(carry: RolloutState, _: Any):
            carry, records = jax.lax.scan(step_fn, carry, None, length=save_every, unroll=unroll)
            return carry, (records, carry.window.positions[-1], carry.window.offsets[-1],
                           with_spins(carry.window).spins)

        def chunk(carry: RolloutState, length: int):
            return jax.lax.scan(frame, carry, None, length=length)

        pieces = []
        carry = state
        if n_chunks:
            one_chunk = remat(functools.partial(chunk, length=frames_per_chunk))
            carry, ys = jax.lax.scan(lambda c, _: one_chunk(c), carry, None, length=n_chunks)
            pieces.append(jax.tree_util.tree_map(
                lambda a: a.reshape((n_chunks * frames_per_chunk,) + a.shape[2:]), ys))
        if rest:
            carry, ys = remat(functools.partial(chunk, length=rest))(carry)
            pieces.append(ys)
        records, positions, offsets, spins = jax.tree_util.tree_map(
            lambda *a: jnp.concatenate(a) if len(a) > 1 else a[0], *pieces)
        records = jax.tree_util.tree_map(lambda a: a.reshape((n_steps,) + a.shape[2:]), records)
        first = state.step.astype(F64)
        t_step = t0 + (first + jnp.arange(1, n_steps + 1, dtype=F64)) * spec.dt
        t_pos = t0 + (first + save_every * jnp.arange(1, n_frames + 1, dtype=F64)) * spec.dt
        return RolloutResult(t_step=t_step, steps=records, t_pos=t_pos, positions=positions,
                             offsets=offsets, final=carry, spins=spins)

    return _jit_canonical(advance, state_arg=True) if jit else advance


def make_rollout(spec: GraphSpec, predictor: Any, n_steps: int, save_every: int = 1, *,
                 jit: bool = True, **options: Any) -> Callable[..., RolloutResult]:
    """A rollout of ``n_steps`` surrogate steps as one pure (by default jitted) function.

    Args:
        spec: the static :class:`sgn_jax.surrogate.graph.GraphSpec` (N, W, R, dt, edge rules,
            capacity).
        predictor: a flax ``SGN`` module, or a :data:`Predictor`
            (:func:`model_predictor`, :func:`replay_predictor`, or your own).
        n_steps: S, steps per call (a multiple of ``save_every``).
        save_every: steps between saved position frames.
        jit: return the ``jax.jit``-ed function (one compilation per argument shapes/types).
        options: :class:`RolloutOptions` (snap-back, query, tiers, separation, memory).

    Returns:
        ``rollout(params, stats, window0, motion, sdf, t0) -> RolloutResult`` where ``window0``
        is a :class:`sgn_jax.surrogate.graph.Window` ending at time ``t0`` (its jar state is
        recomputed from ``motion``, so the result is a function of the motion parameters alone),
        ``sdf`` what ``query`` reads (an ``SDFGrid`` or ``JarParams``), ``t0`` (s since the start of
        motion) the time of the window's newest sample. P = S / save_every + 1 frames, the first
        at t0. Differentiable in ``params``, ``window0`` positions, the motion and the SDF.
    """
    advance = make_rollout_advance(spec, predictor, n_steps, save_every, jit=False, **options)
    opts = RolloutOptions(**options)

    def rollout(params: Any, stats: Any, window0: Window, motion: Motion, sdf: Any,
                t0: Any) -> RolloutResult:
        state = init_state(window0, motion, t0, spec.dt,
                           opts.collision_capacity if opts.collisions else 0)
        result = advance(params, stats, state, motion, sdf, t0)
        return result.replace(
            t_pos=jnp.concatenate([jnp.asarray(t0, F64)[None], result.t_pos]),
            positions=jnp.concatenate([state.window.positions[-1][None], result.positions]),
            offsets=jnp.concatenate([state.window.offsets[-1][None], result.offsets]),
            spins=jnp.concatenate([with_spins(state.window).spins[None], result.spins]))

    return _jit_canonical(rollout, state_arg=False) if jit else rollout


# --------------------------------------------------------------------------------------------
# Host level: a trained model and a dataset -> prediction file


__all__ = [
    "NeighbourList",
    "Predictor",
    "ReplayTable",
    "RolloutError",
    "RolloutResult",
    "RolloutState",
    "SnapBack",
    "StepRecord",
    "analytic_jar_query",
    "check_neighbours",
    "empty_neighbour_list",
    "init_state",
    "jar_state_window",
    "make_rollout",
    "make_rollout_advance",
    "make_rollout_step",
    "RolloutOptions",
    "model_predictor",
    "single_rollout_model",
    "replay_predictor",
    "separate_pairs",
    "snap_back_shift",
]
