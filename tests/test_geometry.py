"""Jar geometry: analytic SDF and patches, meshes, STL loading, mesh distance, CLI."""

from __future__ import annotations

import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh

import sgn_jax  # noqa: F401  (enables x64)
from sgn_jax.config import JarConfig, builtin_config_path, load_config
from sgn_jax.geometry import (
    GeometryError,
    JarParams,
    jar_mesh,
    jar_patch_sdf,
    jar_patch_sdf_and_normal,
    jar_sdf,
    jar_volume,
    mesh_signed_distance,
    patch_names,
)
from sgn_jax.geometry.mesh_distance import signed_distance_grid
from sgn_jax.pipelines.configure import (
    jar_mesh_from_config,
    jar_params_from_config,
    load_stl,
    mesh_report,
)

DEFAULT = JarParams()
POST = JarParams(post_radius=0.006, has_post=True)
BALL_RADIUS = 0.005


# The analytic SDFs run jitted: one compiled program per jar and point shape instead
# of dozens of op-by-op compiles per call; the same functions, the same numbers.
_jar_sdf = jax.jit(jar_sdf)
_jar_patch_sdf = jax.jit(jar_patch_sdf)
_jar_patch_sdf_and_normal = jax.jit(jar_patch_sdf_and_normal)


def sagitta(radius: float, segments: int) -> float:
    """Largest gap between a circle and its inscribed polygon with vertices on the circle."""
    return radius * (1 - math.cos(math.pi / segments))


def random_points(rng: np.random.Generator, n: int, pad: float = 0.004) -> np.ndarray:
    """Uniform points in the default jar's bounding box grown by ``pad`` (inside and outside)."""
    lower = np.array([-0.0375 - pad, -pad, -0.02 - pad])
    upper = np.array([0.0375 + pad, 0.047 + pad, 0.02 + pad])
    return rng.uniform(lower, upper, size=(n, 3))


def cavity_points(params: JarParams, rng: np.random.Generator, n: int) -> np.ndarray:
    """n uniform points strictly inside the cavity (rejection sampling on jar_sdf < 0)."""
    pts = random_points(rng, 6 * n, pad=0.0)
    inside = np.asarray(_jar_sdf(params, jnp.asarray(pts))) < 0
    assert inside.sum() >= n
    return pts[inside][:n]


@pytest.fixture(scope="module")
def default_mesh() -> trimesh.Trimesh:
    return jar_mesh(DEFAULT)


@pytest.fixture(scope="module")
def post_mesh() -> trimesh.Trimesh:
    return jar_mesh(POST)


# --------------------------------------------------------------------------------------------
# Parameters and volume


def test_jar_volume_matches_spec_and_formula():
    r, length, height = 0.020, 0.035, 0.047
    assert jar_volume(DEFAULT) == pytest.approx((math.pi * r**2 + 2 * r * length) * height, rel=1e-12)
    # 124.9 ml: the standard jar of docs/conventions.md section 2
    assert jar_volume(DEFAULT) * 1e6 == pytest.approx(124.9, abs=0.05)
    assert jar_volume(POST) == pytest.approx(jar_volume(DEFAULT) - math.pi * 0.006**2 * height)
    # post_radius is ignored without has_post
    assert jar_volume(JarParams(post_radius=0.006)) == jar_volume(DEFAULT)


def test_params_from_config_and_patch_names():
    cfg = load_config(builtin_config_path("emax_post_motion1"))
    params = jar_params_from_config(cfg.jar)
    assert params.has_post and params.post_radius == pytest.approx(0.006)
    assert patch_names(params) == ("floor", "lid", "side", "post")
    default = jar_params_from_config(load_config(builtin_config_path("emax_300rpm")).jar)
    assert not default.has_post
    assert patch_names(default) == ("floor", "lid", "side")
    with pytest.raises(GeometryError, match="emax"):
        jar_params_from_config(JarConfig(kind="stl", stl_path="x.stl"))


# --------------------------------------------------------------------------------------------
# Mesh


@pytest.mark.parametrize("params_name", ["default", "post"])
def test_jar_mesh_is_closed_and_has_the_analytic_volume(params_name, default_mesh, post_mesh):
    params, mesh = (DEFAULT, default_mesh) if params_name == "default" else (POST, post_mesh)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume > 0  # outward normals
    rel = abs(mesh.volume - jar_volume(params)) / jar_volume(params)
    print(f"{params_name}: mesh {mesh.volume * 1e6:.4f} ml, analytic "
          f"{jar_volume(params) * 1e6:.4f} ml, rel. error {rel:.2e}")
    assert rel < 0.01
    # The inscribed polygon loses at most the sagitta strips: a much tighter check than 1 %.
    perimeter = 2 * math.pi * params.radius + 2 * params.straight_length
    assert rel < perimeter * sagitta(params.radius, 256) * params.height / jar_volume(params) + 1e-3
    np.testing.assert_allclose(mesh.bounds, [[-0.0375, 0, -0.02], [0.0375, 0.047, 0.02]], atol=1e-8)


