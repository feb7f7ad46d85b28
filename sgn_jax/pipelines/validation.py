"""Checks at the boundary: what is physically impossible (an error before any work starts) and
what is merely outside what was validated (a warning), for the DEM and the surrogate.

The rules, each with its reason (docs/validation.md has the table and the numbers):

- **Durations** are > 0 and a whole number of samples ``dt`` (a zero-length run has no power).
- **Fill**: the balls' solid volume (all classes) must stay below :data:`RSA_FILL_LIMIT` (38 %)
  of the cavity's: random sequential insertion, which places the balls, jams near 38 % in 3-D,
  and no packing of spheres exceeds 74 %.
- **Charge** (docs/charge.md): every ball radius spans at least :data:`GRID_POINTS_PER_RADIUS`
  SDF grid spacings; the DEM step resolves the charge's shortest contact as finely as the
  standard case's (:func:`with_charge_step`), and the contact rules below hold for every pair
  of ball classes.
- **Contact resolution** (impossible motions): a ball hit by the wall meets it at up to
  ``v_impact = 2 v_jar,max + sqrt(2 g H)`` (the jar's peak speed reversed, plus a fall through
  the jar's height). At that speed the Hertz contact must last at least
  :data:`MIN_CONTACT_STEPS` DEM steps and its peak overlap stay below
  :data:`MAX_OVERLAP_FRACTION` of the ball radius (Hertz is a small-strain law). A motion that
  breaks either is refused, with the largest admissible speed (for a circle: the largest rpm
  at the config's amplitude).
- **DEM envelope** (a warning): the DEM was validated (no escapes, energy ledger) up to a peak
  jar speed of :data:`DEM_VALIDATED_PEAK_SPEED` (2000 rpm at 17 mm).
- **Surrogate envelope** (a warning): a model promises what it was trained on
  (:func:`model_envelope`); outside it the answer may be wrong (docs/results.md section 4, "The
  motion-general SGN on held-out motions": the paper-setting SGN off its training motion). A
  model that reads the charge also names each charge parameter outside its charge envelope
  (docs/contact_charge.md, "What it covers").

Pure functions of a :class:`sgn_jax.config.Config`; they read no file but the shipped
envelopes, for a charge model whose checkpoint states none.
"""

from __future__ import annotations

import functools
import math
import warnings
from dataclasses import dataclass
from typing import Any

import jax
import numpy as np

from sgn_jax.config import Config, ConfigError, replace_section
from sgn_jax.dem.charge import contact_params, pair_params
from sgn_jax.dem.contact import MIN_CONTACT_STEPS
from sgn_jax.errors import EnvelopeWarning
from sgn_jax.geometry import jar_volume
from sgn_jax.motion import acceleration, frequency_hz, velocity
from sgn_jax.pipelines.configure import (
    charge_from_config,
    contact_law_from_config,
    jar_params_from_config,
    model_takes_charge,
    motion_from_config,
)
from sgn_jax.records.charge_envelope import (
    ChargeEnvelope,
    charge_circle_notes,
    charge_envelope_notes,
    charge_model_envelope,
    load_charge_envelope,
)
from sgn_jax.records.envelope import MotionEnvelope, harmonic_axis_amplitudes, load_envelope
from sgn_jax.records.envelope import envelope_notes as motion_envelope_notes

RSA_FILL_LIMIT = 0.38
"""Largest solid fraction of the cavity that random sequential insertion reaches (3-D jamming)."""

MAX_OVERLAP_FRACTION = 0.10
"""The Hertz peak overlap at the largest impact speed must stay below this fraction of R."""

DEM_VALIDATED_PEAK_SPEED = 3.6
"""m/s: peak jar speed of the fastest validated DEM case (2000 rpm at 17 mm, no escapes)."""


def check_duration(value: float | None, what: str = "--duration", *, dt: float | None = None,
                   allow_none: bool = False) -> float | None:
    """``value`` as a float, or ConfigError if it is not a positive, finite number of seconds
    (and, with ``dt``, at least one sample long)."""
    if value is None:
        if allow_none:
            return None
        raise ConfigError(f"{what} is required (seconds of motion, > 0)")
    v = float(value)
    if not math.isfinite(v) or v <= 0:
        raise ConfigError(f"{what} = {value} s: it must be a finite number of seconds > 0 "
                          "(e.g. 1.0)")
    if dt is not None and v < dt * (1 - 1e-9):
        raise ConfigError(f"{what} = {value} s is shorter than one sample (dt = {dt:g} s); "
                          f"use at least {dt:g} s")
    return v


