"""A motion kind added in one file (tests/extensions/elliptical_orbit.py) runs through the core
motion functions, the DEM and the surrogate rollout; the registry itself (docs/motion-kinds.md).
"""

from __future__ import annotations

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from extensions.elliptical_orbit import ELLIPTICAL, EllipticalOrbitMotion

import sgn_jax  # noqa: F401  (x64)
from sgn_jax.config import (
    MOTION_KINDS,
    MotionConfig,
    builtin_config_path,
    load_config,
    replace_section,
)
from sgn_jax.dem.engine import init_state, make_sampler
from sgn_jax.dem.placement import place_balls
from sgn_jax.design import (
    DesignError,
    apply_parameters,
    check_parameters,
    parameter_unit,
    parameter_values,
)
from sgn_jax.geometry import JarParams
from sgn_jax.motion import (
    CircleMotion,
    MotionKind,
    acceleration,
    frequency_hz,
    motion_kind,
    motion_kind_named,
    motion_kinds,
    offset,
    register_motion_kind,
    spline_from_motion,
    stack_motions,
    unregister_motion_kind,
    velocity,
)
from sgn_jax.pipelines.configure import jar_params_from_config, motion_from_config
from sgn_jax.pipelines.dem_run import setup_from_config
from sgn_jax.surrogate.graph import GraphSpec, Window
from sgn_jax.surrogate.rollout import analytic_jar_query, make_rollout

RPM, SEMI_X, SEMI_Z, PHASE = 300.0, 0.017, 0.010, 0.3


def _ellipse(rpm=RPM, semi_x=SEMI_X, semi_z=SEMI_Z, phase=PHASE) -> EllipticalOrbitMotion:
    return EllipticalOrbitMotion(rpm=jnp.float64(rpm), semi_x=jnp.float64(semi_x),
                                 semi_z=jnp.float64(semi_z), phase=jnp.float64(phase))


def _analytic(rpm, semi_x, semi_z, phase, t):
    """Offset, velocity and acceleration of the ellipse in numpy, (T, 3) each."""
    omega = 2 * np.pi * rpm / 60
    angle = omega * np.asarray(t) + phase
    zero = np.zeros_like(angle)
    x = np.stack([semi_x * np.sin(angle), zero, semi_z * np.cos(angle)], -1)
    v = np.stack([semi_x * omega * np.cos(angle), zero, -semi_z * omega * np.sin(angle)], -1)
    return x, v, -omega**2 * x


TIMES = np.array([0.0, 0.0123, 0.05, 0.1377, 0.9])


# ---------------------------------------------------------------------------------------------
# (a) the core motion functions


def test_offset_velocity_acceleration_frequency_match_the_formula():
    motion = _ellipse()
    x, v, a = _analytic(RPM, SEMI_X, SEMI_Z, PHASE, TIMES)
    # jitted: one compile each instead of op-by-op; the shapes below stay eager
    np.testing.assert_allclose(np.asarray(jax.jit(offset)(motion, TIMES)), x, rtol=0, atol=1e-15)
    np.testing.assert_allclose(np.asarray(jax.jit(velocity)(motion, TIMES)), v, rtol=0,
                               atol=1e-13)
    np.testing.assert_allclose(np.asarray(jax.jit(acceleration)(motion, TIMES)), a, rtol=0,
                               atol=1e-10)
    assert float(frequency_hz(motion)) == pytest.approx(RPM / 60)
    assert offset(motion, 0.05).shape == (3,)
    assert offset(motion, TIMES.reshape(5, 1)).shape == (5, 1, 3)


def test_jit_vmap_stack_and_spline():
    motions = [_ellipse(rpm=240.0 + 30 * i, semi_x=0.012 + 0.002 * i, phase=0.1 * i)
               for i in range(3)]
    stacked = stack_motions(motions)
    assert isinstance(stacked, EllipticalOrbitMotion) and stacked.rpm.shape == (3,)
    batched = jax.jit(jax.vmap(offset, in_axes=(0, None)))(stacked, TIMES)
    batched_v = jax.jit(jax.vmap(velocity, in_axes=(0, None)))(stacked, TIMES)
    freqs = jax.jit(jax.vmap(frequency_hz))(stacked)
    for i, m in enumerate(motions):
        x, v, _ = _analytic(float(m.rpm), float(m.semi_x), float(m.semi_z), float(m.phase), TIMES)
        np.testing.assert_allclose(np.asarray(batched[i]), x, rtol=0, atol=1e-15)
        np.testing.assert_allclose(np.asarray(batched_v[i]), v, rtol=0, atol=1e-13)
        assert float(freqs[i]) == pytest.approx(float(m.rpm) / 60)
    with pytest.raises(ValueError, match="one kind"):
        stack_motions([motions[0], CircleMotion(rpm=300.0, amplitude=0.017)])
    # Any registered kind samples into a spline; the spline goes through its points.
    spline = spline_from_motion(motions[0], 16, 1.0 / float(frequency_hz(motions[0])))
    np.testing.assert_allclose(np.asarray(jax.jit(offset)(spline, 0.0)),
                               np.asarray(jax.jit(offset)(motions[0], 0.0)), atol=1e-15)
    # Differentiable in the new kind's parameters.
    grad = jax.jit(jax.grad(lambda m: offset(m, 0.0123)[0]))(motions[0])
    angle = 2 * np.pi * float(motions[0].rpm) / 60 * 0.0123 + float(motions[0].phase)
    assert float(grad.semi_x) == pytest.approx(np.sin(angle))
    assert float(grad.semi_z) == 0.0


