"""Signed distance sampled on a regular grid, and its trilinear interpolation in jax.

The surrogate reads phi and grad(phi) of the jar from an :class:`SDFGrid` (one combined SDF, as
the paper's model sees it); the DEM uses the analytic wall patches instead (docs/conventions.md
section 3).

A grid holds either one SDF, values (nx, ny, nz) (an STL jar), or one SDF per wall patch,
values (P, nx, ny, nz) (the parametric jar, the default of :func:`sdf_grid_from_jar`). The
cavity is the intersection of the patches' half-spaces, so inside it phi = max_p phi_p exactly;
each phi_p is smooth there while phi has kinks wherever two walls are equally near (the
45-degree medial surfaces of the floor/lid-side edges). Interpolating each patch and taking the
max reproduces those kinks exactly, instead of smearing them over a cell (O(h) errors).

Grid layout: ``values[i, j, k]`` is phi at ``origin + spacing * (i, j, k)`` in the jar frame.
The node counts are odd and the grid is centred on the sampled box, so for a jar that is
symmetric about x = 0 and z = 0 (and for the default dimensions at 0.5 mm, also the floor, the
lid and the ends of the straight walls) nodes lie exactly on the symmetry planes, where phi has
a kink; trilinear interpolation is exact across a kink that lies on a node plane.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from sgn_jax.geometry.common import GeometryError, safe_norm, safe_normalize
from sgn_jax.geometry.jar import (
    JarParams,
    jar_patch_sdf,
    jar_sdf,
)

# Bump when the way a mesh grid is computed changes, so that old cache files are not reused.
_EVAL_CHUNK = 1 << 18  # points per jitted evaluation of an analytic SDF


@flax.struct.dataclass
class SDFGrid:
    """phi sampled on a regular grid (jar frame, negative inside the cavity: docs/conventions.md
    section 1).

    values: (nx, ny, nz) phi at the nodes (m), one combined SDF; or (P, nx, ny, nz), one SDF per
        wall patch, phi = max over the P interpolated patches (see :func:`query_sdf_grid`).
        Which of the two is decided by ``values.ndim`` (static under jit).
    origin: (3,) jar-frame position of node (i, j, k) = (0, 0, 0) (m).
    spacing: node spacing (m), the same on all axes (static).
    """

    values: jax.Array
    origin: jax.Array
    spacing: float = flax.struct.field(pytree_node=False)

    @property
    def shape(self) -> tuple[int, int, int]:
        """(nx, ny, nz): the node counts (without the patch axis of a patch-stacked grid)."""
        return tuple(self.values.shape[-3:])

    @property
    def n_patches(self) -> int:
        """P for values (P, nx, ny, nz); 1 for a plain (nx, ny, nz) grid."""
        return int(self.values.shape[0]) if self.values.ndim == 4 else 1

    @property
    def upper(self) -> jax.Array:
        """(3,) jar-frame position of the last node (nx - 1, ny - 1, nz - 1) (m)."""
        return self.origin + self.spacing * (jnp.asarray(self.shape, self.origin.dtype) - 1)


def grid_layout(lower: Any, upper: Any, spacing: float) -> tuple[np.ndarray, tuple[int, int, int]]:
    """Origin (3,) float64 and node counts of the grid that covers the box [lower, upper].

    Each axis gets an odd number of nodes, 2 ceil(extent / (2 spacing)) + 1, centred on the box,
    so the grid covers the box and has a node plane through the box's centre. A box that
    overshoots a whole number of cells by less than 1e-3 cell (rounding in mesh coordinates)
    does not get an extra pair of nodes.
    """
    lower = np.asarray(lower, dtype=np.float64).reshape(-1)
    upper = np.asarray(upper, dtype=np.float64).reshape(-1)
    if lower.shape != (3,) or upper.shape != (3,):
        raise GeometryError(f"lower and upper must have 3 coordinates, got {lower} and {upper}")
    if not (np.isfinite(spacing) and spacing > 0):
        raise GeometryError(f"grid spacing must be a positive number of metres, got {spacing}")
    if not np.all(upper > lower):
        raise GeometryError(f"grid box must have upper > lower on every axis, got {lower} .. {upper}")
    half_cells = np.ceil((upper - lower) / (2 * spacing) - 1e-3).astype(np.int64)
    shape = tuple(int(n) for n in 2 * half_cells + 1)
    n_nodes = int(np.prod(shape))
    if n_nodes > 2**31 - 1:
        raise GeometryError(
            f"grid of {shape} nodes is too large (> 2^31); use a coarser spacing than {spacing}"
        )
    origin = (lower + upper) / 2 - half_cells * spacing
    return origin, shape


def grid_node_coordinates(grid: SDFGrid) -> np.ndarray:
    """(nx, ny, nz, 3) float64 jar-frame coordinates of the grid nodes (m)."""
    origin = np.asarray(grid.origin, dtype=np.float64)
    axes = [origin[a] + grid.spacing * np.arange(n) for a, n in enumerate(grid.shape)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)


def _node_coordinates(origin: np.ndarray, shape: tuple[int, int, int], spacing: float) -> np.ndarray:
    axes = [origin[a] + spacing * np.arange(n) for a, n in enumerate(shape)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)


def sdf_grid_from_fn(
    fn: Callable[[jax.Array], jax.Array],
    lower: Any,
    upper: Any,
    spacing: float,
    dtype: Any = jnp.float32,
    *,
    per_patch: bool = False,
) -> SDFGrid:
    """Sample a jax SDF ``fn`` ((..., 3) jar-frame points -> (...,) phi) on the grid of
    :func:`grid_layout` (lower, upper, spacing). ``fn`` is evaluated in float64 in jitted chunks;
    values are stored in ``dtype``.

    With ``per_patch=True``, ``fn`` maps (..., 3) points to (..., P) per-patch SDFs (such as
    :func:`sgn_jax.geometry.jar_patch_sdf`) and the grid is patch-stacked, values (P, nx, ny, nz);
    queries return the max over the patches.
    """
    origin, shape = grid_layout(lower, upper, spacing)
    nodes = _node_coordinates(origin, shape, spacing)
    jitted = jax.jit(fn)
    chunk = min(_EVAL_CHUNK, len(nodes))
    values: np.ndarray | None = None
    for start in range(0, len(nodes), chunk):
        block = nodes[start : start + chunk]
        n_valid = len(block)
        if n_valid < chunk:  # keep one static shape, one compilation
            block = np.concatenate([block, np.repeat(block[-1:], chunk - n_valid, 0)])
        out = np.asarray(jitted(jnp.asarray(block, dtype=jnp.float64)), dtype=np.float64)
        if per_patch and (out.ndim != 2 or out.shape[0] != chunk or out.shape[1] < 1):
            raise GeometryError(
                "with per_patch=True the SDF function must map (n, 3) points to (n, P) per-patch "
                f"values, got shape {out.shape}"
            )
        if not per_patch and out.shape != (chunk,):
            raise GeometryError(
                f"the SDF function must map (n, 3) points to (n,) values, got shape {out.shape} "
                "(per-patch SDFs of shape (n, P) need per_patch=True)"
            )
        if values is None:
            values = np.empty((len(nodes),) + out.shape[1:])
        values[start : start + n_valid] = out[:n_valid]
    if not np.all(np.isfinite(values)):
        raise GeometryError("the SDF function returned non-finite values on the grid")
    if per_patch:  # (n_nodes, P) -> (P, nx, ny, nz)
        values = np.moveaxis(values, -1, 0).reshape((values.shape[-1],) + shape)
    else:
        values = values.reshape(shape)
    return SDFGrid(
        values=jnp.asarray(values, dtype=dtype),
        origin=jnp.asarray(origin, dtype=dtype),
        spacing=float(spacing),
    )


def jar_bounds(params: JarParams) -> tuple[np.ndarray, np.ndarray]:
    """(lower, upper) float64 corners of the cavity's bounding box, jar frame (m)."""
    lower, upper = cavity_box(params)
    return np.asarray(lower, np.float64), np.asarray(upper, np.float64)


