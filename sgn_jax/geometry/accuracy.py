"""Accuracy analysis of SDF grids of the parametric jar (used by the tests and the benchmark).

The exact cavity SDF is piecewise smooth: on each *piece* it is the distance to one wall
surface -- a plane (floor, lid, the two straight walls) or a vertical cylinder (the two end
arcs, the post). Where two pieces meet (the medial surfaces, e.g. the 45-degree bisector of the
floor-side edge, the mid-plane z = 0 of the straight section, the arc axes) phi has a kink.
Trilinear interpolation is exact for planes, has the curvature error
(h^2 / 8)(max|f_xx| + max|f_zz|) ~ h^2 / (8 rho) on cylinders (rho: distance from the axis),
and an O(h) error in cells that straddle a kink. :func:`grid_error_report` measures the three.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from sgn_jax.geometry.jar import JarParams, jar_sdf
from sgn_jax.geometry.sdf_grid import grid_sdf

# The exact SDF as one program per shape: op by op it is ~60 small compilations per call shape.
# The same function, so the same distances up to float rounding of the fusion.
_jar_sdf = jax.jit(jar_sdf)

FLOOR, LID, WALL_ZPLUS, WALL_ZMINUS, ARC_RIGHT, ARC_LEFT, POST, CORNER = range(8)
PIECE_NAMES = ("floor", "lid", "wall_z+", "wall_z-", "arc_right", "arc_left", "post", "corner")
PLANAR_PIECES = (FLOOR, LID, WALL_ZPLUS, WALL_ZMINUS)


def piece_labels(params: JarParams, points: np.ndarray) -> np.ndarray:
    """(...,) int: the smooth piece of the exact SDF at each jar-frame point (..., 3).

    Computed from the geometry directly (numpy); CORNER marks outside points whose nearest wall
    point is on an edge (phi is then the distance to that edge, not to a wall surface).
    """
    points = np.asarray(points, dtype=np.float64)
    x, y, z = points[..., 0], points[..., 1], points[..., 2]
    r, half, height = float(params.radius), float(params.straight_length) / 2, float(params.height)
    rho_side = np.hypot(x - np.clip(x, -half, half), z)
    side_label = np.where(
        x > half, ARC_RIGHT, np.where(x < -half, ARC_LEFT, np.where(z >= 0, WALL_ZPLUS, WALL_ZMINUS))
    )
    values = [-y, y - height, rho_side - r]
    labels = [np.full(x.shape, FLOOR), np.full(x.shape, LID), side_label]
    if params.has_post:
        values.append(float(params.post_radius) - np.hypot(x, z))
        labels.append(np.full(x.shape, POST))
    values, labels = np.stack(values, -1), np.stack(labels, -1)
    best = np.argmax(values, axis=-1)
    label = np.take_along_axis(labels, best[..., None], -1)[..., 0]
    phi = np.asarray(_jar_sdf(params, jnp.asarray(points)))
    return np.where(np.abs(values.max(-1) - phi) < 1e-12, label, CORNER)


def cell_corners(origin: Any, spacing: float, points: np.ndarray) -> np.ndarray:
    """(n, 8, 3) corners of the grid cell (grid origin, spacing) holding each point (n, 3)."""
    origin = np.asarray(origin, dtype=np.float64)
    cell = np.floor((np.asarray(points, dtype=np.float64) - origin) / spacing)
    offsets = np.stack(np.meshgrid([0, 1], [0, 1], [0, 1], indexing="ij"), -1).reshape(8, 3)
    return origin + spacing * (cell[:, None, :] + offsets[None])


def smooth_cells(params: JarParams, corners: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """(n,) bool: the point's whole cell (8 corners) lies on the point's own smooth piece."""
    return np.all(piece_labels(params, corners) == labels[:, None], axis=1) & (labels != CORNER)


def curvature_bound(
    params: JarParams, corners: np.ndarray, labels: np.ndarray, spacing: float
) -> np.ndarray:
    """(n,) rigorous trilinear error bound (h^2 / 8)(max|f_xx| + max|f_zz|) over each cell.

    For f = +-(rho - R), rho the distance to a vertical axis: |f_xx| = dz^2 / rho^3 and
    |f_zz| = dx^2 / rho^3 (f_yy = 0), each <= 1 / rho. Zero for planar pieces.
    """
    half = float(params.straight_length) / 2
    axis_x = np.select([labels == ARC_RIGHT, labels == ARC_LEFT], [half, -half], 0.0)
    dx = corners[..., 0] - axis_x[:, None]
    dz = corners[..., 2]
    rho_min = np.hypot(np.clip(0.0, dx.min(1), dx.max(1)), np.clip(0.0, dz.min(1), dz.max(1)))
    ax, az = np.abs(dx).max(1), np.abs(dz).max(1)
    with np.errstate(divide="ignore", invalid="ignore"):
        bound = spacing**2 / 8 * (
            np.minimum(1 / rho_min, az**2 / rho_min**3) + np.minimum(1 / rho_min, ax**2 / rho_min**3)
        )
    return np.where(np.isin(labels, PLANAR_PIECES), 0.0, bound)


def cavity_points(params: JarParams, n: int, seed: int = 0) -> np.ndarray:
    """(n, 3) uniform random points inside the cavity (rejection sampling, numpy seed)."""
    rng = np.random.default_rng(seed)
    r, half, height = float(params.radius), float(params.straight_length) / 2, float(params.height)
    lower, upper = np.array([-half - r, 0.0, -r]), np.array([half + r, height, r])
    out: list[np.ndarray] = []
    while sum(len(o) for o in out) < n:
        pts = rng.uniform(lower, upper, size=(2 * n, 3))
        out.append(pts[np.asarray(_jar_sdf(params, jnp.asarray(pts))) < 0])
    return np.concatenate(out)[:n]


def grid_error_report(
    params: JarParams, grid: Any, n_points: int = 20_000, seed: int = 0, band: float = -0.006
) -> dict[str, dict[str, float]]:
    """Interpolation error of ``grid`` (an SDFGrid of the jar) at random cavity points.

    Returns {category: {"n", "max_um", "rms_um"}} for the categories "all", "smooth_planar",
    "smooth_curved", "crease" (cell straddles a kink), "band" (exact phi > ``band``: where
    wall contacts and wall edges happen) and "band_smooth".
    """
    points = cavity_points(params, n_points, seed)
    exact = np.asarray(_jar_sdf(params, jnp.asarray(points)))
    phi = np.asarray(grid_sdf(grid, jnp.asarray(points, grid.values.dtype)), dtype=np.float64)
    err = np.abs(phi - exact)
    labels = piece_labels(params, points)
    smooth = smooth_cells(params, cell_corners(grid.origin, grid.spacing, points), labels)
    planar = smooth & np.isin(labels, PLANAR_PIECES)
    in_band = exact > band
    categories = {
        "all": np.ones_like(smooth),
        "smooth_planar": planar,
        "smooth_curved": smooth & ~planar,
        "crease": ~smooth,
        "band": in_band,
        "band_smooth": in_band & smooth,
    }
    report = {}
    for name, sel in categories.items():
        e = err[sel]
        report[name] = {
            "n": int(sel.sum()),
            "max_um": float(e.max() * 1e6) if len(e) else 0.0,
            "rms_um": float(np.sqrt(np.mean(e**2)) * 1e6) if len(e) else 0.0,
        }
    return report