def check_count(value: int, what: str, minimum: int = 1) -> int:
    """``value`` as an int >= ``minimum`` or ConfigError naming it."""
    if int(value) != value or int(value) < minimum:
        raise ConfigError(f"{what} = {value}: it must be an integer >= {minimum}")
    return int(value)


# --------------------------------------------------------------------------------------------
# Motion peaks


@dataclass(frozen=True)
class MotionPeaks:
    """Peak jar speed (m/s) and acceleration (m/s^2) over one period of a motion."""

    speed: float
    acceleration: float
    period: float


# One program: op by op, the motion's formulas cost ~25 small compilations (~0.8 s) at the
# start of every process that validates a config (each CLI command, each DEM run).
_velocity_and_acceleration = jax.jit(lambda motion, t: (velocity(motion, t),
                                                        acceleration(motion, t)))


def motion_peaks(motion_cfg: Any, samples: int = 2048) -> MotionPeaks:
    """Peak jar speed and acceleration of a ``[motion]`` config over one period."""
    motion = motion_from_config(motion_cfg)
    f = float(frequency_hz(motion))
    if not math.isfinite(f) or f <= 0:
        raise ConfigError(f"[motion] its frequency is {f} Hz; it must be > 0")
    t = np.linspace(0.0, 1.0 / f, samples, endpoint=False, dtype=np.float64)
    with jax.default_device(jax.devices("cpu")[0]):
        v, a = map(np.asarray, _velocity_and_acceleration(motion, t))
    return MotionPeaks(speed=float(np.max(np.linalg.norm(v, axis=-1))),
                       acceleration=float(np.max(np.linalg.norm(a, axis=-1))), period=1.0 / f)


# --------------------------------------------------------------------------------------------
# Physical checks of a config


def contact_kinds(cfg: Config) -> tuple[Any, dict[str, tuple[Any, float]]]:
    """The DEM's contact law of ``cfg`` ([dem] contact_law) and every kind of contact of its
    charge: name -> (the law's scalar parameters, the smaller radius of the two bodies, m).
    One ball class: "ball-ball" and "ball-wall"; several: "ball-ball a-b" for every pair of
    classes a <= b and "ball-wall a" for every class (classes numbered from 0, ``[balls]``
    first)."""
    law = contact_law_from_config(cfg)
    charge = charge_from_config(cfg)
    pp, pw = contact_params(charge, law)
    radii = [c.radius for c in charge.classes]
    if charge.monodisperse:
        return law, {"ball-ball": (pp, radii[0]), "ball-wall": (pw, radii[0])}
    kinds: dict[str, tuple[Any, float]] = {}
    for a in range(len(radii)):
        for b in range(a, len(radii)):
            kinds[f"ball-ball {a}-{b}"] = (pair_params(pp, a, b), min(radii[a], radii[b]))
        kinds[f"ball-wall {a}"] = (pair_params(pw, a), radii[a])
    return law, kinds


CONTACT_STEPS_AT_1MS = 200
"""The DEM step resolves the charge's shortest contact, a head-on impact at 1 m/s, in at least
this many steps (the standard case's 10 mm steel balls: 204 steps at dt_dem = 9.5e-7 s): a
charge of smaller or lighter balls gets a proportionally smaller step
(:func:`charge_dt_dem_max`), so that every charge is resolved as finely as the validated one."""


def charge_dt_dem_max(cfg: Config) -> float:
    """The largest DEM step (s) the charge allows: the shortest elastic contact time of its
    contact kinds at 1 m/s over :data:`CONTACT_STEPS_AT_1MS`. The DEM runs at the smaller of
    this and ``[dem] dt_dem_max`` (:func:`with_charge_step`)."""
    law, kinds = contact_kinds(cfg)
    return min(float(law.contact_time(params, 1.0)) for params, _ in kinds.values()
               ) / CONTACT_STEPS_AT_1MS


def with_charge_step(cfg: Config) -> Config:
    """``cfg`` with ``[dem] dt_dem_max`` lowered to :func:`charge_dt_dem_max` where the charge
    needs a smaller step (unchanged otherwise, as for the standard case)."""
    limit = charge_dt_dem_max(cfg)
    if cfg.dem.dt_dem_max <= limit:
        return cfg
    return replace_section(cfg, "dem", dt_dem_max=limit)