def cavity_box(params: JarParams) -> tuple[jax.Array, jax.Array]:
    """:func:`jar_bounds` as a traceable function of the jar parameters: (3,) float64 corners
    (m), for a placement in a jar a design study changes."""
    r, length, height = (jnp.asarray(v, jnp.float64) for v in
                         (params.radius, params.straight_length, params.height))
    zero = jnp.zeros((), jnp.float64)
    return (jnp.stack([-(length / 2 + r), zero, -r]),
            jnp.stack([length / 2 + r, height, r]))


def sdf_grid_from_jar(
    params: JarParams,
    spacing: float = 5e-4,
    margin: float = 3e-3,
    dtype: Any = jnp.float32,
    per_patch: bool = True,
) -> SDFGrid:
    """Grid of the parametric jar over the cavity's bounding box grown by ``margin``.

    ``per_patch=True`` (default): one grid per wall patch (:func:`jar_patch_sdf`, values
    (P, nx, ny, nz), P = len(patch_names(params))), queried as the max over the patches. Inside
    the cavity this equals the exact :func:`jar_sdf` up to each patch's own (smooth) interpolation
    error: planes exactly, cylinders h^2 / (8 rho), including the corners where two walls are
    equally near. Outside the cavity the max over the patch half-spaces is not the Euclidean
    distance near convex corners and edges (it is smaller: max(a, b) instead of |(a, b)|), but
    it has the right sign, so an escaped ball still reads phi > 0.

    ``per_patch=False``: a single grid of the combined :func:`jar_sdf` (exact Euclidean distance
    at the nodes everywhere, but O(h) interpolation errors where two walls are equally near).
    """
    lower, upper = jar_bounds(params)
    params64 = jax.tree_util.tree_map(lambda v: jnp.asarray(v, jnp.float64), params)
    if per_patch:
        return sdf_grid_from_fn(
            lambda x: jar_patch_sdf(params64, x), lower - margin, upper + margin, spacing, dtype,
            per_patch=True,
        )
    return sdf_grid_from_fn(
        lambda x: jar_sdf(params64, x), lower - margin, upper + margin, spacing, dtype
    )


