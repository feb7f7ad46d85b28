"""Design sensitivities: the ensemble-mean dissipation power as a differentiable function of named
design parameters (jar motion, jar shape), with a gradient estimator built for chaotic systems.

Pure JAX core: no config, no files (the host side is :mod:`sgn_jax.api`). Three pieces:

1. **Named design parameters** (:data:`PARAMETER_UNITS`, :func:`apply_parameters`): a flat vector
   ``theta`` (D,) of values for names such as ``motion.rpm``, ``motion.amplitude``,
   ``motion.base_frequency_hz``, ``motion.x_sin[0]``, ``motion.scale`` (multiplies the whole
   displacement: the circle's amplitude or every harmonic coefficient), ``jar.straight_length``,
   ``jar.radius``, ``jar.height``, ``jar.post_radius``; applied to a motion pytree and a
   :class:`sgn_jax.geometry.JarParams` pytree. The jar is queried through its exact analytic SDF
   (:func:`sgn_jax.surrogate.rollout.analytic_jar_query`), so jar-shape derivatives are exact
   derivatives of the wall distances the network sees (the SDF grid the model was trained with
   agrees with it to 3.8 um, docs/geometry.md), with no grid to resample per evaluation.
   The charge parameters (:data:`CHARGE_PARAMETER_UNITS`: ball radius, density, material)
   change the balls themselves and are refused here; ``sgn_jax.api.sensitivity`` estimates
   them by central differences of ensembles with packings of their own charge.

2. **The anchored ensemble state.** A packing is a window of ball positions at time ``t``. When
   ``theta`` changes the motion, the balls keep their positions *in the jar frame* and the jar's
   phase at ``t`` is held (``t`` is remapped so that ``f(theta) * t`` is unchanged): a frequency
   change acts from ``t`` on, instead of teleporting the jar by the accumulated phase
   ``2 pi t df`` (the "gradient" of a long rollout with respect to rpm is dominated by that
   artefact: 1.7 mm of jar displacement per rpm after one second).

3. **The estimators** (:func:`make_ensemble_power`; docs/design.md). The charge is chaotic: the
   surrogate's tangent d(state)/d(theta) grows like exp(700 t / s), so the derivative of one
   long trajectory says nothing about the derivative of its time average. The forward pass
   rolls every packing out and measures the ensemble-mean power. Its gradient, returned by
   ``jax.value_and_grad`` through a ``jax.custom_vjp``, is by default (``"difference"``) the
   ensemble central difference with common packings, ``mean_k (P_k(theta + h e_i) -
   P_k(theta - h e_i)) / 2h``: the exact derivative of the power smoothed over +-h, the
   quantity the DEM check measures. ``"horizon"`` is the truncated-horizon alternative: the
   mean over packings and segment starts of the autodiff derivative of the energy dissipated
   in ``horizon`` steps from the (anchored, stop-gradient) state at the segment start; it sees
   only the immediate response (``experiments/reproduce/design_gradients/verify_gradients.py``
   measures both; docs/results.md section 5).
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Callable, Sequence
from typing import Any

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from sgn_jax.dem.engine import DEMParams, DEMSpec, make_sampler, observe
from sgn_jax.dem.engine import init_state as init_dem_state
from sgn_jax.dem.placement import PLACEMENT_GAP, place_balls_traced
from sgn_jax.errors import SGNJaxError
from sgn_jax.geometry import JarParams
from sgn_jax.geometry.jar import jar_sdf
from sgn_jax.geometry.sdf_grid import cavity_box
from sgn_jax.motion import (
    CircleMotion,
    Motion,
    frequency_hz,
    motion_kind,
    motion_kinds,
    offset,
    velocity,
)
from sgn_jax.surrogate.graph import BallCharge, GraphSpec, Window, with_spins
from sgn_jax.surrogate.rollout import (
    Predictor,
    RolloutState,
    analytic_jar_query,
    make_rollout_advance,
    separate_pairs,
    snap_back_shift,
)

F64 = jnp.float64


class DesignError(SGNJaxError, ValueError):
    """Bad design-study input (unknown parameter, wrong sizes) or a gradient that is not finite."""


# --------------------------------------------------------------------------------------------
# Named design parameters

_COEFF = re.compile(r"^motion\.([xyz])_(sin|cos)\[(\d+)\]$")
_FIXED_UNITS = {
    "motion.scale": "1",
    "jar.radius": "m",
    "jar.straight_length": "m",
    "jar.height": "m",
    "jar.post_radius": "m",
}


def parameter_units() -> dict[str, str]:
    """Unit of each fixed-name design parameter of the registered motion kinds and the jar.

    A motion kind declares its own (:attr:`sgn_jax.motion.MotionKind.design_parameters`,
    ``motion.<field>``); ``motion.scale`` multiplies the whole displacement of a kind with a
    ``scale``; harmonic coefficients ``motion.{x,y,z}_{sin,cos}[k]`` (k = 0 is the first
    harmonic, as in the config lists) are in m.
    """
    units = {}
    for kind in motion_kinds():
        for field, unit in kind.design_parameters.items():
            units.setdefault(f"motion.{field}", unit)
    units.update(_FIXED_UNITS)
    return units


PARAMETER_UNITS = parameter_units()
"""Unit of each fixed-name design parameter of the built-in motion kinds and the jar (kinds
registered later add theirs to :func:`parameter_units`); harmonic coefficients
``motion.{x,y,z}_{sin,cos}[k]`` (k = 0 is the first harmonic, as in the config lists) are in m."""

CHARGE_PARAMETER_UNITS = {
    "balls.radius_fill": "m",
    "balls.radius_count": "m",
    "balls.density": "kg/m^3",
    "balls.restitution": "1",
    "balls.friction": "1",
}
"""Unit of each charge parameter (a charge of one ball class; docs/design.md): the ball radius
at the charge's filling (the count follows the radius), the ball radius at its ball count, the
balls' density, and the restitution and sliding friction of the balls' material. A charge
parameter changes the balls themselves, and two of them their count, so it is not a parameter
of a rollout of fixed balls (:func:`check_parameters` refuses it): ``sgn_jax.api.sensitivity``
estimates it by central differences of ensembles, each side with DEM packings of its own
charge."""


def is_charge_parameter(name: str) -> bool:
    """Whether ``name`` is one of :data:`CHARGE_PARAMETER_UNITS`."""
    return name in CHARGE_PARAMETER_UNITS


def parameter_unit(name: str) -> str:
    """The unit of a design or charge parameter (``DesignError`` for an unknown name)."""
    units = parameter_units()
    if name in units:
        return units[name]
    if name in CHARGE_PARAMETER_UNITS:
        return CHARGE_PARAMETER_UNITS[name]
    if _COEFF.match(name) and any(k.coefficient_fields for k in motion_kinds()):
        return "m"
    raise DesignError(f"unknown design parameter {name!r}; known: {sorted(units)}, harmonic "
                      f"coefficients like 'motion.x_sin[0]' and the charge parameters "
                      f"{sorted(CHARGE_PARAMETER_UNITS)}")


def _or_list(items: Sequence[str]) -> str:
    return items[0] if len(items) == 1 else ", ".join(items[:-1]) + " or " + items[-1]


def _motion_parameter_problem(name: str, motion: Motion) -> str | None:
    """Why ``name`` (a ``motion.*`` parameter) is not a design parameter of ``motion``'s kind,
    or None if it is; the kinds are asked through the registry."""
    kind = motion_kind(motion)
    match = _COEFF.match(name)
    if name == "motion.scale":
        has = lambda k: k.scale is not None  # noqa: E731
    elif match:
        has = lambda k: match.group(2) in k.coefficient_fields  # noqa: E731
    else:
        field = name.split(".", 1)[1]
        has = lambda k: field in k.design_parameters  # noqa: E731
    if has(kind):
        if match:
            n_rows = np.shape(getattr(motion, kind.coefficient_fields[match.group(2)]))[0]
            if int(match.group(3)) >= n_rows:
                return f"{name}: the motion has {n_rows} harmonics (k counts from 0)"
        return None
    owners = [k.name for k in motion_kinds() if has(k)]
    alternatives = [f"motion.{field}" for field in kind.design_parameters]
    if kind.scale is not None:
        alternatives.append("motion.scale")
    if kind.coefficient_fields:
        alternatives.append("a harmonic coefficient")
    article = "an" if owners and owners[0][:1] in "aeiou" else "a"
    problem = (f"{name} needs {article} {_or_list(owners)} motion, the config's motion is "
               f"{type(motion).__name__}")
    if alternatives:
        problem += f"; use {_or_list(alternatives)}"
    return problem


def check_parameter_names(names: Sequence[str]) -> tuple[str, ...]:
    """``names`` as a tuple; DesignError for none, a repeat or an unknown name."""
    names = tuple(names)
    if not names:
        raise DesignError("give at least one design parameter, e.g. 'motion.rpm'")
    if len(set(names)) != len(names):
        raise DesignError(f"design parameters repeat: {list(names)}")
    for name in names:
        parameter_unit(name)
    return names


def check_parameters(names: Sequence[str], motion: Motion, jar: JarParams) -> tuple[str, ...]:
    """Validate ``names`` against the motion kind and the jar; returns them as a tuple."""
    names = check_parameter_names(names)
    for name in names:
        if is_charge_parameter(name):
            raise DesignError(
                f"{name} is a charge parameter: it changes the balls (and with "
                "balls.radius_fill their count), so it is not a parameter of a rollout of "
                "fixed balls; sgn_jax.api.sensitivity (`sgn-jax sensitivity --param "
                f"{name}`) estimates it by central differences of ensembles, each side with "
                "DEM packings of its own charge (docs/design.md)")
        if name.startswith("motion."):
            problem = _motion_parameter_problem(name, motion)
            if problem is not None:
                raise DesignError(problem)
        if name == "jar.post_radius" and not jar.has_post:
            raise DesignError("jar.post_radius needs a jar with a post (post_radius > 0 in the "
                              "config); a post cannot grow from zero radius differentiably")
    return names


def parameter_values(names: Sequence[str], motion: Motion, jar: JarParams) -> np.ndarray:
    """The current values (D,) of ``names`` (``motion.scale`` is 1 by definition)."""
    values = []
    for name in names:
        match = _COEFF.match(name)
        if name == "motion.scale":
            values.append(1.0)
        elif match:
            axis, k = "xyz".index(match.group(1)), int(match.group(3))
            coeffs = getattr(motion, motion_kind(motion).coefficient_fields[match.group(2)])
            values.append(float(np.asarray(coeffs)[k, axis]))
        elif name.startswith("motion."):
            values.append(float(np.asarray(getattr(motion, name.split(".", 1)[1]))))
        else:
            values.append(float(np.asarray(getattr(jar, name.split(".", 1)[1]))))
    return np.asarray(values, dtype=np.float64)


def apply_parameters(names: Sequence[str], theta: jax.Array, motion: Motion, jar: JarParams
                     ) -> tuple[Motion, JarParams]:
    """``(motion, jar)`` with the parameters ``names`` set to ``theta`` (D,) (traceable)."""
    theta = jnp.asarray(theta, F64)
    for i, name in enumerate(names):
        value = theta[i]
        match = _COEFF.match(name)
        if name == "motion.scale":
            motion = motion_kind(motion).scale(motion, value)
        elif match:
            axis, k = "xyz".index(match.group(1)), int(match.group(3))
            field = motion_kind(motion).coefficient_fields[match.group(2)]
            coeffs = jnp.asarray(getattr(motion, field), F64).at[k, axis].set(value)
            motion = motion.replace(**{field: coeffs})
        elif name.startswith("motion."):
            motion = motion.replace(**{name.split(".", 1)[1]: value})
        else:
            jar = jar.replace(**{name.split(".", 1)[1]: value})
    return motion, jar


# --------------------------------------------------------------------------------------------
# Anchoring a state to a changed motion


def anchored_window(window: Window, t_now: jax.Array, base_motion: Motion, motion: Motion,
                    dt: float) -> tuple[Window, jax.Array]:
    """``window`` (made under ``base_motion``, newest sample at ``t_now``) moved to ``motion``.

    Returns the window and the effective time of its newest sample, ``t_eff =
    stop_gradient(f(theta) t_now) / f(theta)``: equal to ``t_now`` at the base point, with the
    jar's phase held. Ball positions keep their jar-frame values (stop-gradient): the jar state
    of the slots and the lab positions follow the new motion, the packing does not.
    """
    w = jnp.shape(window.offsets)[0]
    f = frequency_hz(motion)
    t_eff = jax.lax.stop_gradient(f * t_now) / f
    rel = dt * jnp.arange(-w, 1, dtype=F64)                   # the W+1 position slots
    base_offsets = offset(base_motion, jnp.asarray(t_now, F64) + rel)
    jar_frame = jax.lax.stop_gradient(window.positions - base_offsets[:, None, :])
    new_offsets = offset(motion, t_eff + rel)
    window = with_spins(window).replace(
        positions=jar_frame + new_offsets[:, None, :],
        offsets=new_offsets[1:],
        offset_velocities=velocity(motion, t_eff + rel[1:]),
        frequency_hz=jnp.asarray(f, F64))
    return window, t_eff


PACKING_FIT_TOLERANCE = 1.0e-4
"""m: a packing's ball that sinks deeper than this into a changed jar's wall, or into another
ball, is moved out to it by :func:`fit_packing_to_jar` (0.1 mm: twice the DEM's deepest overlaps
in the standard case, so a packing in its own jar is left exactly as it is)."""
PACKING_FIT_ITERATIONS = 64


def fit_packing_to_jar(window: Window, jar: JarParams, radius: float | jax.Array,
                       tolerance: float = PACKING_FIT_TOLERANCE,
                       iterations: int = PACKING_FIT_ITERATIONS) -> Window:
    """``window`` with its balls moved out of ``jar``'s walls and out of each other, beyond
    ``tolerance`` (m), every slot by the same shift (velocities unchanged; stop-gradient: the
    packing does not follow the design, as in :func:`anchored_window`). ``radius``: the balls'
    radius (m), or each ball's (N,) (a window with a charge).

    Why: a packing is settled in the base jar; under a jar-shape parameter it lies in another
    one. 5 mm off the standard jar's ``straight_length``, the standard packings put balls
    2.5 mm inside the end wall, and a rollout started there is kicked out of the bed state by
    the contact impulses that expel them (contact models with an overlap limit doubled the
    power; docs/design.md). ``iterations`` Jacobi sweeps: wall overlaps deeper than
    ``tolerance`` pushed back along the wall normal, then ball pairs separated to it
    (:func:`sgn_jax.surrogate.rollout.separate_pairs`). A packing already within the
    tolerance (any packing in its own jar) gets a shift of exactly 0."""
    newest, offset_now = window.positions[-1], window.offsets[-1]

    def sweep(_, x):
        phi, normal = analytic_jar_query(jar, x, offset_now)
        x = x + snap_back_shift(phi, normal, tolerance - radius)[0]   # walls: overlap <= tol
        shift, _ = separate_pairs(x, radius, tolerance)
        return x + shift

    moved = jax.lax.fori_loop(0, iterations, sweep, newest)
    shift = jax.lax.stop_gradient(moved - newest)
    return window.replace(positions=window.positions + shift[None])


@dataclasses.dataclass(frozen=True)
class PackingStart:
    """How a design study makes each packing's start in the jar it evaluates
    (:func:`make_ensemble_power`'s ``start``).

    Attributes:
        name: what makes it: ``"dem"`` (:func:`make_dem_start`) or ``"settle"`` (the
            surrogate, :func:`make_settled_start`).
        make: ``make(params, stats, candidates (C, 3), motion, jar) -> Window`` (one packing,
            from its unit-box placement candidates; traceable in the jar and the motion).
        t_start: s since the start of motion of the window's newest sample.
    """

    name: str
    make: Callable[..., Window]
    t_start: float


def rest_window(positions: jax.Array, window: int, frequency: jax.Array) -> Window:
    """A :class:`Window` of balls at rest at ``positions`` (N, 3) in a jar at rest at the
    origin: ``window`` + 1 equal slots, zero jar offsets, velocities and spins."""
    positions = jnp.asarray(positions, F64)
    return Window(positions=jnp.broadcast_to(positions, (window + 1, *positions.shape)),
                  offsets=jnp.zeros((window, 3), F64),
                  offset_velocities=jnp.zeros((window, 3), F64),
                  frequency_hz=jnp.asarray(frequency, F64),
                  spins=jnp.zeros(positions.shape, F64))


def _placed(candidates: jax.Array, jar: JarParams, n_balls: int, radius: float) -> jax.Array:
    """(N, 3) jar-frame positions of the DEM's placement from ``candidates`` in ``jar``."""
    lower, upper = cavity_box(jar)
    placed, _ = place_balls_traced(lambda x: jar_sdf(jar, x), lower, upper, candidates,
                                   n_balls, radius, PLACEMENT_GAP)
    return placed


def _one_size(charge: BallCharge, who: str) -> float:
    """The one ball radius (m) of ``charge`` (host side); DesignError for several sizes."""
    radii = np.unique(np.asarray(charge.radius, np.float64)[np.asarray(charge.present, bool)])
    if radii.size != 1:
        raise DesignError(f"{who} places balls of one size, and this charge has "
                          f"{radii.size} ({sorted(radii.tolist())} m); a study of a mixture "
                          "starts from its packings (start='packing')")
    return float(radii[0])


def make_settled_start(spec: GraphSpec, predictor: Predictor, n_settle: int, *,
                       charge: BallCharge | None = None, **options: Any) -> PackingStart:
    """The DEM's procedure for a packing with the surrogate in the DEM's place (``"settle"``).

    ``make(params, stats, candidates, motion, jar)``: the balls placed from ``candidates``
    (C, 3) as the DEM places them in ``jar`` (:func:`sgn_jax.dem.placement.place_balls_traced`,
    clearance :data:`sgn_jax.dem.placement.PLACEMENT_GAP`), at rest; rolled out ``n_settle`` steps by the surrogate
    with the jar at rest at the origin (gravity settles them); then the jar put at
    ``motion``'s offset at t = 0, as the DEM settles at rest at ``offset(0)`` before its motion
    starts. The window's newest sample is at ``t_start = 0``. ``options``: the rollout's
    settings (:func:`sgn_jax.surrogate.rollout.make_rollout_advance`). Cheap (a surrogate
    rollout), but the jar-length gradients from it were 1.2-1.5 SE below the DEM's at all three
    points checked (docs/design.md); the DEM's own settle (:func:`make_dem_start`) is the
    default for a jar-shape parameter. ``charge``: the :class:`BallCharge` of a model that
    reads the charge (one ball size; the window carries it through the settle and after).
    """
    settle = (make_rollout_advance(spec, predictor, n_settle, n_settle, **options)
              if n_settle else None)
    radius = spec.ball_radius if charge is None else _one_size(charge, "the surrogate's settle")

    def settled(params, stats, candidates, motion, jar):
        window = rest_window(_placed(candidates, jar, spec.n_particles, radius),
                             spec.window, frequency_hz(motion))
        if charge is not None:
            window = window.replace(charge=charge)
        zero = jnp.zeros((), F64)
        if settle is not None:
            at_rest = CircleMotion(rpm=zero, amplitude=zero, phase=zero)
            state = RolloutState(window=window, step=jnp.zeros((), jnp.int32), energy=zero)
            window = settle(params, stats, state, at_rest, jar, zero).final.window
        origin = offset(motion, zero)
        return window.replace(positions=window.positions + origin,
                              offsets=window.offsets + origin,
                              offset_velocities=jnp.zeros_like(window.offset_velocities),
                              frequency_hz=jnp.asarray(frequency_hz(motion), F64))

    return PackingStart(name="settle", make=settled, t_start=0.0)


def make_dem_start(dem_spec: DEMSpec, wall_fn: Callable, dem_params: DEMParams, dt: float,
                   substeps: int, settle_samples: int, pp_capacity: int, window: int,
                   charge: BallCharge | None = None) -> PackingStart:
    """A packing made by the DEM in any jar, as :func:`sgn_jax.api.make_packings` makes one
    (``"dem"``; traceable in the jar and the motion, so that a design study makes one in every
    jar it evaluates).

    ``make(params, stats, candidates, motion, jar)``: the balls placed from ``candidates``
    (C, 3) in ``jar`` (:func:`sgn_jax.dem.placement.place_balls_traced`, the DEM's placement),
    settled by the DEM for ``settle_samples`` samples of ``substeps`` DEM steps with the jar at
    rest at ``offset(0)``, then ``window`` samples of ``motion``: the window of samples
    0..W, newest at ``t_start = W dt`` (``dt`` s: ``substeps`` DEM steps), without spins (a
    rollout starts the balls not turning), as :func:`sgn_jax.api.make_packings`'s windows.
    ``dem_params`` gives the balls and the material (its geometry and motion are replaced).
    ``params`` and ``stats`` (the surrogate's) are not used. It costs a DEM settle per packing
    and jar (docs/design.md gives the cost): the price of the start the DEM's own runs in that
    jar have. ``charge``: the :class:`BallCharge` the windows carry, for a model that reads the
    charge (the DEM's balls are ``dem_params``'; one ball size).
    """
    if charge is not None:
        _one_size(charge, "the DEM's start in every jar")
    run = make_sampler(dem_spec, wall_fn, substeps, pp_capacity)
    n_balls, radius = dem_spec.n_balls, float(dem_params.radius)

    def dem_packing(params, stats, candidates, motion, jar):
        p = dem_params.replace(geometry=jar, motion=motion)
        origin = offset(motion, jnp.zeros((), F64))
        state = init_dem_state(dem_spec, p, _placed(candidates, jar, n_balls, radius) + origin,
                               step=-settle_samples * substeps)
        if settle_samples:
            state, _ = run(p, state, settle_samples)
        first = observe(dem_spec, wall_fn, p, state, pp_capacity)
        _, samples = run(p, state, window)
        return Window(positions=jnp.concatenate([first["pos"][None], samples["pos"]]),
                      offsets=samples["offset"], offset_velocities=samples["offset_vel"],
                      frequency_hz=jnp.asarray(frequency_hz(motion), F64), charge=charge)

    return PackingStart(name="dem", make=dem_packing, t_start=window * float(dt))


# --------------------------------------------------------------------------------------------
# The ensemble-mean power and its estimated gradient


@flax.struct.dataclass
class PowerEstimate:
    """What :func:`make_ensemble_power`'s ``estimate`` returns (K packings, G segments, D params).

    Attributes:
        power_W: (K,) mean dissipation power of each packing over the measurement interval (W).
        gradient: (K, G, D) per packing: the central difference of its power (G = 1,
            ``estimator="difference"``), or the truncated-horizon derivative at each of G segment
            starts (``"horizon"``), in W per unit of each parameter.
        horizon_energy_J: (K, G) energy dissipated in each gradient horizon (J; zeros for the
            difference estimator).
        side_powers_W: (2D, K) powers at theta + h_i e_i (rows 0..D-1) and theta - h_i e_i
            (rows D..2D-1) for the difference estimator; (0, K) for the horizon estimator.
    """

    power_W: jax.Array
    gradient: jax.Array
    horizon_energy_J: jax.Array
    side_powers_W: jax.Array


@dataclasses.dataclass(frozen=True)
class EnsemblePower:
    """The jittable functions of one design study (see :func:`make_ensemble_power`).

    ``power(theta, params, stats, windows)`` -> () W, ensemble mean; ``jax.value_and_grad``
    w.r.t. ``theta`` returns the study estimator's gradient (the mean of ``estimate``'s, from
    the same compiled program; jittable, and compiled programs when called eagerly). ``estimate(...)`` ->
    :class:`PowerEstimate` (per packing and segment, for standard errors). ``forward(...)`` ->
    (K,) powers without any gradient work (for finite differences and curves). ``batching``:
    how the packings' rollouts run, "vmap" or "map"; ``start``: where they start, ``"packing"``
    or the :class:`PackingStart`'s name (:func:`make_ensemble_power`).
    """

    power: Callable[..., jax.Array]
    estimate: Callable[..., PowerEstimate]
    forward: Callable[..., jax.Array]
    names: tuple[str, ...]
    n_burn: int
    n_measure: int
    horizon: int
    n_segments: int
    estimator: str = "difference"
    steps: tuple[float, ...] = ()
    batching: str = "vmap"
    start: str = "packing"


def _zero_cotangent(x: Any) -> Any:
    x = jnp.asarray(x)
    if jnp.issubdtype(x.dtype, jnp.inexact):
        return jnp.zeros_like(x)
    return np.zeros(x.shape, dtype=jax.dtypes.float0)


BATCHING = ("vmap", "map")
"""How the packings of an ensemble run: as one vmapped batch, or one after another."""


def check_batching(batching: str) -> None:
    """:class:`DesignError` unless ``batching`` is one of :data:`BATCHING`."""
    if batching not in BATCHING:
        raise DesignError(f"batching must be one of {BATCHING}, got {batching!r}")


def make_ensemble_power(spec: GraphSpec, predictor: Predictor, names: Sequence[str],
                        base_motion: Motion, base_jar: JarParams, t0: float, *,
                        n_burn: int, n_measure: int, horizon: int = 100, n_segments: int = 8,
                        snap_back: bool = True, phi_sb: float = -0.0049,
                        snap_velocity: str = "keep", pp_max_overlap: float | None = None,
                        checkpoint_steps: int = 100, estimator: str = "difference",
                        steps: Sequence[float] | None = None,
                        batching: str = "vmap", start: PackingStart | None = None
                        ) -> EnsemblePower:
    """Build the ensemble-mean power of a design study and its gradient estimator.

    Args:
        spec: the surrogate's :class:`GraphSpec`.
        predictor: ``predictor(params, stats, graph, step)`` (:func:`model_predictor`).
        names: the D design parameters (:func:`check_parameters`).
        base_motion: the design point's motion; ``theta`` replaces ``names``.
        base_jar: the design point's jar.
        t0: time (s since the start of motion) of the packings' newest window sample.
        n_burn: steps rolled out before the measurement starts (the state settles).
        n_measure: steps of the measurement interval (power = energy / (n_measure dt)); a
            multiple of ``n_segments``.
        horizon: steps of each gradient horizon (<= n_measure / n_segments).
        n_segments: gradient segments per packing, one at the start of each of the
            ``n_segments`` equal parts of the measurement interval.
        snap_back: the rollout's snap-back switch
            (:func:`sgn_jax.surrogate.rollout.make_rollout`).
        phi_sb: the snap-back threshold (m).
        snap_velocity: the velocity rule of the snap-back and the separation.
        pp_max_overlap: the ball-ball separation's largest overlap (m), or None (off).
        checkpoint_steps: ``jax.checkpoint`` chunk of the differentiated horizons.
        estimator: ``"difference"`` (default): the gradient is the ensemble central difference
            of the power with common packings, ``(P(theta + h_i e_i) - P(theta - h_i e_i)) /
            2 h_i``, the exact derivative of the power smoothed over +-h (docs/design.md says
            why); ``"horizon"``: the truncated-horizon autodiff estimator (``horizon``,
            ``n_segments``).
        steps: (D,) the difference steps h_i (required for ``"difference"``; see
            :func:`default_step`).
        batching: how the packings' rollouts (the powers and the difference estimator's
            sides) run: ``"vmap"`` (default) as one batch, ``"map"`` one after another
            (``lax.map``), for a predictor of a model's single-rollout form, which a vmap
            would make slower (:func:`sgn_jax.pipelines.studies.over_packings`). The horizon
            estimator's gradients stay vmapped.
        start: where each packing's rollout starts. None (default): from its window
            (the ``starts`` argument), made under ``base_motion`` and ending at ``t0``,
            anchored to ``theta``'s motion and fitted into ``theta``'s jar
            (:func:`fit_packing_to_jar`). A :class:`PackingStart` (:func:`make_dem_start`,
            :func:`make_settled_start`): each packing made in ``theta``'s jar from its
            placement candidates (the ``starts`` argument), under ``theta``'s motion; a
            motion parameter's sides start from those windows (anchored to their motion), a
            jar parameter's sides make theirs in their own jar. For a jar-shape parameter a
            packing settled in the base jar and fitted into another is not the start the DEM's
            runs in that jar have (docs/design.md measures both). Stop-gradient either way
            (as the anchoring): the horizon estimator differentiates from the start.

    Returns:
        an :class:`EnsemblePower`. Its functions take ``(theta (D,), params, stats, starts)``:
        without ``start``, ``starts`` is a :class:`Window` batched over K packings (leading
        axis); with one, the (K, C, 3) unit-box placement candidates of the K packings
        (:func:`sgn_jax.dem.placement.placement_candidates` of their seeds).
    """
    names = check_parameters(names, base_motion, base_jar)
    n_burn, n_measure, horizon, n_segments = int(n_burn), int(n_measure), int(horizon), int(
        n_segments)
    if n_burn < 0 or n_measure < 1 or n_segments < 1 or horizon < 1:
        raise DesignError(f"need n_burn >= 0, n_measure >= 1, n_segments >= 1, horizon >= 1; got "
                          f"{n_burn}, {n_measure}, {n_segments}, {horizon}")
    if n_measure % n_segments:
        raise DesignError(f"the measurement interval ({n_measure} steps) must split into "
                          f"{n_segments} equal segments")
    if estimator not in ("difference", "horizon"):
        raise DesignError(f"estimator must be 'difference' or 'horizon', got {estimator!r}")
    check_batching(batching)
    if estimator == "difference":
        if steps is None or len(steps) != len(names):
            raise DesignError(f"the difference estimator needs one step per parameter "
                              f"({len(names)}), got {steps}")
        steps = tuple(float(h) for h in steps)
        if not all(np.isfinite(h) and h > 0 for h in steps):
            raise DesignError(f"difference steps must be finite and > 0, got {list(steps)}")
    stride = n_measure // n_segments
    if horizon > stride:
        raise DesignError(f"gradient horizon {horizon} steps is longer than a segment "
                          f"({stride} steps = measurement / n_segments); shorten it")
    dt = float(spec.dt)
    options = dict(snap_back=snap_back, phi_sb=phi_sb, snap_velocity=snap_velocity,
                   query=analytic_jar_query, pp_max_overlap=pp_max_overlap, jit=False)
    burn = (make_rollout_advance(spec, predictor, n_burn, n_burn, **options)
            if n_burn else None)
    segment_run = make_rollout_advance(spec, predictor, stride, stride, **options)
    # Frames of c steps inside a horizon, each a jax.checkpoint chunk: reverse mode stores one
    # carry per chunk instead of every step's residuals.
    chunk = _divisor_at_most(horizon, checkpoint_steps)
    horizon_run = make_rollout_advance(spec, predictor, horizon, chunk, checkpoint_steps=chunk,
                                       **options)
    t0 = float(t0) if start is None else float(start.t_start)
    jar_rows = [i for i, name in enumerate(names) if name.startswith("jar.")]
    own_start_rows = jar_rows if start is not None else []   # sides that make their packings

    def design(theta):
        return apply_parameters(names, theta, base_motion, base_jar)

    def packings_at(theta, params, stats, starts):
        """(K windows at ``theta``'s jar, the motion they were made under)."""
        if start is None:
            return starts, base_motion
        motion, jar = design(theta)

        def make(candidates):
            return start.make(params, stats, candidates, motion, jar)

        windows = jax.vmap(make)(starts) if batching == "vmap" else jax.lax.map(make, starts)
        return jax.lax.stop_gradient(windows), jax.lax.stop_gradient(motion)

    def one_forward(theta, params, stats, window0, made_under):
        """Power (W) of one packing and the states at the segment starts."""
        motion, jar = design(theta)
        window, t_eff = anchored_window(window0, jnp.asarray(t0, F64), made_under, motion, dt)
        window = fit_packing_to_jar(window, jar, spec.ball_radius if window.charge is None
                                    else window.charge.radius)
        state = RolloutState(window=window, step=jnp.zeros((), jnp.int32),
                             energy=jnp.zeros((), F64))
        if burn is not None:
            state = burn(params, stats, state, motion, jar, t_eff).final
        state = state.replace(energy=jnp.zeros((), F64))

        def segment(carry, _):
            result = segment_run(params, stats, carry, motion, jar, t_eff)
            return result.final, carry

        final, starts = jax.lax.scan(segment, state, None, length=n_segments)
        return final.energy / (n_measure * dt), starts, t_eff

    def one_horizon_energy(theta, params, stats, start, t_eff0):
        """Energy (J) dissipated in ``horizon`` steps from ``start`` under ``theta``'s design,
        the state anchored (jar frame, jar phase) at the segment start."""
        motion, jar = design(theta)
        theta0 = jax.lax.stop_gradient(theta)
        base_at_theta0, _ = design(theta0)
        t_now = t_eff0 + start.step.astype(F64) * dt
        window, t_eff = anchored_window(start.window, t_now, base_at_theta0, motion, dt)
        state = RolloutState(window=window, step=jnp.zeros((), jnp.int32),
                             energy=jnp.zeros((), F64))
        return horizon_run(params, stats, state, motion, jar, t_eff).final.energy

    horizon_grad = jax.value_and_grad(one_horizon_energy)

    def every_packing(theta, params, stats, windows, made_under):
        """``one_forward`` of each packing: (K,) powers, (K, G) segment starts, (K,) t_eff."""
        if batching == "vmap":
            return jax.vmap(one_forward, in_axes=(None, None, None, 0, None))(
                theta, params, stats, windows, made_under)
        return jax.lax.map(lambda window: one_forward(theta, params, stats, window, made_under),
                           windows)

    def forward(theta, params, stats, starts):
        windows, made_under = packings_at(theta, params, stats, starts)
        return every_packing(theta, params, stats, windows, made_under)[0]

    def segment_gradients(theta, params, stats, starts, t_eff):
        """(K, G) energies and (K, G, D) power derivatives at the segment starts."""
        per_start = jax.vmap(horizon_grad, in_axes=(None, None, None, 0, None))
        per_packing = jax.vmap(per_start, in_axes=(None, None, None, 0, 0))
        energy, grad = per_packing(theta, params, stats, starts, t_eff)
        return energy, grad / (horizon * dt)

    def difference_gradients(theta, params, stats, starts, windows, made_under):
        """(K, 1, D) per-packing central differences and the (2D, K) side powers."""
        h = jnp.asarray(steps, F64)
        d = len(steps)
        deltas = jnp.concatenate([jnp.diag(h), -jnp.diag(h)])              # (2D, D)
        own = [r for i in own_start_rows for r in (i, d + i)]
        shared = [r for r in range(2 * d) if r not in own]
        # One side at a time (lax.map): memory of one ensemble rollout, not 2D of them. The
        # sides that keep theta's jar start from theta's windows; those of a jar parameter
        # with a start of its own make their packings in their jar.
        sides = jnp.zeros((2 * d, jax.tree_util.tree_leaves(starts)[0].shape[0]), F64)
        if shared:
            sides = sides.at[np.asarray(shared)].set(jax.lax.map(
                lambda delta: every_packing(theta + delta, params, stats, windows,
                                            made_under)[0], deltas[np.asarray(shared)]))
        if own:
            sides = sides.at[np.asarray(own)].set(jax.lax.map(
                lambda delta: forward(theta + delta, params, stats, starts),
                deltas[np.asarray(own)]))
        grad = (sides[:d] - sides[d:]) / (2 * h[:, None])                  # (D, K)
        return grad.T[:, None, :], sides

    def estimate(theta, params, stats, starts):
        theta = jnp.asarray(theta, F64)
        windows, made_under = packings_at(theta, params, stats, starts)
        powers, starts_g, t_eff = every_packing(theta, params, stats, windows, made_under)
        if estimator == "difference":
            grad, sides = difference_gradients(theta, params, stats, starts, windows,
                                               made_under)
            energy = jnp.zeros(grad.shape[:2], F64)
        else:
            energy, grad = segment_gradients(theta, params, stats, starts_g, t_eff)
            sides = jnp.zeros((0, powers.shape[0]), F64)
        return PowerEstimate(power_W=powers, gradient=grad, horizon_energy_J=energy,
                             side_powers_W=sides)

    # ``power``'s derivative IS the estimate's mean gradient: its forward pass runs the
    # compiled ``estimate`` program and keeps the gradient for the backward pass, so that
    # ``jax.value_and_grad(power)`` and ``estimate`` compile one program, not two (for a
    # design study of the hidden-256 SGN each takes tens of seconds to compile). Called without
    # a derivative, ``power`` runs the cheaper compiled ``forward``.
    estimate_jit, forward_jit = jax.jit(estimate), jax.jit(forward)

    @jax.custom_vjp
    def power(theta, params, stats, windows):
        return jnp.mean(forward_jit(theta, params, stats, windows))

    def power_fwd(theta, params, stats, windows):
        est = estimate_jit(jnp.asarray(theta, F64), params, stats, windows)
        return jnp.mean(est.power_W), (jnp.mean(est.gradient, axis=(0, 1)), params, stats,
                                       windows)

    def power_bwd(residuals, g):
        grad, params, stats, windows = residuals
        zeros = jax.tree_util.tree_map(_zero_cotangent, (params, stats, windows))
        return (g * grad, *zeros)

    power.defvjp(power_fwd, power_bwd)
    return EnsemblePower(power=power, estimate=estimate_jit, forward=forward_jit, names=names,
                         n_burn=n_burn, n_measure=n_measure, horizon=horizon,
                         n_segments=n_segments, estimator=estimator, steps=tuple(steps or ()),
                         batching=batching,
                         start="packing" if start is None else start.name)


def default_step(name: str, value: float) -> float:
    """A difference / curve step for a parameter: 10 % of its value (1 mm, 0.1 rad or 0.1 where
    the value is 0). At the standard case: 30 rpm, 1.7 mm of amplitude, 3.5 mm of straight
    length."""
    if value != 0:
        return 0.1 * abs(float(value))
    return {"m": 1e-3, "rad": 0.1}.get(parameter_unit(name), 0.1)


def _divisor_at_most(n: int, limit: int) -> int:
    """The largest divisor of ``n`` that is <= ``limit`` (a jax.checkpoint chunk length)."""
    for d in range(min(n, max(1, limit)), 0, -1):
        if n % d == 0:
            return d
    return 1


def summarize_estimate(est: PowerEstimate, names: Sequence[str]) -> dict[str, Any]:
    """Ensemble means and standard errors of an estimate (host side, numpy).

    The standard error of the gradient is taken over the packings' own means (segments of one
    packing are correlated, packings are independent). Raises :class:`DesignError` if any
    power or gradient is not finite, naming the packing, segment and parameter.
    """
    power = np.asarray(est.power_W, np.float64)
    grad = np.asarray(est.gradient, np.float64)
    k = power.shape[0]
    bad_power = np.flatnonzero(~np.isfinite(power))
    if bad_power.size:
        raise DesignError(f"the rollout of packing {int(bad_power[0])} gave a non-finite power "
                          "(the surrogate diverged); check the model's envelope and the "
                          "outside/overflow counts with `sgn-jax rollout`")
    if not np.all(np.isfinite(grad)):
        p, s, d = (int(i[0]) for i in np.nonzero(~np.isfinite(grad)))
        raise DesignError(
            f"the gradient of {names[d]} is not finite at packing {p}, segment {s}: a contact "
            "response in the horizon overflowed; use a shorter gradient horizon")
    per_packing = grad.mean(axis=1)                             # (K, D)
    se = per_packing.std(axis=0, ddof=1) / np.sqrt(k) if k > 1 else np.full(len(names), np.nan)
    return {
        "power_W": float(power.mean()),
        "power_se_W": float(power.std(ddof=1) / np.sqrt(k)) if k > 1 else float("nan"),
        "power_per_packing_W": power.tolist(),
        "gradient": {n: float(v) for n, v in zip(names, per_packing.mean(axis=0), strict=True)},
        "gradient_se": {n: float(v) for n, v in zip(names, se, strict=True)},
        "gradient_per_packing": {n: per_packing[:, i].tolist() for i, n in enumerate(names)},
        "side_powers_W": np.asarray(est.side_powers_W, np.float64).tolist(),
    }


__all__ = [
    "CHARGE_PARAMETER_UNITS",
    "DesignError",
    "EnsemblePower",
    "PARAMETER_UNITS",
    "PowerEstimate",
    "anchored_window",
    "fit_packing_to_jar",
    "is_charge_parameter",
    "BATCHING",
    "check_batching",
    "apply_parameters",
    "check_parameters",
    "default_step",
    "make_ensemble_power",
    "parameter_unit",
    "parameter_values",
    "summarize_estimate",
]
