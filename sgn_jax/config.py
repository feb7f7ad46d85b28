"""Typed, frozen experiment configuration loaded from TOML.

A config file has one table per section (``[case]``, ``[jar]``, ``[motion]``, ``[balls]``,
``[material]``, ``[dem]``, ``[sdf]``, and optionally ``[model]``, ``[train]``, ``[rollout]``).
Rules, chosen so that every number in an artifact can be traced to a file:

- an unknown key (a typo) is an error that names it and lists the allowed keys;
- a key without a default in the dataclass below is required, and its absence is an error
  that names it;
- the resolved config is saved next to every artifact (``save_config``), so defaults that
  were filled in are written out explicitly.

All values are SI units (m, s, kg, Pa) unless the field name says otherwise (``rpm``).
"""

from __future__ import annotations

import dataclasses
import math
import re
import tomllib
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from sgn_jax.errors import SGNJaxError
from sgn_jax.records.io_utils import atomic_write


class ConfigError(SGNJaxError, ValueError):
    """A config file or dict is malformed: unknown key, missing key or wrong type."""


@dataclass(frozen=True)
class CaseConfig:
    """Identification of the case.

    Attributes:
        name: short name of the case, written into artifacts, summaries and logs.
        description: free-text description of the case (optional).
    """

    name: str
    description: str = ""


@dataclass(frozen=True)
class JarConfig:
    """The milling jar.

    ``kind = "emax"``: the parametric Emax-like stadium cavity of docs/conventions.md section 2
    (semicircles of ``radius`` centred at x = +-straight_length/2, height ``height``, optional solid
    central post of radius ``post_radius``; 0 means no post). ``kind = "stl"``: a closed mesh of the
    cavity read from ``stl_path`` in ``stl_units`` ("m" or "mm"), jar-frame coordinates (floor
    centre at the origin, y up).

    Attributes:
        kind: "emax" (the parametric stadium cavity) or "stl" (a closed cavity mesh from a file).
        radius: m, radius of the stadium's semicircular ends (kind "emax").
        straight_length: m, distance between the semicircle centres along x (kind "emax").
        height: m, inner height from the floor (y = 0) to the lid (kind "emax").
        post_radius: m, radius of the solid central post on the y axis, 0 = no post (kind "emax").
        stl_path: path of the cavity STL, relative to the working directory (kind "stl").
        stl_units: length unit of the STL coordinates, "m" or "mm" (kind "stl").
    """

    kind: str
    radius: float = 0.020
    straight_length: float = 0.035
    height: float = 0.047
    post_radius: float = 0.0
    stl_path: str = ""
    stl_units: str = "m"

    def __post_init__(self) -> None:
        if self.kind not in ("emax", "stl"):
            raise ConfigError(f"[jar] kind must be 'emax' or 'stl', got {self.kind!r}")
        if self.kind == "stl" and not self.stl_path:
            raise ConfigError("[jar] kind = 'stl' needs stl_path = 'path/to/jar.stl'")
        if self.stl_units not in ("m", "mm"):
            raise ConfigError(f"[jar] stl_units must be 'm' or 'mm', got {self.stl_units!r}")
        if self.kind == "emax":
            for name in ("radius", "straight_length", "height"):
                if getattr(self, name) <= 0:
                    raise ConfigError(f"[jar] {name} must be > 0, got {getattr(self, name)}")
            if not 0 <= self.post_radius < self.radius:
                raise ConfigError(
                    f"[jar] post_radius must be in [0, radius), got {self.post_radius}"
                )


MOTION_KINDS = ("circle", "harmonic", "spline")


@dataclass(frozen=True)
class MotionConfig:
    """Jar motion (translation in the x-z plane, y allowed for generality).

    - ``circle``: offset = (A sin(2 pi f t + phase), 0, A cos(2 pi f t + phase)), f = rpm / 60.
      Keys: rpm, amplitude, phase.
    - ``harmonic``: each axis a sum over k = 1..K of ``{axis}_sin[k-1] sin(2 pi k f0 t) +
      {axis}_cos[k-1] cos(2 pi k f0 t)`` with f0 = ``base_frequency_hz``; coefficients in m.
      Motion 1 and Motion 2 of docs/conventions.md section 2 are harmonic series.
    - ``spline``: a periodic cubic spline through ``points`` (M x 3, m) sampled uniformly over
      ``period`` seconds, points[0] at t = 0.

    Attributes:
        kind: "circle", "harmonic" or "spline"; a key of another kind is an error.
        rpm: rev/min, rotation speed of the circle, f = rpm / 60 (circle).
        amplitude: m, radius A of the circular jar path (circle).
        phase: rad, phase at t = 0; 0 puts the jar at (0, 0, A) (circle).
        base_frequency_hz: Hz, fundamental frequency f0 of the harmonic series (harmonic).
        x_sin: m, sine coefficients of the x offset for harmonics k = 1..K (harmonic).
        x_cos: m, cosine coefficients of the x offset for harmonics k = 1..K (harmonic).
        y_sin: m, sine coefficients of the y offset for harmonics k = 1..K (harmonic).
        y_cos: m, cosine coefficients of the y offset for harmonics k = 1..K (harmonic).
        z_sin: m, sine coefficients of the z offset for harmonics k = 1..K (harmonic).
        z_cos: m, cosine coefficients of the z offset for harmonics k = 1..K (harmonic).
        period: s, duration of one loop through the spline points (spline).
        points: m, at least 4 offsets [x, y, z] of the periodic spline, points[0] at t = 0 (spline).
    """

    kind: str
    rpm: float = 300.0
    amplitude: float = 0.017
    phase: float = 0.0
    base_frequency_hz: float = 5.0
    x_sin: tuple[float, ...] = ()
    x_cos: tuple[float, ...] = ()
    y_sin: tuple[float, ...] = ()
    y_cos: tuple[float, ...] = ()
    z_sin: tuple[float, ...] = ()
    z_cos: tuple[float, ...] = ()
    period: float = 0.2
    points: tuple[tuple[float, float, float], ...] = ()

    _KEYS_BY_KIND = {
        "circle": {"rpm", "amplitude", "phase"},
        "harmonic": {"base_frequency_hz", "x_sin", "x_cos", "y_sin", "y_cos", "z_sin", "z_cos"},
        "spline": {"period", "points"},
    }

    def __post_init__(self) -> None:
        if self.kind not in MOTION_KINDS:
            raise ConfigError(f"[motion] kind must be one of {MOTION_KINDS}, got {self.kind!r}")
        if self.kind == "circle":
            if not (math.isfinite(self.rpm) and self.rpm > 0):
                raise ConfigError(
                    f"[motion] rpm must be a finite number > 0, got {self.rpm} (the circle's "
                    "sense is fixed: x = A sin, z = A cos; a harmonic motion gives the other)")
            if not (math.isfinite(self.amplitude) and self.amplitude >= 0):
                raise ConfigError(f"[motion] amplitude must be a finite length >= 0 (m), got "
                                  f"{self.amplitude}")
        if self.kind == "harmonic" and not (math.isfinite(self.base_frequency_hz)
                                            and self.base_frequency_hz > 0):
            raise ConfigError(f"[motion] base_frequency_hz must be a finite number > 0, got "
                              f"{self.base_frequency_hz}")
        if self.kind == "harmonic":
            lengths = {len(getattr(self, a)) for a in ("x_sin", "x_cos", "y_sin", "y_cos",
                                                       "z_sin", "z_cos")} - {0}
            if len(lengths) > 1:
                raise ConfigError(
                    "[motion] harmonic coefficient lists must have the same length "
                    f"(or be empty), got lengths {sorted(lengths)}"
                )
            if not lengths:
                raise ConfigError("[motion] kind = 'harmonic' needs at least one of x_sin, "
                                  "x_cos, y_sin, y_cos, z_sin, z_cos")
        if self.kind == "spline":
            if len(self.points) < 4 or any(len(p) != 3 for p in self.points):
                raise ConfigError("[motion] kind = 'spline' needs points = [[x, y, z], ...] with "
                                  "at least 4 points of 3 coordinates each")
            if self.period <= 0:
                raise ConfigError(f"[motion] period must be > 0, got {self.period}")

    @classmethod
    def check_keys_for_kind(cls, kind: str, keys: set[str]) -> None:
        """Reject keys that belong to another motion kind (they would be silently ignored)."""
        allowed = cls._KEYS_BY_KIND.get(kind, set()) | {"kind"}
        foreign = sorted(keys - allowed)
        if foreign:
            raise ConfigError(
                f"[motion] key(s) {foreign} are not used by motion kind {kind!r}; "
                f"allowed keys for this kind: {sorted(allowed)}"
            )