# --------------------------------------------------------------------------------------------
# Interpolation


def _interpolate(grid: SDFGrid, x: jax.Array, keep_patches: bool = False
                 ) -> tuple[jax.Array, jax.Array]:
    """phi (...,) and its gradient (..., 3) at jar-frame points x (..., 3).

    Trilinear inside the grid box. For a patch-stacked grid (values (P, nx, ny, nz)) every patch
    is interpolated with the same weights and phi is the max over the patches; the gradient is
    that of the maximising patch's interpolant (the gradient of the max wherever the max is
    unique; ties are a measure-zero set where any choice is a valid subgradient). Outside the
    grid box, the point is clamped to the box and the distance to the box is added, so phi keeps
    growing (an escaped ball has phi > 0) and is never NaN.

    ``keep_patches``: return every patch, phi (..., P) and gradients (..., P, 3) (P = 1 for a
    single grid), instead of the max.
    """
    values = grid.values
    if values.ndim not in (3, 4):
        raise GeometryError(
            f"SDFGrid.values must have shape (nx, ny, nz) or (P, nx, ny, nz), got {values.shape}"
        )
    x = jnp.asarray(x)
    dtype = jnp.result_type(values.dtype, x.dtype, grid.origin.dtype)
    x = x.astype(dtype)
    origin = grid.origin.astype(dtype)
    h = grid.spacing
    nx, ny, nz = values.shape[-3:]
    last = jnp.asarray([nx - 1, ny - 1, nz - 1], dtype)

    u = (x - origin) / h
    u_clamped = jnp.clip(u, 0, last)
    cell = jnp.clip(jnp.floor(u_clamped), 0, last - 1)
    t = u_clamped - cell
    i = cell.astype(jnp.int32)
    # (n_nodes,) or (P, n_nodes): the corners are gathered along the last axis, so that the
    # patches of a patch-stacked grid get a leading axis that broadcasts against the weights.
    flat = values.reshape(values.shape[:-3] + (-1,))
    base = (i[..., 0] * ny + i[..., 1]) * nz + i[..., 2]
    sx, sy = ny * nz, nz
    # All 8 corners in one gather (faster than 8 gathers), then converted:
    # converting the whole grid first would copy it on every call.
    corner_offsets = jnp.asarray(
        [di * sx + dj * sy + dk for di in (0, 1) for dj in (0, 1) for dk in (0, 1)], jnp.int32
    )
    corners = flat[..., base[..., None] + corner_offsets].astype(dtype)  # ([P,] ..., 8)
    c000, c001, c010, c011, c100, c101, c110, c111 = (corners[..., k] for k in range(8))

    tx, ty, tz = t[..., 0], t[..., 1], t[..., 2]
    # Interpolate along x, then y, then z.
    c00 = c000 + tx * (c100 - c000)
    c10 = c010 + tx * (c110 - c010)
    c01 = c001 + tx * (c101 - c001)
    c11 = c011 + tx * (c111 - c011)
    c0 = c00 + ty * (c10 - c00)
    c1 = c01 + ty * (c11 - c01)
    phi_inside = c0 + tz * (c1 - c0)

    # Analytic gradient of the trilinear interpolant (d/dt, then / h).
    dx0 = (c100 - c000) + ty * ((c110 - c010) - (c100 - c000))
    dx1 = (c101 - c001) + ty * ((c111 - c011) - (c101 - c001))
    d_dtx = dx0 + tz * (dx1 - dx0)
    d_dty = (c10 - c00) + tz * ((c11 - c01) - (c10 - c00))
    d_dtz = c1 - c0
    in_range = (u >= 0) & (u <= last)  # clamped axes do not vary with x
    grad_inside = jnp.stack([d_dtx, d_dty, d_dtz], axis=-1) / h * in_range

    # to_box: the vector from the nearest point of the grid box, written as (u - clamp(u)) h
    # so that it is exactly zero inside the box (x - (origin + u h) leaves rounding noise
    # whose direction would pollute the gradient).
    to_box = (u - u_clamped) * h
    if keep_patches:
        if values.ndim == 3:
            phi_inside, grad_inside = phi_inside[None], grad_inside[None]
        phi_p = jnp.moveaxis(phi_inside, 0, -1) + safe_norm(to_box)[..., None]
        grad_p = jnp.moveaxis(grad_inside, 0, -2) + safe_normalize(to_box)[..., None, :]
        return phi_p, grad_p

    if values.ndim == 4:
        # phi = max_p phi_p; its gradient is the maximising patch's (the first one on a tie).
        # Selecting phi and the gradient with the same mask keeps d phi / dx equal to the
        # returned gradient under autodiff, and a `where` differentiates into the selected patch
        # only (no NaN, no split). P is small and static: an unrolled elementwise chain.
        patch_phi, patch_grad = phi_inside, grad_inside
        phi_inside, grad_inside = patch_phi[0], patch_grad[0]
        for p in range(1, values.shape[0]):
            higher = patch_phi[p] > phi_inside
            phi_inside = jnp.where(higher, patch_phi[p], phi_inside)
            grad_inside = jnp.where(higher[..., None], patch_grad[p], grad_inside)

    phi = phi_inside + safe_norm(to_box)
    grad = grad_inside + safe_normalize(to_box)
    return phi, grad


