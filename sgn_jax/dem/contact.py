"""Hertz-Mindlin contact law with tangential history, Coulomb limit and rolling friction.

Pure, vectorised per-contact math (docs/conventions.md section 3, paper Eqs. 3-18 with the typos
fixed). Every function works on K contacts at once (leading axis K) and knows nothing about balls,
pairs or walls: the engine gathers the contact kinematics, calls :func:`contact_forces`, scatters the
forces and, after the velocity update, calls :func:`contact_dissipation` for the energy ledger.

Sign conventions (per contact, "body i" is a ball, its partner j another ball or a wall patch):

- ``normal`` (K,3) is the unit vector from body i towards its partner (for a wall: the SDF
  normal, pointing from the ball towards the wall);
- ``overlap`` (K,) m is positive in contact: 2R - |x_j - x_i| for two balls, R + phi for a wall;
- ``v_rel`` (K,3) m/s is the velocity of i's material point at the contact minus the partner's;
  ``v_n = v_rel . normal`` is positive while the bodies approach;
- forces and torques returned are those **on body i**; the partner gets the reaction.

All energies are in J, powers are integrated over one step of ``dt`` s.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import flax.struct
import jax.numpy as jnp
import numpy as np

# --------------------------------------------------------------------------------------------
# Material


@flax.struct.dataclass
class ContactLaw:
    """Effective parameters of one contact type (ball-ball or ball-wall), docs/conventions.md
    section 3.

    Attributes:
        young_eff: Y* (Pa), 1/Y* = (1-nu1^2)/Y1 + (1-nu2^2)/Y2.
        shear_eff: G* (Pa), 1/G* = 2(2-nu1)(1+nu1)/Y1 + 2(2-nu2)(1+nu2)/Y2.
        radius_eff: R* (m), 1/R* = 1/R1 + 1/R2 (R2 = inf for a wall).
        mass_eff: m* (kg), 1/m* = 1/m1 + 1/m2 (m2 = inf for a wall).
        damping_factor: -2 sqrt(5/6) beta >= 0 with beta = ln e / sqrt(ln^2 e + pi^2), so that
            gamma_n = damping_factor sqrt(S_n m*) and gamma_t = damping_factor sqrt(S_t m*).
        friction: Coulomb coefficient mu (-).
        rolling_friction: rolling coefficient mu_r (-), EDEM type A constant torque.
    """

    young_eff: float
    shear_eff: float
    radius_eff: float
    mass_eff: float
    damping_factor: float
    friction: float
    rolling_friction: float


def damping_factor_from_restitution(restitution: float) -> float:
    """-2 sqrt(5/6) beta for a coefficient of restitution e in (0, 1] (paper Eqs. 5, 10)."""
    if not 0.0 < restitution <= 1.0:
        raise ValueError(f"restitution must be in (0, 1], got {restitution}")
    log_e = math.log(restitution)
    beta = log_e / math.sqrt(log_e**2 + math.pi**2)
    return -2.0 * math.sqrt(5.0 / 6.0) * beta


def make_contact_law(
    young: float,
    poisson: float,
    restitution: float,
    friction: float,
    rolling_friction: float,
    radius_1: float,
    mass_1: float,
    radius_2: float = math.inf,
    mass_2: float = math.inf,
    young_2: float | None = None,
    poisson_2: float | None = None,
) -> ContactLaw:
    """Effective contact parameters of body 1 against body 2 (a wall: radius_2 = mass_2 = inf).

    Body 2 has the same material as body 1 unless ``young_2`` / ``poisson_2`` are given
    (docs/conventions.md section 2: balls and wall share one material).
    """
    young_2 = young if young_2 is None else young_2
    poisson_2 = poisson if poisson_2 is None else poisson_2
    inv_y = (1 - poisson**2) / young + (1 - poisson_2**2) / young_2
    inv_g = 2 * (2 - poisson) * (1 + poisson) / young + 2 * (2 - poisson_2) * (1 + poisson_2) / young_2
    inv_r = 1.0 / radius_1 + (0.0 if math.isinf(radius_2) else 1.0 / radius_2)
    inv_m = 1.0 / mass_1 + (0.0 if math.isinf(mass_2) else 1.0 / mass_2)
    return ContactLaw(
        young_eff=1.0 / inv_y,
        shear_eff=1.0 / inv_g,
        radius_eff=1.0 / inv_r,
        mass_eff=1.0 / inv_m,
        damping_factor=damping_factor_from_restitution(restitution),
        friction=float(friction),
        rolling_friction=float(rolling_friction),
    )


MIN_CONTACT_STEPS = 20
"""A Hertz contact must last at least this many DEM steps to be resolved: the config check
(sgn_jax.pipelines.validation) applies it to the largest impact speed a motion drives, the run
(sgn_jax.pipelines.dem_run.check_samples) to the relative speeds it reaches."""


def hertz_contact_time(law: ContactLaw, impact_speed: float) -> float:
    """Hertz's elastic contact duration t_c = 2.87 (m*^2 / (R* Y*^2 v))^(1/5) (s)."""
    return 2.87 * (law.mass_eff**2 / (law.radius_eff * law.young_eff**2 * impact_speed)) ** 0.2


