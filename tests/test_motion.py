"""Tests of sgn_jax.motion: docs/conventions.md section 2 formulas, autodiff derivatives, the
periodic spline, batching."""

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import sgn_jax  # noqa: F401  (enables x64)
from sgn_jax.config import config_from_dict, load_config
from sgn_jax.motion import (
    CircleMotion,
    HarmonicMotion,
    SplineMotion,
    acceleration,
    frequency_hz,
    motion1,
    motion2,
    offset,
    spline_from_motion,
    stack_motions,
    standard_circle,
    velocity,
)
from sgn_jax.pipelines.configure import motion_from_config

CONFIG_DIR = Path(__file__).resolve().parents[1] / "experiments" / "configs"
TIMES = np.linspace(-0.05, 0.73, 157)  # not commensurate with the 0.2 s period


def _random_spline(seed: int = 0, n_knots: int = 8, period: float = 0.2) -> SplineMotion:
    rng = np.random.default_rng(seed)
    return SplineMotion(period=jnp.asarray(period), points=jnp.asarray(rng.normal(0, 0.01, (n_knots, 3))))


ALL_MOTIONS = {
    "circle": standard_circle(),
    "circle_phase": CircleMotion(rpm=jnp.asarray(420.0), amplitude=jnp.asarray(0.011), phase=jnp.asarray(0.7)),
    "motion1": motion1(),
    "motion2": motion2(),
    "spline": _random_spline(),
}


# The tests evaluate the motion functions jitted: one compiled program per motion
# kind and time shape instead of dozens of op-by-op compiles; the numbers are the same
# functions'. test_time_shapes_and_jit compares them with the eager calls.
_offset, _velocity, _acceleration = jax.jit(offset), jax.jit(velocity), jax.jit(acceleration)
_JITTED = {offset: _offset, velocity: _velocity, acceleration: _acceleration}


def motion1_formula(t):
    cm = 0.01
    x = 1.7 * np.sin(10 * np.pi * t) - 0.85 * np.cos(20 * np.pi * t)
    z = 1.7 * np.cos(10 * np.pi * t) - 0.85 * np.sin(20 * np.pi * t)
    return np.stack([x, np.zeros_like(t), z], axis=-1) * cm


def motion2_formula(t):
    cm = 0.01
    x = 1.7 * np.sin(10 * np.pi * t)
    z = 1.7 * np.cos(20 * np.pi * t)
    return np.stack([x, np.zeros_like(t), z], axis=-1) * cm


# ---------------------------------------------------------------------------------------------
# Circle


def test_circle_radius_period_and_plane():
    circle = standard_circle()
    xyz = np.asarray(_offset(circle, TIMES))
    assert xyz.shape == (TIMES.size, 3)
    np.testing.assert_allclose(np.hypot(xyz[:, 0], xyz[:, 2]), 0.017, rtol=1e-13)
    np.testing.assert_array_equal(xyz[:, 1], 0.0)
    shifted = np.asarray(_offset(circle, TIMES + 60.0 / 300.0))
    np.testing.assert_allclose(shifted, xyz, atol=1e-14)
    # half a period later the jar is on the opposite side of the orbit
    np.testing.assert_allclose(np.asarray(_offset(circle, TIMES + 0.1)), -xyz, atol=1e-14)
    # docs/conventions.md section 2: offset(0) = (0, 0, A)
    np.testing.assert_allclose(np.asarray(_offset(circle, 0.0)), [0.0, 0.0, 0.017], atol=1e-16)


def test_circle_speed_and_centripetal_acceleration():
    circle = standard_circle()
    omega = 2 * np.pi * 5.0
    v = np.asarray(_velocity(circle, TIMES))
    a = np.asarray(_acceleration(circle, TIMES))
    x = np.asarray(_offset(circle, TIMES))
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), omega * 0.017, rtol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(a, axis=1), omega**2 * 0.017, rtol=1e-12)
    # the acceleration points to the orbit centre: a = -omega^2 x
    np.testing.assert_allclose(a, -(omega**2) * x, atol=1e-12)
    # velocity(0) = (A omega, 0, 0): the jump the DEM sees at the start of motion
    np.testing.assert_allclose(np.asarray(_velocity(circle, 0.0)), [omega * 0.017, 0, 0], atol=1e-14)


