"""Jar motions: pytrees of parameters with a jittable, differentiable ``offset(t)``.

The jar only translates (docs/conventions.md section 1). ``offset(motion, t)`` is the lab-frame
position (m) of the jar-frame origin at time ``t`` (s) since the start of motion; ``velocity`` and
``acceleration`` are its first and second time derivatives, computed by JAX forward-mode
autodiff of ``offset`` (so they can never disagree with it).

Motion kinds register themselves (:class:`MotionKind`, :func:`register_motion_kind`): each kind
is registered once with its name, its class, its scalar offset function, its rotational
frequency, its constructor from plain config values and its design parameters, and every
function here dispatches through the registry by the motion's type (docs/motion-kinds.md shows
a new kind added in one file). Three kinds are built in, all ``flax.struct`` dataclasses whose
every field is a pytree leaf, so that

- every parameter is differentiable (``jax.grad(lambda m: offset(m, t)[0])(motion)``),
- a batch of motions of the same kind (and the same K or M) is one pytree with a leading batch
  axis on every leaf (``stack_motions``) and can be ``jax.vmap``-ed over:
  ``jax.vmap(offset, in_axes=(0, None))(stacked, t)``.

``CircleMotion``
    ``(A sin(2 pi f t + phase), 0, A cos(2 pi f t + phase))`` with ``f = rpm / 60``
    (docs/conventions.md section 2).
``HarmonicMotion``
    per axis ``sum_k sin_coeffs[k-1, axis] sin(2 pi k f0 t) + cos_coeffs[k-1, axis] cos(2 pi k f0 t)``.
    Motion 1 and Motion 2 of docs/conventions.md section 2 are harmonic series (``motion1()``,
    ``motion2()``).
``SplineMotion``
    the periodic cubic spline through ``points[j]`` at ``t_j = j * period / M`` (C2, wraps with
    ``period``); the spline system is solved in ``jnp`` (circulant solve by FFT), so the curve is
    differentiable w.r.t. its points and its period.

Time: ``t`` may be a Python float, a 0-d array or an array of any shape. For an array the
functions are vmapped over its elements and return ``t.shape + (3,)``. Keep ``t`` in float64
(integers are converted to float64): ``2 pi f t`` over 10 s of motion loses ~1e-5 rad in float32.
The result dtype is the JAX promotion of the parameter dtype and the time dtype.

Settling (docs/conventions.md section 2): during DEM settling the jar rests at
``offset(motion, 0)`` with zero velocity; at ``t = 0`` the motion starts and the jar velocity
jumps to ``velocity(motion, 0)``. These functions describe the motion for ``t >= 0`` only (they
are periodic and also defined for ``t < 0``); the rest phase is the DEM driver's business.
"""

from __future__ import annotations

import dataclasses
import types
from collections.abc import Callable, Mapping
from typing import Any

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

_TWO_PI = 2.0 * np.pi


@flax.struct.dataclass
class CircleMotion:
    """Circular translation in the x-z plane (docs/conventions.md section 2).

    Attributes:
        rpm: revolutions per minute (the jar centre's orbit frequency is ``rpm / 60`` Hz).
        amplitude: orbit radius A (m).
        phase: phase at t = 0 (rad); 0 puts the jar at ``(0, 0, A)`` at t = 0.
    """

    rpm: float | jax.Array
    amplitude: float | jax.Array
    phase: float | jax.Array = 0.0


@flax.struct.dataclass
class HarmonicMotion:
    """A finite Fourier series per axis with base frequency ``base_frequency_hz``.

    Attributes:
        base_frequency_hz: f0 (Hz); harmonic k (1-based) oscillates at ``k * f0``.
        sin_coeffs: (K, 3) m, coefficient of ``sin(2 pi k f0 t)`` for harmonic k = row + 1, axis.
        cos_coeffs: (K, 3) m, coefficient of ``cos(2 pi k f0 t)``.
    """

    base_frequency_hz: float | jax.Array
    sin_coeffs: jax.Array
    cos_coeffs: jax.Array


@flax.struct.dataclass
class SplineMotion:
    """Periodic cubic spline through ``points[j]`` at ``t_j = j * period / M``, j = 0..M-1.

    Attributes:
        period: the period (s); the curve returns to ``points[0]`` at ``t = period``.
        points: (M, 3) m, M >= 3, the knots (uniformly spaced in time).
    """

    period: float | jax.Array
    points: jax.Array


