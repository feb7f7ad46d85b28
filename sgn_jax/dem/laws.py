"""Contact laws as a seam of the DEM: the :class:`ContactModel` protocol and a registry.

A *contact law* is a small, frozen, hashable object (it lives in the static
:class:`sgn_jax.dem.engine.DEMSpec` as ``spec.contact_law``) with the operations the engine,
the energy ledger and the step-size checks need. Its numbers live apart, in a pytree of
parameters per contact type (``DEMParams.pp`` for ball-ball, ``DEMParams.pw`` for ball-wall),
built by the law's :meth:`ContactModel.make_params` from the material and ball values, so they
can be batched with ``jax.vmap`` like every other DEM parameter.

Hertz-Mindlin (:data:`HERTZ_MINDLIN`, registered as ``"hertz_mindlin"``) is the default and
the implementation the project is validated with; its parameters are
:class:`sgn_jax.dem.contact.ContactLaw`. A new law is one file: a frozen dataclass with the
methods below, registered with :func:`register_contact_law`; a config selects it by name with
``[dem] contact_law``. See docs/dem.md, "Adding a contact law".

Sign conventions of every method are those of :mod:`sgn_jax.dem.contact`.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Protocol, runtime_checkable

import jax.numpy as jnp

from sgn_jax.dem.contact import (
    ContactDissipation,
    ContactForces,
    contact_dissipation,
    contact_forces,
    hertz_contact_time,
    hertz_energy,
    make_contact_law,
)
from sgn_jax.errors import SGNJaxError


class ContactLawError(SGNJaxError, ValueError):
    """An unknown contact-law name, or an object that is not a contact law."""


@runtime_checkable
class ContactModel(Protocol):
    """What the DEM needs from a contact law (structural: no base class required).

    Attributes:
        name: the registry name (``[dem] contact_law``).
        title: a short human name used in messages ("Hertz").

    Implementations must be hashable and immutable (``@dataclasses.dataclass(frozen=True)``):
    the law is part of the static DEMSpec and changing it recompiles the step.
    """

    name: str
    title: str

    def make_params(self, *, young: float, poisson: float, restitution: float,
                    friction: float, rolling_friction: float, radius_1: float, mass_1: float,
                    radius_2: float = math.inf, mass_2: float = math.inf,
                    young_2: float | None = None, poisson_2: float | None = None) -> Any:
        """The law's parameter pytree for body 1 against body 2 (a wall: radius_2 = mass_2 =
        inf). Body 2 has body 1's elastic constants unless ``young_2`` / ``poisson_2`` are
        given (two materials: :mod:`sgn_jax.dem.charge` passes them only when they differ,
        so a law of one material still serves every single-material charge); restitution,
        friction and rolling friction are the pair's."""
        ...

    def forces(self, params: Any, overlap: jnp.ndarray, normal: jnp.ndarray, arm: jnp.ndarray,
               v_rel: jnp.ndarray, omega_rel: jnp.ndarray, history: jnp.ndarray, dt: float,
               clip_attractive: bool = False) -> ContactForces:
        """Forces and torques on body i of K contacts and the new tangential history; the
        arguments and every output field as in :func:`sgn_jax.dem.contact.contact_forces`
        (:func:`sgn_jax.dem.contact.assemble_contact_forces` does all but the normal spring)."""
        ...

    def dissipation(self, forces: ContactForces, normal: jnp.ndarray, v_rel_mid: jnp.ndarray,
                    omega_rel_mid: jnp.ndarray, dt: float) -> ContactDissipation:
        """Energy dissipated by K contacts over one step, by kind (normal, tangential, slip,
        rolling); :func:`sgn_jax.dem.contact.contact_dissipation` for any law whose
        ContactForces follow its conventions."""
        ...

    def elastic_energy(self, params: Any, overlap: jnp.ndarray) -> jnp.ndarray:
        """Energy (J) stored in the normal spring at each overlap (0 for overlap <= 0); the
        force must be its derivative for the energy ledger to close."""
        ...

    def contact_time(self, params: Any, impact_speed: Any) -> Any:
        """Duration (s) of an elastic (undamped) head-on impact at ``impact_speed`` m/s."""
        ...

    def max_speed_for_duration(self, params: Any, min_duration: float) -> float:
        """The largest impact speed (m/s) whose contact lasts at least ``min_duration`` s
        (inf when every speed does, 0 when none does)."""
        ...

    def max_speed_for_overlap(self, params: Any, max_overlap: float) -> float:
        """The largest impact speed (m/s) whose undamped peak overlap stays <= max_overlap m."""
        ...


# --------------------------------------------------------------------------------------------
# Hertz-Mindlin


