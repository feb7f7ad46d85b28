"""The SGN graph featurizer: a window of states -> a padded ``jraph.GraphsTuple``
(docs/conventions.md section 5).

One function, :func:`build_graph`, is used for training (vmapped over windows of a DEM
trajectory) and for the rollout (inside ``lax.scan``): same rules, same features, static shapes.

Time indexing (``dt`` = sampling step = surrogate step, samples ``x_k = x(t_k)``)
------------------------------------------------------------------------------------
A window *ending at sample n* has W slots ``j = n-W+1 .. n`` and needs the W + 1 positions
``x_{n-W} .. x_n`` because velocities are backward differences, consistent with the
semi-implicit Euler integrator of the rollout::

    v_j = (x_j - x_{j-1}) / dt                        (velocity feature of slot j)
    a_n = (x_{n+1} - 2 x_n + x_{n-1}) / dt^2          (acceleration target of the window)
    dE_n = diss(t_n, t_{n+1}]                         (dissipation target of the window)

The rollout step ``v_{n+1} = v_n + a_n dt``, ``x_{n+1} = x_n + v_{n+1} dt``,
``E_{n+1} = E_n + dE_n`` then reproduces ``x_{n+1}`` and the cumulative dissipation
``E(t_{n+1})`` exactly (to rounding) when fed the true targets. In the dataset format
(docs/conventions.md section 4) ``diss_*[k]`` is the dissipation over ``(t_{k-1}, t_k]``, so
``dE_n`` is the sum of the normal and tangential, ball-ball and ball-wall entries at index
``n + 1``.

Graph layout of one window (jraph "padded with graphs" convention, n_graph = 2)
-------------------------------------------------------------------------------
nodes ``N + 2``: ``0 .. N-1`` balls, ``N`` the wall node, ``N + 1`` the padding node;
``n_node = [N + 1, 1]``. Edges ``E = pp_capacity + 2 N`` slots: first the kept ball-ball edges
(both directions of each pair, adjacent), then the ball-wall edges (wall->ball and ball->wall,
adjacent), then padding edges from and to the padding node; ``n_edge = [n_real, E - n_real]``.

``graph.nodes`` is a dict: ``features`` (N+2, 7W) float32, ``particle`` and ``wall`` (N+2,) bool.
Particle features per slot k (0 = oldest): columns ``7k .. 7k+6`` = [v (3), phi, n (3)] with the
SDF and its unit normal ``n = grad phi / |grad phi|`` at ``x_j`` relative to the jar at ``t_j``.
Wall features per slot: [offset (3), offset velocity (3), rotational frequency].
``graph.edges`` is a dict: ``features`` (E, 3) float32 (E, 5 with ``contact_features``), ``pp``
and ``pw`` (E,) bool. An edge
``sender s -> receiver r`` carries ``x_s - x_r`` (ball-ball, paper Eq. 20 with i = receiver)
or ``phi_b n_b`` of its ball b (ball-wall, Eq. 21, same feature in both directions).
Edges use the newest slot: ball-ball where ``|x_j - x_i| <= 2 R + pp_skin``, ball-wall where
``phi >= phi_pw``. The features are computed in float64 and cast to float32.

A window with a :class:`BallCharge` (``Window.charge``: per-ball radii, masses, classes, a
presence mask and a table of per-class-pair contact properties; the charge-conditioned contact
model's input, :mod:`sgn_jax.surrogate.contact_charge`) gets the rules of its own balls:
ball-ball where ``|x_j - x_i| <= r_i + r_j + pp_skin``, ball-wall where
``phi >= -(r_b + pw_skin)`` (``GraphSpec.pw_skin``), no edge of an absent ball (a padding slot
of a smaller charge), and the graph gains ``nodes["radius"]``, ``nodes["mass"]``,
``nodes["present"]`` (N+2,) and ``edges["pair"]`` (E, P), the table's row of each edge's class
pair (the wall node has the table's last class).
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import flax.struct
import jax
import jax.numpy as jnp
import jraph
import numpy as np

from sgn_jax.errors import SGNJaxError
from sgn_jax.scene import SDFQuery, grid_query, lab_patch_query, patches_of

# One slot's particle columns: velocity (0..2), phi (3), unit normal (4..6).
SLOT_DIM = 7
VELOCITY_COLUMNS_IN_SLOT = (0, 1, 2)


class GraphError(SGNJaxError, ValueError):
    """Inputs to the featurizer are inconsistent (shapes, capacities, trajectory too short)."""


@dataclasses.dataclass(frozen=True)
class GraphSpec:
    """Static description of the graphs (hashable: pass it by closure or as a static argument).

    Attributes:
        n_particles: N, balls per graph.
        window: W, slots per window (a window holds W + 1 positions).
        ball_radius: R (m).
        dt: sampling step (s), used for the finite-difference velocities.
        pp_skin: surface-gap skin s_pp (m): ball-ball edge if ``|x_j - x_i| <= 2 R + s_pp``.
        phi_pw: ball-wall edge if ``phi >= phi_pw`` (m).
        pp_pair_capacity: unordered ball pairs kept per graph (2 directed edges each).
        contact_features: two more edge columns that make a contact visible to the network:
            ball-ball ``[|x_j - x_i| - 2 R, max(0, 2 R - |x_j - x_i|)]`` (surface
            gap and overlap, m), ball-wall ``[-phi - R, max(0, phi + R)]`` (the same for the
            wall). Off: the paper's 3 columns.
        wall_patches: 0 (the paper): one ball-wall edge per ball, to the nearest wall. P > 0:
            one edge per ball and wall PATCH (floor, lid, side, post), as the DEM has one
            contact per ball and patch, so that a ball in the corner of floor and side wall
            feels both; P is the capacity (the jar's query may have at most P patches). The
            node features keep the nearest wall (the max over the same patches).
        node_walls: True (the paper): every slot's nearest-wall phi and normal in the node
            features (W SDF queries per graph). False: those columns are 0 and not computed,
            for a model that reads only the node velocities (the contact kind: its walls are
            its ball-wall edges); with ``wall_patches`` = 0 the newest slot is still queried,
            since the ball-wall edges are built from it. ``graph_spec_from_config`` sets it
            from the model kind (``ModelFactory.node_walls``).
    """

    n_particles: int
    window: int
    ball_radius: float
    dt: float
    pp_skin: float = 1.5e-3
    phi_pw: float = -0.0052
    pp_pair_capacity: int = 96
    contact_features: bool = False
    wall_patches: int = 0
    node_walls: bool = True

    def __post_init__(self) -> None:
        if self.n_particles < 1 or self.window < 1 or self.pp_pair_capacity < 1:
            raise GraphError(
                "GraphSpec needs n_particles >= 1, window >= 1 and pp_pair_capacity >= 1, got "
                f"{self.n_particles}, {self.window}, {self.pp_pair_capacity}"
            )
        if self.dt <= 0 or self.ball_radius <= 0:
            raise GraphError(f"GraphSpec needs dt > 0 and ball_radius > 0, got {self.dt}, "
                             f"{self.ball_radius}")

    @property
    def pp_capacity(self) -> int:
        """Directed ball-ball edge slots per graph."""
        return 2 * self.pp_pair_capacity

    @property
    def pw_capacity(self) -> int:
        """Directed ball-wall edge slots per graph (2 N, or 2 N P with ``wall_patches`` P:
        never overflows)."""
        return 2 * self.n_particles * max(1, self.wall_patches)

    @property
    def edge_capacity(self) -> int:
        return self.pp_capacity + self.pw_capacity

    @property
    def n_node(self) -> int:
        """Node rows of one graph: N balls, the wall node, one padding node."""
        return self.n_particles + 2

    @property
    def feature_dim(self) -> int:
        """Columns of the particle and of the wall features: 7 W."""
        return SLOT_DIM * self.window

    @property
    def edge_dim(self) -> int:
        """Edge feature columns: 3 (displacement or phi n), 5 with ``contact_features``."""
        return 5 if self.contact_features else 3

    @property
    def pp_cutoff(self) -> float:
        """Centre distance (m) up to which two balls are joined by an edge."""
        return 2.0 * self.ball_radius + self.pp_skin

    @property
    def pw_skin(self) -> float:
        """m, how far beyond contact a ball gets its ball-wall edges, ``-phi_pw - R``: with a
        :class:`BallCharge` each ball b gets them where ``phi >= -(r_b + pw_skin)``."""
        return -self.phi_pw - self.ball_radius


def velocity_columns(window: int) -> np.ndarray:
    """Indices of the velocity columns among the 7 W particle feature columns."""
    return np.array([SLOT_DIM * k + c for k in range(window) for c in VELOCITY_COLUMNS_IN_SLOT])


@flax.struct.dataclass
class BallCharge:
    """The balls of a charge as traced arrays (one compiled program serves every charge of the
    same N and table size; batched windows carry a leading axis on every field).

    Attributes:
        radius: (N,) m, each ball's radius (0 for an absent ball).
        mass: (N,) kg, each ball's mass (> 0 also for an absent ball, which is never divided
            into anything that reaches a present one).
        ball_class: (N,) int32, each ball's row of ``pair`` (< K - 1).
        present: (N,) bool; False: a padding slot of a charge of fewer balls than N (no edges,
            not a particle of the graph: the models leave it where it is).
        pair: (K, K, P) float, per pair of classes P contact properties (symmetric); class
            K - 1 is the jar's wall. The graph does not read the columns, it hands each edge
            its row (``edges["pair"]``); their meaning is the model's
            (:data:`sgn_jax.surrogate.contact_charge.PAIR_COLUMNS`).
    """

    radius: jax.Array
    mass: jax.Array
    ball_class: jax.Array
    present: jax.Array
    pair: jax.Array


@flax.struct.dataclass
class Window:
    """The state a graph is built from: W + 1 positions and W jar states (lab frame, SI).

    Attributes:
        positions: (W+1, N, 3) float64 m, ``x_{n-W} .. x_n`` (oldest first).
        offsets: (W, 3) m, jar offset at the slot times ``t_{n-W+1} .. t_n``.
        offset_velocities: (W, 3) m/s, jar velocity at the slot times.
        frequency_hz: () Hz, the motion's rotational frequency (``motion.frequency_hz``).
        spins: (N, 3) rad/s, the balls' angular velocities at the newest sample ``t_n`` (lab
            frame), or None. A model kind that carries spin as state (the contact model with
            ``[model] spin = true``) reads them from the graph (``nodes["spin"]``) and the
            rollout integrates them; every other kind ignores them. The rollout fills zeros
            (balls not turning) where a window has none (:func:`sgn_jax.surrogate.rollout.
            jar_state_window`).
        charge: a :class:`BallCharge`, or None (the balls of ``GraphSpec.ball_radius``, the
            monodisperse graph). With one, the edges follow each ball's own radius and the
            graph carries the charge (module docstring); ``replace`` and
            :func:`slide_window` keep it, so a rollout carries it along.

    Batched windows carry a leading axis on every field (``jax.vmap(build_graph, ...)``).
    """

    positions: jax.Array
    offsets: jax.Array
    offset_velocities: jax.Array
    frequency_hz: jax.Array
    spins: jax.Array | None = None
    charge: BallCharge | None = None


def with_spins(window: Window) -> Window:
    """``window`` with float64 spins: zeros (balls not turning) where it has none. A rollout's
    carry always holds them (:func:`sgn_jax.surrogate.rollout.jar_state_window`)."""
    positions = jnp.asarray(window.positions)
    spins = (jnp.zeros(positions.shape[1:], jnp.float64) if window.spins is None
             else jnp.asarray(window.spins, jnp.float64))
    return window.replace(spins=spins)


def slide_window(window: Window, new_position: jax.Array, new_offset: jax.Array,
                 new_offset_velocity: jax.Array) -> Window:
    """Drop the oldest slot and append the state at the next sample (for the rollout).

    ``new_position`` (N, 3) is ``x_{n+1}``; ``new_offset`` and ``new_offset_velocity`` (3,) are
    the jar state at ``t_{n+1}``. ``spins`` are left as they are (the rollout sets them).
    """
    pos = jnp.concatenate([window.positions[1:], new_position[None].astype(window.positions.dtype)])
    off = jnp.concatenate([window.offsets[1:], new_offset[None].astype(window.offsets.dtype)])
    vel = jnp.concatenate([window.offset_velocities[1:],
                           new_offset_velocity[None].astype(window.offset_velocities.dtype)])
    return window.replace(positions=pos, offsets=off, offset_velocities=vel)


class EdgeCounts(NamedTuple):
    """What the edge rules found in one graph (int32 scalars; batched when vmapped).

    ``pp_dropped > 0`` is a capacity overflow: that many directed ball-ball edges were not put
    in the graph (raise ``[graph] pp_edges_per_particle``). Ball-wall edges cannot overflow.
    """

    n_pp: jax.Array
    n_pw: jax.Array
    pp_dropped: jax.Array


def _default_query() -> SDFQuery:
    return grid_query


def _walls_of(query: SDFQuery | None) -> Any:
    """The wall query behind a lab-frame query made by :func:`sgn_jax.scene.lab_query`."""
    query = _default_query() if query is None else query
    walls = getattr(query, "walls", None)
    if walls is None:
        raise GraphError("GraphSpec.wall_patches needs a wall query made by "
                         "sgn_jax.scene.lab_query (grid_query, analytic_jar_query, ...), "
                         "whose patches it can ask for")
    return walls


def _check_window(window: Window, spec: GraphSpec) -> None:
    w, n = spec.window, spec.n_particles
    expected = {"positions": (w + 1, n, 3), "offsets": (w, 3), "offset_velocities": (w, 3),
                "frequency_hz": ()}
    if window.spins is not None:
        expected["spins"] = (n, 3)
    if window.charge is not None:
        expected.update({"charge.radius": (n,), "charge.mass": (n,), "charge.ball_class": (n,),
                         "charge.present": (n,)})
    for name, shape in expected.items():
        value = window
        for part in name.split("."):
            value = getattr(value, part)
        got = tuple(jnp.shape(value))
        if got != shape:
            raise GraphError(
                f"Window.{name} has shape {got}, expected {shape} for window={w}, "
                f"n_particles={n} (a window of W slots holds W + 1 positions); "
                "vmap build_graph over batched windows"
            )


def particle_slot_features(window: Window, sdf: Any, spec: GraphSpec,
                           query: SDFQuery | None = None) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Per-slot ball quantities in float64: velocity (W, N, 3), phi (W, N), normal (W, N, 3).

    With ``spec.node_walls`` False phi and normal are 0 at every slot but the newest, which is
    queried only when the ball-wall edges need it (``wall_patches`` = 0)."""
    query = _default_query() if query is None else query
    pos = jnp.asarray(window.positions, jnp.float64)
    vel = (pos[1:] - pos[:-1]) / spec.dt
    offsets = jnp.asarray(window.offsets, jnp.float64)
    if spec.node_walls:
        phi, normal = jax.vmap(lambda p, o: query(sdf, p, o))(pos[1:], offsets)
        return vel, jnp.asarray(phi, jnp.float64), jnp.asarray(normal, jnp.float64)
    phi, normal = jnp.zeros(vel.shape[:2], jnp.float64), jnp.zeros_like(vel)
    if not spec.wall_patches:
        phi_new, normal_new = query(sdf, pos[-1], offsets[-1])
        phi = phi.at[-1].set(jnp.asarray(phi_new, jnp.float64))
        normal = normal.at[-1].set(jnp.asarray(normal_new, jnp.float64))
    return vel, phi, normal