Motion = CircleMotion | HarmonicMotion | SplineMotion
"""The built-in kinds, for type hints; every function here takes any registered kind."""


# --------------------------------------------------------------------------------------------
# The registry of motion kinds


@dataclasses.dataclass(frozen=True)
class MotionKind:
    """A motion kind: its pytree class and everything the package dispatches on per kind.

    Register one with :func:`register_motion_kind`; ``offset``, ``velocity``,
    ``acceleration``, ``frequency_hz``, ``stack_motions`` and ``spline_from_motion`` then work
    on its motions, so do the DEM, the rollout and the design study (docs/motion-kinds.md).

    Attributes:
        name: the kind's name, as in the config's ``[motion] kind`` ("circle", ...).
        cls: the motion class, a ``flax.struct`` dataclass whose fields are pytree leaves.
        offset: ``offset(motion, t) -> (3,)``, the jar offset (m) at one scalar time ``t`` (s);
            jittable and differentiable (velocity and acceleration are its autodiff).
        frequency_hz: ``frequency_hz(motion) -> ()``, the rotational frequency (Hz) fed to the
            surrogate's wall node.
        config_keys: the ``[motion]`` keys of the kind (besides ``kind``).
        from_config: ``from_config(values, dtype) -> motion``, the motion of a plain dict
            ``{key: value}`` of the kind's ``config_keys`` (lists as tuples), leaves of
            ``dtype``; used by :func:`sgn_jax.pipelines.configure.motion_from_config`.
        to_config: ``to_config(motion, old_values) -> values``, the inverse: plain config
            values of a (changed) motion, ``old_values`` being those it was built from; used to
            write a design point back into a config. None: the kind cannot be written back.
        design_parameters: ``{field: unit}`` of the scalar fields that are design parameters
            ``motion.<field>`` (:mod:`sgn_jax.design`).
        scale: ``scale(motion, factor) -> motion`` multiplies the whole displacement (the
            design parameter ``motion.scale``); None: the kind has no ``motion.scale``.
        coefficient_fields: ``{"sin": field, "cos": field}``: the (K, 3) fields addressed by
            the design parameters ``motion.{x,y,z}_{sin,cos}[k]``; empty: none.
    """

    name: str
    cls: type
    offset: Callable[[Any, jax.Array], jax.Array]
    frequency_hz: Callable[[Any], jax.Array]
    config_keys: tuple[str, ...] = ()
    from_config: Callable[[Mapping[str, Any], Any], Any] | None = None
    to_config: Callable[[Any, Mapping[str, Any]], dict[str, Any]] | None = None
    design_parameters: Mapping[str, str] = dataclasses.field(default_factory=dict)
    scale: Callable[[Any, jax.Array], Any] | None = None
    coefficient_fields: Mapping[str, str] = dataclasses.field(default_factory=dict)

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name:
            raise ValueError(f"a motion kind needs a non-empty name, got {self.name!r}")
        if not isinstance(self.cls, type) or not dataclasses.is_dataclass(self.cls):
            raise TypeError(f"motion kind {self.name!r}: cls must be a flax.struct dataclass, "
                            f"got {self.cls!r}")
        for attr in ("offset", "frequency_hz"):
            if not callable(getattr(self, attr)):
                raise TypeError(f"motion kind {self.name!r}: {attr} must be callable")
        unknown = sorted(set(self.coefficient_fields) - {"sin", "cos"})
        if unknown:
            raise ValueError(f"motion kind {self.name!r}: coefficient_fields keys must be 'sin' "
                             f"and/or 'cos', got {unknown}")
        object.__setattr__(self, "config_keys", tuple(self.config_keys))
        object.__setattr__(self, "design_parameters",
                           types.MappingProxyType(dict(self.design_parameters)))
        object.__setattr__(self, "coefficient_fields",
                           types.MappingProxyType(dict(self.coefficient_fields)))


_KINDS: dict[str, MotionKind] = {}  # name -> kind, in registration order
_KINDS_BY_CLASS: dict[type, MotionKind] = {}


