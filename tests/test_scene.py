"""The scene: one wall-query protocol for the DEM (patches, jar frame) and the surrogate
(nearest wall, lab frame), and the Scene pytree (geometry + motion + static walls)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import sgn_jax  # noqa: F401  (x64)
from sgn_jax.config import builtin_config_path, load_config
from sgn_jax.geometry import jar_sdf, query_sdf_grid, sdf_grid_from_jar
from sgn_jax.motion import CircleMotion, frequency_hz, offset, stack_motions
from sgn_jax.pipelines.configure import geometry_from_config, jar_params_from_config
from sgn_jax.scene import (
    Scene,
    analytic_jar_query,
    analytic_walls,
    grid_query,
    grid_walls,
    lab_query,
    nearest_wall,
    patch_walls,
)


@pytest.fixture(scope="module")
def jar():
    return jar_params_from_config(load_config(builtin_config_path("emax_300rpm")).jar)


def _points(n=3000, seed=0):
    rng = np.random.default_rng(seed)
    return jnp.asarray(rng.uniform([-0.045, -0.003, -0.03], [0.045, 0.05, 0.03], (n, 3)))


@pytest.mark.slow
def test_the_grid_query_is_the_sdf_grid_lookup_bit_for_bit(jar):
    grid = sdf_grid_from_jar(jar, 1e-3, 3e-3, jnp.float32)
    pts, off = _points(), jnp.asarray([0.01, 0.0, -0.005])
    phi, normal = grid_query(grid, pts, off)
    phi_ref, normal_ref = query_sdf_grid(grid, pts, off)
    np.testing.assert_array_equal(np.asarray(phi), np.asarray(phi_ref))
    np.testing.assert_array_equal(np.asarray(normal), np.asarray(normal_ref))
    assert grid_walls(grid, pts)[0].shape == (len(pts), 1)


@pytest.mark.slow
def test_the_dem_patches_and_the_surrogate_view_agree_inside_the_cavity(jar):
    """The DEM's per-patch walls and the surrogate's exact query are one protocol: the nearest
    patch is the exact SDF wherever one wall is clearly nearest (away from medial kinks)."""
    pts = _points()
    phi_p, n_p = nearest_wall(patch_walls, jar, pts)
    phi_a, n_a = nearest_wall(analytic_walls, jar, pts)
    assert patch_walls(jar, pts)[0].shape[-1] >= 3  # floor, lid, side
    inside = np.asarray(phi_a) < -1e-3
    assert inside.sum() > 500
    np.testing.assert_allclose(np.asarray(phi_p)[inside], np.asarray(phi_a)[inside], atol=1e-12)
    np.testing.assert_allclose(np.asarray(n_p)[inside], np.asarray(n_a)[inside], atol=1e-9)
    np.testing.assert_allclose(np.asarray(phi_a), np.asarray(jax.vmap(
        lambda p: jar_sdf(jar, p))(pts)), atol=0)


def test_lab_query_is_one_function_per_wall_query():
    assert lab_query(analytic_walls) is analytic_jar_query
    assert lab_query(grid_walls) is grid_query


def test_the_dem_jar_of_a_config_uses_the_scene_walls():
    cfg = load_config(builtin_config_path("emax_300rpm"))
    assert geometry_from_config(cfg).wall_fn is patch_walls


def test_a_scene_is_a_pytree_of_geometry_and_motion_with_static_walls(jar):
    motions = stack_motions([CircleMotion(rpm=jnp.asarray(r), amplitude=jnp.asarray(0.017),
                                          phase=jnp.asarray(0.0)) for r in (200.0, 300.0)])
    scenes = Scene(geometry=jar, motion=motions, walls=analytic_walls)
    leaves = jax.tree_util.tree_leaves(scenes)
    assert len(leaves) == len(jax.tree_util.tree_leaves(jar)) + 3  # rpm, amplitude, phase
    pts, t = _points(50), 0.0123

    @jax.jit
    def probe(scene):
        return scene.nearest_wall(pts, t)[0], scene.frequency_hz()

    phi, freq = jax.vmap(lambda m: probe(scenes.replace(motion=m)))(motions)
    np.testing.assert_allclose(np.asarray(freq), [200 / 60, 300 / 60])
    for k, rpm in enumerate((200.0, 300.0)):
        m = CircleMotion(rpm=jnp.asarray(rpm), amplitude=jnp.asarray(0.017),
                         phase=jnp.asarray(0.0))
        ref, _ = jax.jit(lambda m: analytic_jar_query(jar, pts, offset(m, t)))(m)  # one compile
        np.testing.assert_allclose(np.asarray(phi[k]), np.asarray(ref), atol=1e-15)
        assert float(frequency_hz(m)) == pytest.approx(float(freq[k]))


def test_scene_gradients_reach_the_jar_and_the_motion(jar):
    """d(phi)/d(jar radius) and d(phi)/d(amplitude) through the scene are finite and non-zero
    (the design studies differentiate through exactly this)."""
    motion = CircleMotion(rpm=jnp.asarray(300.0), amplitude=jnp.asarray(0.017),
                          phase=jnp.asarray(0.0))
    pts = jnp.asarray([[0.03, 0.01, 0.0], [-0.02, 0.02, 0.005]])

    def total_phi(scene):
        return jnp.sum(scene.nearest_wall(pts, 0.01)[0])

    # jitted: one compile instead of the op-by-op ones
    grads = jax.jit(jax.grad(total_phi))(Scene(geometry=jar, motion=motion, walls=analytic_walls))
    assert np.isfinite(float(grads.geometry.radius)) and float(grads.geometry.radius) != 0
    assert np.isfinite(float(grads.motion.amplitude)) and float(grads.motion.amplitude) != 0
