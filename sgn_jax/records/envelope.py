"""The motion envelope of the motion-general surrogate and space-filling designs over it.

The envelope (``sgn_jax/data/envelope.toml``, docs/envelope.md) is the set of jar motions the
shipped default model promises to cover, in the standard jar with the standard charge:

- circles ``x = A sin(2 pi f t), z = A cos(2 pi f t)`` with f = rpm / 60, rpm in [150, 500],
  A in [10, 20] mm;
- two-harmonic orbits, per axis (x and z) ``A1 sin(2 pi f0 t + p1) + A2 sin(4 pi f0 t + p2)``
  with f0 in [3, 8] Hz, A1 in [0, 20] mm, A2 in [0, 17] mm and A1 + A2 <= 26 mm per axis
  (phases free). Motion 1 (x: A1 = 17, A2 = 8.5 mm) and Motion 2 lie inside.

:func:`latin_hypercube_motions` draws a Latin hypercube (``scipy.stats.qmc``) over these
parameters and returns :class:`~sgn_jax.config.MotionConfig` objects. A harmonic draw whose
per-axis sum exceeds the limit is scaled down onto the limit (both amplitudes by the same
factor), which keeps the design space-filling in frequency and in the amplitude ratio.

:func:`envelope_notes` says why a motion lies outside (empty list: inside).
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sgn_jax.config import ConfigError, MotionConfig

ENVELOPE_PATH = Path(__file__).resolve().parents[1] / "data" / "envelope.toml"
_REL_TOL = 1e-9


@dataclass(frozen=True)
class MotionEnvelope:
    """Ranges (min, max) of the envelope's motion parameters; lengths in m, frequencies in Hz."""

    circle_rpm: tuple[float, float]
    circle_amplitude: tuple[float, float]
    harmonic_base_hz: tuple[float, float]
    harmonic_first_amplitude: tuple[float, float]
    harmonic_second_amplitude: tuple[float, float]
    harmonic_max_axis_sum: float

    def to_meta(self) -> dict[str, Any]:
        """The JSON form stored as a checkpoint's ``envelope`` meta key."""
        return {"circle_rpm": list(self.circle_rpm),
                "circle_amplitude": list(self.circle_amplitude),
                "harmonic_base_hz": list(self.harmonic_base_hz),
                "harmonic_first_amplitude": list(self.harmonic_first_amplitude),
                "harmonic_second_amplitude": list(self.harmonic_second_amplitude),
                "harmonic_max_axis_amplitude": self.harmonic_max_axis_sum}

    @classmethod
    def from_meta(cls, meta: dict[str, Any]) -> MotionEnvelope | None:
        """The inverse of :meth:`to_meta`; None when ``meta`` lacks one of its keys (an
        envelope stated in an older, partial form)."""
        keys = ("circle_rpm", "circle_amplitude", "harmonic_base_hz", "harmonic_first_amplitude",
                "harmonic_second_amplitude", "harmonic_max_axis_amplitude")
        if any(meta.get(k) is None for k in keys):
            return None
        pair = lambda k: (float(meta[k][0]), float(meta[k][1]))  # noqa: E731
        return cls(circle_rpm=pair("circle_rpm"), circle_amplitude=pair("circle_amplitude"),
                   harmonic_base_hz=pair("harmonic_base_hz"),
                   harmonic_first_amplitude=pair("harmonic_first_amplitude"),
                   harmonic_second_amplitude=pair("harmonic_second_amplitude"),
                   harmonic_max_axis_sum=float(meta["harmonic_max_axis_amplitude"]))


def bounds_pair(table: dict[str, Any], key: str, where: str) -> tuple[float, float]:
    value = table.get(key)
    if (not isinstance(value, list) or len(value) != 2
            or not all(isinstance(v, (int, float)) for v in value) or not value[0] <= value[1]):
        raise ConfigError(f"{where}: {key} must be [min, max] with min <= max, got {value!r}")
    return float(value[0]), float(value[1])


