"""Flat test walls: infinite planes as wall patches (for known-answer tests and examples).

``plane_wall_fn(planes, x)`` has the signature of a DEM ``wall_fn``: each plane is one patch
with the SDF ``phi = (x - point) . normal`` (negative on the cavity side) and the constant unit
``normal`` pointing from the cavity into the wall.
"""

from __future__ import annotations

from collections.abc import Sequence

import flax.struct
import jax.numpy as jnp
import numpy as np


@flax.struct.dataclass
class PlaneWalls:
    """P infinite planes. points (P,3) m: a point on each plane; normals (P,3): unit, into the wall."""

    points: jnp.ndarray
    normals: jnp.ndarray


def plane_walls(points: Sequence[Sequence[float]], normals: Sequence[Sequence[float]]
                ) -> PlaneWalls:
    """Planes through ``points`` with (normalised) ``normals`` pointing into the wall."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    if p.shape != n.shape:
        raise ValueError(f"points {p.shape} and normals {n.shape} must have the same shape (P,3)")
    lengths = np.linalg.norm(n, axis=1, keepdims=True)
    if np.any(lengths == 0):
        raise ValueError("plane normals must be non-zero")
    return PlaneWalls(points=jnp.asarray(p), normals=jnp.asarray(n / lengths))


def plane_wall_fn(planes: PlaneWalls, x: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
    """phi (N,P) m and normal (N,P,3) of every ball centre ``x`` (N,3) against every plane."""
    points = planes.points.astype(x.dtype)
    normals = planes.normals.astype(x.dtype)
    phi = jnp.einsum("npk,pk->np", x[:, None, :] - points[None, :, :], normals)
    normal = jnp.broadcast_to(normals[None, :, :], (x.shape[0],) + normals.shape)
    return phi, normal