def hertz_normal_force(law: ContactLaw, overlap: jnp.ndarray) -> jnp.ndarray:
    """Elastic Hertz force (4/3) Y* sqrt(R*) d^(3/2) (N), zero for d <= 0."""
    d = jnp.maximum(overlap, 0.0)
    return (4.0 / 3.0) * law.young_eff * jnp.sqrt(law.radius_eff * d) * d


def hertz_energy(law: ContactLaw, overlap: jnp.ndarray) -> jnp.ndarray:
    """Elastic energy of the Hertz spring (8/15) Y* sqrt(R*) d^(5/2) (J), zero for d <= 0."""
    d = jnp.maximum(overlap, 0.0)
    return (8.0 / 15.0) * law.young_eff * jnp.sqrt(law.radius_eff * d) * d * d


def head_on_normal_force(law: ContactLaw, overlap: Any, approach_rate: Any) -> Any:
    """The normal force (N, repulsive positive) of :func:`contact_forces` for a head-on
    contact: the Hertz spring plus its damping ``gamma_n v_n``, not clipped
    (docs/conventions.md section 3), zero out of contact. numpy, for the host-side 1-D
    references of a contact (:func:`sgn_jax.surrogate.contact_train.impact_stretches`);
    ``law``'s fields and the arguments may be floats or arrays of one shape."""
    d = np.maximum(overlap, 0.0)
    sqrt_rd = np.sqrt(law.radius_eff * d)
    spring = (4.0 / 3.0) * law.young_eff * sqrt_rd * d
    gamma_n = law.damping_factor * np.sqrt(2.0 * law.young_eff * sqrt_rd * law.mass_eff)
    return np.where(np.asarray(overlap) > 0, spring + gamma_n * approach_rate, 0.0)


def head_on_impact(law: ContactLaw, speed: float = 1.0, steps: int = 2000
                   ) -> tuple[float, float]:
    """``(peak, duration)`` of a head-on impact at ``speed`` m/s under ``law`` (its Hertz
    spring and damping, no gravity), integrated with ``steps`` steps per Hertz contact time:
    the deepest overlap (m) and the time (s) from first touch until the overlap is back to zero.
    With this damping (gamma_n ~ (R d)^(1/4)) the impact is self-similar: the peak scales as
    speed^0.8 and the duration as speed^-0.2 exactly (the restitution is the same at every
    speed), so one call at 1 m/s gives both at every speed, and ``speed * duration / peak``
    depends on the restitution alone (5.09 at e = 0.3, 3.41 at 0.74; Hertz's elastic 2.94).
    numpy, host side (the contact models' overlap limit and law rebound)."""
    h = hertz_contact_time(law, speed) / steps
    d, rate, t, peak = 0.0, float(speed), 0.0, None
    while True:
        rate -= float(head_on_normal_force(law, d, rate)) / law.mass_eff * h
        d += rate * h
        t += h
        if peak is None and rate <= 0.0:
            peak = d
        if d <= 0.0:
            return peak, t


def head_on_peak_overlap(law: ContactLaw, speed: float = 1.0, steps: int = 2000) -> float:
    """The deepest overlap (m) of a head-on impact at ``speed`` m/s under ``law``
    (:func:`head_on_impact`)."""
    return head_on_impact(law, speed, steps)[0]


def head_on_contact_time(law: ContactLaw, speed: float = 1.0, steps: int = 2000) -> float:
    """The duration (s) of a head-on impact at ``speed`` m/s under ``law``, first touch to
    separation (:func:`head_on_impact`)."""
    return head_on_impact(law, speed, steps)[1]


# --------------------------------------------------------------------------------------------
# Forces