# ---------------------------------------------------------------------------------------------
# Motion 1 / Motion 2


@pytest.mark.parametrize(
    "make, formula, config_name",
    [(motion1, motion1_formula, "motion1"), (motion2, motion2_formula, "motion2"),
     (motion1, motion1_formula, "emax_post_motion1")],
)
def test_motion1_motion2_match_spec_formulas(make, formula, config_name):
    times = np.array([0.0, 0.0125, 0.03, 0.05, 0.1, 0.137, 1.234, 4.4999])
    expected = formula(times)
    np.testing.assert_allclose(np.asarray(_offset(make(), times)), expected, atol=1e-15)
    cfg = load_config(CONFIG_DIR / f"{config_name}.toml")
    from_config = motion_from_config(cfg.motion)
    assert isinstance(from_config, HarmonicMotion)
    np.testing.assert_allclose(np.asarray(_offset(from_config, times)), expected, atol=1e-15)


def test_standard_config_is_the_standard_circle():
    cfg = load_config(CONFIG_DIR / "emax_300rpm.toml")
    circle = motion_from_config(cfg.motion)
    assert isinstance(circle, CircleMotion)
    np.testing.assert_allclose(np.asarray(_offset(circle, TIMES)),
                               np.asarray(_offset(standard_circle(), TIMES)), atol=0)
    assert float(frequency_hz(circle)) == pytest.approx(5.0, rel=1e-15)


def test_motion_from_config_dtype_and_spline_kind():
    cfg = load_config(CONFIG_DIR / "motion1.toml")
    m32 = motion_from_config(cfg.motion, dtype=jnp.float32)
    assert m32.sin_coeffs.dtype == jnp.float32 and m32.base_frequency_hz.dtype == jnp.float32
    points = [[0.0, 0.0, 0.01], [0.01, 0.0, 0.0], [0.0, 0.0, -0.01], [-0.01, 0.0, 0.0]]
    spline_cfg = config_from_dict(
        {"kind": "spline", "period": 0.25, "points": points}, cls=type(cfg.motion)
    )
    spline = motion_from_config(spline_cfg)
    assert isinstance(spline, SplineMotion)
    np.testing.assert_allclose(np.asarray(_offset(spline, np.arange(4) * 0.25 / 4)), points,
                               atol=1e-15)
    assert float(frequency_hz(spline)) == pytest.approx(4.0)
    with pytest.raises(TypeError, match="MotionConfig"):
        motion_from_config(cfg)


def test_frequency_hz_per_kind():
    assert float(frequency_hz(standard_circle())) == pytest.approx(5.0)
    assert float(frequency_hz(motion1())) == pytest.approx(5.0)
    assert float(frequency_hz(_random_spline(period=0.4))) == pytest.approx(2.5)


# ---------------------------------------------------------------------------------------------
# Derivatives


@pytest.mark.parametrize("name", sorted(ALL_MOTIONS))
def test_velocity_and_acceleration_match_finite_differences(name):
    motion = ALL_MOTIONS[name]
    # keep the stencils inside one spline segment (knots at multiples of 0.025 s)
    times = np.array([0.0031, 0.0417, 0.1093, 0.3381, 0.51])
    h1, h2 = 1e-6, 1e-4
    x = lambda t: np.asarray(_offset(motion, t))  # noqa: E731
    v_fd = (x(times + h1) - x(times - h1)) / (2 * h1)
    a_fd = (x(times + h2) - 2 * x(times) + x(times - h2)) / h2**2
    v = np.asarray(_velocity(motion, times))
    a = np.asarray(_acceleration(motion, times))
    v_scale = np.abs(v).max()
    a_scale = np.abs(a).max()
    assert v_scale > 0.05 and a_scale > 1.0  # the comparison is not trivially between zeros
    np.testing.assert_allclose(v, v_fd, atol=1e-8 * v_scale)
    np.testing.assert_allclose(a, a_fd, atol=2e-5 * a_scale)


