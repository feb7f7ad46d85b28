"""The Emax-like milling jar: parameters, analytic SDFs, wall patches, mesh.

The standard jar and its modified variant are those of docs/conventions.md section 2.

Jar frame: the origin is the centre of the jar floor, y points up. The cavity (the region where
the balls are) is a vertical prism over a *stadium*: two semicircles of radius ``radius`` centred
at x = +-straight_length/2, z = 0, joined by straight segments of length ``straight_length``
along x; the floor is y = 0 and the lid y = ``height``. Optionally a solid cylinder of radius
``post_radius`` stands on the axis x = z = 0 through the full height (the "modified" jar).

Three views of the same parameters:

- :func:`jar_sdf` -- the exact signed distance (negative inside the cavity, the SDF sign convention
  of docs/conventions.md section 1), in jax, differentiable in the points and in the parameters;
- :func:`jar_patch_sdf_and_normal` -- one SDF per wall patch (floor, lid, side[, post]), the
  signed distance to that patch's own infinite surface, for the DEM (docs/conventions.md section 3:
  a ball in a concave edge must feel both walls);
- :func:`jar_mesh` -- a watertight triangle mesh of the cavity for STL export and for sampling
  the SDF grid from a mesh.
"""

from __future__ import annotations

import math
from typing import Any

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from sgn_jax.geometry.common import GeometryError, safe_norm, safe_normalize


@flax.struct.dataclass
class JarParams:
    """Emax-like stadium cavity (docs/conventions.md section 2), all lengths in m, jar frame.

    The float fields are pytree leaves (so ``jax.grad`` can differentiate with respect to the
    jar's dimensions); ``has_post`` is static (it changes the number of wall patches).
    """

    radius: float | jax.Array = 0.020
    straight_length: float | jax.Array = 0.035
    height: float | jax.Array = 0.047
    post_radius: float | jax.Array = 0.0
    has_post: bool = flax.struct.field(pytree_node=False, default=False)


def jar_volume(params: JarParams) -> float | jax.Array:
    """Analytic cavity volume (m^3): ``(pi r^2 + 2 r L) H - pi r_post^2 H`` (post only if has_post).

    Plain arithmetic, so it returns a float for float parameters and an array for traced ones.
    """
    r, length, height = params.radius, params.straight_length, params.height
    volume = (math.pi * r * r + 2 * r * length) * height
    if params.has_post:
        volume = volume - math.pi * params.post_radius * params.post_radius * height
    return volume


def patch_names(params: JarParams) -> tuple[str, ...]:
    """Names of the wall patches, in the order of the last axis of :func:`jar_patch_sdf`."""
    return ("floor", "lid", "side", "post") if params.has_post else ("floor", "lid", "side")


def _side_vector(params: JarParams, x: jax.Array) -> jax.Array:
    """(..., 3) horizontal vector from the nearest point of the stadium's centre segment to x.

    The stadium is the set of points within ``radius`` of the segment x in [-L/2, L/2] on the
    line y = z = 0 (in the x-z plane), so its 2-D signed distance is |this vector| - radius.
    """
    half = params.straight_length / 2
    dx = x[..., 0] - jnp.clip(x[..., 0], -half, half)
    return jnp.stack([dx, jnp.zeros_like(dx), x[..., 2]], axis=-1)


def _axis_vector(x: jax.Array) -> jax.Array:
    """(..., 3) horizontal vector from the jar axis (x = z = 0) to x."""
    return jnp.stack([x[..., 0], jnp.zeros_like(x[..., 0]), x[..., 2]], axis=-1)


def jar_sdf(params: JarParams, x: jax.Array) -> jax.Array:
    """Exact signed distance to the cavity wall (m), negative inside the cavity.

    Args:
        params: the jar.
        x: (..., 3) jar-frame points (m).

    Returns:
        (...,) phi. Exact everywhere, inside and outside: the horizontal cross-section's 2-D SDF
        ``max(|side vector| - r, r_post - |axis vector|)`` is exact (the post lies strictly inside
        the stadium), and the standard prism extrusion of an exact 2-D SDF is exact. Gradients
        with respect to ``x`` and ``params`` are finite everywhere (safe norms); on the medial
        surfaces (where two walls are equally near) phi is continuous but has a kink.
    """
    x = jnp.asarray(x)
    d_plane = safe_norm(_side_vector(params, x)) - params.radius
    if params.has_post:
        d_plane = jnp.maximum(d_plane, params.post_radius - safe_norm(_axis_vector(x)))
    y = x[..., 1]
    d_vertical = jnp.maximum(-y, y - params.height)
    inside = jnp.minimum(jnp.maximum(d_plane, d_vertical), 0)
    outside = safe_norm(
        jnp.stack([jnp.maximum(d_plane, 0), jnp.maximum(d_vertical, 0)], axis=-1)
    )
    return inside + outside


