"""Shared helpers of the geometry package: the error type and NaN-free norms."""

from __future__ import annotations

import jax.numpy as jnp

from sgn_jax.errors import SGNJaxError


class GeometryError(SGNJaxError, ValueError):
    """Bad geometry input: a non-watertight or inconsistently wound STL, a missing file, an
    empty mesh, or grid parameters that cannot describe a grid."""


def safe_norm(v: jnp.ndarray, axis: int = -1) -> jnp.ndarray:
    """Euclidean norm along ``axis`` whose gradient is finite everywhere.

    ``jnp.linalg.norm`` has a NaN gradient at the zero vector (0/0). The double ``where``
    evaluates the square root only on a strictly positive argument, so both the value (0) and
    the gradient (0) are finite at the origin, and the result is exact elsewhere.
    """
    squared = jnp.sum(v * v, axis=axis)
    positive = squared > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, squared, 1)), 0)


def safe_normalize(
    v: jnp.ndarray, fallback: jnp.ndarray | None = None, axis: int = -1
) -> jnp.ndarray:
    """``v / |v|`` along ``axis`` with a finite value and gradient where ``v`` is zero.

    Where ``|v| == 0`` the result is ``fallback`` (broadcast to ``v``; zeros if None).
    """
    squared = jnp.sum(v * v, axis=axis, keepdims=True)
    positive = squared > 0
    inv_norm = jnp.where(positive, 1 / jnp.sqrt(jnp.where(positive, squared, 1)), 0)
    unit = v * inv_norm
    if fallback is None:
        return unit
    return jnp.where(positive, unit, jnp.broadcast_to(jnp.asarray(fallback, v.dtype), v.shape))
