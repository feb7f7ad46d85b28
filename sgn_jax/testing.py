"""Synthetic data and random model weights for tests and examples (not physical)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import jax
import numpy as np

from sgn_jax.surrogate.model import init_params


@dataclass
class SyntheticTrajectory:
    """Trajectory-record-like arrays (only what the featurizer reads): smooth random ball motions
    inside the standard jar, which moves on the standard circle. Not physical: for tests."""

    t: np.ndarray
    pos: np.ndarray
    offset: np.ndarray
    offset_vel: np.ndarray
    diss_pp_normal: np.ndarray
    diss_pp_tangential: np.ndarray
    diss_pw_normal: np.ndarray
    diss_pw_tangential: np.ndarray
    meta: dict[str, Any]
    omega: np.ndarray | None = None


def synthetic_trajectory(n_samples: int = 64, n_particles: int = 8, *, dt: float = 1e-4,
                         radius: float = 0.005, frequency_hz: float = 5.0,
                         amplitude: float = 0.017, seed: int = 0) -> SyntheticTrajectory:
    """Balls wobbling (0.3 mm, 20-60 Hz) about fixed jar-frame centres while the jar circles.

    Half of the balls sit in a row on the floor (centre height just above R, so ball-wall edges
    come and go; neighbours 0.6-1.4 mm apart, so ball-ball edges too); the others float higher,
    spaced so that some pairs cross the ball-ball cutoff. Dissipation: random smooth, >= 0,
    first sample 0. Spins (``omega``): smooth, up to 40 rad/s.
    """
    rng = np.random.default_rng(seed)
    t = np.arange(n_samples) * dt
    w = 2 * np.pi * frequency_hz
    offset = np.stack([amplitude * np.sin(w * t), 0 * t, amplitude * np.cos(w * t)], -1)
    offset_vel = np.stack([amplitude * w * np.cos(w * t), 0 * t, -amplitude * w * np.sin(w * t)],
                          -1)
    n_floor = (n_particles + 1) // 2
    centres = []
    x = -0.03
    for _ in range(n_floor):
        centres.append([x, radius + 1e-4, rng.uniform(-0.005, 0.005) * 0.2])
        x += 2 * radius + rng.uniform(0.6e-3, 1.4e-3)
    x = -0.025
    for _ in range(n_particles - n_floor):
        centres.append([x, 0.022 + rng.uniform(-1e-3, 1e-3), rng.uniform(-0.004, 0.004)])
        x += 2 * radius + rng.uniform(1.0e-3, 2.5e-3)
    centres = np.asarray(centres)
    amp = rng.uniform(1e-4, 3e-4, (n_particles, 3))
    freq = rng.uniform(20.0, 60.0, (n_particles, 3)) * 2 * np.pi
    phase = rng.uniform(0, 2 * np.pi, (n_particles, 3))
    wobble = amp * np.sin(freq * t[:, None, None] + phase)
    pos = centres[None] + offset[:, None, :] + wobble
    diss = [np.abs(rng.normal(0, 1e-5)) * (1 + np.sin(rng.uniform(50, 200) * t
                                                     + rng.uniform(0, 6))) for _ in range(4)]
    for d in diss:
        d[0] = 0.0
    omega = 40.0 * np.sin(0.5 * freq * t[:, None, None] + phase)
    meta = {"dt": dt, "ball_radius": radius, "n_balls": n_particles,
            "config": {"motion": {"kind": "circle", "rpm": 60.0 * frequency_hz,
                                  "amplitude": amplitude, "phase": 0.0}}}
    return SyntheticTrajectory(t=t, pos=pos, offset=offset, offset_vel=offset_vel,
                               diss_pp_normal=diss[0], diss_pp_tangential=diss[1],
                               diss_pw_normal=diss[2], diss_pw_tangential=diss[3], meta=meta,
                               omega=omega)


def random_weights(shapes: Any, seed: int) -> Any:
    """Random weights for a pytree of ``jax.ShapeDtypeStruct`` (``jax.eval_shape`` of a model's
    init), drawn as flax's default init draws them (LeCun-normal kernels truncated at 2 std,
    zero biases) but in numpy: for tests that need some weights, without the init's op-by-op
    compilations (~150, ~6 s) or, jitted, its 3-5 s compile. Leaves whose path ends
    in ``['bias']`` are zeros; the others ``(fan_in, ...)`` kernels."""
    rng = np.random.default_rng(seed)

    def draw(path, leaf):
        if jax.tree_util.keystr(path).endswith("['bias']"):
            return np.zeros(leaf.shape, leaf.dtype)
        z = rng.standard_normal(leaf.shape)
        while np.any(np.abs(z) > 2.0):
            z = np.where(np.abs(z) > 2.0, rng.standard_normal(leaf.shape), z)
        # 0.8796...: the std of a standard normal truncated at +-2 (flax's variance scaling)
        return (z * np.sqrt(1.0 / leaf.shape[0]) / 0.87962566103423978).astype(leaf.dtype)

    return jax.tree_util.tree_map_with_path(draw, shapes)


def random_init_weights(model: Any, graph: Any, seed: int) -> Any:
    """:func:`random_weights` of the shapes ``init_params(model, graph)`` gives (its init is
    only traced, by ``jax.eval_shape``, not run)."""
    return random_weights(jax.eval_shape(lambda g: init_params(model, g, 0), graph), seed)
