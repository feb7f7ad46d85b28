"""Loading and validating a jar cavity given as an STL file.

Rules (see docs/geometry.md): the mesh must be a closed surface (every edge shared by exactly
two triangles) with consistent winding (each shared edge traversed in opposite directions by its
two triangles). A consistently wound mesh that is inside-out (negative volume) is turned
silently; anything else is refused with a :class:`GeometryError` that says what is wrong and how
to repair it. The mesh describes the cavity (where the balls are) in jar-frame coordinates.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from sgn_jax.geometry.common import GeometryError

UNIT_SCALES = {"m": 1.0, "mm": 1e-3}

_REPAIR_HINT = (
    "repair it in a mesh tool (e.g. MeshLab 'Close holes', Blender's 3D-Print toolbox) or in "
    "Python with trimesh.repair.fill_holes(mesh) / trimesh.repair.fix_normals(mesh), export it "
    "again, and check it with `sgn-jax jar`"
)


def edge_use_counts(mesh: Any) -> tuple[int, int]:
    """(open_edges, non_manifold_edges): edges used by one triangle / by more than two."""
    if len(mesh.faces) == 0:
        return 0, 0
    _, counts = np.unique(mesh.edges_sorted, axis=0, return_counts=True)
    return int(np.sum(counts == 1)), int(np.sum(counts > 2))


def check_closed_mesh(mesh: Any, name: str = "mesh") -> Any:
    """Validate a cavity mesh; return it with outward normals (inverted in place if inside-out).

    Raises GeometryError for an empty mesh, open (boundary) or non-manifold edges, inconsistent
    winding, or zero volume.
    """
    if len(mesh.faces) == 0:
        raise GeometryError(f"{name}: the mesh has no triangles")
    if not np.all(np.isfinite(mesh.vertices)):
        raise GeometryError(f"{name}: the mesh has non-finite vertex coordinates")
    open_edges, non_manifold_edges = edge_use_counts(mesh)
    if open_edges or non_manifold_edges or not mesh.is_watertight:
        problems = []
        if open_edges:
            problems.append(f"{open_edges} open (boundary) edges, i.e. holes in the surface")
        if non_manifold_edges:
            problems.append(f"{non_manifold_edges} non-manifold edges (shared by > 2 triangles)")
        raise GeometryError(
            f"{name}: the mesh is not watertight: {' and '.join(problems) or 'open surface'}; "
            f"the jar cavity must be a closed surface so that inside and outside are defined; "
            f"{_REPAIR_HINT}"
        )
    if not mesh.is_winding_consistent:
        raise GeometryError(
            f"{name}: inconsistent triangle winding: some neighbouring triangles traverse their "
            "shared edge in the same direction, so their normals disagree and inside/outside is "
            "ambiguous; fix the winding (trimesh.repair.fix_winding(mesh) or "
            f"trimesh.repair.fix_normals(mesh)); {_REPAIR_HINT}"
        )
    volume = float(mesh.volume)
    if volume == 0 or not np.isfinite(volume):
        raise GeometryError(f"{name}: the closed mesh encloses no volume (volume = {volume})")
    if volume < 0:
        # Consistent but inside-out: flip every triangle so that normals point outward.
        mesh.invert()
    return mesh