def _contact_columns(gap: jax.Array) -> jax.Array:
    """(K,) surface gaps (m, negative in contact) -> (K, 2) ``[gap, overlap = max(0, -gap)]``."""
    return jnp.stack([gap, jnp.maximum(0.0, -gap)], axis=-1)


def _pairs_within_reach(x: jax.Array, spec: GraphSpec, charge: BallCharge | None,
                        pi: jax.Array, pj: jax.Array, extra: float = 0.0
                        ) -> tuple[jax.Array, jax.Array | None, jax.Array]:
    """The ball-ball edge rule on the pairs (pi, pj) (P,) at positions ``x`` (N, 3) m:
    ``(rij = x_j - x_i (P, 3), contact distance r_i + r_j (P,) or None without a charge,
    within (P,) bool)`` with within: |rij| <= the graph's reach + ``extra`` (the reach
    ``pp_cutoff``, or r_i + r_j + ``pp_skin`` with both balls present)."""
    rij = x[pj] - x[pi]
    dist2 = jnp.sum(rij * rij, axis=-1)
    if charge is None:
        return rij, None, dist2 <= (spec.pp_cutoff + extra) ** 2
    radius = jnp.asarray(charge.radius, jnp.float64)
    present = jnp.asarray(charge.present, bool)
    reach = radius[pi] + radius[pj]          # the pair's contact distance r_i + r_j
    return rij, reach, ((dist2 <= (reach + spec.pp_skin + extra) ** 2)
                        & present[pi] & present[pj])