@dataclass(frozen=True)
class BallClassConfig:
    """A further ball class of a mixed charge (``[[balls.mix]]``, docs/charge.md).

    Attributes:
        count: number of balls of this class (>= 1).
        radius: m, their radius.
        density: kg/m^3, their density.
        material: name of their material ("" = the ``[material]`` section's, the jar's).
    """

    count: int
    radius: float
    density: float
    material: str = ""

    def __post_init__(self) -> None:
        _check_ball_class("[[balls.mix]]", self.count, self.radius, self.density)


def _check_ball_class(where: str, count: int, radius: float, density: float) -> None:
    if count < 1:
        raise ConfigError(f"{where} count must be >= 1, got {count}")
    if not (radius > 0 and density > 0):
        raise ConfigError(f"{where} radius and density must be > 0 (m, kg/m^3), got radius = "
                          f"{radius}, density = {density}")


@dataclass(frozen=True)
class BallsConfig:
    """The grinding balls: one class, or several (a mixed charge, docs/charge.md).

    Attributes:
        count: number of balls of the first class (>= 1).
        radius: m, their radius.
        density: kg/m^3, their density.
        material: name of their material ("" = the ``[material]`` section's, the jar's).
        mix: further ball classes (``[[balls.mix]]`` tables), each its own count, radius,
            density and material; the balls are numbered class by class.
    """

    count: int
    radius: float
    density: float
    material: str = ""
    mix: tuple[BallClassConfig, ...] = ()

    def __post_init__(self) -> None:
        _check_ball_class("[balls]", self.count, self.radius, self.density)

    @property
    def classes(self) -> tuple[BallClassConfig, ...]:
        """Every ball class, the ``[balls]`` one first."""
        first = BallClassConfig(count=self.count, radius=self.radius, density=self.density,
                                material=self.material)
        return (first, *self.mix)

    @property
    def n_balls(self) -> int:
        """N, the number of balls of all classes."""
        return self.count + sum(c.count for c in self.mix)

    @property
    def single_class(self) -> bool:
        """One ball class (one size, density and material)."""
        return not self.mix

    @property
    def solid_volume(self) -> float:
        """m^3, the volume of all balls of all classes."""
        return sum(c.count * 4.0 / 3.0 * math.pi * c.radius**3 for c in self.classes)

    @property
    def mass(self) -> float:
        """kg, the mass of all balls of all classes."""
        return sum(c.count * 4.0 / 3.0 * math.pi * c.radius**3 * c.density for c in self.classes)


@dataclass(frozen=True)
class MaterialConfig:
    """A contact material (docs/charge.md). ``[material]`` is the jar's and the default ball
    material; ``[[materials]]`` tables add ball materials. Restitution, friction and rolling
    friction are those of a contact of the material with itself; two materials meet through
    ``[[interactions]]`` or, where none is given, the mean of their values.

    Attributes:
        name: the name ``[balls] material`` and ``[[interactions]]`` refer to it by.
        young: Pa, Young's modulus (Hertz-Mindlin stiffness).
        poisson: Poisson's ratio, dimensionless, in (-1, 0.5).
        restitution: coefficient of normal restitution, in (0, 1] (sets the contact damping).
        friction: Coulomb sliding friction coefficient, dimensionless.
        rolling_friction: rolling friction coefficient mu_r (EDEM type A), dimensionless.
    """

    young: float
    poisson: float
    restitution: float
    friction: float
    rolling_friction: float
    name: str = "steel"

    def __post_init__(self) -> None:
        if not self.name:
            raise ConfigError("[material] / [[materials]] name must not be empty")
        where = f"material {self.name!r}"
        if not 0 < self.restitution <= 1:
            raise ConfigError(f"{where}: restitution must be in (0, 1], got {self.restitution}")
        if self.young <= 0:
            raise ConfigError(f"{where}: young must be > 0, got {self.young}")
        if not -1 < self.poisson < 0.5:
            raise ConfigError(f"{where}: poisson must be in (-1, 0.5), got {self.poisson}")
        if self.friction < 0 or self.rolling_friction < 0:
            raise ConfigError(f"{where}: friction and rolling_friction must be >= 0")


NEIGHBOUR_SEARCHES = ("auto", "all_pairs", "cells")


@dataclass(frozen=True)
class InteractionConfig:
    """The restitution, friction and rolling friction of contacts between two named materials
    (``[[interactions]]``; pairs not listed take the mean of the two materials' values).

    Attributes:
        materials: the two material names (a material with itself: the name twice).
        restitution: coefficient of normal restitution, in (0, 1].
        friction: Coulomb coefficient (>= 0).
        rolling_friction: rolling friction coefficient (>= 0).
    """

    materials: tuple[str, str]
    restitution: float
    friction: float
    rolling_friction: float

    def __post_init__(self) -> None:
        if not 0 < self.restitution <= 1:
            raise ConfigError(f"[[interactions]] {list(self.materials)}: restitution must be in "
                              f"(0, 1], got {self.restitution}")
        if self.friction < 0 or self.rolling_friction < 0:
            raise ConfigError(f"[[interactions]] {list(self.materials)}: friction and "
                              "rolling_friction must be >= 0")


