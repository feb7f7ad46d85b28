"""A linear spring-dashpot contact law, added to the DEM in this one file (docs/dem.md,
"Adding a contact law").

Normal force ``F_n = k_n d + c_n v_n`` (repulsive positive, the dashpot active over the whole
contact, attractive values kept unless ``clip_attractive``), a linear tangential spring
``k_t`` with dashpot ``c_t``, and the Coulomb limit, history rotation and rolling friction of
the Hertz-Mindlin law (shared through :func:`sgn_jax.dem.contact.assemble_contact_forces`).

From the material: ``k_n`` is the secant stiffness of the Hertz spring of the same bodies at
``reference_overlap`` (so ``F_n`` agrees with Hertz there), ``k_t = tangential_ratio k_n``,
and ``c = 2 zeta sqrt(k m*)`` with ``zeta = -ln e / sqrt(ln^2 e + pi^2)``, for which a
head-on impact has the restitution ``exp(-pi zeta / sqrt(1 - zeta^2)) = e`` and lasts
``pi / omega_d``, ``omega_d = sqrt(k_n / m*) sqrt(1 - zeta^2)``, at every speed.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import flax.struct
import jax.numpy as jnp

from sgn_jax.dem import (
    assemble_contact_forces,
    contact_dissipation,
    make_contact_law,
    register_contact_law,
)


@flax.struct.dataclass
class LinearParams:
    """Parameters of one contact type: stiffnesses N/m, damping N s/m, m* kg, mu, mu_r."""

    stiffness_n: float
    stiffness_t: float
    damping_n: float
    damping_t: float
    mass_eff: float
    friction: float
    rolling_friction: float

    @property
    def zeta(self) -> float:
        """Normal damping ratio c_n / (2 sqrt(k_n m*))."""
        return self.damping_n / (2.0 * math.sqrt(self.stiffness_n * self.mass_eff))


def damping_ratio(restitution: float) -> float:
    """zeta with exp(-pi zeta / sqrt(1 - zeta^2)) = e."""
    log_e = math.log(restitution)
    return -log_e / math.sqrt(log_e**2 + math.pi**2)


@dataclasses.dataclass(frozen=True)
class LinearSpringDashpot:
    name: str = "linear_spring_dashpot"
    title: str = "linear spring-dashpot"
    reference_overlap: float = 1e-4  # m
    tangential_ratio: float = 2.0 / 7.0

    def make_params(self, *, young, poisson, restitution, friction, rolling_friction, radius_1,
                    mass_1, radius_2=math.inf, mass_2=math.inf) -> LinearParams:
        hertz = make_contact_law(young, poisson, restitution, friction, rolling_friction,
                                 radius_1=radius_1, mass_1=mass_1, radius_2=radius_2,
                                 mass_2=mass_2)
        k_n = 4.0 / 3.0 * hertz.young_eff * math.sqrt(hertz.radius_eff * self.reference_overlap)
        k_t = self.tangential_ratio * k_n
        zeta = damping_ratio(restitution)
        return LinearParams(
            stiffness_n=k_n, stiffness_t=k_t,
            damping_n=2.0 * zeta * math.sqrt(k_n * hertz.mass_eff),
            damping_t=2.0 * zeta * math.sqrt(k_t * hertz.mass_eff),
            mass_eff=hertz.mass_eff, friction=float(friction),
            rolling_friction=float(rolling_friction))

    def forces(self, params, overlap, normal, arm, v_rel, omega_rel, history, dt,
               clip_attractive=False):
        in_contact = overlap > 0
        d = jnp.where(in_contact, overlap, 0.0)
        ones = jnp.ones_like(d)
        return assemble_contact_forces(
            params.stiffness_n * d, params.stiffness_t * ones, params.damping_n * ones,
            params.damping_t * ones, params.friction, params.rolling_friction, in_contact,
            normal, arm, v_rel, omega_rel, history, dt, clip_attractive)

    def dissipation(self, forces, normal, v_rel_mid, omega_rel_mid, dt):
        return contact_dissipation(forces, normal, v_rel_mid, omega_rel_mid, dt)

    def elastic_energy(self, params, overlap):
        d = jnp.maximum(overlap, 0.0)
        return 0.5 * params.stiffness_n * d * d

    def contact_time(self, params, impact_speed) -> Any:
        # Undamped: half a period of sqrt(k_n / m*), whatever the speed.
        t_c = math.pi * math.sqrt(params.mass_eff / params.stiffness_n)
        return t_c + 0.0 * jnp.asarray(impact_speed) if jnp.ndim(impact_speed) else t_c

    def max_speed_for_duration(self, params, min_duration) -> float:
        return math.inf if self.contact_time(params, 1.0) >= min_duration else 0.0

    def max_speed_for_overlap(self, params, max_overlap) -> float:
        # Undamped peak overlap v sqrt(m* / k_n).
        return max_overlap * math.sqrt(params.stiffness_n / params.mass_eff)


LINEAR_SPRING_DASHPOT = register_contact_law("linear_spring_dashpot", LinearSpringDashpot())
