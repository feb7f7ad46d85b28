"""The charge: ball classes (size, count, density, material), materials and their pair rules.

A *charge* is what a mill user loads: one or more ball classes, each ``count`` balls of one
radius, density and material, in a jar of its own material. The DEM needs, per ball, a radius,
a mass and a moment of inertia, and per kind of contact (class a against class b, class a
against the wall) the contact law's effective parameters; :func:`charge_params` builds them.

Materials and pairs (docs/charge.md, the convention EDEM and LIGGGHTS users know):

- a material has its elastic constants (Young's modulus, Poisson's ratio) and the restitution,
  Coulomb friction and rolling friction of a contact **with itself**;
- two materials meet through the Hertz effective modulus 1/Y* = (1-nu1^2)/Y1 + (1-nu2^2)/Y2
  (and the Mindlin shear modulus likewise): that is physics, not a choice;
- the restitution, friction and rolling friction of a contact of two different materials are
  properties of the pair: an explicit :class:`PairRule` for the pair (as EDEM's interaction
  table and LIGGGHTS' ``peratomtypepair`` matrices take them) or, when none is given, the
  arithmetic mean of the two materials' own values (:func:`mixed_pair_rule`);
- two balls of different sizes meet with R* = R1 R2 / (R1 + R2) and m* = m1 m2 / (m1 + m2);
  a wall has R2 = m2 = inf.

The balls are ordered class by class (the first ``classes[0].count`` balls are class 0, ...).
A charge of one class gives the scalar parameters of :func:`sgn_jax.dem.engine.make_params`
(the monodisperse fast path); several classes give per-ball arrays and per-class-pair tables.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from sgn_jax.dem.engine import DEMParams
from sgn_jax.dem.laws import HERTZ_MINDLIN, ContactLawError, resolve_contact_law
from sgn_jax.errors import SGNJaxError


class ChargeError(SGNJaxError, ValueError):
    """A charge that cannot be built: unknown material, bad ball class, bad pair rule."""


@dataclasses.dataclass(frozen=True)
class Material:
    """A ball or jar material.

    Attributes:
        name: the name ball classes and pair rules refer to it by.
        young: Pa, Young's modulus.
        poisson: Poisson's ratio, in (-1, 0.5).
        restitution: coefficient of normal restitution of a contact with itself, in (0, 1].
        friction: Coulomb coefficient of a contact with itself (>= 0).
        rolling_friction: rolling friction coefficient mu_r (EDEM type A) with itself (>= 0).
    """

    name: str
    young: float
    poisson: float
    restitution: float
    friction: float
    rolling_friction: float

    def __post_init__(self) -> None:
        if not self.name:
            raise ChargeError("a material needs a non-empty name")
        if not self.young > 0:
            raise ChargeError(f"material {self.name!r}: young must be > 0 Pa, got {self.young}")
        if not -1 < self.poisson < 0.5:
            raise ChargeError(f"material {self.name!r}: poisson must be in (-1, 0.5), got "
                              f"{self.poisson}")
        _check_pair_values(f"material {self.name!r}", self.restitution, self.friction,
                           self.rolling_friction)


@dataclasses.dataclass(frozen=True)
class PairRule:
    """Restitution, friction and rolling friction of a contact between two materials."""

    restitution: float
    friction: float
    rolling_friction: float

    def __post_init__(self) -> None:
        _check_pair_values("pair rule", self.restitution, self.friction, self.rolling_friction)


def _check_pair_values(what: str, restitution: float, friction: float,
                       rolling_friction: float) -> None:
    if not 0 < restitution <= 1:
        raise ChargeError(f"{what}: restitution must be in (0, 1], got {restitution}")
    if not (friction >= 0 and rolling_friction >= 0):
        raise ChargeError(f"{what}: friction and rolling_friction must be >= 0, got "
                          f"{friction}, {rolling_friction}")


def mixed_pair_rule(a: Material, b: Material) -> PairRule:
    """The default rule of two materials without an explicit one: the arithmetic mean of their
    own restitution, friction and rolling friction (a material with itself: its own values)."""
    return PairRule(restitution=0.5 * (a.restitution + b.restitution),
                    friction=0.5 * (a.friction + b.friction),
                    rolling_friction=0.5 * (a.rolling_friction + b.rolling_friction))


@dataclasses.dataclass(frozen=True)
class BallClass:
    """``count`` identical balls.

    Attributes:
        count: number of balls (>= 1).
        radius: m.
        density: kg/m^3.
        material: their material.
    """

    count: int
    radius: float
    density: float
    material: Material

    def __post_init__(self) -> None:
        if self.count < 1:
            raise ChargeError(f"a ball class needs count >= 1, got {self.count}")
        if not (self.radius > 0 and self.density > 0):
            raise ChargeError(f"a ball class needs radius > 0 m and density > 0 kg/m^3, got "
                              f"{self.radius}, {self.density}")

    @property
    def mass(self) -> float:
        """kg, one ball."""
        return self.density * 4.0 / 3.0 * math.pi * self.radius**3

    @property
    def volume(self) -> float:
        """m^3, all balls of the class."""
        return self.count * 4.0 / 3.0 * math.pi * self.radius**3


@dataclasses.dataclass(frozen=True)
class Charge:
    """Ball classes in a jar of material ``wall``, with explicit pair rules where given.

    Attributes:
        classes: the ball classes, in ball order.
        wall: the jar's material.
        pair_rules: ``((name_a, name_b), PairRule)`` entries; a pair not listed mixes
            (:func:`mixed_pair_rule`). Order of the two names does not matter.
    """

    classes: tuple[BallClass, ...]
    wall: Material
    pair_rules: tuple[tuple[tuple[str, str], PairRule], ...] = ()

    def __post_init__(self) -> None:
        if not self.classes:
            raise ChargeError("a charge needs at least one ball class")
        known = {m.name: m for m in self.materials}
        seen: set[frozenset[str]] = set()
        for (a, b), _ in self.pair_rules:
            for name in (a, b):
                if name not in known:
                    raise ChargeError(f"pair rule for ({a!r}, {b!r}) names material {name!r}, "
                                      f"which no ball class or the jar uses; materials: "
                                      f"{sorted(known)}")
            key = frozenset((a, b))
            if key in seen:
                raise ChargeError(f"two pair rules for materials ({a!r}, {b!r})")
            seen.add(key)
        for name in known:  # one name, one material
            defs = {m for m in self.materials if m.name == name}
            if len(defs) > 1:
                raise ChargeError(f"material name {name!r} is used for different materials")

    @property
    def materials(self) -> tuple[Material, ...]:
        """Every material of the charge: the jar's, then the balls' (in class order)."""
        out: list[Material] = [self.wall]
        for c in self.classes:
            if c.material not in out:
                out.append(c.material)
        return tuple(out)

    @property
    def n_balls(self) -> int:
        return sum(c.count for c in self.classes)

    @property
    def n_classes(self) -> int:
        return len(self.classes)

    @property
    def monodisperse(self) -> bool:
        """One ball class (the DEM's scalar fast path)."""
        return len(self.classes) == 1

    @property
    def ball_class(self) -> np.ndarray:
        """(N,) int32, each ball's class index."""
        return np.repeat(np.arange(len(self.classes), dtype=np.int32),
                         [c.count for c in self.classes])

    def per_ball(self, name: str) -> np.ndarray:
        """(N,) float64 of a BallClass attribute (``"radius"``, ``"density"``, ``"mass"``)."""
        return np.repeat(np.array([float(getattr(c, name)) for c in self.classes]),
                         [c.count for c in self.classes])

    @property
    def radii(self) -> np.ndarray:
        return self.per_ball("radius")

    @property
    def masses(self) -> np.ndarray:
        return self.per_ball("mass")

    @property
    def min_radius(self) -> float:
        return min(c.radius for c in self.classes)

    @property
    def max_radius(self) -> float:
        return max(c.radius for c in self.classes)

    @property
    def total_mass(self) -> float:
        """kg, all balls."""
        return sum(c.count * c.mass for c in self.classes)

    @property
    def ball_volume(self) -> float:
        """m^3, all balls."""
        return sum(c.volume for c in self.classes)

    def pair_rule(self, a: Material, b: Material) -> PairRule:
        """The rule of a contact of materials ``a`` and ``b``: an explicit one, else the mix."""
        for (na, nb), rule in self.pair_rules:
            if {na, nb} == {a.name, b.name}:
                return rule
        return mixed_pair_rule(a, b)


def single_class_charge(count: int, radius: float, density: float, material: Material
                        ) -> Charge:
    """The classic charge: ``count`` balls of one size and material in a jar of the same
    material."""
    return Charge(classes=(BallClass(count, radius, density, material),), wall=material)


def _law_kwargs(a: Material, b: Material, rule: PairRule) -> dict[str, Any]:
    kwargs = dict(young=a.young, poisson=a.poisson, restitution=rule.restitution,
                  friction=rule.friction, rolling_friction=rule.rolling_friction)
    if (b.young, b.poisson) != (a.young, a.poisson):
        kwargs.update(young_2=b.young, poisson_2=b.poisson)
    return kwargs


def contact_params(charge: Charge, contact_law: Any = HERTZ_MINDLIN) -> tuple[Any, Any]:
    """The contact law's parameters ``(pp, pw)`` of a charge.

    One class: the law's scalar parameters (ball-ball, ball-wall). Several classes: the same
    pytrees with every leaf a table, ``pp`` leaves (C, C) (class a against class b,
    symmetric) and ``pw`` leaves (C,) (class a against the wall), as float64 numpy arrays.
    """
    try:
        law = resolve_contact_law(contact_law)
    except ContactLawError as exc:
        raise ChargeError(str(exc)) from None
    classes = charge.classes

    def pp_of(a: BallClass, b: BallClass) -> Any:
        rule = charge.pair_rule(a.material, b.material)
        return law.make_params(radius_1=a.radius, mass_1=a.mass, radius_2=b.radius,
                               mass_2=b.mass, **_law_kwargs(a.material, b.material, rule))

    def pw_of(a: BallClass) -> Any:
        rule = charge.pair_rule(a.material, charge.wall)
        return law.make_params(radius_1=a.radius, mass_1=a.mass,
                               **_law_kwargs(a.material, charge.wall, rule))

    if charge.monodisperse:
        return pp_of(classes[0], classes[0]), pw_of(classes[0])
    n = len(classes)
    pp_rows = [pp_of(a, b) for a in classes for b in classes]
    pp = jax.tree_util.tree_map(
        lambda *leaves: np.asarray(leaves, np.float64).reshape(n, n), *pp_rows)
    pw = jax.tree_util.tree_map(lambda *leaves: np.asarray(leaves, np.float64),
                                *[pw_of(a) for a in classes])
    return pp, pw


def pair_params(table: Any, class_a: int, class_b: int | None = None) -> Any:
    """The scalar parameters of one contact kind from :func:`contact_params`' tables: class a
    against class b (``pp``) or against the wall (``pw``, ``class_b`` None). Host side."""
    if class_b is None:
        return jax.tree_util.tree_map(lambda leaf: float(np.asarray(leaf)[class_a]), table)
    return jax.tree_util.tree_map(lambda leaf: float(np.asarray(leaf)[class_a, class_b]), table)


def charge_params(charge: Charge, gravity: Any, geometry: Any, motion: Any,
                  contact_law: Any = HERTZ_MINDLIN) -> Any:
    """:class:`sgn_jax.dem.engine.DEMParams` of a charge: for one class the scalar layout of
    :func:`sgn_jax.dem.engine.make_params` (the same numbers when the jar is of the balls'
    material), for several the per-ball arrays and class-pair tables (``ball_class`` set)."""
    pp, pw = contact_params(charge, contact_law)
    gravity = jnp.asarray(gravity, dtype=jnp.float64)
    if charge.monodisperse:
        c = charge.classes[0]
        return DEMParams(radius=float(c.radius), mass=float(c.mass),
                         inertia=0.4 * c.mass * c.radius**2, pp=pp, pw=pw, gravity=gravity,
                         geometry=geometry, motion=motion)
    radii, masses = charge.radii, charge.masses
    return DEMParams(radius=radii, mass=masses, inertia=0.4 * masses * radii**2, pp=pp, pw=pw,
                     gravity=gravity, geometry=geometry, motion=motion,
                     ball_class=np.asarray(charge.ball_class, np.int32))