@dataclass(frozen=True)
class DEMConfig:
    """DEM solver settings.

    ``dt`` is the sampling step (s); the solver step is ``dt / k`` with the smallest integer k such
    that ``dt / k <= dt_dem_max`` (docs/conventions.md section 2), so that every sample falls on a
    step.

    Attributes:
        dt: s, sampling step of the DEM trajectory, also the surrogate's time step.
        dt_dem_max: s, upper bound of the DEM solver step (the step is dt / k).
        settle_time: s, settling with the jar at rest at offset(0) before t = 0.
        duration: s, motion simulated after settling (``sgn-jax dem --duration`` overrides it).
        seed: seed of the random initial placement of the balls.
        dtype: "float64" or "float32" for positions, velocities and forces (ledger always float64).
        clip_attractive: clip the normal contact force at zero (off by default;
            docs/conventions.md section 3).
        gravity: m/s^2, gravity vector [x, y, z] in the lab frame (y up).
        chunk_samples: samples per jitted DEM chunk, also the resume checkpoint interval.
        pp_capacity: slots for touching ball pairs recorded per sample (pp_pairs), 0 = 3 * count.
        neighbour_capacity: Verlet list capacity in pairs per ball (ceil(capacity * N / 2) pairs).
        neighbour_skin: m, surface gap within which a ball pair enters the Verlet list.
        neighbour_search: how the Verlet list is rebuilt: "all_pairs" (tests all N(N-1)/2
            pairs), "cells" (a cell list, cost growing with N) or "auto" (cells from 500
            balls, where the cell list becomes the faster; docs/charge.md). Both give the same
            list, so the same run.
        contact_law: name of the contact law (sgn_jax.dem.laws registry); "hertz_mindlin" is
            the validated default, other laws are registered by code (docs/dem.md).
        kick_speed: m/s; 0 (the default): the motion starts from the settled bed at rest. > 0:
            at t = 0 every ball gets a random velocity on top of the settled bed (direction
            uniform, magnitude uniform in [0, kick_speed], from the placement seed): isolated
            impacts at known speeds, training data for contact models (docs/contact.md).
        collisions: keep the collision ledger (docs/collisions.md): every contact from first
            touch to separation as one event, written with the trajectory record as
            ``collision_*`` arrays (it makes the DEM 14-15 % slower; false leaves it out).
        collision_capacity: events the ledger's buffer holds per chunk of ``chunk_samples``
            samples; 0 (the default) sizes it from the chunk's duration and the ball count
            (1,000 events per ball per second, at least 4,096). More events in a chunk stop
            the run with an error saying to raise it.
    """

    dt: float = 1e-4
    dt_dem_max: float = 9.5e-7
    settle_time: float = 0.5
    duration: float = 10.0
    seed: int = 0
    dtype: str = "float64"
    clip_attractive: bool = False
    gravity: tuple[float, float, float] = (0.0, -9.81, 0.0)
    chunk_samples: int = 1000
    pp_capacity: int = 0
    # Verlet list of the DEM (sgn_jax.dem): pairs per ball it can hold, and its skin (m).
    neighbour_capacity: int = 8
    neighbour_skin: float = 0.001
    neighbour_search: str = "auto"
    # Contact law by registry name (sgn_jax.dem.laws); checked when the DEM is set up.
    contact_law: str = "hertz_mindlin"
    kick_speed: float = 0.0
    collisions: bool = True
    collision_capacity: int = 0

    def __post_init__(self) -> None:
        if not self.kick_speed >= 0:
            raise ConfigError(f"[dem] kick_speed must be >= 0 m/s, got {self.kick_speed}")
        if not isinstance(self.contact_law, str) or not self.contact_law:
            raise ConfigError("[dem] contact_law must be the name of a registered contact law, "
                              f"got {self.contact_law!r}")
        if self.neighbour_capacity < 1 or self.neighbour_skin < 0:
            raise ConfigError("[dem] neighbour_capacity must be >= 1 and neighbour_skin >= 0")
        if self.neighbour_search not in NEIGHBOUR_SEARCHES:
            raise ConfigError(f"[dem] neighbour_search must be one of {list(NEIGHBOUR_SEARCHES)}, "
                              f"got {self.neighbour_search!r}")
        if self.collision_capacity < 0:
            raise ConfigError(f"[dem] collision_capacity must be >= 0 (0: sized from the chunk), "
                              f"got {self.collision_capacity}")
        if self.dtype not in ("float64", "float32"):
            raise ConfigError(f"[dem] dtype must be 'float64' or 'float32', got {self.dtype!r}")
        if self.dt <= 0 or self.dt_dem_max <= 0:
            raise ConfigError("[dem] dt and dt_dem_max must be > 0")
        if self.settle_time < 0 or self.duration < 0:
            raise ConfigError("[dem] settle_time and duration must be >= 0")
        if len(self.gravity) != 3:
            raise ConfigError("[dem] gravity must have 3 components")

    @property
    def substeps(self) -> int:
        """Number of DEM steps per sample: the smallest k with dt / k <= dt_dem_max."""
        import math

        k = math.ceil(self.dt / self.dt_dem_max - 1e-9)
        return max(k, 1)

    @property
    def dt_dem(self) -> float:
        return self.dt / self.substeps


@dataclass(frozen=True)
class SDFConfig:
    """SDF grid sampling for the surrogate (spacing no coarser than 0.5 mm by default).

    Attributes:
        spacing: m, distance between grid nodes along each axis.
        margin: m, the grid box is the cavity's bounding box grown by this on every side.
    """

    spacing: float = 0.0005
    margin: float = 0.003

    def __post_init__(self) -> None:
        if self.spacing <= 0 or self.margin < 0:
            raise ConfigError("[sdf] spacing must be > 0 and margin >= 0")


