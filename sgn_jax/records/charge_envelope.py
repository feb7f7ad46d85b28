"""The charge envelope and space-filling designs of charges over it (docs/charge.md).

The envelope (``sgn_jax/data/charge_envelope.toml``) is the set of charges the charge-general
work covers, in the standard jar on the standard circle: ball diameters 6-15 mm, the balls'
solid volume 5-20 % of the jar's (4 to about 220 balls), one ball material per charge with a
density of 2,600-7,800 kg/m^3, restitution 0.3-0.8 and friction 0.1-0.5 (the jar lined with the
same material), one size or a mixture of two, at 200-600 rpm.

:func:`latin_hypercube_charges` draws a scrambled Latin hypercube (``scipy.stats.qmc``) over
it and returns :class:`ChargeDesign` rows; :meth:`ChargeDesign.apply` turns one into a config.
Optional constraints put chosen rows into a sub-range of one parameter (a held-out set that
must hold a mixture, a large charge, a light or a bouncy material) while the other parameters
stay space-filling. :func:`charge_envelope_notes` says why a config's charge lies outside,
:func:`charge_circle_notes` why its motion is not one of the envelope's circles.

A model that reads the charge states the envelope it covers in its checkpoint meta
(:func:`charge_model_envelope`): the charge envelope under the key ``charge``
(:meth:`ChargeEnvelope.to_meta`) beside the motion envelope's keys
(:meth:`sgn_jax.records.envelope.MotionEnvelope.to_meta`) when it was trained over one too.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sgn_jax.config import (
    BallClassConfig,
    Config,
    ConfigError,
    MaterialConfig,
    MotionConfig,
    read_toml,
    replace_section,
)
from sgn_jax.records.envelope import MotionEnvelope, bounds_pair

CHARGE_ENVELOPE_PATH = Path(__file__).resolve().parents[1] / "data" / "charge_envelope.toml"
CHARGE_MATERIAL = "charge"
"""The name of a design's material (its balls and the jar's lining)."""


def ball_volume(diameter: float) -> float:
    """m^3, one ball."""
    return math.pi / 6.0 * diameter**3


@dataclass(frozen=True)
class ChargeEnvelope:
    """Ranges (min, max) of the charge envelope; lengths in m, densities in kg/m^3."""

    diameter: tuple[float, float]
    fill: tuple[float, float]
    mixture_share: float
    small_volume_share: tuple[float, float]
    density: tuple[float, float]
    restitution: tuple[float, float]
    friction: tuple[float, float]
    rolling_friction: float
    young: float
    poisson: float
    rpm: tuple[float, float]
    amplitude: float

    def to_meta(self) -> dict[str, Any]:
        """The JSON form stored in a checkpoint's ``envelope`` meta under ``charge``."""
        return {k: list(v) if isinstance(v, tuple) else v
                for k, v in dataclasses.asdict(self).items()}

    @classmethod
    def from_meta(cls, meta: dict[str, Any] | None) -> ChargeEnvelope | None:
        """The inverse of :meth:`to_meta`; None when ``meta`` is None or lacks one of its
        keys."""
        names = [f.name for f in dataclasses.fields(cls)]
        if not isinstance(meta, dict) or any(meta.get(k) is None for k in names):
            return None
        return cls(**{k: (float(meta[k][0]), float(meta[k][1])) if isinstance(meta[k], list)
                      else float(meta[k]) for k in names})