def hertz_peak_overlap(law: Any, speed: float) -> float:
    """Peak overlap (m) of an undamped Hertz impact at ``speed``:
    (15 m* v^2 / (16 Y* sqrt(R*)))^(2/5)."""
    return (15 * law.mass_eff * speed**2 / (16 * law.young_eff * math.sqrt(law.radius_eff))
            ) ** 0.4


def max_resolved_impact_speed(cfg: Config) -> tuple[float, str]:
    """The largest impact speed (m/s) the DEM of ``cfg`` resolves, and the rule that sets it.

    The contact law ([dem] contact_law) inverts both rules
    (``max_speed_for_duration``, ``max_speed_for_overlap``); for Hertz in closed form:
    t_c(v) = t_c(1) v^(-1/5) >= MIN_CONTACT_STEPS dt_dem gives
    v <= (t_c(1) / (MIN_CONTACT_STEPS dt_dem))^5; delta(v) <= f R gives
    v^2 <= 16 Y* sqrt(R*) (f R)^(5/2) / (15 m*).
    """
    dt_dem = cfg.dem.dt_dem
    best = (math.inf, "")
    law, kinds = contact_kinds(cfg)
    for name, (law_params, radius) in kinds.items():
        v_time = law.max_speed_for_duration(law_params, MIN_CONTACT_STEPS * dt_dem)
        overlap = MAX_OVERLAP_FRACTION * radius
        v_overlap = law.max_speed_for_overlap(law_params, overlap)
        if v_time < best[0]:
            best = (v_time, f"a {name} contact must last >= {MIN_CONTACT_STEPS} DEM steps "
                            f"(dt_dem = {dt_dem:.3g} s)")
        if v_overlap < best[0]:
            best = (v_overlap, f"the {name} {law.title} overlap must stay below "
                               f"{MAX_OVERLAP_FRACTION:.0%} of the ball radius")
    return best


def impact_speed(cfg: Config, peak_jar_speed: float) -> float:
    """Estimated largest impact speed (m/s): 2 v_jar + sqrt(2 g H)."""
    g = float(np.linalg.norm(cfg.dem.gravity))
    return 2 * peak_jar_speed + math.sqrt(2 * g * max(cfg.jar.height, 0.0))


def check_fill(cfg: Config) -> float:
    """Solid fraction of the balls in the cavity; ConfigError above :data:`RSA_FILL_LIMIT`."""
    if cfg.jar.kind != "emax":
        return float("nan")  # an STL cavity's volume needs the mesh; placement will say
    volume = float(jar_volume(jar_params_from_config(cfg.jar)))
    fraction = cfg.balls.solid_volume / volume
    if fraction > RSA_FILL_LIMIT:
        if cfg.balls.single_class:
            most = int(RSA_FILL_LIMIT * volume / (4.0 / 3.0 * math.pi * cfg.balls.radius**3))
            what = (f"[balls] count = {cfg.balls.count} balls of radius {cfg.balls.radius:g} m "
                    f"fill")
            remedy = f"(here about {most} balls): use count <= {most}, smaller"
        else:
            what = f"the {cfg.balls.n_balls} balls of [balls] and [[balls.mix]] fill"
            remedy = "of the cavity: use fewer or smaller"
        raise ConfigError(
            f"{what} {fraction:.0%} of the jar's {volume * 1e6:.1f} ml; random insertion places "
            f"at most {RSA_FILL_LIMIT:.0%} {remedy} balls or a larger jar")
    return fraction


def check_resolution(cfg: Config) -> None:
    """ConfigError when a ball is too small for the jar's SDF grid: an STL jar is read from a
    grid of ``[sdf] spacing``, and a ball's contact with it is only as accurate as the grid
    is fine against the ball (at least :data:`GRID_POINTS_PER_RADIUS` spacings per radius).
    The parametric jar's walls are exact, but the surrogate's features sample the same grid,
    so the rule holds for every jar."""
    smallest = min(c.radius for c in cfg.balls.classes)
    if smallest < GRID_POINTS_PER_RADIUS * cfg.sdf.spacing:
        raise ConfigError(
            f"a ball radius of {smallest:g} m is below {GRID_POINTS_PER_RADIUS} [sdf] spacings "
            f"({cfg.sdf.spacing:g} m): the jar's SDF grid cannot resolve it; use [sdf] spacing "
            f"<= {smallest / GRID_POINTS_PER_RADIUS:.3g} m or larger balls")