@dataclass(frozen=True)
class GraphConfig:
    """The SGN graph featurizer (docs/conventions.md section 5, paper Table 3).

    ``window`` slots of [v, phi, grad phi] per particle (a window needs window + 1 positions);
    ball-ball edges where the centre distance is <= 2 R + ``pp_skin`` (a surface gap, m);
    ball-wall edges where phi >= ``phi_pw`` (m); rollout snap-back where phi >= ``phi_sb``.
    ``pp_edges_per_particle``: the static capacity of directed ball-ball edges per graph is this
    times the number of balls (an overflow is counted and reported, never silently dropped).

    Attributes:
        window: velocity slots [v, phi, grad phi] per ball in the node features (>= 1).
        pp_skin: m, surface gap: a ball-ball edge where centre distance <= 2 R + pp_skin.
        phi_pw: m, a ball-wall edge where the ball centre's phi >= phi_pw.
        phi_sb: m, rollout snap-back threshold, phi_pw < phi_sb < 0.
        pp_edges_per_particle: static directed ball-ball edge slots per graph, per ball.
        contact_features: two more edge columns, the surface gap and the overlap of the two
            balls (or of ball and wall), so the network sees a contact coming (docs/sgn.md).
            Off: the paper's 3 columns (displacement, phi n).
        wall_patches: 0 (the paper): one ball-wall edge per ball, to the nearest wall; P > 0:
            one ball-wall edge per ball and wall patch (floor, lid, side, post), at most P
            patches, as the DEM has one contact per ball and patch (the contact model; a ball
            in the corner of floor and side wall feels both walls).
    """

    window: int = 7
    pp_skin: float = 1.5e-3
    phi_pw: float = -0.0052
    phi_sb: float = -0.0049
    pp_edges_per_particle: int = 8
    contact_features: bool = False
    wall_patches: int = 0

    def __post_init__(self) -> None:
        if not 0 <= self.wall_patches <= 8:
            raise ConfigError(f"[graph] wall_patches must be 0 (nearest wall) or the number of "
                              f"wall patches (1..8), got {self.wall_patches}")
        if self.window < 1:
            raise ConfigError(f"[graph] window must be >= 1, got {self.window}")
        if self.pp_skin < 0:
            raise ConfigError(f"[graph] pp_skin must be >= 0 (a surface gap, m), got {self.pp_skin}")
        if not self.phi_pw < self.phi_sb < 0:
            raise ConfigError(
                f"[graph] need phi_pw < phi_sb < 0 (m), got phi_pw={self.phi_pw}, "
                f"phi_sb={self.phi_sb}"
            )
        if self.pp_edges_per_particle < 1:
            raise ConfigError(
                f"[graph] pp_edges_per_particle must be >= 1, got {self.pp_edges_per_particle}"
            )