def jar_patch_sdf_and_normal(params: JarParams, x: jax.Array) -> tuple[jax.Array, jax.Array]:
    """One SDF per wall patch and its analytic unit normal.

    Each patch's phi is the signed distance to that patch's own *infinite* surface (floor plane
    y = 0, lid plane y = H, the infinite stadium cylinder, the infinite post cylinder), negative on
    the cavity side, so that a ball in a concave edge sees both walls
    (docs/conventions.md section 3). Inside the cavity ``max`` over the patches equals :func:`jar_sdf`.

    Args:
        params: the jar.
        x: (..., 3) jar-frame points (m).

    Returns:
        phi (..., P) and normal (..., P, 3) with P = len(patch_names(params)); the normal is the
        gradient of the patch's phi: it points from the point towards that wall. On a cylinder's
        axis (where the direction is undefined and the point is a full radius away from that
        wall) a fixed unit vector is returned instead.
    """
    x = jnp.asarray(x)
    y = x[..., 1]
    dtype = jnp.result_type(x.dtype, jnp.float32)
    ones = jnp.ones_like(y, dtype=dtype)
    zeros = jnp.zeros_like(y, dtype=dtype)

    side_vector = _side_vector(params, x)
    phis = [-y, y - params.height, safe_norm(side_vector) - params.radius]
    normals = [
        jnp.stack([zeros, -ones, zeros], axis=-1),
        jnp.stack([zeros, ones, zeros], axis=-1),
        safe_normalize(side_vector, fallback=jnp.array([0.0, 0.0, 1.0], dtype)),
    ]
    if params.has_post:
        axis_vector = _axis_vector(x)
        phis.append(params.post_radius - safe_norm(axis_vector))
        normals.append(-safe_normalize(axis_vector, fallback=jnp.array([0.0, 0.0, 1.0], dtype)))
    phi = jnp.stack(jnp.broadcast_arrays(*phis), axis=-1)
    normal = jnp.stack(normals, axis=-2)
    return phi, normal


def jar_patch_sdf(params: JarParams, x: jax.Array) -> jax.Array:
    """(..., P) signed distance of x to each wall patch's surface; see :func:`jar_patch_sdf_and_normal`."""
    return jar_patch_sdf_and_normal(params, x)[0]


# --------------------------------------------------------------------------------------------
# Mesh


def _stadium_polygon(radius: float, straight_length: float, segments: int) -> np.ndarray:
    """(M, 2) counter-clockwise stadium outline in the (x, z) plane; vertices lie on the arcs.

    ``segments`` is the number of polygon edges per full circle (each semicircle gets half).
    """
    n_half = max(segments // 2, 2)
    angles = np.linspace(-np.pi / 2, np.pi / 2, n_half + 1)
    right = np.stack([straight_length / 2 + radius * np.cos(angles), radius * np.sin(angles)], 1)
    left = np.stack(
        [-straight_length / 2 + radius * np.cos(angles + np.pi), radius * np.sin(angles + np.pi)],
        1,
    )
    return np.concatenate([right, left])


def _circle_polygon(radius: float, segments: int) -> np.ndarray:
    angles = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    return np.stack([radius * np.cos(angles), radius * np.sin(angles)], 1)


def jar_mesh(params: JarParams, segments: int = 256) -> Any:
    """Watertight closed triangle mesh of the cavity (the region where the balls are).

    The cross-section (stadium minus the post disc) is built as polygons with ``segments`` edges
    per full circle and vertices exactly on the arcs (so the polygon lies inside the true curve by
    at most the sagitta ``r (1 - cos(pi / segments))``: 1.5 um for r = 20 mm and 256 segments),
    extruded with manifold3d and turned so that the extrusion axis is y. Faces are wound so
    that normals point out of the cavity. Returns a ``trimesh.Trimesh`` in m, jar frame.
    """
    import manifold3d
    import trimesh

    if segments < 8:
        raise GeometryError(f"jar_mesh needs segments >= 8 per circle, got {segments}")
    radius, straight_length = float(params.radius), float(params.straight_length)
    height, post_radius = float(params.height), float(params.post_radius)
    if min(radius, height) <= 0 or straight_length < 0:
        raise GeometryError(
            f"jar dimensions must be positive: radius={radius}, height={height}, "
            f"straight_length={straight_length} (>= 0)"
        )
    section = manifold3d.CrossSection([_stadium_polygon(radius, straight_length, segments)])
    if params.has_post:
        if not 0 < post_radius < radius:
            raise GeometryError(f"post_radius must be in (0, radius={radius}), got {post_radius}")
        section = section - manifold3d.CrossSection([_circle_polygon(post_radius, segments)])
    solid = manifold3d.Manifold.extrude(section, height)
    raw = solid.to_mesh64() if hasattr(solid, "to_mesh64") else solid.to_mesh()
    xyz = np.asarray(raw.vert_properties, dtype=np.float64)[:, :3]
    faces = np.asarray(raw.tri_verts, dtype=np.int64)
    # Manifold extrudes along +Z from the (X, Y) plane; the jar's axis is y. (X, Y, Z) ->
    # (X, Z, -Y) is a proper rotation (det +1), so outward normals stay outward.
    vertices = np.stack([xyz[:, 0], xyz[:, 2], -xyz[:, 1]], axis=1)
    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, process=True)
    if not (mesh.is_watertight and mesh.is_winding_consistent) or mesh.volume <= 0:
        raise GeometryError(
            "internal error: the jar mesh is not a closed, consistently wound solid "
            f"(watertight={mesh.is_watertight}, volume={mesh.volume})"
        )
    return mesh