GRID_POINTS_PER_RADIUS = 4
"""A ball's radius spans at least this many SDF grid spacings (the standard 5 mm ball: 10)."""


def check_motion(cfg: Config) -> list[str]:
    """ConfigError if the DEM cannot resolve the contacts this motion drives; a list of
    warnings (strings) when it lies beyond the validated DEM envelope."""
    peaks = motion_peaks(cfg.motion)
    v_impact = impact_speed(cfg, peaks.speed)
    v_max, rule = max_resolved_impact_speed(cfg)
    if not math.isfinite(peaks.speed) or v_impact > v_max:
        g = float(np.linalg.norm(cfg.dem.gravity))
        jar_max = max((v_max - math.sqrt(2 * g * cfg.jar.height)) / 2, 0.0)
        m = cfg.motion
        if m.kind == "circle" and m.amplitude > 0:
            allowed = (f"at amplitude {m.amplitude:g} m, rpm <= "
                       f"{jar_max / (2 * math.pi * m.amplitude) * 60:.4g}")
        else:
            allowed = (f"scale the displacement by <= {jar_max / peaks.speed:.3g}"
                       if peaks.speed > 0 else "a slower motion")
        remedy = (", or a smaller [dem] dt_dem_max" if "DEM steps" in rule
                  else ", or stiffer balls ([material] young)")
        raise ConfigError(
            f"[motion] {_describe_motion(cfg.motion)} drives the jar at up to "
            f"{peaks.speed:.4g} m/s (peak acceleration {peaks.acceleration:.3g} m/s^2): balls "
            f"would hit the wall at about {v_impact:.4g} m/s, but {rule} only up to "
            f"{v_max:.4g} m/s, so the DEM cannot represent this motion. Allowed: peak jar speed "
            f"<= {jar_max:.4g} m/s ({allowed}){remedy}")
    notes = []
    if peaks.speed > DEM_VALIDATED_PEAK_SPEED:
        notes.append(
            f"[motion] peak jar speed {peaks.speed:.3g} m/s is beyond the DEM's validated "
            f"range (<= {DEM_VALIDATED_PEAK_SPEED} m/s: 2000 rpm at 17 mm, docs/dem.md); the run "
            "checks itself for escapes and unresolved contacts")
    return notes


def _describe_motion(m: Any) -> str:
    if m.kind == "circle":
        return f"circle rpm = {m.rpm:g}, amplitude = {m.amplitude:g} m"
    if m.kind == "harmonic":
        return f"harmonic base_frequency_hz = {m.base_frequency_hz:g}"
    return f"spline period = {m.period:g} s"


def check_dem_config(cfg: Config, *, warn: bool = True, step_given: bool = False
                     ) -> list[str]:
    """All physical checks of a DEM run of ``cfg`` (raises ConfigError); returns the
    envelope notes, also issued as :class:`EnvelopeWarning` when ``warn``. The contacts are
    checked at the step the run takes: the charge's (:func:`with_charge_step`), or ``[dem]
    dt_dem_max`` as it is when ``step_given`` (a step chosen on purpose)."""
    check_fill(cfg)
    check_resolution(cfg)
    notes = check_motion(cfg if step_given else with_charge_step(cfg))
    if warn:
        for note in notes:
            warnings.warn(note, EnvelopeWarning, stacklevel=2)
    return notes


# --------------------------------------------------------------------------------------------
# The surrogate's envelope