class ContactForces(NamedTuple):
    """Output of :func:`contact_forces` for K contacts (forces and torques on body i).

    Attributes:
        force: (K,3) N, total contact force on body i (normal + tangential).
        torque_tangential: (K,3) N m, arm x F_t on body i, arm = R_c * normal.
        torque_rolling: (K,3) N m, rolling-friction torque on body i (the partner gets minus it).
        normal_total: (K,) N, signed normal force (positive = repulsive), spring + damping
            (clipped at 0 when attractive forces are clipped).
        normal_spring: (K,) N, the elastic Hertz part.
        tangential: (K,3) N, applied tangential force on body i (spring + damping, Coulomb-limited).
        tangential_damping: (K,3) N, the applied damping part of ``tangential``.
        history: (K,3) m, new tangential displacement (0 where the contact is open).
        sliding: (K,) bool, the Coulomb limit was hit this step.
        spring_energy: (K,) J, tangential spring energy 1/2 S_t |history|^2 after the step.
        spring_energy_old_now: (K,) J, the energy of the old history at the current stiffness:
            its difference with the old stored energy is the energy released (or taken up) by
            the change of S_t with the overlap.
        in_contact: (K,) bool, overlap > 0.
    """

    force: jnp.ndarray
    torque_tangential: jnp.ndarray
    torque_rolling: jnp.ndarray
    normal_total: jnp.ndarray
    normal_spring: jnp.ndarray
    tangential: jnp.ndarray
    tangential_damping: jnp.ndarray
    history: jnp.ndarray
    sliding: jnp.ndarray
    spring_energy: jnp.ndarray
    spring_energy_old_now: jnp.ndarray
    in_contact: jnp.ndarray


def _dot(a: jnp.ndarray, b: jnp.ndarray) -> jnp.ndarray:
    return jnp.sum(a * b, axis=-1)


def contact_forces(
    law: ContactLaw,
    overlap: jnp.ndarray,
    normal: jnp.ndarray,
    arm: jnp.ndarray,
    v_rel: jnp.ndarray,
    omega_rel: jnp.ndarray,
    history: jnp.ndarray,
    dt: float,
    clip_attractive: bool = False,
    rolling: str = "edem_a",
) -> ContactForces:
    """Hertz-Mindlin forces on body i for K contacts (docs/conventions.md section 3).

    Args:
        law: effective parameters of this contact type.
        overlap: (K,) m, > 0 in contact.
        normal: (K,3) unit normal from body i towards its partner.
        arm: (K,) m, R_c, distance from i's centre to the contact point (middle of the overlap).
        v_rel: (K,3) m/s, velocity of i's contact point relative to the partner's.
        omega_rel: (K,3) rad/s, i's angular velocity relative to the partner (a wall: i's own).
        history: (K,3) m, tangential displacement stored at the previous step.
        dt: the DEM step (s), used to integrate the tangential displacement.
        clip_attractive: clip the normal force at zero (off by default; docs/conventions.md,
            section 3).
        rolling: the rolling-friction law: "edem_a" (the default, the paper's: mu_r times the
            whole |F_n| times the arm R_c, against the whole relative spin) or "cdt"
            (LIGGGHTS' ``rolling_friction cdt``: mu_r times the elastic Hertz force times R*,
            against the relative spin without its twist about n).

    Steps, per contact:

    1. Hertz spring F_s = 4/3 Y* sqrt(R*) d^1.5 and damping gamma_n v_n with
       gamma_n = -2 sqrt(5/6) beta sqrt(S_n m*), S_n = 2 Y* sqrt(R* d);
       F_n = F_s + gamma_n v_n (repulsive positive).
    2. The old tangential displacement is rotated onto the current tangent plane keeping its
       length (a plain projection would silently drain spring energy), then advanced:
       d_trial = rot(d_old) + v_t dt.
    3. Trial tangential force F_t = -S_t d_trial - gamma_t v_t, S_t = 8 G* sqrt(R* d).
    4. Coulomb, applied to the *whole* tangential force (spring + damping): if
       |F_t| > mu |F_n| both parts are scaled by s = mu |F_n| / |F_t|, so that |F_t| = mu |F_n|
       exactly, and the stored displacement is s d_trial (the spring stays at the Coulomb
       limit while sliding). The damping loss stays >= 0; the slip loss is formed in
       :func:`contact_dissipation`.
    5. Rolling friction tau_r = -mu_r |F_n| R_c w/|w| (zero for w = 0).
    Open contacts (d <= 0) give zero force and a zero history (reset when a contact ends).
    """
    in_contact = overlap > 0
    d = jnp.where(in_contact, overlap, 0.0)
    sqrt_rd = jnp.sqrt(law.radius_eff * d)
    normal_spring = (4.0 / 3.0) * law.young_eff * sqrt_rd * d
    stiff_n = 2.0 * law.young_eff * sqrt_rd
    stiff_t = 8.0 * law.shear_eff * sqrt_rd
    gamma_n = law.damping_factor * jnp.sqrt(stiff_n * law.mass_eff)
    gamma_t = law.damping_factor * jnp.sqrt(stiff_t * law.mass_eff)
    if rolling not in ROLLING_LAWS:
        raise ValueError(f"rolling={rolling!r}: use one of {ROLLING_LAWS}")
    cdt = rolling == "cdt"
    return assemble_contact_forces(
        normal_spring, stiff_t, gamma_n, gamma_t, law.friction, law.rolling_friction, in_contact,
        normal, arm, v_rel, omega_rel, history, dt, clip_attractive,
        rolling_load=normal_spring if cdt else None,
        rolling_arm=jnp.broadcast_to(law.radius_eff, jnp.shape(overlap)) if cdt else None,
        rolling_twist=not cdt)


