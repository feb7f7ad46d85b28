"""Jar geometry: parameters, analytic SDFs and wall patches, meshes, STL loading, SDF grids.

See docs/geometry.md for the definitions, sign conventions, error analysis and caching.
"""

from sgn_jax.geometry.common import GeometryError, safe_norm, safe_normalize
from sgn_jax.geometry.jar import (
    JarParams,
    jar_mesh,
    jar_patch_sdf,
    jar_patch_sdf_and_normal,
    jar_sdf,
    jar_volume,
    patch_names,
)
from sgn_jax.geometry.mesh_distance import mesh_signed_distance, signed_distance_grid
from sgn_jax.geometry.sdf_grid import (
    SDFGrid,
    grid_layout,
    grid_node_coordinates,
    grid_sdf,
    jar_bounds,
    query_sdf_grid,
    query_sdf_grid_patches,
    sdf_grid_from_fn,
    sdf_grid_from_jar,
)
from sgn_jax.geometry.stl import check_closed_mesh

__all__ = [
    "GeometryError",
    "JarParams",
    "SDFGrid",
    "check_closed_mesh",
    "grid_layout",
    "grid_node_coordinates",
    "grid_sdf",
    "jar_bounds",
    "jar_mesh",
    "jar_patch_sdf",
    "jar_patch_sdf_and_normal",
    "jar_sdf",
    "jar_volume",
    "mesh_signed_distance",
    "signed_distance_grid",
    "patch_names",
    "query_sdf_grid",
    "query_sdf_grid_patches",
    "safe_norm",
    "safe_normalize",
    "sdf_grid_from_fn",
    "sdf_grid_from_jar",
]