def build_graph(window: Window, sdf: Any, spec: GraphSpec,
                query: SDFQuery | None = None,
                candidates: jax.Array | None = None) -> tuple[jraph.GraphsTuple, EdgeCounts]:
    """Featurize one window (static shapes, jittable, differentiable in positions and offsets).

    Args:
        window: one :class:`Window` (no batch axis; vmap for many).
        sdf: the jar SDF handed to ``query``, by default an ``sgn_jax.geometry.SDFGrid``.
        spec: static :class:`GraphSpec`.
        query: ``query(sdf, points_lab, offset) -> (phi, unit normal)``; default
            ``sgn_jax.geometry.query_sdf_grid``.
        candidates: (C, 2) int32 ball pairs (i, j), i < j, in the order of
            ``np.triu_indices`` (unused rows (N, N)): the only pairs tested for ball-ball
            edges, e.g. a neighbour list (:func:`neighbour_pairs`) that holds every pair within
            reach. Default: all N (N - 1) / 2 pairs. A list that holds every pair within the
            graph's reach gives the same graph, edge for edge.

    Returns:
        ``(graph, counts)``: the padded graph (layout in the module docstring; raw, un-normalised
        float32 features) and the :class:`EdgeCounts` with the overflow.
    """
    _check_window(window, spec)
    n, w = spec.n_particles, spec.window
    wall, pad = n, n + 1
    vel, phi, normal = particle_slot_features(window, sdf, spec, query)
    if spec.wall_patches:
        # Every patch at the newest positions (the node features keep the nearest wall: the
        # max over the same patches, which is what the nearest-wall query returns).
        patch_query = lab_patch_query(patches_of(_walls_of(query)))
        phi_patch, normal_patch = patch_query(
            sdf, jnp.asarray(window.positions[-1], jnp.float64),
            jnp.asarray(window.offsets[-1], jnp.float64))
        phi_patch = jnp.asarray(phi_patch, jnp.float64)
        normal_patch = jnp.asarray(normal_patch, jnp.float64)
        if phi_patch.shape[-1] > spec.wall_patches:
            raise GraphError(f"the jar has {phi_patch.shape[-1]} wall patches, more than "
                             f"GraphSpec.wall_patches = {spec.wall_patches}")

    # Nodes: (N, W, 7) -> (N, 7W), slot-major columns.
    particle = jnp.concatenate([vel, phi[..., None], normal], axis=-1)  # (W, N, 7)
    particle = jnp.transpose(particle, (1, 0, 2)).reshape(n, SLOT_DIM * w)
    freq = jnp.broadcast_to(jnp.asarray(window.frequency_hz, jnp.float64), (w, 1))
    wall_feat = jnp.concatenate([jnp.asarray(window.offsets, jnp.float64),
                                 jnp.asarray(window.offset_velocities, jnp.float64), freq], -1)
    node_features = jnp.concatenate(
        [particle, wall_feat.reshape(1, SLOT_DIM * w), jnp.zeros((1, SLOT_DIM * w))], axis=0)
    node_ids = jnp.arange(n + 2)
    is_particle = node_ids < n
    is_wall = node_ids == wall
    charge = window.charge
    if charge is not None:
        # each ball's own radius; an absent ball (padding of a smaller charge) has no edges
        # and is no particle
        present = jnp.asarray(charge.present, bool)
        radius = jnp.asarray(charge.radius, jnp.float64)
        is_particle = is_particle & jnp.concatenate([present, jnp.zeros((2,), bool)])

    x = jnp.asarray(window.positions[-1], jnp.float64)  # newest positions (N, 3)
    phi_now, normal_now = phi[-1], normal[-1]

    # Ball-ball: unordered pairs i < j; both directions of a kept pair are kept together.
    if candidates is None:
        pi, pj = (jnp.asarray(a, jnp.int32) for a in np.triu_indices(n, k=1))
        listed = True
    else:   # a neighbour list: its unused rows (N, N) are clamped for the gathers, never kept
        listed = candidates[:, 0] < n
        pi, pj = (jnp.minimum(candidates[:, c], n - 1).astype(jnp.int32) for c in (0, 1))
    rij, reach, pair_ok = _pairs_within_reach(x, spec, charge, pi, pj)
    pair_ok = pair_ok & listed
    n_pairs = jnp.sum(pair_ok, dtype=jnp.int32)
    cap_pairs = spec.pp_pair_capacity
    kept_pairs = jnp.minimum(n_pairs, cap_pairs)
    n_pp_kept = 2 * kept_pairs
    e_cap = spec.edge_capacity
    pp_feat_j, pp_feat_i = rij, -rij
    if spec.contact_features:
        # sqrt of the squared distance + tiny: differentiable also at coincident centres
        dist = jnp.sqrt(jnp.sum(rij * rij, axis=-1) + 1e-30)
        contact = _contact_columns(dist - (2.0 * spec.ball_radius if charge is None else reach))
        pp_feat_j = jnp.concatenate([rij, contact], axis=-1)
        pp_feat_i = jnp.concatenate([-rij, contact], axis=-1)

    # Ball-wall: wall -> b and b -> wall, both with phi_b n_b, placed after the kept pp edges
    # (with wall_patches: one such pair per ball and patch, ball-major).
    if spec.wall_patches:
        balls = jnp.repeat(jnp.arange(n, dtype=jnp.int32), phi_patch.shape[-1])
        phi_now, normal_now = phi_patch.reshape(-1), normal_patch.reshape(-1, 3)
    else:
        balls = jnp.arange(n, dtype=jnp.int32)
    if charge is None:
        ball_ok = phi_now >= spec.phi_pw
    else:
        ball_ok = (phi_now >= -(radius[balls] + spec.pw_skin)) & present[balls]
    n_walled = jnp.sum(ball_ok, dtype=jnp.int32)
    # The ranks of the kept pairs and walled balls by one cumsum (a small charge's rollout
    # step costs per XLA operation). Slot 2r: j -> i (feature x_j - x_i); slot 2r + 1: i -> j.
    # Out-of-capacity pairs go to an out-of-range slot and are dropped by the scatter (and
    # counted in pp_dropped).
    ranks = jnp.cumsum(jnp.concatenate([pair_ok, ball_ok]), dtype=jnp.int32)
    pair_rank = ranks[:pair_ok.shape[0]] - 1
    ball_rank = ranks[pair_ok.shape[0]:] - n_pairs - 1
    slot = jnp.where(pair_ok & (pair_rank < cap_pairs), 2 * pair_rank, spec.edge_capacity)
    bslot = jnp.where(ball_ok, n_pp_kept + 2 * ball_rank, e_cap)
    pw_feat = phi_now[:, None] * normal_now
    if spec.contact_features:
        r_b = spec.ball_radius if charge is None else radius[balls]
        pw_feat = jnp.concatenate([pw_feat, _contact_columns(-phi_now - r_b)], axis=-1)
    # Every edge of both kinds in one scatter per array (a small charge's step costs per
    # operation): the kept slots are distinct, the others out of range and dropped.
    slots = jnp.concatenate([slot, slot + 1, bslot, bslot + 1])
    walls = jnp.full_like(balls, wall)
    ends = jnp.stack([jnp.concatenate([pj, pi, walls, balls]),       # senders
                      jnp.concatenate([pi, pj, balls, walls])], -1)  # receivers
    ends = jnp.full((e_cap, 2), pad, jnp.int32).at[slots].set(ends, mode="drop")
    senders, receivers = ends[:, 0], ends[:, 1]
    efeat = jnp.zeros((e_cap, spec.edge_dim), jnp.float64).at[slots].set(
        jnp.concatenate([pp_feat_j, pp_feat_i, pw_feat, pw_feat]), mode="drop")

    n_real = n_pp_kept + 2 * n_walled
    edge_ids = jnp.arange(e_cap)
    is_pp = edge_ids < n_pp_kept
    is_pw = (edge_ids >= n_pp_kept) & (edge_ids < n_real)

    nodes = {"features": node_features.astype(jnp.float32), "particle": is_particle,
             "wall": is_wall}
    if window.spins is not None:
        # (N + 2, 3) rad/s, float64 (a resting ball's spin is tiny); 0 for the wall and padding
        nodes["spin"] = jnp.concatenate([jnp.asarray(window.spins, jnp.float64),
                                         jnp.zeros((2, 3), jnp.float64)])
    edges = {"features": efeat.astype(jnp.float32), "pp": is_pp, "pw": is_pw}
    if charge is not None:
        table = jnp.asarray(charge.pair)
        wall_class = table.shape[0] - 1
        # (N + 2,): the wall node and the padding node have the wall's class, radius 0 and
        # mass 1 (never used as a ball's: they are no particles)
        node_class = jnp.concatenate([jnp.asarray(charge.ball_class, jnp.int32),
                                      jnp.full((2,), wall_class, jnp.int32)])
        nodes["radius"] = jnp.concatenate([radius, jnp.zeros((2,), jnp.float64)])
        nodes["mass"] = jnp.concatenate([jnp.asarray(charge.mass, jnp.float64),
                                         jnp.ones((2,), jnp.float64)])
        nodes["present"] = is_particle
        edges["pair"] = table[node_class[receivers], node_class[senders]]
    graph = jraph.GraphsTuple(
        nodes=nodes,
        edges=edges,
        senders=senders,
        receivers=receivers,
        n_node=jnp.array([n + 1, 1], jnp.int32),
        n_edge=jnp.stack([n_real, e_cap - n_real]).astype(jnp.int32),
        globals=None,
    )
    counts = EdgeCounts(n_pp=2 * n_pairs, n_pw=2 * n_walled,
                        pp_dropped=2 * (n_pairs - kept_pairs))
    return graph, counts