@dataclass(frozen=True)
class ModelConfig:
    """The SGN network (paper Table 3): MLPs of ``mlp_layers`` linear layers of width ``hidden``.

    ``velocity_encoding``: "absolute" (the paper: each slot's velocity, standardised per column)
    or "differences" (older slots enter as ``v_k - v_{k+1}``; same information, trains much
    faster; see docs/sgn.md and ``sgn_jax.surrogate.normalization.encode_velocities``).

    ``kind`` names the surrogate in the model registry
    (:func:`sgn_jax.surrogate.model.register_model`; the built-in kinds are "sgn", the paper's
    SGN, and "contact", the contact-impulse model of docs/contact.md); the other keys are its
    hyperparameters. A config of kind "contact" that sets a key the contact kind does not read
    (``interaction_layers``, ``velocity_encoding``: the SGN's) is refused, naming the key.

    Attributes:
        kind: registered surrogate kind ("sgn" or "contact"; others after
            sgn_jax.surrogate.model.register_model).
        hidden: width of the MLPs' hidden layers and of the node and edge embeddings.
        mlp_layers: linear layers per MLP (>= 2).
        interaction_layers: message-passing (interaction) layers (>= 1); kind "sgn" only.
        velocity_encoding: "absolute" (the paper) or "differences" (see above); kind "sgn" only.
        spin: the balls' angular velocities as rollout state (kind "contact" only; the SGN has
            no spin and refuses it).
        overlap_limit: m, kind "contact" only; 0 = off. The rigid limit of the contact law:
            each contact's normal impulse is at least the one that keeps its overlap at the end
            of the step (ballistically, as if it were the balls' only contact) within this
            depth (docs/contact.md, "One step", item 7); the SGN refuses a non-zero value.
        overlap_law_factor: kind "contact" only; 0 = off (needs overlap_limit > 0). The limit
            grows with the contact's approach speed as this factor times the DEM contact law's
            own deepest overlap at that speed (fast impacts go as deep as the DEM's, scaled).
        law_rebound: contact kinds only (needs overlap_law_factor > 0). A fresh impact (a
            contact whose gap was open within the model's window) ends with the contact law's
            rebound: once the law's contact time t_c(v) at its closing speed v has passed, the
            step ends with the pair separating at e v at least (docs/contact.md, "One step",
            item 7).
        law_rebound_exact: contact kinds only; "off", "wall", "all" or "fresh" (all but
            "off" need law_rebound): the law rebound is also the ceiling of a fresh impact's
            normal impulse, so the step ends with the pair separating at e v exactly (or as
            the overlap limit needs), not faster: at every fresh impact ("all") or at
            ball-wall ones ("wall"), where also a contact closed over the whole window (a
            ball resting on the wall) separates no faster than e times the largest closing
            speed the ball's contacts saw in the window; "fresh": as "all", and before its
            contact time a fresh impact separates no faster than e times the largest
            closing speed its balls' contacts saw in the window (no impact gives back more
            than its restitution leaves).
        overlap_sweeps: kind "contact" only; 0 = off (needs overlap_limit > 0). Jacobi sweeps
            of the limit over all contacts together after the impulses, so that a ball's other
            contacts cannot push it deeper than the limit into this one (a chain, a bed
            compressed by an impact; docs/contact.md, "One step", item 7).
        friction_sweeps: kind "contact" with spin only; 0 = off. Projected Jacobi sweeps of
            Coulomb sticking over all contacts together after the impulses, so that a packed
            bed holds as the DEM's does instead of creeping (docs/contact.md, "One step",
            item 8).
        friction_sweep_contacts: kind "contact_charge" only: which contacts the friction
            sweeps act on, "all" (default) or "wall" (ball-wall contacts only; each ball-ball
            contact keeps its learned stick, so balls that ride the wall side by side are not
            bound into one body; the shipped contact_charge's setting; docs/contact_charge.md,
            "Limits").
        rebound_sweeps: kind "contact_charge" only (needs law_rebound and overlap_sweeps):
            "off" (default), "all" or "free": the overlap sweeps also keep each impact past its
            contact time at its law's rebound, e v, with every ball's other contacts acting
            (a ball struck while it touches the wall or another ball), not only for the
            contact alone: every such impact ("all"), or the ball-ball impacts of balls that
            no contact closed over the window holds ("free", the shipped contact_charge's
            setting; docs/contact_charge.md, "Limits").
        damping_target: kind "contact" only: how the model's dissipation target (the DEM's
            damping, what `dE` and the power report) comes from its own losses: "kind" (a
            share of all losses per contact kind, fitted from the records) or "contact" (per
            contact: the normal losses whole, the tangential ones by the DEM's tangential
            damping share, rolling friction's none; the charge kind's rule; docs/contact.md,
            "The dissipation target").
    """

    kind: str = "sgn"
    hidden: int = 256
    mlp_layers: int = 4
    interaction_layers: int = 1
    velocity_encoding: str = "absolute"
    spin: bool = False
    overlap_limit: float = 0.0
    overlap_law_factor: float = 0.0
    law_rebound: bool = False
    law_rebound_exact: str = "off"
    overlap_sweeps: int = 0
    friction_sweeps: int = 0
    friction_sweep_contacts: str = "all"
    rebound_sweeps: str = "off"
    damping_target: str = "kind"

    # The keys a built-in kind reads, for a kind that does not read them all; a kind not listed
    # (the SGN, a registered kind) reads every key or refuses a value it cannot use itself.
    _KEYS_BY_KIND = {
        "contact": {"kind", "hidden", "mlp_layers", "spin", "overlap_limit",
                    "overlap_law_factor", "law_rebound", "law_rebound_exact", "overlap_sweeps",
                    "friction_sweeps", "damping_target"},
        "contact_charge": {"kind", "hidden", "mlp_layers", "spin", "overlap_limit",
                           "overlap_law_factor", "law_rebound", "law_rebound_exact",
                           "overlap_sweeps", "friction_sweeps", "friction_sweep_contacts",
                           "rebound_sweeps"},
    }

    def __post_init__(self) -> None:
        if self.kind == "contact" and self.interaction_layers != 1:
            raise ConfigError(f"[model] interaction_layers = {self.interaction_layers}: kind "
                              "'contact' has no message passing (one impulse per contact); the "
                              "key is the SGN's (kind 'sgn'): remove it")
        if not (self.overlap_limit >= 0 and self.overlap_law_factor >= 0):
            raise ConfigError(f"[model] overlap_limit (m; 0 = off) and overlap_law_factor must "
                              f"be >= 0, got {self.overlap_limit} and {self.overlap_law_factor}")
        if self.overlap_law_factor > 0 and self.overlap_limit <= 0:
            raise ConfigError("[model] overlap_law_factor needs overlap_limit > 0 (the limit of "
                              "a contact at rest, m), got overlap_limit = 0")
        if self.law_rebound and self.overlap_law_factor <= 0:
            raise ConfigError("[model] law_rebound = true needs overlap_law_factor > 0 (the "
                              "law's scale, from which its contact time follows), got "
                              f"overlap_law_factor = {self.overlap_law_factor}")
        if self.law_rebound_exact not in ("off", "wall", "all", "fresh"):
            raise ConfigError("[model] law_rebound_exact must be 'off', 'wall' (ball-wall "
                              "impacts), 'all' (every fresh impact past its contact time) or "
                              "'fresh' (every fresh impact, through it), got "
                              f"{self.law_rebound_exact!r}")
        if self.law_rebound_exact != "off" and not self.law_rebound:
            raise ConfigError(f"[model] law_rebound_exact = {self.law_rebound_exact!r} needs "
                              "law_rebound = true (the rebound it makes exact)")
        if self.overlap_sweeps < 0 or (self.overlap_sweeps > 0 and self.overlap_limit <= 0):
            raise ConfigError(f"[model] overlap_sweeps must be >= 0 and needs overlap_limit > 0 "
                              f"(m), got overlap_sweeps = {self.overlap_sweeps} and "
                              f"overlap_limit = {self.overlap_limit}")
        if self.friction_sweeps < 0 or (self.friction_sweeps > 0 and not self.spin):
            raise ConfigError(f"[model] friction_sweeps must be >= 0 and needs spin = true (the "
                              f"sweeps stop the contact point's slip, which turns the balls), "
                              f"got friction_sweeps = {self.friction_sweeps} and spin = "
                              f"{self.spin}")
        if self.friction_sweep_contacts not in ("all", "wall"):
            raise ConfigError("[model] friction_sweep_contacts must be 'all' (every acting "
                              "contact) or 'wall' (ball-wall contacts only), got "
                              f"{self.friction_sweep_contacts!r}")
        if self.rebound_sweeps not in ("off", "all", "free"):
            raise ConfigError("[model] rebound_sweeps must be 'off', 'all' (every impact past "
                              "its contact time) or 'free' (ball-ball impacts of balls held by "
                              f"no resting contact), got {self.rebound_sweeps!r}")
        if self.rebound_sweeps != "off" and not (self.law_rebound and self.overlap_sweeps > 0):
            raise ConfigError(f"[model] rebound_sweeps = {self.rebound_sweeps!r} needs "
                              "law_rebound = true and overlap_sweeps > 0 (the sweeps it joins), "
                              "got law_rebound = "
                              f"{self.law_rebound} and overlap_sweeps = {self.overlap_sweeps}")
        # Whether the kind is registered is checked where the model is built (the registry
        # lives in the core, sgn_jax.surrogate.model): a config naming a kind registered
        # later loads.
        if not self.kind or not self.kind.strip():
            raise ConfigError("[model] kind must be a non-empty string (default 'sgn')")
        if self.damping_target not in ("kind", "contact"):
            raise ConfigError("[model] damping_target must be 'kind' (a damping share of all "
                              "losses per contact kind) or 'contact' (per contact, from its "
                              f"normal and tangential losses), got {self.damping_target!r}")
        if self.velocity_encoding not in ("absolute", "differences"):
            raise ConfigError("[model] velocity_encoding must be 'absolute' or 'differences', "
                              f"got {self.velocity_encoding!r}")
        if self.hidden < 1 or self.mlp_layers < 2 or self.interaction_layers < 1:
            raise ConfigError(
                "[model] need hidden >= 1, mlp_layers >= 2 and interaction_layers >= 1, got "
                f"hidden={self.hidden}, mlp_layers={self.mlp_layers}, "
                f"interaction_layers={self.interaction_layers}"
            )

    @classmethod
    def keys_read_by(cls, kind: str) -> set[str] | None:
        """The [model] keys ``kind`` reads (None: all of them)."""
        return cls._KEYS_BY_KIND.get(kind)

    @classmethod
    def check_keys_for_kind(cls, kind: str, keys: set[str]) -> None:
        """Refuse [model] keys that ``kind`` does not read (they would be silently ignored)."""
        read = cls.keys_read_by(kind)
        unread = sorted(keys - read) if read is not None else []
        if unread:
            raise ConfigError(
                f"[model] key(s) {unread} are not read by model kind {kind!r} (they are the "
                f"SGN's, kind 'sgn'); remove them from [model]. Keys of kind {kind!r}: "
                f"{sorted(read)}")