def test_mesh_vertices_lie_on_the_analytic_surface(default_mesh, post_mesh):
    for params, mesh in [(DEFAULT, default_mesh), (POST, post_mesh)]:
        phi = np.asarray(_jar_sdf(params, jnp.asarray(mesh.vertices)))
        # manifold3d rounds the cross-section coordinates at the nanometre level
        assert np.abs(phi).max() < 1e-8
        # the face normals point out of the cavity: phi grows along them
        centers = mesh.triangles_center + 1e-4 * mesh.face_normals
        assert np.all(np.asarray(_jar_sdf(params, jnp.asarray(centers))) > 0)


def test_jar_mesh_rejects_bad_input():
    with pytest.raises(GeometryError, match="segments"):
        jar_mesh(DEFAULT, segments=4)
    with pytest.raises(GeometryError, match="post_radius"):
        jar_mesh(JarParams(post_radius=0.03, has_post=True))


# --------------------------------------------------------------------------------------------
# STL


@pytest.mark.parametrize("units,scale", [("m", 1.0), ("mm", 1000.0)])
def test_stl_round_trip(tmp_path, default_mesh, units, scale):
    path = tmp_path / f"jar_{units}.stl"
    exported = default_mesh.copy()
    exported.apply_scale(scale)
    exported.export(path)
    loaded = load_stl(path, units)
    assert loaded.is_watertight and loaded.is_winding_consistent
    assert loaded.volume == pytest.approx(default_mesh.volume, rel=1e-6)
    np.testing.assert_allclose(loaded.bounds, default_mesh.bounds, atol=1e-8)
    assert len(loaded.faces) == len(default_mesh.faces)


def _box_stl(tmp_path, name, edit) -> str:
    box = trimesh.creation.box(extents=(0.02, 0.01, 0.03))
    faces = edit(np.array(box.faces))
    path = tmp_path / name
    trimesh.Trimesh(box.vertices, faces, process=False).export(path)
    return str(path)


def test_load_stl_refuses_open_mesh(tmp_path):
    path = _box_stl(tmp_path, "open.stl", lambda f: f[1:])  # one triangle removed
    with pytest.raises(GeometryError, match=r"not watertight: 3 open \(boundary\) edges") as err:
        load_stl(path)
    assert "fill_holes" in str(err.value)  # says how to fix it


def test_load_stl_refuses_inconsistent_winding(tmp_path):
    def flip_one(f):
        f[0] = f[0][::-1]
        return f

    path = _box_stl(tmp_path, "flipped.stl", flip_one)
    with pytest.raises(GeometryError, match="inconsistent triangle winding"):
        load_stl(path)


def test_load_stl_turns_inside_out_mesh(tmp_path):
    path = _box_stl(tmp_path, "inverted.stl", lambda f: f[:, ::-1])
    mesh = load_stl(path)
    assert mesh.volume == pytest.approx(0.02 * 0.01 * 0.03, rel=1e-6)


def test_load_stl_missing_file_and_bad_units(tmp_path):
    with pytest.raises(GeometryError, match="not found"):
        load_stl(tmp_path / "nope.stl")
    path = _box_stl(tmp_path, "box.stl", lambda f: f)
    with pytest.raises(GeometryError, match="units"):
        load_stl(path, "inch")
    bad = tmp_path / "garbage.stl"
    bad.write_bytes(b"\x00" * 10)
    with pytest.raises(GeometryError):
        load_stl(bad)


def test_mesh_from_config_and_report(tmp_path, default_mesh):
    cfg = load_config(builtin_config_path("emax_300rpm"))
    mesh = jar_mesh_from_config(cfg.jar)
    report = mesh_report(mesh, cfg.jar)
    json.dumps(report)  # JSON-able
    assert report["watertight"] and report["winding_consistent"]
    assert report["n_faces"] == len(mesh.faces)
    assert abs(report["volume_ml"] - report["analytic_volume_ml"]) < 0.01 * report["analytic_volume_ml"]
    path = tmp_path / "jar_mm.stl"
    scaled = default_mesh.copy()
    scaled.apply_scale(1000.0)
    scaled.export(path)
    stl_cfg = JarConfig(kind="stl", stl_path=str(path), stl_units="mm")
    stl_mesh = jar_mesh_from_config(stl_cfg)
    stl_report = mesh_report(stl_mesh, stl_cfg)
    assert "analytic_volume_ml" not in stl_report
    assert stl_report["volume_ml"] == pytest.approx(report["volume_ml"], rel=1e-6)