def test_the_registry():
    assert motion_kind(_ellipse()) is ELLIPTICAL
    assert motion_kind(EllipticalOrbitMotion) is ELLIPTICAL
    assert motion_kind_named("elliptical") is ELLIPTICAL
    names = [k.name for k in motion_kinds()]
    assert names[:3] == ["circle", "harmonic", "spline"] and "elliptical" in names
    # The built-in kinds declare exactly the keys their config section allows.
    for kind in MOTION_KINDS:
        assert set(motion_kind_named(kind).config_keys) == MotionConfig._KEYS_BY_KIND[kind]
    # The config adapter builds through the registry (a built-in kind).
    circle = motion_from_config(MotionConfig(kind="circle", rpm=200.0, amplitude=0.01))
    assert isinstance(circle, CircleMotion) and float(circle.rpm) == 200.0
    # The kind's constructor from plain config values, and back.
    values = {"rpm": RPM, "semi_x": SEMI_X, "semi_z": SEMI_Z, "phase": PHASE}
    motion = ELLIPTICAL.from_config(values, jnp.float32)
    assert motion.semi_x.dtype == jnp.float32
    assert ELLIPTICAL.to_config(_ellipse(), values) == values
    # A name or a class registers once; a non-motion is refused with the registered kinds.
    with pytest.raises(ValueError, match="already registered"):
        register_motion_kind(ELLIPTICAL)
    with pytest.raises(ValueError, match="unknown motion kind 'nope'"):
        motion_kind_named("nope")
    with pytest.raises(TypeError, match="EllipticalOrbitMotion"):
        offset({"rpm": 300.0}, 0.1)

    @flax.struct.dataclass
    class Still:
        where: jax.Array

    still = register_motion_kind(MotionKind(name="still", cls=Still,
                                            offset=lambda m, t: m.where + 0.0 * t,
                                            frequency_hz=lambda m: jnp.asarray(1.0)))
    try:
        np.testing.assert_array_equal(np.asarray(offset(Still(jnp.ones(3)), TIMES)),
                                      np.ones((5, 3)))
        np.testing.assert_array_equal(np.asarray(velocity(Still(jnp.ones(3)), 0.1)), 0.0)
    finally:
        assert unregister_motion_kind("still") is still
    with pytest.raises(TypeError, match="registered kind"):
        offset(Still(jnp.ones(3)), 0.1)


def test_design_parameters_declared_by_the_kind():
    motion, jar = _ellipse(), JarParams()
    names = check_parameters(["motion.semi_x", "motion.rpm", "motion.scale"], motion, jar)
    assert parameter_unit("motion.semi_z") == "m"
    np.testing.assert_allclose(parameter_values(names, motion, jar), [SEMI_X, RPM, 1.0])
    moved, _ = apply_parameters(names, jnp.array([0.02, 240.0, 0.5]), motion, jar)
    assert float(moved.semi_x) == pytest.approx(0.01) and float(moved.rpm) == 240.0
    assert float(moved.semi_z) == pytest.approx(0.5 * SEMI_Z)
    with pytest.raises(DesignError, match="motion.x_sin.0. needs a harmonic motion"):
        check_parameters(["motion.x_sin[0]"], motion, jar)
    with pytest.raises(DesignError, match="motion.semi_x needs an elliptical motion"):
        check_parameters(["motion.semi_x"], CircleMotion(rpm=300.0, amplitude=0.017), jar)


# ---------------------------------------------------------------------------------------------
# (b) the DEM

N_BALLS = 4
N_SAMPLES = 2000  # 0.2 s of motion: one revolution at 300 rpm


@pytest.fixture(scope="module")
def standard_setup():
    cfg = load_config(builtin_config_path("emax_300rpm"))
    return setup_from_config(replace_section(cfg, "balls", count=N_BALLS))