def register_motion_kind(kind: MotionKind, *, replace: bool = False) -> MotionKind:
    """Register ``kind`` (returned, so a module can keep it); its name and class must be new.

    ``replace=True`` replaces a kind of the same name (and its class) instead of refusing.
    """
    if not isinstance(kind, MotionKind):
        raise TypeError(f"register_motion_kind expects a MotionKind, got {type(kind).__name__}")
    old = _KINDS.get(kind.name)
    holder = _KINDS_BY_CLASS.get(kind.cls)
    if not replace:
        if old is not None:
            raise ValueError(f"motion kind {kind.name!r} is already registered (class "
                             f"{old.cls.__name__}); pass replace=True to replace it")
        if holder is not None:
            raise ValueError(f"class {kind.cls.__name__} is already registered as motion kind "
                             f"{holder.name!r}")
    if old is not None:
        _KINDS_BY_CLASS.pop(old.cls, None)
    if holder is not None and holder.name != kind.name:
        _KINDS.pop(holder.name, None)
    _KINDS[kind.name] = kind
    _KINDS_BY_CLASS[kind.cls] = kind
    return kind


def unregister_motion_kind(name: str) -> MotionKind:
    """Remove the kind ``name`` from the registry (tests); returns it."""
    kind = motion_kind_named(name)
    del _KINDS[name]
    _KINDS_BY_CLASS.pop(kind.cls, None)
    return kind


def motion_kinds() -> tuple[MotionKind, ...]:
    """The registered kinds, in registration order (the built-ins first)."""
    return tuple(_KINDS.values())


def motion_kind_named(name: str) -> MotionKind:
    """The registered kind called ``name`` (ValueError listing the kinds if there is none)."""
    try:
        return _KINDS[name]
    except (KeyError, TypeError):
        raise ValueError(f"unknown motion kind {name!r}; registered kinds: "
                         f"{sorted(_KINDS)}") from None


def motion_kind(motion: Any) -> MotionKind:
    """The registered kind of ``motion`` (an instance or a class), found by its type.

    A subclass of a registered class has its parent's kind unless registered itself.
    """
    cls = motion if isinstance(motion, type) else type(motion)
    for base in cls.__mro__:
        kind = _KINDS_BY_CLASS.get(base)
        if kind is not None:
            return kind
    classes = ", ".join(k.cls.__name__ for k in _KINDS.values())
    raise TypeError(
        f"expected a motion of a registered kind ({classes}), got {cls.__name__}; "
        "build one with motion_from_config(cfg.motion) or register its kind with "
        "register_motion_kind"
    )


# --------------------------------------------------------------------------------------------
# Time handling


def _as_time(t: float | jax.Array) -> jax.Array:
    """``t`` as a floating JAX array (integers -> float64, so ``velocity`` can differentiate)."""
    t = jnp.asarray(t)
    if not jnp.issubdtype(t.dtype, jnp.floating):
        t = t.astype(jnp.float64)
    return t


def _map_over_time(scalar_fn: Callable[[Motion, jax.Array], jax.Array],
                   motion: Motion, t: float | jax.Array) -> jax.Array:
    """Apply a scalar-time function to a scalar or an array of times (vmapped, shape t.shape+(3,))."""
    t = _as_time(t)
    if t.ndim == 0:
        return scalar_fn(motion, t)
    flat = jax.vmap(scalar_fn, in_axes=(None, 0))(motion, t.reshape(-1))
    return flat.reshape(t.shape + (3,))


# --------------------------------------------------------------------------------------------
# Offsets per kind (scalar t)


def _circle_offset(motion: CircleMotion, t: jax.Array) -> jax.Array:
    angle = _TWO_PI * (motion.rpm / 60.0) * t + motion.phase
    amplitude = jnp.asarray(motion.amplitude)
    zero = jnp.zeros_like(amplitude * angle)
    return jnp.stack([amplitude * jnp.sin(angle), zero, amplitude * jnp.cos(angle)])


def _check_coeffs(name: str, coeffs: jax.Array) -> None:
    if coeffs.ndim != 2 or coeffs.shape[1] != 3:
        raise ValueError(
            f"HarmonicMotion.{name} must have shape (K, 3) (one row per harmonic, columns x y z), "
            f"got {coeffs.shape}; for a batch of motions use jax.vmap over the leading axis"
        )


def _harmonic_offset(motion: HarmonicMotion, t: jax.Array) -> jax.Array:
    sin_coeffs = jnp.asarray(motion.sin_coeffs)
    cos_coeffs = jnp.asarray(motion.cos_coeffs)
    _check_coeffs("sin_coeffs", sin_coeffs)
    _check_coeffs("cos_coeffs", cos_coeffs)
    if sin_coeffs.shape != cos_coeffs.shape:
        raise ValueError(
            "HarmonicMotion.sin_coeffs and cos_coeffs must have the same shape (K, 3), got "
            f"{sin_coeffs.shape} and {cos_coeffs.shape}; pad the shorter one with zero rows"
        )
    harmonics = jnp.arange(1, sin_coeffs.shape[0] + 1, dtype=t.dtype)  # (K,)
    angles = _TWO_PI * motion.base_frequency_hz * harmonics * t  # (K,)
    return jnp.sin(angles) @ sin_coeffs + jnp.cos(angles) @ cos_coeffs