def test_cli_jar_writes_stl_and_prints_report(tmp_path, capsys):
    from sgn_jax.cli import main

    out = tmp_path / "jar.stl"
    assert main(["jar", "--config", str(builtin_config_path("emax_post_motion1")), "--out", str(out)]) == 0
    report = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert report["watertight"] and out.is_file()
    assert load_stl(out).volume * 1e6 == pytest.approx(report["volume_ml"], rel=1e-6)
    assert report["volume_ml"] == pytest.approx(jar_volume(POST) * 1e6, rel=0.01)


# --------------------------------------------------------------------------------------------
# Analytic SDF


@pytest.mark.parametrize("params_name", ["default", "post"])
def test_jar_sdf_is_the_exact_distance(params_name):
    """Compare with the exact distance to a fine mesh (independent code: triangles, brute
    force): they may differ only by the polygon's sagitta."""
    params = DEFAULT if params_name == "default" else POST
    segments = 1024
    fine = jar_mesh(params, segments=segments)
    pts = random_points(np.random.default_rng(0), 4000)
    phi = np.asarray(_jar_sdf(params, jnp.asarray(pts)))
    reference = mesh_signed_distance(fine, pts)
    tolerance = sagitta(params.radius, segments) + 1e-8
    err = np.abs(phi - reference)
    print(f"{params_name}: max |jar_sdf - mesh distance| = {err.max():.2e} m (inside and outside)")
    assert err.max() < tolerance
    assert (phi < 0).sum() > 1000 and (phi > 0).sum() > 500  # both sides were tested


def test_jar_sdf_gradients_are_finite_and_unit_everywhere():
    # Special points: the stadium's centre segment, the post axis, arc centres, faces, edges,
    # corners, and points exactly on the ridge z = 0.
    special = np.array([
        [0.0, 0.02, 0.0], [0.0175, 0.02, 0.0], [-0.0175, 0.0235, 0.0], [0.01, 0.0, 0.0],
        [0.0375, 0.0, 0.0], [0.0375, 0.047, 0.0], [0.0, 0.047, 0.02], [0.0, 0.03, -0.02],
        [0.04, -0.002, 0.0], [0.0, 0.05, 0.023], [0.0175, 0.0, 0.02],
    ])
    for params in (DEFAULT, POST):
        grad_fn = jax.jit(jax.vmap(jax.grad(lambda x, p=params: jar_sdf(p, x))))
        assert np.all(np.isfinite(np.asarray(grad_fn(jnp.asarray(special)))))
        # the parameter gradient is finite at the special points too
        pgrad = jax.jit(jax.grad(lambda p: jnp.sum(jar_sdf(p, jnp.asarray(special)))))(
            jax.tree_util.tree_map(jnp.asarray, params))
        assert all(np.isfinite(float(v)) for v in jax.tree_util.tree_leaves(pgrad))
        pts = random_points(np.random.default_rng(1), 2000)
        grad = np.asarray(grad_fn(jnp.asarray(pts)))
        np.testing.assert_allclose(np.linalg.norm(grad, axis=1), 1.0, atol=1e-9)  # eikonal


def test_jar_sdf_gradients_match_finite_differences():
    rng = np.random.default_rng(2)
    params = JarParams(radius=jnp.float64(0.02), straight_length=jnp.float64(0.035),
                       height=jnp.float64(0.047), post_radius=jnp.float64(0.006), has_post=True)
    pts = jnp.asarray(random_points(rng, 64))
    eps = 1e-7

    @jax.jit
    def total(p):
        return jnp.sum(jar_sdf(p, pts))

    grads = jax.grad(total)(params)
    for name in ("radius", "straight_length", "height", "post_radius"):
        value = getattr(params, name)
        plus = params.replace(**{name: value + eps})
        minus = params.replace(**{name: value - eps})
        fd = (total(plus) - total(minus)) / (2 * eps)
        assert float(getattr(grads, name)) == pytest.approx(float(fd), rel=1e-5, abs=1e-6), name
    # ... and with respect to the points
    x = pts[:16]
    g = jax.jit(jax.vmap(jax.grad(lambda xi: jar_sdf(params, xi))))(x)
    steps = eps * jnp.eye(3)[:, None, :]  # (3, 1, 3)
    fd = jax.jit(lambda x: (jar_sdf(params, x + steps) - jar_sdf(params, x - steps)) / (2 * eps))(x)
    np.testing.assert_allclose(np.asarray(g).T, np.asarray(fd), atol=1e-6)


# --------------------------------------------------------------------------------------------
# Wall patches