@dataclass(frozen=True)
class TrainStage:
    """One stage of a staged training run of the contact-impulse surrogate ([[train.stages]]).

    ``sgn-jax train --config CFG --data DIR --out OUT`` runs the stages in order, each in
    ``OUT/<name>/``; a stage after the first starts from the previous stage's best checkpoint
    (warm start). The learning rate follows a cosine decay from ``lr_init`` to ``lr_final``
    over ``schedule_steps`` optimiser steps (0: over ``steps``), and the stage stops after
    ``steps`` steps, so a stage can end part-way down its schedule (docs/training.md).

    Attributes:
        name: the stage's directory under the run's output folder (letters, digits, _ and -).
        records: glob patterns of DEM records (.npz), relative to the --data directory; every
            pattern must match at least one file.
        steps: optimiser steps of the stage.
        schedule_steps: length of the cosine learning-rate schedule in steps (0 = steps;
            otherwise >= steps).
        unroll: model steps per training stretch (the loss is summed over them).
        pushforward: later steps of a stretch start from the model's own prediction (no
            gradient through the earlier steps) instead of the DEM's.
        lr_init: learning rate at the stage's first step.
        lr_final: learning rate at the end of the schedule (0 < lr_final <= lr_init).
        relative_floor: m/s, the floor of the per-ball velocity-change scale of the loss.
        spin_weight: weight of the spin error (R |w - w_DEM|) beside the velocity error.
        position_noise: m, std of the random-walk noise on the training positions (0 = off).
        batch_size: stretches per optimiser step.
        checkpoint_every: steps between checkpoints and log lines.
        init_from: a checkpoint the stage starts from instead of the previous stage's best (a
            shipped model's name such as "contact", a training run or a checkpoint directory;
            a fine-tuning stage); empty: the previous stage's best, the first from scratch.
    """

    name: str
    records: tuple[str, ...]
    steps: int
    unroll: int
    lr_init: float
    lr_final: float
    schedule_steps: int = 0
    pushforward: bool = False
    relative_floor: float = 1e-3
    spin_weight: float = 1.0
    position_noise: float = 0.0
    batch_size: int = 32
    checkpoint_every: int = 100
    init_from: str = ""

    def __post_init__(self) -> None:
        if not re.fullmatch(r"[A-Za-z0-9_-]+", self.name):
            raise ConfigError(f"[[train.stages]] name {self.name!r}: use letters, digits, _ "
                              "and - only (it names the stage's directory)")
        if not self.records:
            raise ConfigError(f"[[train.stages]] {self.name}: records needs at least one glob "
                              "pattern, e.g. records = [\"envelope/train_*.npz\"]")
        if self.steps < 1 or self.unroll < 1 or self.batch_size < 1 or self.checkpoint_every < 1:
            raise ConfigError(f"[[train.stages]] {self.name}: steps, unroll, batch_size and "
                              f"checkpoint_every must be >= 1, got {self.steps}, {self.unroll}, "
                              f"{self.batch_size}, {self.checkpoint_every}")
        if self.schedule_steps and self.schedule_steps < self.steps:
            raise ConfigError(f"[[train.stages]] {self.name}: schedule_steps "
                              f"{self.schedule_steps} < steps {self.steps}; use 0 (= steps) "
                              "or a longer schedule")
        if not 0 < self.lr_final <= self.lr_init:
            raise ConfigError(f"[[train.stages]] {self.name}: need 0 < lr_final <= lr_init, "
                              f"got {self.lr_final}, {self.lr_init}")
        if self.relative_floor <= 0 or self.spin_weight < 0 or self.position_noise < 0:
            raise ConfigError(f"[[train.stages]] {self.name}: need relative_floor > 0, "
                              "spin_weight >= 0 and position_noise >= 0")


@dataclass(frozen=True)
class TrainConfig:
    """SGN training (docs/conventions.md section 5). Defaults are the paper's (batch 2, 2000 epochs,
    GPU).

    The learning rate decays exponentially from ``lr_init`` to ``lr_final`` over all epochs.
    Loss = ``node_loss_weight`` * Huber(node) + ``global_loss_weight`` * Huber(global), Huber as
    in paper Eq. 30 with threshold ``huber_delta``; ``global_loss_weight = 0`` is the paper's
    appendix ablation without the global loss. ``noise_std``: Gaussian noise on the normalised velocity features.
    Split per trajectory, chronological: windows whose target step ends at t <= ``train_time``
    (s of motion) train; windows lying wholly in (train_time, train_time + val_time] validate.
    Each step packs up to ``batch_size`` graphs under a static edge capacity (docs/sgn.md).

    Attributes:
        batch_size: graphs (windows) per optimisation step.
        epochs: passes over the training windows.
        lr_init: learning rate at the first step.
        lr_final: learning rate at the last step (exponential decay, 0 < lr_final <= lr_init).
        node_loss_weight: weight of the per-ball acceleration Huber loss.
        global_loss_weight: weight of the dissipated-energy Huber loss (0 = no global loss).
        huber_delta: Huber threshold of paper Eq. 30, in normalised units.
        noise_std: std of the Gaussian noise on the normalised velocity features.
        train_time: s of motion; windows whose target step ends at t <= train_time train.
        val_time: s; windows wholly in (train_time, train_time + val_time] validate.
        seed: seed of the initial parameters, the shuffling and the noise.
        window_stride: use every k-th window of each trajectory (training and validation);
            neighbouring windows 1e-4 s apart are nearly the same sample, so a stride > 1
            spreads a fixed budget of samples over more trajectories.
        position_noise_std: m/s, GNS random-walk noise on the training position windows: the
            std of the velocity noise at the last slot (0 = off; docs/sgn.md, "Training noise").
        envelope: the motion envelope the model is trained for and promises to cover: "" (its
            single training motion), "default" (sgn_jax/data/envelope.toml) or a TOML path;
            stored in the checkpoint meta (key ``envelope``).
        devices: data-parallel training over this many local devices (1 = one device, the
            default); each step's ``batch_size`` graphs are split evenly over the devices, so
            batch_size must be a multiple (docs/sgn.md, "Data-parallel training").
        stages: the staged training of the contact-impulse surrogate ([[train.stages]],
            :class:`TrainStage`; docs/training.md). Empty for an SGN, which trains for
            ``epochs`` with the keys above.
    """

    batch_size: int = 2
    epochs: int = 2000
    lr_init: float = 1e-4
    lr_final: float = 1e-6
    node_loss_weight: float = 3.0
    global_loss_weight: float = 1.0
    huber_delta: float = 2.0
    noise_std: float = 0.005
    train_time: float = 4.5
    val_time: float = 0.5
    seed: int = 0
    window_stride: int = 1
    position_noise_std: float = 0.0
    envelope: str = ""
    devices: int = 1
    stages: tuple[TrainStage, ...] = ()

    def __post_init__(self) -> None:
        if self.batch_size < 1 or self.epochs < 1:
            raise ConfigError("[train] batch_size and epochs must be >= 1")
        if self.devices < 1 or self.batch_size % self.devices:
            raise ConfigError(f"[train] devices must be >= 1 and divide batch_size, got devices "
                              f"= {self.devices}, batch_size = {self.batch_size}")
        if not 0 < self.lr_final <= self.lr_init:
            raise ConfigError(
                f"[train] need 0 < lr_final <= lr_init, got {self.lr_final}, {self.lr_init}"
            )
        if self.huber_delta <= 0 or self.noise_std < 0 or self.node_loss_weight < 0:
            raise ConfigError("[train] need huber_delta > 0, noise_std >= 0, node_loss_weight >= 0")
        if self.global_loss_weight < 0:
            raise ConfigError("[train] need global_loss_weight >= 0 (0: no global loss)")
        if self.window_stride < 1:
            raise ConfigError(f"[train] window_stride must be >= 1, got {self.window_stride}")
        if not (math.isfinite(self.position_noise_std) and self.position_noise_std >= 0):
            raise ConfigError(f"[train] position_noise_std must be >= 0 (m/s), got "
                              f"{self.position_noise_std}")
        if self.train_time <= 0 or self.val_time < 0:
            raise ConfigError("[train] need train_time > 0 and val_time >= 0 (s)")
        names = [stage.name for stage in self.stages]
        if len(set(names)) != len(names):
            raise ConfigError(f"[[train.stages]] names must differ, got {names}")


