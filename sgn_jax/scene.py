"""The scene: the jar geometry and its motion, and the one wall-query protocol of both simulators.

A scene is three things (:class:`Scene`):

- ``geometry``: a pytree the walls are computed from (``JarParams`` of the parametric jar, or the
  ``SDFGrid`` sampled from a mesh); traced, so it is differentiable and vmappable;
- ``motion``: a :mod:`sgn_jax.motion` pytree, ``offset(motion, t)`` is the lab position of the
  jar-frame origin; traced;
- ``walls``: a :data:`WallQuery`, static (a function).

**The wall-query protocol.** ``walls(geometry, x_jar) -> (phi (..., P), normal (..., P, 3))``:
at jar-frame points ``x_jar`` (..., 3) (m), the signed distance of each of P wall patches
(negative inside the cavity, docs/conventions.md section 1) and its unit normal (pointing towards
the wall). The implementations:

- :func:`patch_walls` - the parametric jar as P separate analytic patches (floor, lid, side,
  post): a ball in a concave edge feels both walls (the DEM's default for the parametric jar);
- :func:`analytic_walls` - the parametric jar's exact combined SDF as one patch, normal by
  autodiff (the surrogate's exact query, differentiable in the jar parameters);
- :func:`grid_walls` - a sampled SDF grid (patch-stacked or one combined grid) as one patch;
  a mesh (STL) jar is sampled into a grid by :func:`sgn_jax.pipelines.configure.sdf_grid_from_config`
  and read through this query.

The DEM uses the patches directly (:func:`sgn_jax.dem.engine.make_dem_step` takes the
``walls``); the surrogate's featurizer needs the nearest wall in the lab frame, which
:func:`lab_query` derives from the same protocol: ``lab_query(walls)(geometry, points, offset)``
is the patch with the largest phi at ``points - offset``. The rotational-frequency feature of the
surrogate is ``sgn_jax.motion.frequency_hz`` of the same motion object, in training
(:mod:`sgn_jax.pipelines.features`) and in the rollout.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any, NamedTuple

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from sgn_jax.geometry import (
    JarParams,
    SDFGrid,
    grid_sdf,
    jar_bounds,
    jar_patch_sdf_and_normal,
    jar_sdf,
    patch_names,
    query_sdf_grid,
    query_sdf_grid_patches,
    safe_normalize,
)
from sgn_jax.motion import Motion, frequency_hz, offset, velocity

WallQuery = Callable[[Any, jax.Array], tuple[jax.Array, jax.Array]]
"""``walls(geometry, x_jar (..., 3)) -> (phi (..., P), unit normal (..., P, 3))``, jar frame."""

SDFQuery = Callable[[Any, jax.Array, jax.Array], tuple[jax.Array, jax.Array]]
"""``query(geometry, points (..., 3), jar_offset (3,)) -> (phi (...), normal (..., 3))``: the
nearest wall at lab-frame points of a jar at ``jar_offset`` (the surrogate's form)."""


# ---------------------------------------------------------------------------------------------
# Wall queries (jar frame)


def patch_walls(jar: JarParams, x_jar: jax.Array) -> tuple[jax.Array, jax.Array]:
    """The parametric jar's analytic wall patches (P = 3, or 4 with a post)."""
    return jar_patch_sdf_and_normal(jar, x_jar)


def analytic_walls(jar: JarParams, x_jar: jax.Array) -> tuple[jax.Array, jax.Array]:
    """The parametric jar's exact SDF as one patch (P = 1); the normal is the autodiff gradient
    of :func:`sgn_jax.geometry.jar_sdf` (a kink only on the medial surfaces, where two walls are
    equally near). Differentiable in the points and the jar parameters."""
    x = jnp.asarray(x_jar)
    flat = x.reshape(-1, 3)
    phi, grad = jax.vmap(jax.value_and_grad(lambda p: jar_sdf(jar, p)))(flat)
    return (phi.reshape(x.shape[:-1])[..., None],
            safe_normalize(grad).reshape(x.shape)[..., None, :])


def grid_walls(grid: SDFGrid, x_jar: jax.Array) -> tuple[jax.Array, jax.Array]:
    """A sampled SDF grid as one patch (P = 1): trilinear phi and the normalised gradient of the
    interpolant (the max over the patches of a patch-stacked grid); results in ``x_jar``'s dtype."""
    x_jar = jnp.asarray(x_jar)
    phi, normal = query_sdf_grid(grid, x_jar, jnp.zeros(3, dtype=x_jar.dtype))
    return phi[..., None].astype(x_jar.dtype), normal[..., None, :].astype(x_jar.dtype)


def grid_patch_walls(grid: SDFGrid, x_jar: jax.Array) -> tuple[jax.Array, jax.Array]:
    """A patch-stacked SDF grid as its P patches (each patch's trilinear interpolant; P = 1
    for a single grid); its max over the patches is :func:`grid_walls`."""
    x_jar = jnp.asarray(x_jar)
    phi, normal = query_sdf_grid_patches(grid, x_jar, jnp.zeros(3, dtype=x_jar.dtype))
    return phi.astype(x_jar.dtype), normal.astype(x_jar.dtype)


# A wall query that merges patches (one column) -> the same walls patch by patch: a surrogate
# with one ball-wall edge per patch (GraphSpec.wall_patches) asks for this form.
_PATCHES_OF: dict[Any, WallQuery] = {}


def patches_of(walls: WallQuery) -> WallQuery:
    """The per-patch form of a wall query: ``analytic_walls`` -> ``patch_walls`` (the jar's
    exact patches), ``grid_walls`` -> ``grid_patch_walls``; a query that already has one
    column per patch is its own per-patch form."""
    return _PATCHES_OF.get(walls, walls)


def nearest_wall(walls: WallQuery, geometry: Any, x_jar: jax.Array
                 ) -> tuple[jax.Array, jax.Array]:
    """``(phi (...), normal (..., 3))`` of the patch with the largest phi (the nearest wall, or
    the one a ball penetrates most)."""
    phi, normal = walls(geometry, x_jar)
    if phi.shape[-1] == 1:  # static: one patch, nothing to choose
        return phi[..., 0], normal[..., 0, :]
    k = jnp.argmax(phi, axis=-1)
    return (jnp.take_along_axis(phi, k[..., None], axis=-1)[..., 0],
            jnp.take_along_axis(normal, k[..., None, None], axis=-2)[..., 0, :])


@functools.cache
def lab_query(walls: WallQuery) -> SDFQuery:
    """The surrogate's lab-frame :data:`SDFQuery` of a :data:`WallQuery` (one function object
    per ``walls``, so jit caches keyed on the query are reused)."""
    def query(geometry: Any, points: jax.Array, jar_offset: jax.Array
              ) -> tuple[jax.Array, jax.Array]:
        return nearest_wall(walls, geometry, jnp.asarray(points) - jnp.asarray(jar_offset))

    query.walls = walls  # type: ignore[attr-defined]
    return query


def lab_patch_query(walls: WallQuery) -> SDFQuery:
    """The lab-frame query of every patch of ``walls``: ``query(geometry, points (..., 3),
    jar_offset) -> (phi (..., P), normal (..., P, 3))``."""
    def query(geometry: Any, points: jax.Array, jar_offset: jax.Array
              ) -> tuple[jax.Array, jax.Array]:
        return walls(geometry, jnp.asarray(points) - jnp.asarray(jar_offset))

    query.walls = walls  # type: ignore[attr-defined]
    return query


_PATCHES_OF.update({analytic_walls: patch_walls, grid_walls: grid_patch_walls})

analytic_jar_query: SDFQuery = lab_query(analytic_walls)
"""The exact SDF of a ``JarParams`` jar in the surrogate's query form (design studies, tests)."""

grid_query: SDFQuery = lab_query(grid_walls)
"""An ``SDFGrid`` in the surrogate's query form (the featurizer's default)."""


# ---------------------------------------------------------------------------------------------
# The jar as the DEM sees it


class JarGeometry(NamedTuple):
    """A jar for the DEM: the geometry pytree, its wall query and what placement needs.

    Attributes:
        geometry: pytree given to ``wall_fn`` / ``sdf_fn`` (JarParams or SDFGrid).
        wall_fn: the :data:`WallQuery` ``wall_fn(geometry, x_jar) -> (phi (N,P), normal (N,P,3))``.
        sdf_fn: ``sdf_fn(geometry, x_jar) -> phi (N,)``, the combined SDF (placement, escapes).
        patch_names: names of the P patches.
        lower, upper: (3,) float64 corners of the cavity's bounding box, jar frame (m).
    """

    geometry: Any
    wall_fn: WallQuery
    sdf_fn: Callable[[Any, jnp.ndarray], jnp.ndarray]
    patch_names: tuple[str, ...]
    lower: np.ndarray
    upper: np.ndarray


def parametric_jar(params: JarParams) -> JarGeometry:
    """The parametric jar with one contact per analytic wall patch (floor, lid, side[, post]),
    parameters in float64."""
    params = jax.tree_util.tree_map(lambda v: jnp.asarray(v, jnp.float64), params)
    lower, upper = jar_bounds(params)
    return JarGeometry(params, patch_walls, jar_sdf, patch_names(params), lower, upper)


def grid_jar(grid: SDFGrid, margin: float) -> JarGeometry:
    """A jar read from an SDF grid (a single patch; ``margin`` (m) is the grid's padding around
    the cavity): a ball in a concave edge feels only the nearer wall, and the wall is only as
    smooth as the trilinear grid (documented limitation, docs/conventions.md section 3)."""
    lower = np.asarray(grid.origin, np.float64) + margin
    upper = np.asarray(grid.upper, np.float64) - margin
    return JarGeometry(grid, grid_walls, grid_sdf, ("mesh",), lower, upper)


# ---------------------------------------------------------------------------------------------
# The scene


@flax.struct.dataclass
class Scene:
    """Jar geometry + motion (traced pytrees) and the static wall query of both simulators.

    ``scene.wall_query(x_jar)`` is the DEM's view (patches, jar frame);
    ``scene.nearest_wall(points, t)`` the surrogate's (nearest wall, lab frame, at time ``t`` s
    since the start of motion); ``scene.sdf_query`` the :data:`SDFQuery` the rollout takes.
    """

    geometry: Any
    motion: Motion
    walls: WallQuery = flax.struct.field(pytree_node=False, default=grid_walls)

    def jar_offset(self, t: float | jax.Array) -> jax.Array:
        """Lab position (m) of the jar-frame origin at time ``t``: ``t.shape + (3,)``."""
        return offset(self.motion, t)

    def jar_velocity(self, t: float | jax.Array) -> jax.Array:
        """Jar velocity (m/s) at time ``t``."""
        return velocity(self.motion, t)

    def frequency_hz(self) -> jax.Array:
        """The motion's rotational frequency (Hz), the surrogate's wall-node feature."""
        return frequency_hz(self.motion)

    def wall_query(self, x_jar: jax.Array) -> tuple[jax.Array, jax.Array]:
        """The patches at jar-frame points: ``(phi (..., P), normal (..., P, 3))``."""
        return self.walls(self.geometry, x_jar)

    def nearest_wall(self, points: jax.Array, t: float | jax.Array
                     ) -> tuple[jax.Array, jax.Array]:
        """The nearest wall at lab-frame ``points`` (..., 3) at time ``t`` (a scalar)."""
        return self.sdf_query(self.geometry, points, self.jar_offset(t))

    @property
    def sdf_query(self) -> SDFQuery:
        """The lab-frame query of :attr:`walls`, for
        :func:`sgn_jax.surrogate.rollout.make_rollout`."""
        return lab_query(self.walls)


__all__ = [
    "JarGeometry",
    "SDFQuery",
    "Scene",
    "WallQuery",
    "analytic_jar_query",
    "analytic_walls",
    "grid_jar",
    "grid_query",
    "grid_patch_walls",
    "grid_walls",
    "lab_patch_query",
    "lab_query",
    "nearest_wall",
    "parametric_jar",
    "patch_walls",
    "patches_of",
]
