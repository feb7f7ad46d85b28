"""SDF grids: layout, accuracy of trilinear interpolation, mesh vs analytic grids, caching,
normals, gradients, jit/vmap, points outside the grid, dtypes."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import sgn_jax  # noqa: F401  (enables x64)
from sgn_jax.config import builtin_config_path, load_config, replace_section
from sgn_jax.geometry import (
    GeometryError,
    JarParams,
    SDFGrid,
    accuracy,
    grid_layout,
    grid_node_coordinates,
    grid_sdf,
    jar_mesh,
    jar_sdf,
    query_sdf_grid,
    sdf_grid_from_config,
    sdf_grid_from_fn,
    sdf_grid_from_jar,
    sdf_grid_from_mesh,
)
from sgn_jax.geometry.accuracy import PLANAR_PIECES, POST, piece_labels

DEFAULT = JarParams()
POST_JAR = JarParams(post_radius=0.006, has_post=True)
SPACING = 5e-4



def cavity_points(params: JarParams, n: int, seed: int) -> np.ndarray:
    return accuracy.cavity_points(params, n, seed)


def cell_corners(grid: SDFGrid, pts: np.ndarray) -> np.ndarray:
    return accuracy.cell_corners(grid.origin, grid.spacing, pts)


@pytest.fixture(scope="module")
def grids():
    return {
        ("default", "f32"): sdf_grid_from_jar(DEFAULT, SPACING),
        ("default", "f64"): sdf_grid_from_jar(DEFAULT, SPACING, dtype=jnp.float64),
        ("post", "f32"): sdf_grid_from_jar(POST_JAR, SPACING),
    }


# --------------------------------------------------------------------------------------------
# Layout


def test_grid_layout_is_centred_odd_and_covers_the_box():
    lower, upper = np.array([-0.0405, -0.003, -0.023]), np.array([0.0405, 0.05, 0.023])
    origin, shape = grid_layout(lower, upper, SPACING)
    assert all(n % 2 == 1 for n in shape)
    last = origin + SPACING * (np.array(shape) - 1)
    assert np.all(origin <= lower + 1e-12) and np.all(last >= upper - 1e-12)
    np.testing.assert_allclose((origin + last) / 2, (lower + upper) / 2, atol=1e-15)
    for bad in [(lower, upper, 0.0), (lower, upper, -1.0), (upper, lower, SPACING),
                (lower[:2], upper, SPACING)]:
        with pytest.raises(GeometryError):
            grid_layout(*bad)


def test_default_jar_grid_has_nodes_on_its_planes(grids):
    """At 0.5 mm the default jar's floor, lid, symmetry planes and straight-wall ends are node
    planes (so the kinks of phi there are reproduced exactly)."""
    grid = grids[("default", "f64")]
    nodes = grid_node_coordinates(grid)
    assert nodes.shape == grid.shape + (3,)
    x_axis, y_axis, z_axis = nodes[:, 0, 0, 0], nodes[0, :, 0, 1], nodes[0, 0, :, 2]
    for axis, planes in [(x_axis, [0.0, 0.0175, -0.0175]), (y_axis, [0.0, 0.047]), (z_axis, [0.0])]:
        for plane in planes:
            assert np.abs(axis - plane).min() < 1e-12, plane
    np.testing.assert_allclose(np.asarray(grid.values), np.asarray(jar_sdf(DEFAULT, jnp.asarray(nodes))),
                               atol=1e-15)


# --------------------------------------------------------------------------------------------
# Accuracy


@pytest.mark.parametrize("name", ["default", "post"])
def test_interpolation_error_against_exact_distance(grids, name):
    params = DEFAULT if name == "default" else POST_JAR
    grid = grids[(name, "f32")]
    h = grid.spacing
    pts = cavity_points(params, 20_000, seed=11)
    exact = np.asarray(jar_sdf(params, jnp.asarray(pts)))
    phi = np.asarray(grid_sdf(grid, jnp.asarray(pts, jnp.float32)), dtype=np.float64)
    err = np.abs(phi - exact)

    corners = cell_corners(grid, pts)
    point_label = piece_labels(params, pts)
    smooth = accuracy.smooth_cells(params, corners, point_label)
    planar = smooth & np.isin(point_label, PLANAR_PIECES)
    curved = smooth & ~planar
    band = exact > -0.006  # where wall contacts and PW edges happen (ball radius 5 mm)
    rms = lambda e: float(np.sqrt(np.mean(e**2))) if len(e) else 0.0  # noqa: E731
    print(f"\n{name} jar, h = {h * 1e3:.2f} mm, float32 grid, {len(pts)} random cavity points:")
    for label, sel in [("all", np.ones_like(smooth)), ("smooth planar cells", planar),
                       ("smooth curved cells", curved), ("crease cells (walls meet)", ~smooth),
                       ("band phi > -6 mm", band), ("band, smooth cells", band & smooth)]:
        print(f"  {label:27s} n={sel.sum():6d}  max {err[sel].max() * 1e6:8.3f} um"
              f"  rms {rms(err[sel]) * 1e6:7.3f} um")

    # Planes: trilinear interpolation is exact up to float32 rounding.
    assert err[planar].max() < 5e-8
    # Cylinders: within the rigorous curvature bound (h^2/8)(max|f_xx| + max|f_zz|).
    bound = accuracy.curvature_bound(params, corners, point_label, h)
    assert np.all(err[curved] <= bound[curved] + 5e-8)
    # Creases (the medial surfaces where two walls are equidistant): phi is 1-Lipschitz, so
    # the interpolant is within the largest corner distance, sqrt(3) h / 2, and no better
    # than O(h) -- see docs/geometry.md.
    assert err.max() <= math.sqrt(3) * h / 2
    if name == "default":
        # The 20 mm walls: below 5 um wherever balls touch the walls (smooth cells of the band).
        assert err[band & smooth].max() < 5e-6
    else:
        # The 6 mm post: h^2/(8 r_post) = 5.2 um; measured below the rigorous bound and above
        # what the 20 mm walls give.
        near_post = curved & (point_label == POST)
        assert err[near_post].max() > 2e-6
        assert err[near_post].max() <= h**2 / (8 * 0.006) * 1.2


def test_mesh_grid_matches_analytic_grid(tmp_path):
    spacing = 1e-3
    for params in (DEFAULT, POST_JAR):
        segments = 256
        mesh = jar_mesh(params, segments)
        from_mesh = sdf_grid_from_mesh(mesh, spacing, dtype=jnp.float64, cache_dir=tmp_path)
        analytic = sdf_grid_from_jar(params, spacing, dtype=jnp.float64)
        assert from_mesh.shape == analytic.shape
        np.testing.assert_allclose(np.asarray(from_mesh.origin), np.asarray(analytic.origin), atol=1e-8)
        diff = np.abs(np.asarray(from_mesh.values) - np.asarray(analytic.values))
        sag = params.radius * (1 - math.cos(math.pi / segments))
        print(f"mesh vs analytic grid: max {diff.max() * 1e6:.3f} um (sagitta {sag * 1e6:.3f} um)")
        # the polygon lies inside the circle by at most the sagitta; manifold3d rounds ~3 nm
        assert diff.max() <= sag + 1e-8


def test_mesh_grid_cache(tmp_path):
    mesh = jar_mesh(DEFAULT, 64)
    first = sdf_grid_from_mesh(mesh, 2e-3, cache_dir=tmp_path)
    files = list(tmp_path.glob("sdf_grid_*.npz"))
    assert len(files) == 1
    # A cache hit returns the stored values (tamper with the file to prove it was read).
    with np.load(files[0]) as data:
        stored = {k: data[k] for k in data.files}
    stored["values"] = stored["values"] + 1.0
    np.savez(files[0], **stored)
    again = sdf_grid_from_mesh(mesh, 2e-3, cache_dir=tmp_path)
    np.testing.assert_allclose(np.asarray(again.values), np.asarray(first.values) + 1.0, rtol=1e-6)
    # another spacing or another mesh is another key
    sdf_grid_from_mesh(mesh, 2.5e-3, cache_dir=tmp_path)
    sdf_grid_from_mesh(jar_mesh(DEFAULT, 72), 2e-3, cache_dir=tmp_path)
    assert len(list(tmp_path.glob("sdf_grid_*.npz"))) == 3
    assert not list(tmp_path.glob(".*.tmp"))  # atomic writes leave no temporaries
    # a corrupt file is recomputed and replaced
    files[0].write_bytes(b"not an npz")
    fixed = sdf_grid_from_mesh(mesh, 2e-3, cache_dir=tmp_path)
    np.testing.assert_allclose(np.asarray(fixed.values), np.asarray(first.values))


def test_grid_from_config_emax_and_stl(tmp_path, monkeypatch):
    monkeypatch.setenv("SGN_JAX_CACHE", str(tmp_path / "cache"))
    cfg = load_config(builtin_config_path("emax_300rpm"))
    cfg = replace_section(cfg, "sdf", spacing=2e-3)
    emax = sdf_grid_from_config(cfg)
    assert emax.values.dtype == jnp.float32 and emax.spacing == 2e-3
    path = tmp_path / "jar.stl"
    jar_mesh(DEFAULT).export(path)
    stl_cfg = replace_section(cfg, "jar", kind="stl", stl_path=str(path))
    stl = sdf_grid_from_config(stl_cfg)
    assert stl.shape == emax.shape
    assert np.abs(np.asarray(stl.values) - np.asarray(emax.values)).max() < 2e-6
    assert list((tmp_path / "cache").glob("sdf_grid_*.npz"))  # $SGN_JAX_CACHE was used


# --------------------------------------------------------------------------------------------
# Queries: normals, gradients, transforms


def test_normals_are_unit_and_point_to_the_nearest_wall(grids):
    grid = grids[("default", "f64")]
    pts = cavity_points(DEFAULT, 5000, seed=12)
    query = jax.jit(query_sdf_grid)
    phi, normal = query(grid, jnp.asarray(pts), jnp.zeros(3))
    normal = np.asarray(normal)
    np.testing.assert_allclose(np.linalg.norm(normal, axis=1), 1.0, atol=1e-12)
    exact_normal = np.asarray(jax.jit(jax.vmap(jax.grad(lambda x: jar_sdf(DEFAULT, x))))(jnp.asarray(pts)))
    labels = piece_labels(DEFAULT, pts)
    smooth = accuracy.smooth_cells(DEFAULT, cell_corners(grid, pts), labels)
    cosine = np.sum(normal * exact_normal, axis=1)
    # in smooth cells near the walls the normal is the wall's normal
    near = smooth & (np.asarray(phi) > -0.01)
    assert near.sum() > 1000 and cosine[near].min() > 0.999
    # everywhere: a step along the normal approaches the wall
    stepped, _ = query(grid, jnp.asarray(pts + 1e-4 * normal), jnp.zeros(3))
    assert np.all(np.asarray(stepped) > np.asarray(phi))


def test_gradients_match_finite_differences(grids):
    grid = grids[("default", "f64")]
    rng = np.random.default_rng(13)
    points = jnp.asarray(cavity_points(DEFAULT, 64, seed=14))
    offset = jnp.asarray(rng.uniform(-0.017, 0.017, 3) * np.array([1, 0, 1]))
    lab = points + offset

    def total(values, pts, off):
        return jnp.sum(query_sdf_grid(SDFGrid(values, grid.origin, grid.spacing), pts, off)[0])

    g_values, g_points, g_offset = jax.jit(jax.grad(total, argnums=(0, 1, 2)))(grid.values, lab, offset)
    # d phi / d offset = - sum of d phi / d points
    np.testing.assert_allclose(np.asarray(g_offset), -np.asarray(g_points).sum(0), atol=1e-12)
    query = jax.jit(query_sdf_grid)
    # d phi / d point is the gradient behind the returned normal
    phi, normal = query(grid, lab, offset)
    norms = np.linalg.norm(np.asarray(g_points), axis=1)
    np.testing.assert_allclose(np.asarray(g_points), np.asarray(normal) * norms[:, None], atol=1e-12)
    # finite differences in the points (inside a cell the interpolant is smooth)
    eps = 1e-8
    for axis in range(3):
        step = jnp.zeros(3).at[axis].set(eps)
        fd = query(grid, lab + step, offset)[0] - query(grid, lab - step, offset)[0]
        np.testing.assert_allclose(np.asarray(g_points)[:, axis], np.asarray(fd) / (2 * eps),
                                   rtol=1e-5, atol=1e-6)
    # and in the grid values (phi is linear in them: the weights sum to one per point)
    assert float(jnp.sum(g_values)) == pytest.approx(len(points), rel=1e-12)
    total_jit = jax.jit(total)
    touched = np.argwhere(np.asarray(g_values) != 0)[:5]
    for idx in map(tuple, touched):
        bumped = grid.values.at[idx].add(1e-3)
        fd = (total_jit(bumped, lab, offset) - total_jit(grid.values, lab, offset)) / 1e-3
        assert float(fd) == pytest.approx(float(g_values[idx]), rel=1e-8)


def test_offset_translates_the_field(grids):
    grid = grids[("default", "f32")]
    pts = jnp.asarray(cavity_points(DEFAULT, 100, seed=15), jnp.float32)
    offset = jnp.array([0.017, 0.0, -0.004], jnp.float32)
    query = jax.jit(query_sdf_grid)
    phi_lab, n_lab = query(grid, pts + offset, offset)
    phi_jar, n_jar = query(grid, pts, jnp.zeros(3, jnp.float32))
    np.testing.assert_allclose(np.asarray(phi_lab), np.asarray(phi_jar), atol=2e-8)
    np.testing.assert_allclose(np.asarray(n_lab), np.asarray(n_jar), atol=1e-3)


def test_jit_and_vmap(grids):
    grid = grids[("post", "f32")]
    pts = jnp.asarray(cavity_points(POST_JAR, 256, seed=16), jnp.float32)
    offsets = jnp.asarray(np.random.default_rng(17).uniform(-0.02, 0.02, (256, 3)), jnp.float32)
    direct = query_sdf_grid(grid, pts + offsets, offsets)
    vmapped = jax.jit(jax.vmap(query_sdf_grid, in_axes=(None, 0, 0)))(grid, pts + offsets, offsets)
    jitted = jax.jit(query_sdf_grid)(grid, pts + offsets, offsets)
    grid_vmapped = jax.jit(jax.vmap(lambda g, p: query_sdf_grid(g, p, jnp.zeros(3, jnp.float32)),
                                    in_axes=(None, 0)))(grid, pts[:, None, :])
    for phi, normal in (vmapped, jitted):
        # float32: fusion may reorder roundings; normals are differences of values / h
        np.testing.assert_allclose(np.asarray(phi), np.asarray(direct[0]), atol=1e-9)
        np.testing.assert_allclose(np.asarray(normal), np.asarray(direct[1]), atol=1e-5)
    assert grid_vmapped[0].shape == (256, 1)
    # a grid is a pytree: values and origin are leaves, spacing is static
    leaves = jax.tree_util.tree_leaves(grid)
    assert len(leaves) == 2


def test_points_outside_the_grid_are_finite_and_positive(grids):
    grid = grids[("default", "f32")]
    upper = np.asarray(grid.upper, dtype=np.float64)
    directions = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [1, 1, 1]], float)
    distances = np.array([1e-3, 1e-2, 1.0, 1e3])
    pts = (directions[:, None, :] * (upper + distances[:, None])[None]).reshape(-1, 3)
    phi, normal = query_sdf_grid(grid, jnp.asarray(pts, jnp.float32), jnp.zeros(3, jnp.float32))
    phi, normal = np.asarray(phi), np.asarray(normal)
    assert np.all(np.isfinite(phi)) and np.all(np.isfinite(normal))
    assert np.all(phi > 0)
    np.testing.assert_allclose(np.linalg.norm(normal, axis=1), 1.0, atol=1e-5)
    # phi keeps growing away from the grid, at least as fast as the distance from the box
    phi = phi.reshape(len(directions), len(distances))
    assert np.all(np.diff(phi, axis=1) > 0)
    # an escaped ball at 1 km still gets a gradient pointing outwards
    grad = jax.grad(lambda p: grid_sdf(grid, p))(jnp.array([1e3, 0.01, 0.0], jnp.float32))
    assert np.all(np.isfinite(np.asarray(grad))) and float(grad[0]) > 0.99
    # the exact distance there is also positive and close (the box margin is 3 mm)
    exact = np.asarray(jar_sdf(DEFAULT, jnp.asarray(pts)))
    assert np.all(exact > 0)


def test_dtype_follows_inputs(grids):
    g32, g64 = grids[("default", "f32")], grids[("default", "f64")]
    pts32 = jnp.asarray(cavity_points(DEFAULT, 8, seed=18), jnp.float32)
    phi, normal = query_sdf_grid(g32, pts32, jnp.zeros(3, jnp.float32))
    assert phi.dtype == jnp.float32 and normal.dtype == jnp.float32
    phi, normal = query_sdf_grid(g32, pts32.astype(jnp.float64), jnp.zeros(3))
    assert phi.dtype == jnp.float64
    phi, _ = query_sdf_grid(g64, pts32.astype(jnp.float64), jnp.zeros(3))
    assert phi.dtype == jnp.float64


def test_sdf_grid_from_fn_validates_and_evaluates_in_chunks():
    # a sphere SDF on a box larger than one evaluation chunk
    grid = sdf_grid_from_fn(lambda x: jnp.linalg.norm(x, axis=-1) - 0.01, [-0.02] * 3, [0.02] * 3,
                            4e-4, dtype=jnp.float64)
    nodes = grid_node_coordinates(grid)
    assert nodes.size // 3 > 1 << 18
    np.testing.assert_allclose(np.asarray(grid.values), np.linalg.norm(nodes, axis=-1) - 0.01,
                               atol=1e-15)
    with pytest.raises(GeometryError, match="non-finite"):
        sdf_grid_from_fn(lambda x: jnp.log(x[..., 0]), [-1.0] * 3, [1.0] * 3, 0.5)
    with pytest.raises(GeometryError, match=r"\(n,\)"):
        sdf_grid_from_fn(lambda x: x, [-1.0] * 3, [1.0] * 3, 0.5)


@pytest.mark.slow
def test_mesh_grid_matches_analytic_grid_at_production_spacing(tmp_path):
    """The production setting (0.5 mm, 1.6 M nodes): same check as above, plus timing."""
    import time

    for params in (DEFAULT, POST_JAR):
        mesh = jar_mesh(params, 256)
        start = time.perf_counter()
        from_mesh = sdf_grid_from_mesh(mesh, SPACING, dtype=jnp.float64, cache_dir=tmp_path)
        elapsed = time.perf_counter() - start
        analytic = sdf_grid_from_jar(params, SPACING, dtype=jnp.float64)
        diff = np.abs(np.asarray(from_mesh.values) - np.asarray(analytic.values)).max()
        print(f"0.5 mm mesh grid {from_mesh.shape}: {elapsed:.1f} s, max diff {diff * 1e6:.3f} um")
        assert diff <= params.radius * (1 - math.cos(math.pi / 256)) + 1e-8
        assert elapsed < 60