@dataclass(frozen=True)
class ModelEnvelope:
    """The motions and jars a trained model promises to cover.

    ``circle_rpm`` / ``circle_amplitude`` (min, max) for circles, ``harmonic_base_hz`` and
    ``harmonic_max_axis_amplitude`` (m, per axis the sum of the harmonics' amplitudes) for
    harmonic orbits
    (None: that kind is not covered); ``jar``: the (radius, straight_length, height,
    post_radius) of the trained jar, or None for any jar. ``motion``: the full
    :class:`sgn_jax.records.envelope.MotionEnvelope` when the model states one (then its motion
    checks are :func:`sgn_jax.records.envelope.envelope_notes`, per-harmonic limits included).
    ``charge``: the one charge the model was trained on, ``{"[balls] count": 24, ...}`` (the
    ball count, radius and density, the material's restitution, friction and rolling
    friction), or None for any charge. ``charges``: the charge envelope of a model that reads
    the charge, or None; such a model covers every charge inside it, on the motions above and
    on the charge envelope's own circles (``charges.rpm`` at ``charges.amplitude``).
    """

    circle_rpm: tuple[float, float] | None = None
    circle_amplitude: tuple[float, float] | None = None
    harmonic_base_hz: tuple[float, float] | None = None
    harmonic_max_axis_amplitude: float | None = None
    jar: tuple[float, float, float, float] | None = None
    source: str = ""
    motion: MotionEnvelope | None = None
    charge: dict[str, float] | None = None
    charges: ChargeEnvelope | None = None


def charge_key(cfg: Config) -> dict[str, float]:
    """The charge of a one-class config as the values a model trained on it knows: ball count,
    radius and density, and its material's restitution, friction and rolling friction."""
    material = cfg.material_named(cfg.balls.material)
    return {"[balls] count": float(cfg.balls.count), "[balls] radius (m)": cfg.balls.radius,
            "[balls] density (kg/m^3)": cfg.balls.density,
            "[material] restitution": material.restitution,
            "[material] friction": material.friction,
            "[material] rolling_friction": material.rolling_friction}


@functools.cache
def recipe_charge_envelope() -> dict[str, Any]:
    """The ``envelope`` meta of the charge model's training recipe (experiments/charges/
    train.sh): the shipped motion envelope and the shipped charge envelope. Not to be mutated
    (cached)."""
    return charge_model_envelope(load_envelope(), load_charge_envelope())


def model_envelope(model_config: Config, meta: dict[str, Any] | None = None) -> ModelEnvelope:
    """The envelope a model states in its checkpoint meta (key ``envelope``), or else the one
    point it was trained at: its training config's motion (within 1 %) and jar. Its charge is
    the training config's, except for a kind that reads the charge (``model_takes_charge``:
    it covers the charge envelope its meta states under ``envelope.charge``) or an envelope
    that states ``any_charge``. A kind that reads the charge and states no envelope (trained
    before its checkpoints stated one) covers its training recipe's,
    :func:`recipe_charge_envelope`."""
    jar = model_config.jar
    takes_charge = model_takes_charge(model_config)
    charge = None if takes_charge else charge_key(model_config)
    jar_key = (jar.radius, jar.straight_length, jar.height, jar.post_radius)
    stated = (meta or {}).get("envelope")
    source = "the model's stated envelope"
    if not stated and takes_charge:
        stated = recipe_charge_envelope()
        source = ("the envelope of the charge model's training recipe "
                  "(docs/contact_charge.md; its checkpoint states none)")
    if stated:
        def pair(key):
            return tuple(stated[key]) if stated.get(key) is not None else None

        return ModelEnvelope(circle_rpm=pair("circle_rpm"),
                             circle_amplitude=pair("circle_amplitude"),
                             harmonic_base_hz=pair("harmonic_base_hz"),
                             harmonic_max_axis_amplitude=stated.get("harmonic_max_axis_amplitude"),
                             jar=None if stated.get("any_jar") else jar_key,
                             source=source,
                             motion=MotionEnvelope.from_meta(stated),
                             charge=None if stated.get("any_charge") else charge,
                             charges=(ChargeEnvelope.from_meta(stated.get("charge"))
                                      if takes_charge else None))
    m = model_config.motion
    if m.kind == "circle":
        return ModelEnvelope(circle_rpm=(m.rpm * 0.99, m.rpm * 1.01),
                             circle_amplitude=(m.amplitude * 0.99, m.amplitude * 1.01),
                             jar=jar_key, source="the single motion the model was trained on",
                             charge=charge)
    return ModelEnvelope(jar=jar_key, source="the single motion the model was trained on",
                         charge=charge)


def _axis_amplitudes(m: Any) -> list[float]:
    """Per axis, the sum over harmonics of each harmonic's amplitude hypot(sin, cos) (m)."""
    return [sum(amps) for amps in harmonic_axis_amplitudes(m).values()]