@pytest.mark.parametrize("name", sorted(ALL_MOTIONS))
def test_gradients_wrt_parameters_match_finite_differences(name):
    motion = ALL_MOTIONS[name]
    t = 0.0437

    def objective(m):
        weights = jnp.asarray([1.0, 0.3, -0.7])
        return jnp.dot(offset(m, t), weights) + 0.01 * jnp.dot(velocity(m, t), weights)

    grads = jax.jit(jax.grad(objective))(motion)
    objective_jit = jax.jit(objective)  # one compilation for every evaluation below
    leaves, treedef = jax.tree.flatten(motion)
    grad_leaves = jax.tree.leaves(grads)
    eps = 1e-6
    for leaf_index, (leaf, grad_leaf) in enumerate(zip(leaves, grad_leaves, strict=True)):
        leaf = np.asarray(leaf, dtype=np.float64)
        fd = np.zeros_like(leaf)
        for idx in np.ndindex(leaf.shape):
            step = eps * max(1.0, abs(leaf[idx]))
            plus, minus = leaf.copy(), leaf.copy()
            plus[idx] += step
            minus[idx] -= step
            def value(arr, i=leaf_index):
                new_leaves = list(leaves)
                new_leaves[i] = jnp.asarray(arr)
                return float(objective_jit(jax.tree.unflatten(treedef, new_leaves)))
            fd[idx] = (value(plus) - value(minus)) / (2 * step)
        np.testing.assert_allclose(np.asarray(grad_leaf), fd, rtol=1e-6,
                                   atol=1e-8 * max(1.0, np.abs(fd).max()))
    assert max(float(jnp.abs(g).max()) for g in grad_leaves) > 0


# ---------------------------------------------------------------------------------------------
# Spline


def test_spline_interpolates_is_periodic_and_c2():
    spline = _random_spline(seed=3, n_knots=9, period=0.3)
    h = 0.3 / 9
    knots = np.arange(9) * h
    np.testing.assert_allclose(np.asarray(_offset(spline, knots)), np.asarray(spline.points),
                               atol=1e-15)
    np.testing.assert_allclose(np.asarray(_offset(spline, TIMES + 0.3)),
                               np.asarray(_offset(spline, TIMES)), atol=1e-14)
    np.testing.assert_allclose(np.asarray(_offset(spline, TIMES - 0.6)),
                               np.asarray(_offset(spline, TIMES)), atol=1e-14)
    # C2 at every knot, including the wrap-around knot t = period: left and right limits agree.
    eps = 1e-9
    edges = np.append(knots, 0.3)
    for fn in (_offset, _velocity, _acceleration):
        left = np.asarray(fn(spline, edges - eps))
        right = np.asarray(fn(spline, edges + eps))
        scale = np.abs(right).max()
        np.testing.assert_allclose(left, right, atol=1e-6 * scale)
    # ...but a cubic spline is not C3: the third derivative jumps, so the check above can fail.
    jerk = jax.jit(jax.vmap(jax.jacfwd(lambda t: acceleration(spline, t))))
    jump = np.abs(np.asarray(jerk(edges - eps)) - np.asarray(jerk(edges + eps))).max()
    assert jump > 1e-3 * np.abs(np.asarray(jerk(edges + eps))).max()


def test_spline_sampled_from_circle_reproduces_it():
    circle = standard_circle()
    spline = spline_from_motion(circle, 64, 0.2)
    assert spline.points.shape == (64, 3)
    dense = np.linspace(-0.2, 0.6, 4001)
    error = np.abs(np.asarray(_offset(spline, dense)) - np.asarray(_offset(circle, dense))).max()
    assert error < 1e-6
    # a coarse spline is measurably worse: the bound above is a real test of the spline order
    coarse = spline_from_motion(circle, 8, 0.2)
    assert np.abs(np.asarray(_offset(coarse, dense)) - np.asarray(_offset(circle, dense))).max() > 1e-5
    # differentiable through the sampling
    grad_rpm = jax.jit(jax.grad(lambda m: offset(spline_from_motion(m, 64, 0.2), 0.031)[0]))(
        circle).rpm
    assert np.isfinite(float(grad_rpm)) and float(grad_rpm) != 0.0