# The slow tier (`pytest -m slow`; the default run's time): a DEM run driven by the example motion; its registration and kinematics stay in the default run.
@pytest.mark.slow
def test_dem_driven_by_the_elliptical_motion(standard_setup):
    setup = standard_setup
    motion = _ellipse()
    params = setup.params.replace(motion=motion)
    jar = setup.jar
    x_jar = place_balls(lambda x: jar.sdf_fn(jar.geometry, x), jar.lower, jar.upper, N_BALLS,
                        float(params.radius), seed=3)
    state = init_state(setup.spec, params, x_jar + np.asarray(offset(motion, 0.0)))
    np.testing.assert_allclose(np.asarray(state.offset), np.asarray(offset(motion, 0.0)),
                               atol=1e-15)
    run = make_sampler(setup.spec, jar.wall_fn, setup.substeps, setup.pp_capacity)
    _, samples = jax.device_get(run(params, state, N_SAMPLES))
    t = (np.arange(N_SAMPLES) + 1) * setup.substeps * setup.dt_dem
    x, v, _ = _analytic(RPM, SEMI_X, SEMI_Z, PHASE, t)
    # The jar the DEM moves is the motion's, at every sample.
    np.testing.assert_allclose(samples["offset"], x, rtol=0, atol=1e-12)
    np.testing.assert_allclose(samples["offset_vel"], v, rtol=0, atol=1e-10)
    # The jar went once round the ellipse (not a circle) and the balls stayed inside it.
    assert np.abs(samples["offset"][:, 0]).max() == pytest.approx(SEMI_X, rel=1e-4)
    assert np.abs(samples["offset"][:, 2]).max() == pytest.approx(SEMI_Z, rel=1e-4)
    phi = jax.jit(jax.vmap(lambda p: jar.sdf_fn(jar.geometry, p)))(
        jnp.asarray(samples["pos"] - samples["offset"][:, None, :]))
    assert float(jnp.max(phi)) < 0.0
    assert np.all(np.isfinite(samples["pos"]))
    assert float(np.abs(samples["pos"][-1] - samples["pos"][0]).max()) > 1e-4  # balls moved


# ---------------------------------------------------------------------------------------------
# (c) the surrogate rollout

W = 3
N_STEPS = 12
T0 = 0.0371


def _checking_predictor(spec: GraphSpec, t0: float):
    """Zero accelerations; as its "dissipation" the largest difference between the wall node's
    features the network would see at this step and the motion's jar state at the slot times
    (offset, velocity, frequency), so the rollout's records say what the network saw."""

    def predictor(motion, stats, graph, step):
        del stats
        times = t0 + (step - (spec.window - 1) + jnp.arange(spec.window)) * spec.dt
        expected = jnp.concatenate(
            [offset(motion, times), velocity(motion, times),
             jnp.broadcast_to(frequency_hz(motion), (spec.window, 1))], axis=-1)
        wall = graph.nodes["features"][spec.n_particles].reshape(spec.window, 7)
        error = jnp.max(jnp.abs(wall.astype(jnp.float64) - expected))
        return jnp.zeros((spec.n_particles, 3)), error

    return predictor


def test_rollout_driven_by_the_elliptical_motion():
    cfg = load_config(builtin_config_path("emax_300rpm"))
    jar = jar_params_from_config(cfg.jar)
    spec = GraphSpec(n_particles=N_BALLS, window=W, ball_radius=0.005, dt=1e-4,
                     pp_pair_capacity=N_BALLS * 2)
    motions = [_ellipse(), _ellipse(rpm=420.0, semi_x=0.008, semi_z=0.015, phase=-1.0)]
    x_jar = np.array([[0.0, 0.006, 0.0], [0.012, 0.006, 0.0], [-0.012, 0.006, 0.0],
                      [0.0, 0.02, 0.0]])
    window0 = Window(positions=np.broadcast_to(x_jar, (W + 1, N_BALLS, 3)).copy(),
                     offsets=np.zeros((W, 3)), offset_velocities=np.zeros((W, 3)),
                     frequency_hz=np.float64(0.0))  # the jar state comes from the motion
    rollout = make_rollout(spec, _checking_predictor(spec, T0), N_STEPS, 1, snap_back=False,
                           query=analytic_jar_query, jit=False)
    # The motion is both the "params" (read by the checking predictor) and the rollout's motion.
    batched = jax.device_get(jax.jit(jax.vmap(
        lambda m: rollout(m, None, window0, m, jar, T0)))(stack_motions(motions)))
    for i, motion in enumerate(motions):
        rpm, a, b, ph = (float(getattr(motion, k)) for k in ("rpm", "semi_x", "semi_z", "phase"))
        # Every step's wall node carried the motion's jar state (float32 features).
        assert float(np.max(batched.steps.dE[i])) < 1e-6, batched.steps.dE[i]
        t_pos = batched.t_pos[i]
        np.testing.assert_allclose(t_pos, T0 + np.arange(N_STEPS + 1) * spec.dt, atol=1e-15)
        np.testing.assert_allclose(batched.offsets[i], _analytic(rpm, a, b, ph, t_pos)[0],
                                   rtol=0, atol=1e-15)
        final = jax.tree_util.tree_map(lambda leaf, i=i: leaf[i], batched.final.window)
        t_slots = T0 + (N_STEPS - W + 1 + np.arange(W)) * spec.dt
        x, v, _ = _analytic(rpm, a, b, ph, t_slots)
        np.testing.assert_allclose(final.offsets, x, rtol=0, atol=1e-15)
        np.testing.assert_allclose(final.offset_velocities, v, rtol=0, atol=1e-12)
        assert float(final.frequency_hz) == pytest.approx(rpm / 60)
        # No accelerations: the balls keep their (zero) velocity in the lab frame.
        np.testing.assert_allclose(batched.positions[i][-1], x_jar, atol=1e-15)