def _motion_notes(m: Any, envelope: ModelEnvelope) -> list[str]:
    """Why the motion ``m`` lies outside ``envelope``'s motions (empty list: inside)."""
    notes: list[str] = []

    def outside(value, bounds, what):
        if bounds is None:
            notes.append(f"{what} = {value:g}: the model covers no {m.kind} motion")
        elif not bounds[0] <= value <= bounds[1]:
            notes.append(f"{what} = {value:g} is outside the model's range "
                         f"[{bounds[0]:g}, {bounds[1]:g}]")

    if envelope.motion is not None:
        notes.extend(motion_envelope_notes(m, envelope.motion))
    elif m.kind == "circle":
        outside(m.rpm, envelope.circle_rpm, "[motion] rpm")
        if envelope.circle_rpm is not None:
            outside(m.amplitude, envelope.circle_amplitude, "[motion] amplitude (m)")
    elif m.kind == "harmonic":
        outside(m.base_frequency_hz, envelope.harmonic_base_hz, "[motion] base_frequency_hz")
        limit = envelope.harmonic_max_axis_amplitude
        if envelope.harmonic_base_hz is not None and limit is not None:
            worst = max(_axis_amplitudes(m))
            if worst > limit * (1 + 1e-9):
                notes.append(f"[motion] harmonic amplitude per axis {worst:g} m exceeds the "
                             f"model's {limit:g} m")
    else:
        notes.append(f"[motion] kind = {m.kind!r}: the model covers no {m.kind} motion")
    return notes


def envelope_notes(cfg: Config, envelope: ModelEnvelope) -> list[str]:
    """Why ``cfg``'s motion, jar and charge lie outside ``envelope`` (empty list: inside). A
    motion is inside when it lies in the envelope's motions or, for a model with a charge
    envelope, on that envelope's circles; outside both, the notes name both ranges."""
    notes = _motion_notes(cfg.motion, envelope)
    if envelope.charges is not None:
        circle = charge_circle_notes(cfg.motion, envelope.charges)
        if not circle:
            notes = []
        elif (envelope.motion is None and envelope.circle_rpm is None
              and envelope.harmonic_base_hz is None):   # the charge envelope's circles only
            notes = circle
        elif notes:
            notes = notes + circle
    if envelope.jar is not None:
        j = cfg.jar
        key = (j.radius, j.straight_length, j.height, j.post_radius)
        if cfg.jar.kind != "emax" or not np.allclose(key, envelope.jar, rtol=1e-6, atol=1e-9):
            notes.append(f"[jar] {key} (radius, straight_length, height, post_radius, m) differs "
                         f"from the trained jar {envelope.jar}")
    if envelope.charge is not None and cfg.balls.single_class:
        for what, value in charge_key(cfg).items():
            trained = envelope.charge[what]
            if not math.isclose(value, trained, rel_tol=1e-6):
                notes.append(f"{what} = {value:g} differs from the model's charge ({trained:g}): "
                             "it was trained on one charge (docs/charge.md)")
    if envelope.charges is not None:
        volume = (float(jar_volume(jar_params_from_config(cfg.jar))) if cfg.jar.kind == "emax"
                  else None)   # an STL cavity's volume needs its mesh (its jar note is above)
        notes.extend(charge_envelope_notes(cfg, envelope.charges, volume))
    if notes:
        notes.append(f"the model's envelope is {envelope.source}; outside it its powers and "
                     "gradients are extrapolations (docs/validation.md)")
    return notes


def warn_outside_envelope(cfg: Config, model_config: Config, meta: dict[str, Any] | None = None
                          ) -> list[str]:
    """Issue an :class:`EnvelopeWarning` per note of :func:`envelope_notes`; returns them."""
    notes = envelope_notes(cfg, model_envelope(model_config, meta))
    for note in notes:
        warnings.warn(f"outside the surrogate's envelope: {note}", EnvelopeWarning, stacklevel=2)
    return notes


__all__ = [
    "DEM_VALIDATED_PEAK_SPEED",
    "MAX_OVERLAP_FRACTION",
    "MIN_CONTACT_STEPS",
    "ModelEnvelope",
    "MotionPeaks",
    "RSA_FILL_LIMIT",
    "check_count",
    "check_dem_config",
    "check_duration",
    "check_fill",
    "check_motion",
    "envelope_notes",
    "hertz_peak_overlap",
    "impact_speed",
    "max_resolved_impact_speed",
    "model_envelope",
    "motion_peaks",
    "recipe_charge_envelope",
    "warn_outside_envelope",
]