def spline_second_derivatives(period: float | jax.Array, points: jax.Array) -> jax.Array:
    """Second time derivatives (m/s^2) of the periodic cubic spline at its knots, shape (M, 3).

    With knot spacing ``h = period / M`` the C2 conditions read
    ``m[j-1] + 4 m[j] + m[j+1] = 6 (p[j+1] - 2 p[j] + p[j-1]) / h^2`` (indices mod M), a
    circulant system: it is diagonalised by the DFT with eigenvalues ``4 + 2 cos(2 pi k / M)``
    (always >= 2, so the system is never singular) and solved by FFT, differentiably.
    """
    points = jnp.asarray(points)
    n_knots = points.shape[0]
    h = period / n_knots
    rhs = 6.0 * (jnp.roll(points, -1, axis=0) - 2.0 * points + jnp.roll(points, 1, axis=0)) / h**2
    k = jnp.arange(n_knots, dtype=points.dtype)
    eigenvalues = 4.0 + 2.0 * jnp.cos(_TWO_PI * k / n_knots)  # (M,)
    solution = jnp.fft.ifft(jnp.fft.fft(rhs, axis=0) / eigenvalues[:, None], axis=0)
    return jnp.real(solution).astype(rhs.dtype)


def _spline_offset(motion: SplineMotion, t: jax.Array) -> jax.Array:
    points = jnp.asarray(motion.points)
    if points.ndim != 2 or points.shape[1] != 3 or points.shape[0] < 3:
        raise ValueError(
            f"SplineMotion.points must have shape (M, 3) with M >= 3, got {points.shape}; "
            "for a batch of motions use jax.vmap over the leading axis"
        )
    n_knots = points.shape[0]
    period = motion.period
    h = period / n_knots
    second = spline_second_derivatives(period, points)
    # Local coordinate: segment j from t_j to t_{j+1}; jnp.mod wraps negative t too. The clip
    # guards against mod returning `period` itself by rounding.
    s = jnp.mod(t, period) / h
    j = jnp.clip(jnp.floor(s), 0, n_knots - 1).astype(jnp.int32)
    u = s - j  # in [0, 1]; d u / d t = 1 / h (floor has zero derivative)
    j_next = jnp.mod(j + 1, n_knots)
    p0, p1 = points[j], points[j_next]
    m0, m1 = second[j], second[j_next]
    # Standard cubic-spline segment in terms of u = x / h.
    return (
        m0 * h**2 * (1.0 - u) ** 3 / 6.0
        + m1 * h**2 * u**3 / 6.0
        + (p0 - m0 * h**2 / 6.0) * (1.0 - u)
        + (p1 - m1 * h**2 / 6.0) * u
    )


# --------------------------------------------------------------------------------------------
# The built-in kinds register themselves


def _circle_from_config(values: Mapping[str, Any], dtype: Any) -> CircleMotion:
    return CircleMotion(rpm=jnp.asarray(values["rpm"], dtype),
                        amplitude=jnp.asarray(values["amplitude"], dtype),
                        phase=jnp.asarray(values["phase"], dtype))


def _circle_to_config(motion: CircleMotion, old: Mapping[str, Any]) -> dict[str, Any]:
    return {"rpm": float(motion.rpm), "amplitude": float(motion.amplitude),
            "phase": float(motion.phase)}


_HARMONIC_LISTS = ("x_sin", "y_sin", "z_sin", "x_cos", "y_cos", "z_cos")


def _harmonic_from_config(values: Mapping[str, Any], dtype: Any) -> HarmonicMotion:
    """Coefficient lists that are empty mean zero; the others all have length K."""
    n_harmonics = max(len(values[name]) for name in _HARMONIC_LISTS)
    sin_coeffs = np.zeros((n_harmonics, 3))
    cos_coeffs = np.zeros((n_harmonics, 3))
    for axis, letter in enumerate("xyz"):
        for target, kind in ((sin_coeffs, "sin"), (cos_coeffs, "cos")):
            coeffs = values[f"{letter}_{kind}"]
            if coeffs:
                target[:, axis] = coeffs
    return HarmonicMotion(base_frequency_hz=jnp.asarray(values["base_frequency_hz"], dtype),
                          sin_coeffs=jnp.asarray(sin_coeffs, dtype),
                          cos_coeffs=jnp.asarray(cos_coeffs, dtype))


