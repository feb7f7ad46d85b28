"""The charge-conditioned contact-impulse surrogate (model kind "contact_charge").

The contact kind (:mod:`sgn_jax.surrogate.contact`, docs/contact.md) knows one charge: one ball
radius and mass, one material, inputs scaled by fixed SI scales tuned to 10 mm steel balls.
This kind is the same model (the same impulses, cone, rigid limit, sweeps, ledger; its code by
inheritance) with every contact **conditioned on its own physical parameters** and its inputs
**dimensionless per contact**, so that one set of weights serves every charge and a ball size
the model never saw is not an out-of-range input (docs/contact_charge.md).

The charge reaches the model through the graph (:class:`sgn_jax.surrogate.graph.BallCharge` on
the window): per ball its radius r, mass m and class; per edge the row of a table of its class
pair (the wall is the table's last class), with the columns of :data:`PAIR_COLUMNS`. All are
traced arrays: one compiled program serves every charge of the same ball count N and table size
(smaller charges: padded with absent balls).

Per contact c (a pair r, s or a ball r and the wall)::

    R* = r_r r_s / (r_r + r_s),  m* = m_r m_s / (m_r + m_s)       (a wall: R* = r_r, m* = m_r)
    L  = peak_coef (m* / (Y* sqrt(R*)))^(2/5)     the contact law's deepest overlap of a
                                                  head-on impact at 1 m/s (m; the law is
                                                  self-similar: at speed v it is L v^0.8)
    V  = L / dt                                   the contact speed scale: the speed that
                                                  closes L in one step

    inputs   per history slot: clip(gap / 2L, -1, 3), tanh(gap / 0.1 L),
             clip(u / 10 V, -5, 5), tanh(u / 0.05 V); then the tangential and (with spin) the
             contact point's slip speed likewise, the wall's relative acceleration over a step
             tanh(a dt / 0.05 V); and the contact's constants: log10(V / 1 m/s), e, mu,
             10 mu_r, the size ratio min(r) / max(r) and the mass balance 4 m_r m_s / (m_r +
             m_s)^2 (both 0 for a wall). Every input is symmetric in the two balls of a pair
             (the model computes each contact once).
    outputs  du_n = V softplus(out_0) >= 0 (repulsive), the tangential part inside the Coulomb
             cone mu_c du_n with the contact's own mu_c; J = m* (-du_n n + du_t t).

With the SI scales of the contact kind a 15 mm ball's impact overlap is an input 14x its
5-um fine scale and a 6 mm ball's slow contacts look like a 10 mm ball's fast ones; here both
are the same dimensionless state as the 10 mm ball's at the speed that scales with L.

The rest as the contact kind, per contact: the rigid limit ``max(overlap_limit L / L_REF,
overlap_law_factor L v^0.8)`` and the gate margin ``gate_margin L / L_REF`` (L_REF the standard
10 mm steel ball-ball peak, so a config's values keep their meaning for the standard charge);
the stick impulse with k = 1 + m* (a_r^2 / I_r + a_s^2 / I_s); each ball's own arm a_i = r_i -
overlap / 2 (the DEM's contact point); rolling friction with the DEM's rolling radius (the
harmonic mean of the arms) and I_eff = I_r I_s / (I_r + I_s); the contacts' velocity changes
by each ball's own mass and inertia.

The dissipation target per contact from its own impulses: the normal part of its dissipation
is all damping (the Hertz spring stores, the normal damper dissipates), its rolling friction
none, its tangential part a share ``sigmoid(share_logit[kind])`` (the DEM's tangential damping
against its Coulomb slip, fitted from records:
:func:`sgn_jax.surrogate.contact_train.tangential_damping_shares`).
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

from sgn_jax.dem.charge import Charge
from sgn_jax.dem.contact import head_on_impact, make_contact_law
from sgn_jax.surrogate.contact import (
    DTYPE,
    REBOUND_SWEEPS,
    ContactModelError,
    ContactNet,
    GateRule,
    InputScales,
    _larger_ball_count,
    _safe_norm,
    at_both_ends,
    check_rebound_exact,
    contact_rows,
    edge_kinematics,
    per_contact_damping,
    sum_at_both_ends,
)
from sgn_jax.surrogate.graph import BallCharge
from sgn_jax.surrogate.model import register_model

# The columns of the class-pair table (BallCharge.pair), per pair of classes (the wall the
# table's last class): restitution, Coulomb friction, rolling friction (EDEM type A), the Hertz
# effective modulus Y* (Pa) and the law's peak coefficient, the deepest overlap of a head-on
# impact at 1 m/s over (m* / (Y* sqrt(R*)))^(2/5) (the law is self-similar: it depends on the
# restitution alone, so a ball of any size of the class pair gets its L from it), and the
# law's v t_c(v) / peak(v) (its contact time over its peak, also a function of the restitution
# alone: the law rebound of ChargePhysics.law_rebound).
PAIR_COLUMNS = ("restitution", "friction", "rolling_friction", "young_eff", "peak_coef",
                "rebound_time")
PAIR_DIM = len(PAIR_COLUMNS)

L_REF = 4.53e-5          # m, the standard 10 mm steel ball-ball peak at 1 m/s (the contact kind's)
SPEED_REF = 1.0          # m/s, the speed of L (and of log10(V / SPEED_REF))
GAP_COARSE = 2.0         # clip(gap / (2 L), -1, 3): an impact reaches gap ~ -L
GAP_FINE = 0.1           # tanh(gap / 0.1 L): resolves resting overlaps
SPEED_COARSE = 10.0      # clip(u / (10 V), -5, 5): up to 50 L per step
SPEED_FINE = 0.05        # tanh(u / 0.05 V): resolves resting contacts (g dt)
ROLLING_INPUT = 10.0     # 10 mu_r: mu_r ~ 0.01-0.1
# Inputs per contact: 4 per history slot, then |v_t| (2), the wall's acceleration (1),
# the slip (2, spin only) and the contact's constants (6).
N_CONSTANTS = 6


@dataclasses.dataclass(frozen=True)
class ChargePhysics:
    """The known physics of the charge-conditioned model that is not the charge's (static).

    The balls' radii and masses and every contact's material come with the graph
    (:class:`sgn_jax.surrogate.graph.BallCharge`); what stays static is the step, gravity, the
    graph's layout and the solver's settings, with the contact kind's meanings
    (:class:`sgn_jax.surrogate.contact.ContactPhysics`) except that the two lengths are those
    of the reference contact (``L_REF``) and scale with each contact's L.

    Attributes:
        dt: s. gravity: m/s^2. window: W. history: slots used as inputs (<= W).
        gate_margin: m at L_REF; a contact acts where its gap now or at the end of a ballistic
            step is below ``gate_margin L / L_REF``.
        wall_patches: the graphs' ``GraphSpec.wall_patches`` or None (as the contact kind's).
        overlap_limit: m at L_REF; 0 = off. overlap_law_factor: c (0 = off); the limit of a
            contact is ``max(overlap_limit L / L_REF, c L v^0.8)``.
        law_rebound: fresh impacts end with each contact's own law's rebound, as the contact
            kind's ``rebound_time_pp/pw`` (the pair table's ``rebound_time`` column; needs
            ``overlap_law_factor``).
        rebound_exact: "off", "wall", "all" or "fresh": where the law rebound is also the normal
            impulse's ceiling, as the contact kind's (``ContactPhysics.rebound_exact``, with
            each contact's own restitution).
        overlap_sweeps, friction_sweeps: as the contact kind's.
        friction_sweep_contacts: "all" (the contact kind's) or "wall": the friction sweeps act
            on the ball-wall contacts only, each ball-ball contact keeping its learned stick.
        rebound_sweeps: "off", "all" or "free" (``contact.REBOUND_SWEEPS``):
            the overlap sweeps also keep each impact past its contact time (every one, or the
            ball-ball impacts of balls no resting contact holds) separating at its law's
            rebound e v with all contacts acting; the law rebound alone sets it for the
            contact by itself (needs ``law_rebound`` and ``overlap_sweeps``).
    """

    dt: float = 2.0e-4
    gravity: tuple[float, float, float] = (0.0, -9.81, 0.0)
    window: int = 7
    history: int = 3
    gate_margin: float = 5.0e-5
    wall_patches: int | None = None
    overlap_limit: float = 0.0
    overlap_law_factor: float = 0.0
    law_rebound: bool = False
    overlap_sweeps: int = 0
    friction_sweeps: int = 0
    rebound_exact: str = "off"
    friction_sweep_contacts: str = "all"
    rebound_sweeps: str = "off"

    def __post_init__(self) -> None:
        if not 1 <= self.history <= self.window:
            raise ContactModelError(f"history must be in 1..window={self.window}, got {self.history}")
        if not (self.overlap_limit >= 0 and self.overlap_law_factor >= 0):
            raise ContactModelError("overlap_limit and overlap_law_factor must be >= 0")
        if self.law_rebound and self.overlap_law_factor <= 0:
            raise ContactModelError("law_rebound needs the law's limit (overlap_law_factor > 0)")
        if self.overlap_law_factor > 0 and self.overlap_limit <= 0:
            raise ContactModelError("overlap_law_factor needs overlap_limit > 0")
        if self.overlap_sweeps < 0 or (self.overlap_sweeps > 0 and self.overlap_limit <= 0):
            raise ContactModelError("overlap_sweeps must be >= 0 and needs overlap_limit > 0")
        if self.friction_sweeps < 0:
            raise ContactModelError(f"friction_sweeps must be >= 0, got {self.friction_sweeps}")
        if self.friction_sweep_contacts not in ("all", "wall"):
            raise ContactModelError("friction_sweep_contacts must be 'all' or 'wall', got "
                                    f"{self.friction_sweep_contacts!r}")
        check_rebound_exact(self.rebound_exact, self.law_rebound, "the law rebound (law_rebound)")
        if self.rebound_sweeps not in REBOUND_SWEEPS:
            raise ContactModelError(f"rebound_sweeps must be one of {REBOUND_SWEEPS}, got "
                                    f"{self.rebound_sweeps!r}")
        if self.rebound_sweeps != "off" and not (self.law_rebound and self.overlap_sweeps > 0):
            raise ContactModelError("rebound_sweeps needs law_rebound = true and "
                                    "overlap_sweeps > 0")


# --------------------------------------------------------------------------------------------
# The charge as arrays (host side, numpy)


def _pair_row(a_material: Any, b_material: Any, rule: Any, radius_1: float, mass_1: float,
              radius_2: float = math.inf, mass_2: float = math.inf) -> list[float]:
    law = make_contact_law(a_material.young, a_material.poisson, rule.restitution,
                           rule.friction, rule.rolling_friction, radius_1, mass_1,
                           radius_2=radius_2, mass_2=mass_2, young_2=b_material.young,
                           poisson_2=b_material.poisson)
    scale = (law.mass_eff / (law.young_eff * math.sqrt(law.radius_eff))) ** 0.4
    peak, duration = head_on_impact(law)
    return [rule.restitution, rule.friction, rule.rolling_friction, law.young_eff,
            peak / scale, duration / peak]


def pair_table(charge: Charge, classes: int | None = None) -> np.ndarray:
    """(K, K, P) float32, K = ``classes`` + 1 (default: the charge's classes + 1): the
    :data:`PAIR_COLUMNS` of every pair of ball classes and, in row and column K - 1, of each
    class against the jar's wall. Rows of classes the charge does not have repeat class 0's
    (finite; no ball uses them). A ms of host numpy per pair (the law's peak)."""
    c = charge.n_classes
    k = (c if classes is None else int(classes)) + 1
    if k - 1 < c:
        raise ContactModelError(f"a table of {k - 1} classes cannot hold a charge of {c}")
    table = np.zeros((k, k, PAIR_DIM), np.float64)
    cls = charge.classes
    for i in range(k - 1):
        a = cls[i] if i < c else cls[0]
        for j in range(k - 1):
            b = cls[j] if j < c else cls[0]
            rule = charge.pair_rule(a.material, b.material)
            table[i, j] = _pair_row(a.material, b.material, rule, a.radius, a.mass, b.radius,
                                    b.mass)
        rule = charge.pair_rule(a.material, charge.wall)
        table[i, k - 1] = table[k - 1, i] = _pair_row(a.material, charge.wall, rule, a.radius,
                                                      a.mass)
    table[k - 1, k - 1] = table[0, k - 1]     # wall-wall: never a contact
    return table.astype(np.float32)


def ball_charge(charge: Charge, n_balls: int | None = None, classes: int | None = None,
                radii: np.ndarray | None = None, masses: np.ndarray | None = None
                ) -> BallCharge:
    """The :class:`BallCharge` of a charge, padded to ``n_balls`` (default: its own count)
    with absent balls (radius 0, mass 1, class 0) and to a table of ``classes`` classes.
    ``radii`` and ``masses`` (N,) override the class values (a record's ``ball_radii`` and
    ``ball_masses``)."""
    n = charge.n_balls
    total = n if n_balls is None else int(n_balls)
    if total < n:
        raise ContactModelError(f"cannot pad a charge of {n} balls to {total}")
    radius = np.zeros(total, np.float64)
    mass = np.ones(total, np.float64)
    radius[:n] = charge.radii if radii is None else np.asarray(radii, np.float64)
    mass[:n] = charge.masses if masses is None else np.asarray(masses, np.float64)
    ball_class = np.zeros(total, np.int32)
    ball_class[:n] = charge.ball_class
    present = np.arange(total) < n
    return BallCharge(radius=radius, mass=mass, ball_class=ball_class, present=present,
                      pair=pair_table(charge, classes))


# --------------------------------------------------------------------------------------------
# The model


def _pair_columns(pair: jax.Array) -> dict[str, jax.Array]:
    return {name: pair[:, i] for i, name in enumerate(PAIR_COLUMNS)}


class ContactChargeNet(ContactNet):
    """The contact-impulse surrogate conditioned on each contact's physical parameters
    (module docstring). Its graph must carry a charge (a window with a
    :class:`sgn_jax.surrogate.graph.BallCharge`). ``physics`` is a :class:`ChargePhysics`;
    everything else (spin, the single-rollout forms, the sweeps, the ledger, collisions) as
    :class:`sgn_jax.surrogate.contact.ContactNet`."""

    physics: Any = ChargePhysics()

    # ---- geometry and inputs

    def _edge_geometry(self, graph: jraph.GraphsTuple) -> dict[str, jax.Array]:
        """The contact kind's geometry (:func:`sgn_jax.surrogate.contact.edge_geometry`, its
        keys) per contact with its own radii, masses and material, plus ``m_star``,
        ``scale_l`` (m, L), ``scale_v`` (m/s, V), ``mu``, ``mu_r``, ``k`` (the stick's
        slip factor) and with spin ``arm_s`` (the sender's arm), ``roll_radius``, ``i_eff``."""
        phys = self.physics
        if "pair" not in graph.edges or "radius" not in graph.nodes:
            raise ContactModelError("the charge-conditioned contact model needs a graph with a "
                                    "charge: build it from a Window with a BallCharge")
        w, h, dt = phys.window, phys.history, phys.dt
        senders, receivers = graph.senders[0::2], graph.receivers[0::2]
        r_node = jnp.asarray(graph.nodes["radius"], DTYPE)
        m_node = jnp.asarray(graph.nodes["mass"], DTYPE)
        r_r, r_s = r_node[receivers], r_node[senders]
        kin = edge_kinematics(graph, w, dt, r_r + r_s, r_r, primary_only=True)
        is_pp = kin["is_pp"]
        normal, gap, v_t, speed_t = kin["normal"], kin["gap"], kin["v_t"], kin["speed_t"]
        mat, m_r, m_s, safe_m, m_star, scale_l = self._contact_scale(graph, receivers, senders,
                                                                     is_pp)
        scale_v = scale_l / dt
        size_ratio = jnp.where(is_pp, jnp.minimum(r_r, r_s) / jnp.maximum(
            jnp.maximum(r_r, r_s), 1e-30), 0.0)
        mass_balance = jnp.where(is_pp, 4.0 * m_r * m_s / (safe_m * safe_m), 0.0)

        extra: dict[str, jax.Array] = {}
        i_node = 0.4 * m_node * r_node ** 2
        overlap = jnp.maximum(-gap[-1], 0.0)
        # each ball's own arm, r_i - overlap / 2 (the DEM's contact point: the middle of the
        # overlap), so that the arms of a pair add up to the centre distance
        arm = r_r - 0.5 * overlap
        arm_s = jnp.where(is_pp, r_s - 0.5 * overlap, 0.0)
        i_r = jnp.where(i_node[receivers] > 0, i_node[receivers], 1.0)
        i_s = jnp.where(is_pp & (i_node[senders] > 0), i_node[senders], 1.0)
        # the slip falls by k du_t (through both balls' velocities and spins)
        k = 1.0 + m_star * (arm ** 2 / i_r + jnp.where(is_pp, arm_s ** 2 / i_s, 0.0))
        if self.spin:
            if "spin" not in graph.nodes:
                raise ContactModelError("a contact model with spin needs the balls' spins in "
                                        "the graph (a Window with spins)")
            w_node = jnp.asarray(graph.nodes["spin"], DTYPE)
            w_r, w_s = w_node[receivers], w_node[senders]      # the wall node's spin row is 0
            v_slip = v_t - jnp.cross(arm[:, None] * w_r + arm_s[:, None] * w_s, normal)
            slip_c = _safe_norm(v_slip)
            # the DEM's rolling radius of a pair: the harmonic mean of the arms
            roll_radius = jnp.where(is_pp, 2.0 * arm * arm_s / jnp.where(
                is_pp, jnp.maximum(arm + arm_s, 1e-30), 1.0), arm)
            i_eff = jnp.where(is_pp, i_r * i_s / (i_r + i_s), i_r)
            extra = {"w_node": w_node, "w_rel": w_r - w_s, "arm": arm, "arm_s": arm_s,
                     "slip": slip_c, "roll_radius": roll_radius, "i_eff": i_eff,
                     "i_node": i_node}
        else:
            v_slip, slip_c = v_t, speed_t

        lengths = scale_l / L_REF
        rows = contact_rows(
            graph, kin, v_slip, slip_c, history=h, dt=dt, gravity=phys.gravity,
            scales=InputScales(GAP_COARSE * scale_l, GAP_FINE * scale_l, SPEED_COARSE * scale_v,
                               SPEED_FINE * scale_v, 5.0),
            gate_rule=GateRule(phys.overlap_limit > 0, phys.overlap_limit * lengths,
                               phys.overlap_law_factor, scale_l, phys.gate_margin * lengths,
                               SPEED_REF,
                               rebound_time=mat["rebound_time"] if phys.law_rebound else None,
                               restitution=mat["restitution"],
                               rebound_exact=phys.rebound_exact,
                               rebound_sweeps=phys.rebound_sweeps),
            spin=self.spin,
            constant_inputs=(jnp.log10(scale_v / SPEED_REF), mat["restitution"],
                             mat["friction"], ROLLING_INPUT * mat["rolling_friction"],
                             size_ratio, mass_balance))
        return {
            **rows, "speed_c": slip_c,
            "m_node": m_node, "m_star": m_star, "scale_l": scale_l, "scale_v": scale_v,
            "mu": mat["friction"], "mu_r": mat["rolling_friction"], "k": k, **extra,
        }

    def _contact_scale(self, graph: jraph.GraphsTuple, receivers: jax.Array,
                       senders: jax.Array, is_pp: jax.Array):
        """Per primary row: ``(mat, m_r, m_s, safe_m, m_star, scale_l)``, the pair-table
        columns, the two masses (kg), their sum (1 where no pair), m* and L (m); padding rows
        (no contact) get the receiver's R* and m* and finite values."""
        r_node = jnp.asarray(graph.nodes["radius"], DTYPE)
        m_node = jnp.asarray(graph.nodes["mass"], DTYPE)
        r_r, r_s = r_node[receivers], r_node[senders]
        mat = _pair_columns(jnp.asarray(graph.edges["pair"][0::2], DTYPE))
        m_r, m_s = m_node[receivers], m_node[senders]
        safe_r = jnp.where(is_pp, r_r + r_s, 1.0)
        safe_m = jnp.where(is_pp, m_r + m_s, 1.0)
        r_r_ok = jnp.where(r_r > 0, r_r, L_REF)
        r_star = jnp.where(is_pp, r_r * r_s / safe_r, r_r_ok)
        m_star = jnp.where(is_pp, m_r * m_s / safe_m, m_r)
        young = jnp.where(mat["young_eff"] > 0, mat["young_eff"], 1.0)
        scale_l = mat["peak_coef"] * (m_star / (young * jnp.sqrt(r_star))) ** 0.4
        return mat, m_r, m_s, safe_m, m_star, jnp.where(scale_l > 0, scale_l, L_REF)

    def _reach_and_margin(self, graph: jraph.GraphsTuple, receivers: jax.Array,
                          senders: jax.Array, is_pp: jax.Array):
        """Per primary row: r_r + r_s, r_r and the gate margin ``gate_margin L / L_REF`` (m),
        as :meth:`_edge_geometry` uses them."""
        r_node = jnp.asarray(graph.nodes["radius"], DTYPE)
        r_r = r_node[receivers]
        scale_l = self._contact_scale(graph, receivers, senders, is_pp)[-1]
        return r_r + r_node[senders], r_r, self.physics.gate_margin * scale_l / L_REF

    # ---- impulses

    def _learned_normal(self, geo: dict[str, jax.Array], logits: jax.Array) -> jax.Array:
        """(E,) m/s: du_n in units of the contact's speed scale V."""
        return geo["scale_v"] * nn.softplus(logits[:, 0])

    def _reduced_mass(self, geo: dict[str, jax.Array]) -> jax.Array:
        return geo["m_star"]

    def _impulses(self, geo: dict[str, jax.Array], logits: jax.Array):
        """As the contact kind's (:meth:`ContactNet._impulses`) with the contact's own cone
        mu_c du_n and slip factor k."""
        du_n = self._normal_impulse(geo, logits)
        cone = geo["mu"] * du_n
        if self.spin:
            stick = (2.0 * jax.nn.sigmoid(logits[:, 1]) * geo["slip"]
                     / (geo["k"] * geo["contacts_max"]))
            du_t = cone * jnp.tanh(stick / (cone + 1e-12))
        else:
            du_t = cone * jnp.tanh(logits[:, 1])
        m_star = geo["m_star"]
        impulse = ((m_star * (-du_n))[:, None] * geo["normal"]
                   + (m_star * du_t)[:, None] * geo["tangent"])
        return impulse, du_n, du_t

    def _rolling(self, geo: dict[str, jax.Array], du_n: jax.Array) -> jax.Array:
        """(E, 3) N m s, the rolling friction's angular impulse on the receiver (the sender
        gets the opposite): -min(mu_r r_roll J_n, I_eff |w_rel|) w_rel / |w_rel|."""
        w_rel = geo["w_rel"]
        w_norm = _safe_norm(w_rel)
        roll = jnp.minimum(geo["mu_r"] * geo["roll_radius"] * geo["m_star"] * du_n,
                           geo["i_eff"] * w_norm)
        return -roll[:, None] * (w_rel / jnp.where(w_norm > 0, w_norm, 1.0)[:, None])

    def _angular_impulses(self, geo: dict[str, jax.Array], impulse: jax.Array, du_n: jax.Array
                          ) -> tuple[jax.Array, jax.Array]:
        """The torque of J at the contact point on each ball with its own arm (a_r n x J on
        the receiver, a_s n x J on the sender: the same point, so the pair's angular momentum
        is kept) and the rolling friction."""
        l_roll = self._rolling(geo, du_n)
        n_x_j = jnp.cross(geo["normal"], impulse)
        a_recv = geo["arm"][:, None] * n_x_j + l_roll
        a_send = (geo["arm_s"][:, None] * n_x_j - l_roll) * geo["is_pp"][:, None]
        return a_recv, a_send

    def _spin_change(self, geo: dict[str, jax.Array], a_recv: jax.Array, a_send: jax.Array,
                     n_node: int, is_particle: jax.Array) -> jax.Array:
        total = sum_at_both_ends(a_recv, a_send, geo["receivers"], geo["senders"], n_node)
        inertia = jnp.where(is_particle, geo["i_node"], 1.0)
        return jnp.where(is_particle[:, None], total / inertia[:, None], 0.0)

    def _impulse_velocity_change(self, geo: dict[str, jax.Array], impulse: jax.Array,
                                 n_node: int, is_particle: jax.Array) -> jax.Array:
        receivers, senders = geo["receivers"], geo["senders"]
        total = sum_at_both_ends(impulse, -impulse * geo["is_pp"][:, None], receivers, senders,
                                 n_node)
        mass = jnp.where(is_particle, geo["m_node"], 1.0)
        return jnp.where(is_particle[:, None], total / mass[:, None], 0.0)

    def _project_friction(self, geo: dict[str, jax.Array], impulse: jax.Array, du_n: jax.Array,
                          dv: jax.Array, dw: jax.Array, angular: tuple[jax.Array, jax.Array],
                          n_node: int, is_particle: jax.Array):
        """The contact kind's friction sweeps (:meth:`ContactNet._project_friction`) with each
        contact's own cone, slip factor and arms and each ball's own mass and inertia; with
        ``friction_sweep_contacts = "wall"`` on the ball-wall contacts only (a ball-ball
        contact's tangential impulse stays the network's)."""
        receivers, senders, normal = geo["receivers"], geo["senders"], geo["normal"]
        gate, arm, arm_s, k = geo["gate"], geo["arm"], geo["arm_s"], geo["k"]
        walls_only = self.physics.friction_sweep_contacts == "wall"
        if walls_only:   # (E,) 1 where the sweeps act: the ball-wall rows
            swept = geo["is_pw"].astype(gate.dtype)
            gate = gate * swept
        m_star = geo["m_star"]
        count = _larger_ball_count(gate, receivers, senders, geo["is_pp"], n_node)
        cone = geo["mu"] * m_star * du_n
        wall_end = geo["u_wall"] + geo["jar_dv"]
        tangential = impulse - jnp.einsum("ec,ec->e", impulse, normal)[:, None] * normal
        a_recv, a_send = angular
        is_pp = geo["is_pp"][:, None]
        mass = jnp.where(is_particle, geo["m_node"], 1.0)
        inertia = jnp.where(is_particle, geo["i_node"], 1.0)
        mass_inertia = jnp.concatenate([jnp.repeat(mass[:, None], 3, axis=1),
                                        jnp.repeat(inertia[:, None], 3, axis=1)], axis=1)
        for _ in range(self.physics.friction_sweeps):
            state = jnp.concatenate([geo["v_node"] + dv, geo["w_node"] + dw], axis=-1)
            at_recv, at_send = at_both_ends(state, receivers, senders)
            partner = jnp.where(geo["is_pw"][:, None], wall_end, at_send[:, :3])
            v_rel = partner - at_recv[:, :3]
            v_t = v_rel - jnp.einsum("ec,ec->e", v_rel, normal)[:, None] * normal
            slip = v_t - jnp.cross(arm[:, None] * at_recv[:, 3:] + arm_s[:, None] * at_send[:, 3:],
                                   normal)
            wanted = tangential + (m_star * gate / (k * count))[:, None] * slip
            size = _safe_norm(wanted)
            scale = jnp.minimum(1.0, cone / jnp.maximum(size, 1e-30))
            extra = wanted * scale[:, None] - tangential
            if walls_only:
                extra = extra * swept[:, None]
            tangential = tangential + extra
            impulse = impulse + extra
            n_x_extra = jnp.cross(normal, extra)
            t_recv, t_send = arm[:, None] * n_x_extra, arm_s[:, None] * n_x_extra * is_pp
            a_recv, a_send = a_recv + t_recv, a_send + t_send
            on_balls = sum_at_both_ends(jnp.concatenate([extra, t_recv], axis=-1),
                                        jnp.concatenate([-extra * is_pp, t_send], axis=-1),
                                        receivers, senders, n_node)
            change = jnp.where(is_particle[:, None], on_balls / mass_inertia, 0.0)
            dv, dw = dv + change[:, :3], dw + change[:, 3:]
        return impulse, _safe_norm(tangential) / m_star, dv, dw, (a_recv, a_send)

    # ---- the dissipation target

    def _dissipation_target(self, parts: dict[str, jax.Array], seg: Any) -> jax.Array:
        """Per contact: its normal dissipation counts whole (the DEM's normal damping), its
        rolling friction's not at all (the DEM's rolling losses), the rest (the tangential
        impulse and its torques) by the kind's tangential damping share, the DEM's tangential
        damping against its Coulomb slip (``share_logit``, fitted from records)."""
        share = jax.nn.sigmoid(jax.lax.stop_gradient(self.share_logit))
        return seg(per_contact_damping(parts, share, self.spin))


def physics_from_config(cfg: Any) -> ChargePhysics:
    """The :class:`ChargePhysics` of an experiment config (``dem.dt`` and ``gravity``,
    ``graph.window`` and ``wall_patches``, the ``[model]`` overlap and sweep keys)."""
    return ChargePhysics(dt=float(cfg.dem.dt), gravity=tuple(float(g) for g in cfg.dem.gravity),
                         window=int(cfg.graph.window), wall_patches=int(cfg.graph.wall_patches),
                         overlap_limit=float(getattr(cfg.model, "overlap_limit", 0.0)),
                         overlap_law_factor=float(getattr(cfg.model, "overlap_law_factor", 0.0)),
                         law_rebound=bool(getattr(cfg.model, "law_rebound", False)),
                         overlap_sweeps=int(getattr(cfg.model, "overlap_sweeps", 0)),
                         friction_sweeps=int(getattr(cfg.model, "friction_sweeps", 0)),
                         rebound_exact=str(getattr(cfg.model, "law_rebound_exact", "off")),
                         friction_sweep_contacts=str(getattr(cfg.model, "friction_sweep_contacts",
                                                             "all")),
                         rebound_sweeps=str(getattr(cfg.model, "rebound_sweeps", "off")))


def make_contact_charge_net(cfg: Any) -> ContactChargeNet:
    """The factory of kind "contact_charge" (``[model] hidden``, ``mlp_layers``, ``spin`` and
    the keys of :func:`physics_from_config`)."""
    return ContactChargeNet(physics=physics_from_config(cfg), hidden=int(cfg.model.hidden),
                            mlp_layers=int(cfg.model.mlp_layers), spin=bool(cfg.model.spin))


register_model("contact_charge", make_contact_charge_net, builds_from="config",
               node_walls=False, takes_charge=True,
               description="contact-impulse model conditioned on each contact's radii, masses "
                           "and material, with inputs dimensionless per contact")