@dataclass(frozen=True)
class RolloutConfig:
    """The surrogate rollout (docs/conventions.md section 5, paper 2.2.3; docs/rollout.md).

    ``save_every``: steps between saved position frames (10 = every 1 ms at dt = 1e-4 s).
    ``chunk_steps``: steps per jitted call of the host-level run (progress-bar granularity; a
    multiple of save_every). ``checkpoint_steps``: steps per ``jax.checkpoint`` chunk, which
    bounds the memory of a differentiated rollout (a multiple of save_every).
    ``snap_back``: move balls with phi >= ``[graph] phi_sb`` back to phi_sb along -n.
    ``snap_velocity``: "keep" (the paper's choice: the velocity is unchanged, the ball's window
    history is moved with it) or "position" (the finite-difference velocity follows the moved
    position).
    ``pp_separation``: the ball-ball analogue of the snap-back (not in the paper;
    docs/rollout.md): pairs overlapping by more than ``pp_max_overlap`` (m) after a step are
    moved apart to it, with the velocity rule of ``snap_velocity``.

    Attributes:
        save_every: rollout steps between saved position frames.
        chunk_steps: steps per jitted call of the host-level run (a multiple of save_every).
        checkpoint_steps: steps per jax.checkpoint chunk when differentiating (multiple of save_every).
        snap_back: move balls with phi >= [graph] phi_sb back to phi_sb along -n after each step.
        snap_velocity: "keep" (the paper) or "position": the velocity rule of the moves.
        pp_separation: move ball pairs overlapping by more than pp_max_overlap apart (not the paper).
        pp_max_overlap: m, largest ball-ball overlap that pp_separation leaves.
    """

    save_every: int = 10
    chunk_steps: int = 2000
    checkpoint_steps: int = 100
    snap_back: bool = True
    snap_velocity: str = "keep"
    pp_separation: bool = False
    pp_max_overlap: float = 5e-5

    def __post_init__(self) -> None:
        if self.save_every < 1:
            raise ConfigError(f"[rollout] save_every must be >= 1, got {self.save_every}")
        for name in ("chunk_steps", "checkpoint_steps"):
            value = getattr(self, name)
            if value < 1 or value % self.save_every:
                raise ConfigError(f"[rollout] {name} must be a positive multiple of save_every "
                                  f"= {self.save_every}, got {value}")
        if self.pp_max_overlap < 0:
            raise ConfigError(f"[rollout] pp_max_overlap must be >= 0 m, got {self.pp_max_overlap}")
        if self.snap_velocity not in ("keep", "position"):
            raise ConfigError(f"[rollout] snap_velocity must be 'keep' or 'position', got "
                              f"{self.snap_velocity!r}")


@dataclass(frozen=True)
class Config:
    """A whole experiment config: one attribute per TOML section.

    Attributes:
        case: identification of the case.
        jar: the milling jar (parametric Emax-like cavity or an STL mesh).
        motion: the jar's translation over time.
        balls: the grinding balls (one class, or a mix).
        material: the jar's material, also the balls' unless they name another.
        materials: further ball materials (``[[materials]]``).
        interactions: explicit rules for pairs of materials (``[[interactions]]``).
        dem: DEM solver settings.
        sdf: SDF grid sampling for the surrogate.
        graph: the SGN graph featurizer.
        model: the SGN network.
        train: SGN training.
        rollout: the surrogate rollout.
    """

    case: CaseConfig
    jar: JarConfig
    motion: MotionConfig
    balls: BallsConfig
    material: MaterialConfig
    dem: DEMConfig = field(default_factory=DEMConfig)
    sdf: SDFConfig = field(default_factory=SDFConfig)
    graph: GraphConfig = field(default_factory=GraphConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    rollout: RolloutConfig = field(default_factory=RolloutConfig)
    materials: tuple[MaterialConfig, ...] = ()
    interactions: tuple[InteractionConfig, ...] = ()

    def __post_init__(self) -> None:
        self._check_materials()
        if self.train.stages and self.model.kind != "contact":
            raise ConfigError(f"[[train.stages]] trains the contact-impulse surrogate ([model] "
                              f"kind = 'contact'), got kind = {self.model.kind!r}; an SGN "
                              "trains for [train] epochs: remove the stages")

    def material_named(self, name: str) -> MaterialConfig:
        """The material called ``name`` ("" = ``[material]``)."""
        if not name or name == self.material.name:
            return self.material
        for m in self.materials:
            if m.name == name:
                return m
        raise ConfigError(f"unknown material {name!r}; defined: "
                          f"{[self.material.name] + [m.name for m in self.materials]} "
                          "(add a [[materials]] table with this name)")

    def _check_materials(self) -> None:
        names = [self.material.name] + [m.name for m in self.materials]
        if len(set(names)) != len(names):
            raise ConfigError(f"material names must be unique, got {names} ([material] name "
                              "and [[materials]] names)")
        for where, c in [("[balls]", self.balls)] + [("[[balls.mix]]", m)
                                                      for m in self.balls.mix]:
            if c.material and c.material not in names:
                raise ConfigError(f"{where} material = {c.material!r} is not defined; defined: "
                                  f"{names} (add a [[materials]] table with this name)")
        seen: set[frozenset[str]] = set()
        for rule in self.interactions:
            for name in rule.materials:
                if name not in names:
                    raise ConfigError(f"[[interactions]] materials = {list(rule.materials)} "
                                      f"names {name!r}, which is not defined; defined: {names}")
            key = frozenset(rule.materials)
            if key in seen:
                raise ConfigError(f"two [[interactions]] for materials {list(rule.materials)}")
            seen.add(key)


# --------------------------------------------------------------------------------------------
# Generic strict loading


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", str(tp))


def _coerce(value: Any, tp: Any, where: str) -> Any:
    """Convert a TOML value to the annotated type, or raise ConfigError naming ``where``."""
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if value is None:
            return None
        return _coerce(value, args[0], where)
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where} must be a list, got {type(value).__name__}")
        args = typing.get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(v, args[0], f"{where}[{i}]") for i, v in enumerate(value))
        if len(args) != len(value):
            raise ConfigError(f"{where} must have {len(args)} elements, got {len(value)}")
        return tuple(_coerce(v, a, f"{where}[{i}]") for i, (a, v) in enumerate(zip(args, value, strict=True)))
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where} must be a number, got {value!r}")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where} must be an integer, got {value!r}")
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where} must be true or false, got {value!r}")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where} must be a string, got {value!r}")
        return value
    if dataclasses.is_dataclass(tp):
        return _build_dataclass(tp, value, where)
    raise ConfigError(f"{where}: unsupported type {_type_name(tp)}")