ROLLING_LAWS = ("edem_a", "cdt")
"""The rolling-friction laws of :func:`contact_forces`."""


def assemble_contact_forces(
    normal_spring: jnp.ndarray,
    stiff_t: jnp.ndarray,
    gamma_n: jnp.ndarray,
    gamma_t: jnp.ndarray,
    friction: Any,
    rolling_friction: Any,
    in_contact: jnp.ndarray,
    normal: jnp.ndarray,
    arm: jnp.ndarray,
    v_rel: jnp.ndarray,
    omega_rel: jnp.ndarray,
    history: jnp.ndarray,
    dt: float,
    clip_attractive: bool = False,
    rolling_load: jnp.ndarray | None = None,
    rolling_arm: jnp.ndarray | None = None,
    rolling_twist: bool = True,
) -> ContactForces:
    """Steps 1-5 of :func:`contact_forces` from a law's normal spring force and coefficients.

    The part every spring-dashpot law with a tangential spring history shares (see
    :mod:`sgn_jax.dem.laws`): a law computes, per contact, its elastic normal force
    ``normal_spring`` (K,) N, which must be 0 where ``in_contact`` is False (the ledger's normal
    damping is ``normal_total - normal_spring``), its tangential stiffness ``stiff_t`` (K,) N/m
    and its damping coefficients ``gamma_n``, ``gamma_t`` (K,) N s/m; this function adds the
    normal damping, the rotated tangential history, the Coulomb limit on spring + damping and
    rolling friction as documented in :func:`contact_forces`, masks open contacts, and fills
    every field of :class:`ContactForces` that :func:`contact_dissipation` and the engine
    read. ``friction`` and ``rolling_friction`` are mu and mu_r. The rolling torque is
    mu_r * load * arm against the relative spin: by default the load |F_n| (spring and damping),
    the arm ``arm`` and the whole spin; ``rolling_load`` (K,) N, ``rolling_arm`` (K,) m and
    ``rolling_twist=False`` (the spin without its component along n) replace them.
    """
    v_n = _dot(v_rel, normal)
    normal_total = normal_spring + gamma_n * v_n
    if clip_attractive:
        normal_total = jnp.maximum(normal_total, 0.0)
    normal_total = jnp.where(in_contact, normal_total, 0.0)
    v_t = v_rel - v_n[..., None] * normal

    # Rotate the old displacement onto the current tangent plane, keeping its length.
    old_sq = _dot(history, history)
    projected = history - _dot(history, normal)[..., None] * normal
    proj_sq = _dot(projected, projected)
    rescale = jnp.sqrt(old_sq / jnp.where(proj_sq > 0, proj_sq, 1.0))
    rotated = jnp.where((proj_sq > 0)[..., None], projected * rescale[..., None], 0.0)
    trial = rotated + v_t * dt

    spring_trial = -stiff_t[..., None] * trial
    damping_trial = -gamma_t[..., None] * v_t
    total_trial = spring_trial + damping_trial
    trial_sq = _dot(total_trial, total_trial)
    limit = friction * jnp.abs(normal_total)
    sliding = trial_sq > limit * limit
    scale = jnp.where(sliding, limit / jnp.sqrt(jnp.where(sliding, trial_sq, 1.0)), 1.0)

    history_new = jnp.where(in_contact[..., None], scale[..., None] * trial, 0.0)
    tangential = jnp.where(in_contact[..., None], scale[..., None] * total_trial, 0.0)
    tangential_damping = jnp.where(in_contact[..., None], scale[..., None] * damping_trial, 0.0)
    spring_energy = 0.5 * stiff_t * _dot(history_new, history_new)
    spring_energy_old_now = jnp.where(in_contact, 0.5 * stiff_t * old_sq, 0.0)

    if not rolling_twist:  # the spin about the normal is twisting, not rolling
        omega_rel = omega_rel - _dot(omega_rel, normal)[..., None] * normal
    omega_sq = _dot(omega_rel, omega_rel)
    omega_norm = jnp.sqrt(jnp.where(omega_sq > 0, omega_sq, 1.0))
    load = jnp.abs(normal_total) if rolling_load is None else rolling_load
    roll_mag = rolling_friction * load * (arm if rolling_arm is None else rolling_arm)
    torque_rolling = jnp.where(
        (omega_sq > 0)[..., None], -(roll_mag / omega_norm)[..., None] * omega_rel, 0.0
    )

    force = -normal_total[..., None] * normal + tangential
    torque_tangential = jnp.cross(arm[..., None] * normal, tangential)
    return ContactForces(
        force=force,
        torque_tangential=torque_tangential,
        torque_rolling=torque_rolling,
        normal_total=normal_total,
        normal_spring=normal_spring,
        tangential=tangential,
        tangential_damping=tangential_damping,
        history=history_new,
        sliding=sliding & in_contact,
        spring_energy=spring_energy,
        spring_energy_old_now=spring_energy_old_now,
        in_contact=in_contact,
    )