def neighbour_pairs(positions: jax.Array, spec: GraphSpec, charge: BallCharge | None,
                    extra_skin: float, capacity: int) -> tuple[jax.Array, jax.Array]:
    """The ball pairs within the graph's reach plus ``extra_skin``: a neighbour (Verlet) list.

    A pair (i, j), i < j, is listed when |x_j - x_i| <= reach + ``extra_skin`` (reach: the
    graph's ``pp_cutoff``, or r_i + r_j + ``pp_skin`` with a charge, both balls present).
    While no ball has moved more than ``extra_skin`` / 2 since, the list holds every pair that
    :func:`build_graph` would keep, so ``build_graph(..., candidates=pairs)`` builds the same
    graph from C rows instead of N (N - 1) / 2 (what makes a rollout step of many balls
    linear in N; :class:`sgn_jax.surrogate.rollout.NeighbourList` keeps it up to date).

    Args:
        positions: (N, 3) m. spec: the graph's. charge: the window's charge or None.
        extra_skin: m, the list's margin over the graph's reach. capacity: C, pairs it holds.
    Returns:
        ``(pairs (C, 2) int32 in the order of np.triu_indices, unused rows (N, N); n_found ()
        int32)``: more than C found is an overflow (the list misses pairs), for the caller to
        refuse.
    """
    n = spec.n_particles
    pi, pj = (jnp.asarray(a, jnp.int32) for a in np.triu_indices(n, k=1))
    _, _, ok = _pairs_within_reach(jnp.asarray(positions, jnp.float64), spec, charge, pi, pj,
                                   extra_skin)
    rank = jnp.cumsum(ok, dtype=jnp.int32) - 1
    slot = jnp.where(ok & (rank < capacity), rank, capacity)
    pairs = jnp.full((capacity, 2), n, jnp.int32).at[slot].set(
        jnp.stack([pi, pj], axis=-1), mode="drop")
    return pairs, jnp.sum(ok, dtype=jnp.int32)