def _build_dataclass(cls: type, table: Any, where: str) -> Any:
    if not isinstance(table, dict):
        raise ConfigError(f"{where} must be a table, got {type(table).__name__}")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(table) - set(fields))
    if unknown:
        raise ConfigError(
            f"unknown key(s) {', '.join(f'{where}.{k}' for k in unknown)}; "
            f"allowed keys in {where}: {', '.join(sorted(fields))}"
        )
    kwargs = {}
    for name, f in fields.items():
        if name in table:
            kwargs[name] = _coerce(table[name], hints[name], f"{where}.{name}")
        elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            raise ConfigError(f"missing required key {where}.{name}")
    # An unknown kind is reported by MotionConfig itself (listing the kinds), not as foreign keys.
    if cls is MotionConfig and table.get("kind") in MOTION_KINDS:
        MotionConfig.check_keys_for_kind(table["kind"], set(table))
    if cls is ModelConfig and isinstance(table.get("kind"), str):
        ModelConfig.check_keys_for_kind(table["kind"], set(table))
    try:
        return cls(**kwargs)
    except ConfigError:
        raise
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{where}: {exc}") from exc


def config_from_dict(data: dict[str, Any], cls: type = Config) -> Any:
    """Build a (frozen) config dataclass from a nested dict, strictly. Raises ConfigError."""
    return _build_dataclass(cls, data, "config" if cls is Config else cls.__name__)


def saved_config_from_dict(data: dict[str, Any]) -> Config:
    """:func:`config_from_dict` of a config saved in a record (a checkpoint's or a prediction's
    metadata). A saved config lists every key; the [model] keys its kind does not read are
    dropped (the writer, :func:`config_to_dict`, leaves them out), the rest is read strictly."""
    model = data.get("model")
    read = (ModelConfig.keys_read_by(model.get("kind"))
            if isinstance(model, dict) and isinstance(model.get("kind"), str) else None)
    if read is not None:
        data = {**data, "model": {k: v for k, v in model.items() if k in read}}
    return config_from_dict(data)


def _to_plain(value: Any) -> Any:
    if isinstance(value, MotionConfig):
        # Only the keys of the motion's own kind: the others are unused and would be rejected.
        keys = MotionConfig._KEYS_BY_KIND[value.kind] | {"kind"}
        return {f.name: _to_plain(getattr(value, f.name))
                for f in dataclasses.fields(value) if f.name in keys}
    if isinstance(value, ModelConfig):
        # Only the keys the model's kind reads: the others would be refused.
        keys = ModelConfig.keys_read_by(value.kind)
        return {f.name: _to_plain(getattr(value, f.name))
                for f in dataclasses.fields(value) if keys is None or f.name in keys}
    if dataclasses.is_dataclass(value):
        return {f.name: _to_plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, tuple):
        return [_to_plain(v) for v in value]
    return value


def config_to_dict(cfg: Any) -> dict[str, Any]:
    """The config as a nested dict of plain TOML/JSON types (tuples become lists)."""
    return _to_plain(cfg)


def read_toml(path: str | Path, error: type[Exception] = ConfigError,
              what: str = "config file") -> dict[str, Any]:
    """Read a TOML file as a dict; a missing file or bad TOML raises ``error`` naming the file."""
    path = Path(path)
    if not path.is_file():
        raise error(f"{what} not found: {path}")
    try:
        with open(path, "rb") as fh:
            return tomllib.load(fh)
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{path}: not valid TOML: {exc}") from exc


def load_config(path: str | Path) -> Config:
    """Load and validate a TOML config file. Raises ConfigError with the file name on error."""
    data = read_toml(path)
    try:
        return config_from_dict(data)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from exc


def config_to_toml(cfg: Any) -> str:
    import tomli_w

    return tomli_w.dumps(config_to_dict(cfg))


def save_config(cfg: Any, path: str | Path) -> None:
    """Write the resolved config (defaults filled in) as TOML, atomically."""
    with atomic_write(path, "w") as fh:
        fh.write(config_to_toml(cfg))


def replace_section(cfg: Config, section: str, **changes: Any) -> Config:
    """Return a copy of ``cfg`` with fields of one section replaced (validated again)."""
    new_section = dataclasses.replace(getattr(cfg, section), **changes)
    return dataclasses.replace(cfg, **{section: new_section})


def builtin_config_path(name: str) -> Path:
    """Path of a config shipped with the package (``sgn_jax/configs/NAME.toml``)."""
    path = Path(__file__).parent / "configs" / f"{name}.toml"
    if not path.is_file():
        available = sorted(p.stem for p in path.parent.glob("*.toml"))
        raise ConfigError(f"no built-in config {name!r}; available: {available}")
    return path


def resolve_config(name_or_path: str | Path) -> Config:
    """A built-in config by name (``"emax_300rpm"``, ``"motion1"``, ...) or a TOML file by path.

    A text with a ``.toml`` suffix or a ``/``, or naming an existing file, is a path.
    """
    text = str(name_or_path)
    path = Path(text)
    if path.suffix == ".toml" or "/" in text or path.exists():
        if not path.is_file():
            raise ConfigError(f"config file {text!r} does not exist; pass a TOML file or the "
                              "name of a built-in config (e.g. emax_300rpm)")
        return load_config(path)
    return load_config(builtin_config_path(text))