DISSIPATION_KINDS = ("normal", "tangential", "slip", "rolling", "stiffness")
"""The kinds of the DEM's energy ledger: the four of :class:`ContactDissipation` and the energy
the tangential spring releases as its stiffness changes (formed by the engine)."""


class ContactDissipation(NamedTuple):
    """Energy dissipated by K contacts over one step (J, each (K,))."""

    normal: jnp.ndarray
    tangential: jnp.ndarray
    slip: jnp.ndarray
    rolling: jnp.ndarray


def contact_dissipation(
    forces: ContactForces,
    normal: jnp.ndarray,
    v_rel_mid: jnp.ndarray,
    omega_rel_mid: jnp.ndarray,
    dt: float,
) -> ContactDissipation:
    """Energy dissipated over one step, with the step's mean velocities (J, per contact).

    With the symplectic Euler update the change of kinetic energy over a step is exactly
    F . (v_old + v_new)/2 dt, so every power is evaluated with the mid-step relative velocity
    ``v_rel_mid`` (and ``omega_rel_mid``) of the contact point: the ledger then closes up to the
    time-integration error of the conservative springs alone.

    - normal: (F_n - F_s) v_n,mid dt, the work of the applied normal damping (Eq. 17);
    - tangential: -F_t,damping . v_mid dt (Eq. 18);
    - slip (only on steps where the Coulomb limit is hit): the energy the tangential spring
      cannot store, E_old + W_spring - E_new, where W_spring = -F_t,spring . v_mid dt is the
      work done on the spring and E = 1/2 S_t |d_t|^2 (both at the current stiffness). It is
      the friction work F_t,spring . v_slip dt of steady sliding. (A closed-form "energy removed
      by the scaling", 1/2 S_t (1 - s^2) |d_trial|^2, would also count the 1/2 S_t |v_t dt|^2
      that the explicit update of d_t adds each step without any work being done: with
      mu = 0 that is pure bookkeeping error.) On sticking steps the spring's own O(dt^2)
      integration error is left in the ledger residual, where it averages out;
    - rolling: -tau_r . w_rel,mid dt.

    The fifth ledger term, the energy released by the tangential spring because S_t changes with
    the overlap at a fixed displacement, is a sum over contacts of
    ``spring_energy_old - spring_energy_old_now`` and is formed by the engine, which keeps the
    stored spring energy as one scalar per contact type.
    """
    v_n_mid = _dot(v_rel_mid, normal)
    diss_normal = (forces.normal_total - forces.normal_spring) * v_n_mid * dt
    diss_tangential = -_dot(forces.tangential_damping, v_rel_mid) * dt
    spring_force = forces.tangential - forces.tangential_damping
    spring_work = -_dot(spring_force, v_rel_mid) * dt
    diss_slip = jnp.where(
        forces.sliding,
        forces.spring_energy_old_now + spring_work - forces.spring_energy,
        0.0,
    )
    diss_rolling = -_dot(forces.torque_rolling, omega_rel_mid) * dt
    return ContactDissipation(
        normal=diss_normal,
        tangential=diss_tangential,
        slip=diss_slip,
        rolling=diss_rolling,
    )