def true_indices(mask: jax.Array, size: int, fill_value: int) -> jax.Array:
    """(K, size) int32: per row of ``mask`` (K, R) bool the indices of its first ``size`` True
    entries in order, then ``fill_value``: ``jnp.nonzero(mask[k], size=size,
    fill_value=fill_value)[0]`` of every row, by one cumsum and one scatter for all rows
    (nonzero takes two cumsums and a scatter per row, and a small charge's rollout step costs
    per XLA operation)."""
    k, rows = mask.shape
    rank = jnp.cumsum(mask, axis=1, dtype=jnp.int32) - 1
    slot = jnp.where(mask & (rank < size),
                     rank + size * jnp.arange(k, dtype=jnp.int32)[:, None], k * size)
    index = jnp.full((k * size,), fill_value, jnp.int32).at[slot.reshape(-1)].set(
        jnp.tile(jnp.arange(rows, dtype=jnp.int32), k), mode="drop")
    return index.reshape(k, size)


def compact_edge_pairs(graph: jraph.GraphsTuple, keep: jax.Array, capacity: int
                       ) -> jraph.GraphsTuple:
    """The graph of :func:`build_graph` (one graph and its padding graph, no batch axis) with
    only the edge pairs whose primary row is kept, in their order, padded to ``capacity`` pairs.

    Args:
        keep: (E / 2,) bool, per edge pair (slot 2r and its reverse 2r + 1, the layout of
            :func:`build_graph`: ball-ball pairs first, then ball-wall ones, then padding).
        capacity: C, the pairs the result holds; pairs past the C-th kept one are DROPPED (the
            caller checks ``sum(keep) <= C`` and does not use the result otherwise).

    Returns the graph with 2C edge slots: the kept pairs at ``[0, 2 kept)`` (their kinds'
    order kept: ball-ball before ball-wall), then padding (sender and receiver the padding
    node, no kind, zero features and pair row). Nodes unchanged; every edge counts to graph 0
    (``n_edge = [2C, 0]``), which is right for a model whose padding edges give exactly zero
    (the contact kinds: an edge acts only through its gated impulse).
    """
    rows = keep.shape[0]
    index = true_indices(keep[None], capacity, rows)[0]
    valid = jnp.repeat(index < rows, 2)                              # (2C,)
    slots = jnp.where(valid, jnp.stack([2 * index, 2 * index + 1], axis=-1).reshape(-1), 0)
    pad = graph.nodes["features"].shape[0] - 1

    def take(values: jax.Array) -> jax.Array:
        mask = valid.reshape((-1,) + (1,) * (values.ndim - 1))
        return jnp.where(mask, values[slots], jnp.zeros((), values.dtype))

    return graph._replace(
        senders=jnp.where(valid, graph.senders[slots], pad),
        receivers=jnp.where(valid, graph.receivers[slots], pad),
        edges={name: take(values) for name, values in graph.edges.items()},
        n_edge=jnp.asarray([2 * capacity, 0], graph.n_edge.dtype))


