"""A new jar motion kind in one file: the elliptical orbit (used by tests/test_extension_motion.py).

``offset(t) = (a sin(2 pi f t + phase), 0, b cos(2 pi f t + phase))`` with ``f = rpm / 60``:
the standard circle with two semi-axes. Importing this module registers the kind "elliptical";
from then on :func:`sgn_jax.motion.offset`, ``velocity``, ``frequency_hz``, ``stack_motions``,
the DEM, the rollout and the design study take an :class:`EllipticalOrbitMotion` like a
built-in motion. Nothing else in the package changes (docs/motion-kinds.md).

``tests/extensions`` is a namespace package: the tests import it as ``extensions.*`` because
pytest puts ``tests/`` on ``sys.path`` (the test files are not a package).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from sgn_jax.motion import MotionKind, register_motion_kind


@flax.struct.dataclass
class EllipticalOrbitMotion:
    """An elliptical orbit in the x-z plane.

    Attributes:
        rpm: revolutions per minute (frequency ``rpm / 60`` Hz).
        semi_x: semi-axis a along x (m).
        semi_z: semi-axis b along z (m).
        phase: phase at t = 0 (rad); 0 puts the jar at ``(0, 0, b)``.
    """

    rpm: float | jax.Array
    semi_x: float | jax.Array
    semi_z: float | jax.Array
    phase: float | jax.Array = 0.0


def elliptical_offset(motion: EllipticalOrbitMotion, t: jax.Array) -> jax.Array:
    """The jar offset (3,) m at one scalar time ``t`` (s)."""
    angle = 2.0 * np.pi * (motion.rpm / 60.0) * t + motion.phase
    x = motion.semi_x * jnp.sin(angle)
    z = motion.semi_z * jnp.cos(angle)
    return jnp.stack([x, jnp.zeros_like(x), z])


def _from_config(values: Mapping[str, Any], dtype: Any) -> EllipticalOrbitMotion:
    return EllipticalOrbitMotion(**{key: jnp.asarray(values[key], dtype) for key in KEYS})


def _to_config(motion: EllipticalOrbitMotion, old: Mapping[str, Any]) -> dict[str, Any]:
    return {key: float(getattr(motion, key)) for key in KEYS}


KEYS = ("rpm", "semi_x", "semi_z", "phase")

ELLIPTICAL = register_motion_kind(MotionKind(
    name="elliptical",
    cls=EllipticalOrbitMotion,
    offset=elliptical_offset,
    frequency_hz=lambda m: jnp.asarray(m.rpm) / 60.0,
    config_keys=KEYS,
    from_config=_from_config,
    to_config=_to_config,
    design_parameters={"rpm": "rpm", "semi_x": "m", "semi_z": "m", "phase": "rad"},
    scale=lambda m, factor: m.replace(semi_x=m.semi_x * factor, semi_z=m.semi_z * factor),
))