@dataclass(frozen=True)
class ChargeDesign:
    """One charge of a design: one or two ball classes of one material, and the jar's rpm.

    Attributes:
        name: a label (``train_03``, ``heldout_02``).
        diameters: m, one per class (the larger first in a mixture).
        counts: balls per class.
        density: kg/m^3. restitution, friction: the material's (with itself and the jar).
        rpm: the standard circle's speed.
    """

    name: str
    diameters: tuple[float, ...]
    counts: tuple[int, ...]
    density: float
    restitution: float
    friction: float
    rpm: float

    @property
    def n_balls(self) -> int:
        return sum(self.counts)

    @property
    def mixture(self) -> bool:
        return len(self.diameters) > 1

    def fill(self, jar_volume: float) -> float:
        """The balls' solid volume over the jar's."""
        return sum(n * ball_volume(d) for n, d in zip(self.counts, self.diameters,
                                                      strict=True)) / jar_volume

    def apply(self, cfg: Config, env: ChargeEnvelope) -> Config:
        """``cfg`` (the standard case) with this charge: the classes in ``[balls]`` and
        ``[[balls.mix]]``, the material in ``[material]`` (the jar's lining too), the rpm."""
        material = MaterialConfig(name=CHARGE_MATERIAL, young=env.young, poisson=env.poisson,
                                  restitution=self.restitution, friction=self.friction,
                                  rolling_friction=env.rolling_friction)
        first, *rest = zip(self.counts, self.diameters, strict=True)
        mix = tuple({"count": n, "radius": d / 2, "density": self.density} for n, d in rest)
        cfg = dataclasses.replace(cfg, material=material, materials=(), interactions=())
        cfg = replace_section(cfg, "balls", count=first[0], radius=first[1] / 2,
                              density=self.density, material="",
                              mix=tuple(BallClassConfig(**m) for m in mix))
        cfg = replace_section(cfg, "motion", rpm=self.rpm, amplitude=env.amplitude)
        return replace_section(cfg, "case", name=self.name,
                               description=f"charge design {self.name}: {self.label()}")

    def label(self) -> str:
        sizes = " + ".join(f"{n} x {d * 1e3:.1f} mm" for n, d in zip(self.counts, self.diameters,
                                                                        strict=True))
        return (f"{sizes}, {self.density:.0f} kg/m^3, e = {self.restitution:.2f}, "
                f"mu = {self.friction:.2f}, {self.rpm:.0f} rpm")

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def _number(table: dict[str, Any], key: str, where: str) -> float:
    value = table.get(key)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(f"{where}: {key} must be a number, got {value!r}")
    return float(value)


def load_charge_envelope(path: str | Path = CHARGE_ENVELOPE_PATH) -> ChargeEnvelope:
    """Read a charge-envelope TOML (default: the shipped one)."""
    path = Path(path)
    data = read_toml(path, what="charge envelope file")
    b, m, mo = data.get("balls", {}), data.get("material", {}), data.get("motion", {})
    w = str(path)
    return ChargeEnvelope(
        diameter=bounds_pair(b, "diameter", w + " [balls]"), fill=bounds_pair(b, "fill", w + " [balls]"),
        mixture_share=_number(b, "mixture_share", w + " [balls]"),
        small_volume_share=bounds_pair(b, "small_volume_share", w + " [balls]"),
        density=bounds_pair(m, "density", w + " [material]"),
        restitution=bounds_pair(m, "restitution", w + " [material]"),
        friction=bounds_pair(m, "friction", w + " [material]"),
        rolling_friction=_number(m, "rolling_friction", w + " [material]"),
        young=_number(m, "young", w + " [material]"),
        poisson=_number(m, "poisson", w + " [material]"),
        rpm=bounds_pair(mo, "rpm", w + " [motion]"), amplitude=_number(mo, "amplitude", w + " [motion]"))


# The design's unit-cube dimensions, in this order.
DIMENSIONS = ("diameter", "fill", "density", "restitution", "friction", "rpm", "mixture",
              "second_diameter", "small_volume_share")


def _scale(u: float, bounds: tuple[float, float]) -> float:
    return bounds[0] + u * (bounds[1] - bounds[0])


def design_row(name: str, u: np.ndarray, env: ChargeEnvelope, jar_volume: float,
               max_balls: int | None = None) -> ChargeDesign:
    """The charge at unit-cube point ``u`` (:data:`DIMENSIONS`). ``max_balls`` lowers the
    fill so the charge holds at most that many balls (a training charge)."""
    row = dict(zip(DIMENSIONS, (float(x) for x in u), strict=True))
    d_a = _scale(row["diameter"], env.diameter)
    fill = _scale(row["fill"], env.fill)
    if row["mixture"] < env.mixture_share:
        d_b = _scale(row["second_diameter"], env.diameter)
        large, small = max(d_a, d_b), min(d_a, d_b)
        share = _scale(row["small_volume_share"], env.small_volume_share)
        diameters = (large, small)
        shares = (1.0 - share, share)
    else:
        diameters, shares = (d_a,), (1.0,)

    def counts_at(f: float) -> tuple[int, ...]:
        return tuple(max(1, round(s * f * jar_volume / ball_volume(d)))
                     for s, d in zip(shares, diameters, strict=True))

    counts = counts_at(fill)
    if max_balls is not None and sum(counts) > max_balls:
        fill *= max_balls / sum(counts)
        counts = counts_at(fill)
        while sum(counts) > max_balls:
            fill *= 0.98
            counts = counts_at(fill)
    return ChargeDesign(name=name, diameters=tuple(round(d, 5) for d in diameters),
                        counts=counts, density=round(_scale(row["density"], env.density), 1),
                        restitution=round(_scale(row["restitution"], env.restitution), 3),
                        friction=round(_scale(row["friction"], env.friction), 3),
                        rpm=round(_scale(row["rpm"], env.rpm), 1))