def load_envelope(path: str | Path = ENVELOPE_PATH) -> MotionEnvelope:
    """Read an envelope TOML (default: the shipped one)."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError(f"envelope file {path}: {exc}") from None
    c, h = data.get("circle", {}), data.get("harmonic", {})
    where = str(path)
    max_sum = h.get("max_axis_sum")
    if not isinstance(max_sum, (int, float)) or max_sum <= 0:
        raise ConfigError(f"{where}: [harmonic] max_axis_sum must be a length > 0 (m), got "
                          f"{max_sum!r}")
    return MotionEnvelope(circle_rpm=bounds_pair(c, "rpm", where + " [circle]"),
                          circle_amplitude=bounds_pair(c, "amplitude", where + " [circle]"),
                          harmonic_base_hz=bounds_pair(h, "base_frequency_hz", where + " [harmonic]"),
                          harmonic_first_amplitude=bounds_pair(h, "first_amplitude", where + " [harmonic]"),
                          harmonic_second_amplitude=bounds_pair(h, "second_amplitude",
                                                          where + " [harmonic]"),
                          harmonic_max_axis_sum=float(max_sum))


def harmonic_axis_amplitudes(m: MotionConfig) -> dict[str, list[float]]:
    """Per axis, the amplitude sqrt(sin^2 + cos^2) of each harmonic k = 1..K (m)."""
    out = {}
    for axis in "xyz":
        s, c = list(getattr(m, f"{axis}_sin")), list(getattr(m, f"{axis}_cos"))
        k = max(len(s), len(c))
        s, c = s + [0.0] * (k - len(s)), c + [0.0] * (k - len(c))
        out[axis] = [math.hypot(a, b) for a, b in zip(s, c, strict=True)]
    return out


def envelope_notes(m: MotionConfig, env: MotionEnvelope) -> list[str]:
    """Why the motion ``m`` lies outside ``env`` (empty list: inside)."""
    notes: list[str] = []

    def check(value: float, bounds: tuple[float, float], what: str) -> None:
        lo, hi = bounds
        tol = _REL_TOL * max(abs(lo), abs(hi), 1.0)
        if not lo - tol <= value <= hi + tol:
            notes.append(f"{what} = {value:g} is outside the envelope's [{lo:g}, {hi:g}]")

    if m.kind == "circle":
        check(m.rpm, env.circle_rpm, "[motion] rpm")
        check(m.amplitude, env.circle_amplitude, "[motion] amplitude (m)")
    elif m.kind == "harmonic":
        check(m.base_frequency_hz, env.harmonic_base_hz, "[motion] base_frequency_hz")
        for axis, amps in harmonic_axis_amplitudes(m).items():
            if len(amps) > 2 and any(a > 0 for a in amps[2:]):
                notes.append(f"[motion] {axis}: harmonics above the second are outside the "
                             "envelope")
            if axis == "y" and any(a > 0 for a in amps):
                notes.append("[motion] y: the envelope's orbits lie in the x-z plane")
                continue
            if amps:
                check(amps[0], env.harmonic_first_amplitude, f"[motion] {axis} first-harmonic "
                      "amplitude (m)")
            if len(amps) > 1:
                check(amps[1], env.harmonic_second_amplitude, f"[motion] {axis} second-harmonic "
                      "amplitude (m)")
            total = sum(amps[:2])
            if total > env.harmonic_max_axis_sum * (1 + 1e-6):
                notes.append(f"[motion] {axis}: A1 + A2 = {total:g} m exceeds the envelope's "
                             f"{env.harmonic_max_axis_sum:g} m")
    else:
        notes.append(f"[motion] kind = {m.kind!r}: the envelope has circles and two-harmonic "
                     "orbits only")
    return notes


def _scale(unit: np.ndarray, bounds: tuple[float, float]) -> np.ndarray:
    return bounds[0] + unit * (bounds[1] - bounds[0])


def latin_hypercube_motions(env: MotionEnvelope, n_circle: int, n_harmonic: int, seed: int
                            ) -> list[MotionConfig]:
    """``n_circle`` circles then ``n_harmonic`` two-harmonic orbits, each set a scrambled
    Latin hypercube (``scipy.stats.qmc.LatinHypercube(seed=seed)``) over the envelope.

    Circle dimensions: rpm, amplitude. Harmonic dimensions: f0, A1x, A2x, A1z, A2z and the
    four phases (uniform in [0, 2 pi)); a per-axis sum A1 + A2 above the limit is scaled onto it.
    Coefficients are rounded to 1e-6 m and frequencies to 1e-3 so the TOML files stay readable.
    """
    if n_circle < 0 or n_harmonic < 0:
        raise ValueError(f"motion counts must be >= 0, got {n_circle}, {n_harmonic}")
    # scipy.stats is imported here, not at the top: it costs 0.7 s of every process's start
    # (each CLI command, each test worker) and only the design of new motions needs it.
    from scipy.stats import qmc

    motions: list[MotionConfig] = []
    if n_circle:
        u = qmc.LatinHypercube(d=2, seed=seed).random(n_circle)
        for rpm, amp in zip(_scale(u[:, 0], env.circle_rpm), _scale(u[:, 1], env.circle_amplitude),
                            strict=True):
            motions.append(MotionConfig(kind="circle", rpm=round(float(rpm), 3),
                                        amplitude=round(float(amp), 6), phase=0.0))
    if n_harmonic:
        u = qmc.LatinHypercube(d=9, seed=seed + 1).random(n_harmonic)
        for row in u:
            f0 = round(float(_scale(row[0], env.harmonic_base_hz)), 3)
            coeffs = {}
            for i, axis in enumerate("xz"):
                a1 = float(_scale(row[1 + 2 * i], env.harmonic_first_amplitude))
                a2 = float(_scale(row[2 + 2 * i], env.harmonic_second_amplitude))
                total = a1 + a2
                limit = env.harmonic_max_axis_sum - 4e-6  # room for the 1e-6 m rounding
                if total > limit:
                    a1, a2 = (a * limit / total for a in (a1, a2))
                p1, p2 = 2 * math.pi * row[5 + 2 * i], 2 * math.pi * row[6 + 2 * i]
                # A sin(w t + p) = A cos(p) sin(w t) + A sin(p) cos(w t)
                coeffs[f"{axis}_sin"] = (round(a1 * math.cos(p1), 6), round(a2 * math.cos(p2), 6))
                coeffs[f"{axis}_cos"] = (round(a1 * math.sin(p1), 6), round(a2 * math.sin(p2), 6))
            motions.append(MotionConfig(kind="harmonic", base_frequency_hz=f0, **coeffs))
    for m in motions:  # the rounding must not leave the envelope
        notes = envelope_notes(m, env)
        if notes:
            raise AssertionError(f"latin_hypercube_motions left the envelope: {notes}")
    return motions


def motion_label(m: MotionConfig) -> str:
    """A short human label: ``circle 300 rpm, A = 17 mm`` or ``harmonic f0 = 5 Hz, x 17+8.5 mm,
    z 17+8.5 mm``."""
    if m.kind == "circle":
        return f"circle {m.rpm:.0f} rpm, A = {m.amplitude * 1e3:.1f} mm"
    if m.kind == "harmonic":
        amps = harmonic_axis_amplitudes(m)
        parts = [f"{a} " + "+".join(f"{v * 1e3:.1f}" for v in amps[a][:2]) + " mm"
                 for a in "xz" if amps[a]]
        return f"harmonic f0 = {m.base_frequency_hz:.2f} Hz, " + ", ".join(parts)
    return m.kind


__all__ = ["ENVELOPE_PATH", "MotionEnvelope", "bounds_pair", "envelope_notes", "harmonic_axis_amplitudes",
           "latin_hypercube_motions", "load_envelope", "motion_label"]