def make_graph_builder(sdf_query: SDFQuery | None, spec: GraphSpec):
    """A jitted ``build(windows, sdf) -> (graphs, counts)`` vmapped over a batch of windows."""

    def one(window: Window, sdf: Any):
        return build_graph(window, sdf, spec, sdf_query)

    return jax.jit(jax.vmap(one, in_axes=(0, None)))


# --------------------------------------------------------------------------------------------
# Windows and targets from a trajectory


DISSIPATION_TARGET_FIELDS = ("diss_pp_normal", "diss_pp_tangential", "diss_pw_normal",
                             "diss_pw_tangential")


def dissipation_per_interval(traj: Any) -> np.ndarray:
    """(T,) J: normal + tangential damping, ball-ball + ball-wall, over ``(t_{k-1}, t_k]``."""
    missing = [f for f in DISSIPATION_TARGET_FIELDS if getattr(traj, f, None) is None]
    if missing:
        raise GraphError(f"trajectory lacks dissipation array(s) {missing} "
                         "(docs/conventions.md section 4)")
    return np.sum([np.asarray(getattr(traj, f), np.float64) for f in DISSIPATION_TARGET_FIELDS],
                  axis=0)


def valid_window_ends(n_samples: int, window: int) -> np.ndarray:
    """Sample indices n that can end a training window: W <= n <= T - 2 (needs x_{n+1})."""
    if n_samples < window + 2:
        raise GraphError(
            f"a trajectory of {n_samples} samples is too short for window {window}: "
            f"need at least window + 2 = {window + 2} samples"
        )
    return np.arange(window, n_samples - 1)