@dataclasses.dataclass(frozen=True)
class HertzMindlin:
    """Hertz normal spring, Mindlin tangential spring, restitution-based damping, Coulomb and
    rolling friction (:mod:`sgn_jax.dem.contact`, docs/conventions.md section 3). Parameters:
    :class:`sgn_jax.dem.contact.ContactLaw`."""

    name: str = "hertz_mindlin"
    title: str = "Hertz"
    rolling: str = "edem_a"

    @property
    def rolling_uses_arm(self) -> bool:
        """The rolling torque's arm is the contact arm R_c (the engine then gives two unequal
        balls the harmonic mean of their arms, docs/charge.md); False for "cdt" (R*)."""
        return self.rolling == "edem_a"

    def make_params(self, *, young: float, poisson: float, restitution: float,
                    friction: float, rolling_friction: float, radius_1: float, mass_1: float,
                    radius_2: float = math.inf, mass_2: float = math.inf,
                    young_2: float | None = None, poisson_2: float | None = None) -> Any:
        return make_contact_law(young, poisson, restitution, friction, rolling_friction,
                                radius_1=radius_1, mass_1=mass_1, radius_2=radius_2,
                                mass_2=mass_2, young_2=young_2, poisson_2=poisson_2)

    def forces(self, params: Any, overlap: jnp.ndarray, normal: jnp.ndarray, arm: jnp.ndarray,
               v_rel: jnp.ndarray, omega_rel: jnp.ndarray, history: jnp.ndarray, dt: float,
               clip_attractive: bool = False) -> ContactForces:
        return contact_forces(params, overlap, normal, arm, v_rel, omega_rel, history, dt,
                              clip_attractive, rolling=self.rolling)

    def dissipation(self, forces: ContactForces, normal: jnp.ndarray, v_rel_mid: jnp.ndarray,
                    omega_rel_mid: jnp.ndarray, dt: float) -> ContactDissipation:
        return contact_dissipation(forces, normal, v_rel_mid, omega_rel_mid, dt)

    def elastic_energy(self, params: Any, overlap: jnp.ndarray) -> jnp.ndarray:
        return hertz_energy(params, overlap)

    def contact_time(self, params: Any, impact_speed: Any) -> Any:
        return hertz_contact_time(params, impact_speed)

    def max_speed_for_duration(self, params: Any, min_duration: float) -> float:
        # t_c(v) = t_c(1) v^(-1/5) >= T  <=>  v <= (t_c(1) / T)^5
        return float(hertz_contact_time(params, 1.0) / min_duration) ** 5

    def max_speed_for_overlap(self, params: Any, max_overlap: float) -> float:
        # undamped peak overlap (15 m* v^2 / (16 Y* sqrt(R*)))^(2/5) <= max_overlap
        return math.sqrt(16 * params.young_eff * math.sqrt(params.radius_eff)
                         * max_overlap**2.5 / (15 * params.mass_eff))


HERTZ_MINDLIN = HertzMindlin()
"""The default contact law (the one every DEM number in docs/dem.md was measured with)."""

HERTZ_MINDLIN_CDT = HertzMindlin(name="hertz_mindlin_cdt", title="Hertz (cdt rolling)",
                                 rolling="cdt")
"""Hertz-Mindlin with LIGGGHTS' ``rolling_friction cdt`` (the elastic force, the arm R*, no
twist; :func:`sgn_jax.dem.contact.contact_forces`), for comparisons with LIGGGHTS
(experiments/reproduce/liggghts/)."""


# --------------------------------------------------------------------------------------------
# Registry

_REGISTRY: dict[str, Any] = {}


def check_contact_law(law: Any) -> Any:
    """``law`` if it is a usable contact law (all :class:`ContactModel` members, hashable),
    else ContactLawError saying what is missing."""
    missing = [m for m in ("name", "title", "make_params", "forces", "dissipation",
                           "elastic_energy", "contact_time", "max_speed_for_duration",
                           "max_speed_for_overlap") if not hasattr(law, m)]
    if missing:
        raise ContactLawError(f"{law!r} is not a contact law: it lacks {', '.join(missing)} "
                              "(see sgn_jax.dem.laws.ContactModel)")
    try:
        hash(law)
    except TypeError as exc:
        raise ContactLawError(f"contact law {law!r} must be hashable (a frozen dataclass): it "
                              "is part of the static DEMSpec") from exc
    return law


def register_contact_law(name: str, law: Any, *, replace: bool = False) -> Any:
    """Make ``law`` selectable as ``name`` (``[dem] contact_law = name``, or
    ``DEMSpec(contact_law=name)``); returns it. Registering a taken name with another law is
    an error unless ``replace``; registering the same law again is a no-op."""
    check_contact_law(law)
    if not isinstance(name, str) or not name:
        raise ContactLawError(f"a contact law's name must be a non-empty string, got {name!r}")
    if name in _REGISTRY and _REGISTRY[name] != law and not replace:
        raise ContactLawError(f"contact law {name!r} is already registered as "
                              f"{_REGISTRY[name]!r}; pass replace=True to replace it")
    _REGISTRY[name] = law
    return law


def contact_law(name: str) -> Any:
    """The contact law registered as ``name``."""
    try:
        return _REGISTRY[name]
    except (KeyError, TypeError):
        raise ContactLawError(
            f"unknown contact law {name!r}; registered: {', '.join(sorted(_REGISTRY))} "
            "(a new law is registered with sgn_jax.dem.register_contact_law)") from None


def contact_law_names() -> tuple[str, ...]:
    """The registered names, sorted."""
    return tuple(sorted(_REGISTRY))


def resolve_contact_law(law: Any) -> Any:
    """A law object from a law or a registered name."""
    return contact_law(law) if isinstance(law, str) else check_contact_law(law)


register_contact_law(HERTZ_MINDLIN.name, HERTZ_MINDLIN)
register_contact_law(HERTZ_MINDLIN_CDT.name, HERTZ_MINDLIN_CDT)