def _harmonic_to_config(motion: HarmonicMotion, old: Mapping[str, Any]) -> dict[str, Any]:
    """A list that was empty stays empty while its coefficients stay zero."""
    sin_c, cos_c = np.asarray(motion.sin_coeffs), np.asarray(motion.cos_coeffs)
    values: dict[str, Any] = {"base_frequency_hz": float(motion.base_frequency_hz)}
    for axis, letter in enumerate("xyz"):
        for name, coeffs in (("sin", sin_c), ("cos", cos_c)):
            key = f"{letter}_{name}"
            values[key] = (tuple(float(v) for v in coeffs[:, axis])
                           if old.get(key) or np.any(coeffs[:, axis]) else ())
    return values


def _spline_from_config(values: Mapping[str, Any], dtype: Any) -> SplineMotion:
    return SplineMotion(period=jnp.asarray(values["period"], dtype),
                        points=jnp.asarray(np.array(values["points"]), dtype))


def _spline_to_config(motion: SplineMotion, old: Mapping[str, Any]) -> dict[str, Any]:
    return {"period": float(motion.period),
            "points": tuple(tuple(float(c) for c in p) for p in np.asarray(motion.points))}


register_motion_kind(MotionKind(
    name="circle", cls=CircleMotion, offset=_circle_offset,
    frequency_hz=lambda m: jnp.asarray(m.rpm) / 60.0,
    config_keys=("rpm", "amplitude", "phase"),
    from_config=_circle_from_config, to_config=_circle_to_config,
    design_parameters={"rpm": "rpm", "amplitude": "m", "phase": "rad"},
    scale=lambda m, factor: m.replace(amplitude=m.amplitude * factor),
))
register_motion_kind(MotionKind(
    name="harmonic", cls=HarmonicMotion, offset=_harmonic_offset,
    frequency_hz=lambda m: jnp.asarray(m.base_frequency_hz),
    config_keys=("base_frequency_hz",) + _HARMONIC_LISTS,
    from_config=_harmonic_from_config, to_config=_harmonic_to_config,
    design_parameters={"base_frequency_hz": "Hz"},
    scale=lambda m, factor: m.replace(sin_coeffs=m.sin_coeffs * factor,
                                      cos_coeffs=m.cos_coeffs * factor),
    coefficient_fields={"sin": "sin_coeffs", "cos": "cos_coeffs"},
))
register_motion_kind(MotionKind(
    name="spline", cls=SplineMotion, offset=_spline_offset,
    frequency_hz=lambda m: 1.0 / jnp.asarray(m.period),
    config_keys=("period", "points"),
    from_config=_spline_from_config, to_config=_spline_to_config,
))


def _scalar_offset(motion: Motion, t: jax.Array) -> jax.Array:
    return motion_kind(motion).offset(motion, t)


def _scalar_velocity(motion: Motion, t: jax.Array) -> jax.Array:
    return jax.jvp(lambda tt: _scalar_offset(motion, tt), (t,), (jnp.ones_like(t),))[1]


def _scalar_acceleration(motion: Motion, t: jax.Array) -> jax.Array:
    return jax.jvp(lambda tt: _scalar_velocity(motion, tt), (t,), (jnp.ones_like(t),))[1]


# --------------------------------------------------------------------------------------------
# Public API


def offset(motion: Motion, t: float | jax.Array) -> jax.Array:
    """Lab-frame position (m) of the jar-frame origin at time ``t`` (s) since the start of motion.

    Args:
        motion: a motion of a registered kind (CircleMotion, HarmonicMotion, SplineMotion, ...).
        t: scalar time (s), or an array of times (vmapped).
    Returns:
        (3,) for scalar ``t``, ``t.shape + (3,)`` for an array. Jittable and differentiable in
        ``t`` and in every motion parameter.
    """
    return _map_over_time(_scalar_offset, motion, t)


def velocity(motion: Motion, t: float | jax.Array) -> jax.Array:
    """Jar velocity d offset / dt (m/s) by forward-mode autodiff; shape as ``offset``."""
    return _map_over_time(_scalar_velocity, motion, t)