def windows_from_arrays(pos: np.ndarray, offset: np.ndarray, offset_vel: np.ndarray,
                        frequency_hz: float, ends: np.ndarray, window: int,
                        omega: np.ndarray | None = None) -> Window:
    """Batched :class:`Window` (leading axis S) ending at samples ``ends`` (S,), numpy float64;
    with ``omega`` (T, N, 3) rad/s (a DEM record's), the windows carry the spins at ``ends``."""
    ends = np.asarray(ends, np.int64)
    if ends.size and (ends.min() < window or ends.max() > len(pos) - 1):
        raise GraphError(f"window ends must lie in [{window}, {len(pos) - 1}]")
    pos_idx = ends[:, None] + np.arange(-window, 1)[None]  # (S, W+1)
    slot_idx = pos_idx[:, 1:]
    return Window(
        positions=np.asarray(pos, np.float64)[pos_idx],
        offsets=np.asarray(offset, np.float64)[slot_idx],
        offset_velocities=np.asarray(offset_vel, np.float64)[slot_idx],
        frequency_hz=np.full(len(ends), float(frequency_hz), np.float64),
        spins=None if omega is None else np.asarray(omega, np.float64)[ends],
    )


def targets_from_arrays(pos: np.ndarray, diss_per_interval: np.ndarray, ends: np.ndarray,
                        dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Targets of windows ending at ``ends``: ``a_n`` (S, N, 3) m/s^2 and ``dE_n`` (S,) J.

    ``a_n = (x_{n+1} - 2 x_n + x_{n-1}) / dt^2`` and ``dE_n = diss_per_interval[n + 1]``, the
    dissipation over the step (t_n, t_{n+1}] that the surrogate takes from this window.
    """
    pos = np.asarray(pos, np.float64)
    ends = np.asarray(ends, np.int64)
    accel = (pos[ends + 1] - 2.0 * pos[ends] + pos[ends - 1]) / dt**2
    return accel, np.asarray(diss_per_interval, np.float64)[ends + 1]