def query_sdf_grid_patches(grid: SDFGrid, points: jax.Array, offset: jax.Array
                           ) -> tuple[jax.Array, jax.Array]:
    """Every patch of a patch-stacked grid at lab-frame points: phi (..., P) and unit normals
    (..., P, 3) of each patch's trilinear interpolant (P = 1 for a single grid); the max over
    the patches is :func:`query_sdf_grid`."""
    phi, grad = _interpolate(grid, jnp.asarray(points) - jnp.asarray(offset), keep_patches=True)
    return phi, safe_normalize(grad)


def grid_sdf(grid: SDFGrid, x_jar: jax.Array) -> jax.Array:
    """phi (...,) at jar-frame points x_jar (..., 3) by trilinear interpolation; for a
    patch-stacked grid the max over the interpolated patches (see :func:`query_sdf_grid` for
    the behaviour outside the grid)."""
    return _interpolate(grid, x_jar)[0]


def query_sdf_grid(
    grid: SDFGrid, points: jax.Array, offset: jax.Array
) -> tuple[jax.Array, jax.Array]:
    """phi and unit normal at lab-frame points for a jar whose origin is at ``offset``.

    Args:
        grid: the jar's SDF grid (jar frame).
        points: (..., 3) lab-frame points (m).
        offset: (3,) lab-frame position of the jar-frame origin (m) (broadcastable to points).

    Returns:
        phi (...,) = grid_sdf(grid, points - offset) and normal (..., 3) = grad phi / |grad phi|
        of the trilinear interpolant, pointing towards the nearest wall (zero where the gradient
        vanishes). For a patch-stacked grid (values (P, nx, ny, nz)) phi is the max over the
        interpolated patches and the normal that of the maximising patch. Outside the grid
        box phi is the value at the nearest box point plus the distance to the box: finite and
        growing. Jittable, vmappable, differentiable with respect
        to points, offset and grid.values. Compute dtype follows the inputs.
    """
    phi, grad = _interpolate(grid, jnp.asarray(points) - jnp.asarray(offset))
    return phi, safe_normalize(grad)