def acceleration(motion: Motion, t: float | jax.Array) -> jax.Array:
    """Jar acceleration d^2 offset / dt^2 (m/s^2) by forward-mode autodiff; shape as ``offset``."""
    return _map_over_time(_scalar_acceleration, motion, t)


def frequency_hz(motion: Motion) -> jax.Array:
    """The "rotational frequency" (Hz) fed to the surrogate's wall node (docs/conventions.md
    section 5).

    The kind's ``frequency_hz``: ``rpm / 60`` for a circle, ``base_frequency_hz`` for a
    harmonic series, ``1 / period`` for a spline.
    """
    return motion_kind(motion).frequency_hz(motion)


def standard_circle(dtype: jnp.dtype = jnp.float64) -> CircleMotion:
    """The standard case (docs/conventions.md section 2): circle, 300 rpm, amplitude 0.017 m,
    phase 0."""
    return CircleMotion(rpm=jnp.asarray(300.0, dtype), amplitude=jnp.asarray(0.017, dtype),
                        phase=jnp.asarray(0.0, dtype))


def motion1(dtype: jnp.dtype = jnp.float64) -> HarmonicMotion:
    """Motion 1 (docs/conventions.md section 2): x = 1.7 sin(10 pi t) - 0.85 cos(20 pi t),
    z = 1.7 cos(10 pi t) - 0.85 sin(20 pi t) (cm); f0 = 5 Hz."""
    sin_coeffs = [[0.017, 0.0, 0.0], [0.0, 0.0, -0.0085]]
    cos_coeffs = [[0.0, 0.0, 0.017], [-0.0085, 0.0, 0.0]]
    return HarmonicMotion(base_frequency_hz=jnp.asarray(5.0, dtype),
                          sin_coeffs=jnp.asarray(sin_coeffs, dtype),
                          cos_coeffs=jnp.asarray(cos_coeffs, dtype))


def motion2(dtype: jnp.dtype = jnp.float64) -> HarmonicMotion:
    """Motion 2 (docs/conventions.md section 2): x = 1.7 sin(10 pi t), z = 1.7 cos(20 pi t) (cm);
    f0 = 5 Hz."""
    sin_coeffs = [[0.017, 0.0, 0.0], [0.0, 0.0, 0.0]]
    cos_coeffs = [[0.0, 0.0, 0.0], [0.0, 0.0, 0.017]]
    return HarmonicMotion(base_frequency_hz=jnp.asarray(5.0, dtype),
                          sin_coeffs=jnp.asarray(sin_coeffs, dtype),
                          cos_coeffs=jnp.asarray(cos_coeffs, dtype))


def spline_from_motion(motion: Motion, n_points: int, period: float | jax.Array) -> SplineMotion:
    """Sample any motion at ``t_j = j * period / n_points`` into a periodic spline.

    ``period`` should be a period of ``motion`` (e.g. ``1 / frequency_hz(motion)``), otherwise
    the spline closes a curve that does not close. Differentiable w.r.t. the motion's parameters.
    """
    if not isinstance(n_points, (int, np.integer)) or n_points < 3:
        raise ValueError(f"n_points must be an integer >= 3, got {n_points!r}")
    period = jnp.asarray(period)
    times = jnp.arange(n_points, dtype=jnp.result_type(period, jnp.float32)) * (period / n_points)
    return SplineMotion(period=period, points=offset(motion, times))


def stack_motions(motions: list[Motion]) -> Motion:
    """Stack motions of one kind (same K or M) into one pytree with a leading batch axis.

    Use with ``jax.vmap(offset, in_axes=(0, None))(stacked, t)``.
    """
    if not motions:
        raise ValueError("stack_motions needs at least one motion")
    kinds = {type(m) for m in motions}
    if len(kinds) != 1:
        raise ValueError(f"stack_motions needs motions of one kind, got {sorted(k.__name__ for k in kinds)}")
    return jax.tree.map(lambda *leaves: jnp.stack([jnp.asarray(x) for x in leaves]), *motions)


__all__ = [
    "CircleMotion",
    "HarmonicMotion",
    "Motion",
    "MotionKind",
    "SplineMotion",
    "acceleration",
    "frequency_hz",
    "motion1",
    "motion2",
    "motion_kind",
    "motion_kind_named",
    "motion_kinds",
    "offset",
    "register_motion_kind",
    "spline_from_motion",
    "spline_second_derivatives",
    "stack_motions",
    "standard_circle",
    "unregister_motion_kind",
    "velocity",
]