def test_bad_inputs_give_clear_errors():
    with pytest.raises(ValueError, match=r"\(M, 3\)"):
        offset(SplineMotion(period=0.2, points=jnp.zeros((5, 2))), 0.1)
    with pytest.raises(ValueError, match=r"\(K, 3\)"):
        offset(HarmonicMotion(base_frequency_hz=5.0, sin_coeffs=jnp.zeros(3),
                              cos_coeffs=jnp.zeros(3)), 0.1)
    with pytest.raises(ValueError, match="same shape"):
        offset(HarmonicMotion(base_frequency_hz=5.0, sin_coeffs=jnp.zeros((2, 3)),
                              cos_coeffs=jnp.zeros((1, 3))), 0.1)
    with pytest.raises(TypeError, match="CircleMotion"):
        offset({"rpm": 300.0}, 0.1)
    with pytest.raises(ValueError, match="n_points"):
        spline_from_motion(standard_circle(), 2, 0.2)


# ---------------------------------------------------------------------------------------------
# jit / vmap


@pytest.mark.slow
def test_time_shapes_and_jit():
    circle = standard_circle()
    grid = np.linspace(0, 0.1, 12).reshape(3, 4)
    assert offset(circle, grid).shape == (3, 4, 3)
    np.testing.assert_allclose(np.asarray(offset(circle, grid))[1, 2],
                               np.asarray(offset(circle, grid[1, 2])), atol=0)
    jitted = jax.jit(lambda m, t: (offset(m, t), velocity(m, t), acceleration(m, t)))
    for motion in ALL_MOTIONS.values():
        for eager, compiled in zip((offset(motion, 0.0713), velocity(motion, 0.0713),
                                    acceleration(motion, 0.0713)), jitted(motion, 0.0713),
                                   strict=True):
            np.testing.assert_allclose(np.asarray(compiled), np.asarray(eager), rtol=1e-13,
                                       atol=1e-15)
    # integer time is accepted (converted to float64)
    np.testing.assert_allclose(np.asarray(velocity(circle, 1)), np.asarray(velocity(circle, 1.0)))


def _batches():
    rng = np.random.default_rng(7)
    circles = [CircleMotion(rpm=jnp.asarray(r), amplitude=jnp.asarray(a), phase=jnp.asarray(p))
               for r, a, p in zip(rng.uniform(100, 500, 8), rng.uniform(0.005, 0.02, 8),
                                  rng.uniform(-3, 3, 8), strict=True)]
    harmonics = [HarmonicMotion(base_frequency_hz=jnp.asarray(f),
                                sin_coeffs=jnp.asarray(rng.normal(0, 0.01, (3, 3))),
                                cos_coeffs=jnp.asarray(rng.normal(0, 0.01, (3, 3))))
                 for f in rng.uniform(2, 8, 8)]
    splines = [_random_spline(seed=s, n_knots=6, period=p)
               for s, p in zip(range(8), rng.uniform(0.1, 0.4, 8), strict=True)]
    return {"circle": circles, "harmonic": harmonics, "spline": splines}


@pytest.mark.parametrize("kind", ["circle", "harmonic", "spline"])
def test_vmap_over_parameter_batch_equals_loop(kind):
    motions = _batches()[kind]
    stacked = stack_motions(motions)
    times = np.array([0.0, 0.0123, 0.377])
    for fn in (offset, velocity, acceleration):
        batched = np.asarray(jax.jit(jax.vmap(fn, in_axes=(0, None)))(stacked, times))
        looped = np.stack([np.asarray(_JITTED[fn](m, times)) for m in motions])  # one jit per fn
        assert batched.shape == (8, 3, 3)
        np.testing.assert_allclose(batched, looped, rtol=1e-12, atol=1e-14)
    freqs = np.asarray(jax.vmap(frequency_hz)(stacked))
    np.testing.assert_allclose(freqs, [float(frequency_hz(m)) for m in motions], rtol=1e-15)
    with pytest.raises(ValueError, match="one kind"):
        stack_motions([standard_circle(), motion1()])