def latin_hypercube_charges(env: ChargeEnvelope, n: int, seed: int, jar_volume: float, *,
                            prefix: str = "charge", max_balls: int | None = None,
                            constraints: dict[int, dict[str, tuple[float, float]]] | None = None
                            ) -> list[ChargeDesign]:
    """``n`` charges from a scrambled Latin hypercube over :data:`DIMENSIONS`
    (``scipy.stats.qmc.LatinHypercube(seed=seed)``).

    ``constraints`` maps a row index to ``{dimension: (lo, hi)}`` unit sub-ranges: that row's
    coordinate u becomes ``lo + u (hi - lo)`` (e.g. ``{"mixture": (0, share)}`` makes it a
    mixture), keeping the design's spread in every other dimension."""
    from scipy.stats import qmc  # 0.7 s of import, only for new designs

    u = qmc.LatinHypercube(d=len(DIMENSIONS), seed=seed).random(n)
    for index, subranges in (constraints or {}).items():
        for dim, (lo, hi) in subranges.items():
            k = DIMENSIONS.index(dim)
            u[index, k] = lo + u[index, k] * (hi - lo)
    return [design_row(f"{prefix}_{i:02d}", u[i], env, jar_volume, max_balls)
            for i in range(n)]


def charge_envelope_notes(cfg: Config, env: ChargeEnvelope, jar_volume: float | None
                          ) -> list[str]:
    """Why the charge of ``cfg`` lies outside the envelope (empty: inside), one line per
    parameter, naming the value and the range. ``jar_volume`` (m^3) is the cavity's; None (an
    STL cavity, whose volume needs its mesh) leaves the fill unchecked."""
    notes = []

    def check(value: float, bounds: tuple[float, float], what: str) -> None:
        lo, hi = bounds
        if not lo * (1 - 1e-9) <= value <= hi * (1 + 1e-9):
            notes.append(f"{what} = {value:g} is outside the charge envelope [{lo:g}, {hi:g}]")

    classes = cfg.balls.classes
    if len(classes) > 2:
        notes.append(f"{len(classes)} ball classes: the charge envelope has one or two")
    for k, c in enumerate(classes):
        check(2 * c.radius, env.diameter, f"ball class {k} diameter (m)")
        check(c.density, env.density, f"ball class {k} density (kg/m^3)")
        mat = cfg.material_named(c.material)
        check(mat.restitution, env.restitution, f"ball class {k} restitution")
        check(mat.friction, env.friction, f"ball class {k} friction")
    if jar_volume is not None:
        check(cfg.balls.solid_volume / jar_volume, env.fill,
              "the balls' volume fraction of the jar")
    return notes


def charge_circle_notes(m: MotionConfig, env: ChargeEnvelope) -> list[str]:
    """Why the motion ``m`` is not one of the charge envelope's circles, ``env.rpm`` at
    amplitude ``env.amplitude`` (empty: it is one), naming the value and the range."""
    if m.kind != "circle":
        return [f"[motion] kind = {m.kind!r}: the charge envelope's motions are circles "
                f"({env.rpm[0]:g}-{env.rpm[1]:g} rpm at {env.amplitude:g} m)"]
    notes = []
    lo, hi = env.rpm
    if not lo * (1 - 1e-9) <= m.rpm <= hi * (1 + 1e-9):
        notes.append(f"[motion] rpm = {m.rpm:g} is outside the charge envelope's circles "
                     f"[{lo:g}, {hi:g}]")
    if not math.isclose(m.amplitude, env.amplitude, rel_tol=1e-6):
        notes.append(f"[motion] amplitude (m) = {m.amplitude:g} is not the charge envelope's "
                     f"circles' {env.amplitude:g}")
    return notes


def charge_model_envelope(motion: MotionEnvelope | None, charge: ChargeEnvelope
                          ) -> dict[str, Any]:
    """The ``envelope`` meta of a model that reads the charge: the keys of ``motion``
    (:meth:`MotionEnvelope.to_meta`; None: a model trained on the charge envelope's circles
    only) and ``charge``, the charge envelope (:meth:`ChargeEnvelope.to_meta`). The model
    covers every charge of ``charge`` on every motion of ``motion`` and on ``charge``'s
    circles (docs/contact_charge.md, "What it covers")."""
    return {**(motion.to_meta() if motion is not None else {}), "charge": charge.to_meta()}


__all__ = ["CHARGE_ENVELOPE_PATH", "CHARGE_MATERIAL", "ChargeDesign", "ChargeEnvelope",
           "DIMENSIONS", "ball_volume", "charge_circle_notes", "charge_envelope_notes",
           "charge_model_envelope", "design_row", "latin_hypercube_charges",
           "load_charge_envelope"]