@pytest.mark.parametrize("params", [DEFAULT, POST], ids=["default", "post"])
def test_patch_max_equals_jar_sdf_inside(params):
    pts = jnp.asarray(cavity_points(params, np.random.default_rng(3), 5000))
    patches = _jar_patch_sdf(params, pts)
    assert patches.shape == (5000, len(patch_names(params)))
    np.testing.assert_allclose(np.asarray(patches.max(axis=-1)), np.asarray(_jar_sdf(params, pts)),
                               atol=1e-15)


@pytest.mark.parametrize("params", [DEFAULT, POST], ids=["default", "post"])
def test_patch_normals_are_unit_gradients(params):
    pts = jnp.asarray(random_points(np.random.default_rng(4), 500))
    phi, normal = _jar_patch_sdf_and_normal(params, pts)
    n_patches = len(patch_names(params))
    assert normal.shape == (500, n_patches, 3)
    np.testing.assert_allclose(np.linalg.norm(np.asarray(normal), axis=-1), 1.0, atol=1e-12)
    jac = jax.jit(jax.vmap(jax.jacfwd(lambda x: jar_patch_sdf(params, x))))(pts)  # (500, P, 3)
    np.testing.assert_allclose(np.asarray(jac), np.asarray(normal), atol=1e-12)
    # The normal points towards the wall: moving along it by delta raises phi by delta.
    delta = 1e-4
    moved = jax.jit(lambda x, n: jnp.stack([jar_patch_sdf(params, x + delta * n[:, k])[:, k]
                                            for k in range(n_patches)], axis=-1))(pts, normal)
    np.testing.assert_allclose(np.asarray(moved - phi), delta, atol=1e-12)


def test_ball_in_floor_side_edge_feels_both_walls():
    # A ball (R = 5 mm) resting in the concave edge where the floor meets the straight wall:
    # its centre is 4 mm above the floor and 4 mm from the side wall (both overlapping 1 mm).
    centre = jnp.array([0.005, 0.004, 0.020 - 0.004])
    phi = np.asarray(_jar_patch_sdf(DEFAULT, centre))
    names = patch_names(DEFAULT)
    touching = {names[k] for k in range(len(names)) if phi[k] > -BALL_RADIUS}
    assert touching == {"floor", "side"}
    np.testing.assert_allclose(phi[[0, 2]], [-0.004, -0.004], atol=1e-15)
    # the combined SDF sees only one contact distance, the patches give two
    assert float(_jar_sdf(DEFAULT, centre)) == pytest.approx(-0.004, abs=1e-15)
    # the same near the post and the lid
    centre = jnp.array([0.0, 0.047 - 0.003, 0.006 + 0.002])
    phi = dict(zip(patch_names(POST), np.asarray(_jar_patch_sdf(POST, centre)), strict=True))
    assert {k for k, v in phi.items() if v > -BALL_RADIUS} == {"lid", "post"}


# --------------------------------------------------------------------------------------------
# Mesh distance (exact branch-and-bound on grids vs brute force)


@pytest.mark.slow
def test_grid_mesh_distance_matches_brute_force(post_mesh):
    origin = np.array([-0.041, -0.0033, -0.0237])  # unaligned on purpose
    shape = (23, 17, 15)
    spacing = 0.0037
    grid = signed_distance_grid(post_mesh, origin, shape, spacing)
    axes = [origin[a] + spacing * np.arange(n) for a, n in enumerate(shape)]
    nodes = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    brute = mesh_signed_distance(post_mesh, nodes)
    np.testing.assert_allclose(grid.ravel(), brute, atol=1e-12)
    # and the sign agrees with trimesh's ray-test containment (trimesh: inside = positive)
    inside = post_mesh.contains(nodes)
    far = np.abs(brute) > 1e-6
    assert np.array_equal(inside[far], brute[far] < 0)


def test_grid_mesh_distance_is_exact_for_a_rotated_box():
    """Against the closed-form box SDF (inside and outside, faces, edges and corners). trimesh's
    own signed_distance is off by ~15 um on this case; ours must be exact to rounding."""
    extents = np.array([0.01, 0.02, 0.005])
    rotation = trimesh.transformations.random_rotation_matrix(np.random.default_rng(5).random(3))
    box = trimesh.creation.box(extents)
    box.apply_transform(rotation)
    origin, shape, spacing = box.bounds[0] - 0.0023, (21, 19, 23), 0.0013
    grid = signed_distance_grid(box, origin, shape, spacing)
    axes = [origin[a] + spacing * np.arange(n) for a, n in enumerate(shape)]
    nodes = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    local = nodes @ rotation[:3, :3]  # R^T p for row vectors
    q = np.abs(local) - extents / 2
    exact = np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(axis=1), 0)
    np.testing.assert_allclose(grid.ravel(), exact, atol=1e-12)
    assert (exact < 0).sum() > 50  # some nodes are inside
