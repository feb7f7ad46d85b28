"""The lax.scan rollout: DEM replay, snap-back, gradients, vmap, compilation count, host run, CLI."""

import json
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import sgn_jax  # noqa: F401  (x64)
from sgn_jax.analysis.metrics import pairs_within
from sgn_jax.config import config_to_dict, replace_section
from sgn_jax.geometry import JarParams, query_sdf_grid
from sgn_jax.motion import CircleMotion, offset
from sgn_jax.pipelines.configure import (
    graph_spec_from_config,
    motion_from_config,
    sdf_grid_from_config,
)
from sgn_jax.pipelines.rollout_run import initial_window, run_rollout
from sgn_jax.surrogate.graph import (
    GraphSpec,
    Window,
    build_graph,
    dissipation_per_interval,
    targets_from_arrays,
)
from sgn_jax.surrogate.model import init_params
from sgn_jax.surrogate.normalization import Moments, NormStats, normalize_graph
from sgn_jax.surrogate.rollout import (
    ReplayTable,
    RolloutError,
    analytic_jar_query,
    jar_state_window,
    make_rollout,
    make_rollout_advance,
    model_predictor,
    replay_predictor,
    separate_pairs,
)
from sgn_jax.surrogate.sgn import SGN

REPLAY_STEPS = 1000
START = 7  # the first sample with a full window (W = 7)


@pytest.fixture(scope="module")
def dem(standard_dem_file):
    """A short real DEM trajectory of the standard case (0.101 s of motion, 1011 samples; made
    once per session, conftest.py)."""
    from sgn_jax.records.trajectory import load_trajectory

    traj = load_trajectory(standard_dem_file)
    spec = graph_spec_from_config(traj.config)
    return traj, spec, sdf_grid_from_config(traj.config), motion_from_config(traj.config.motion)


def _replay_table(traj, spec, n_steps, start=START):
    ends = start + np.arange(n_steps)
    accel, de = targets_from_arrays(traj.pos, dissipation_per_interval(traj), ends, spec.dt)
    return ReplayTable(accel=jnp.asarray(accel), dE=jnp.asarray(de)), ends, de


def test_replay_reproduces_dem_positions_and_energy(dem):
    traj, spec, grid, motion = dem
    table, ends, de = _replay_table(traj, spec, REPLAY_STEPS)
    rollout = make_rollout(spec, replay_predictor(), REPLAY_STEPS, 10, snap_back=False)
    res = jax.device_get(rollout(table, None, initial_window(traj, START, spec.window), motion,
                                 grid, traj.t[START]))
    frames = slice(START, START + REPLAY_STEPS + 1, 10)

    # Semi-implicit Euler fed a_n = (x_{n+1} - 2 x_n + x_{n-1}) / dt^2 reproduces x_{n+1}; the
    # rounding (a few ulp of |x| ~ 0.04 m, ~7e-18 m, per step) accumulates like n^1.5 in this
    # two-step recursion: ~1e-13 m after 1000 steps.
    assert res.positions.shape == (REPLAY_STEPS // 10 + 1, spec.n_particles, 3)
    assert np.abs(res.positions - traj.pos[frames]).max() < 1e-12
    # The cumulative energy is the same float64 running sum: exactly equal.
    np.testing.assert_array_equal(res.steps.energy_cum, np.cumsum(de))
    np.testing.assert_array_equal(res.steps.dE, de)
    # Time and jar state on the DEM's grid: t_step ends each step, offsets from the motion.
    np.testing.assert_allclose(res.t_step, traj.t[START + 1:START + REPLAY_STEPS + 1],
                               rtol=0, atol=1e-12)
    np.testing.assert_allclose(res.t_pos, traj.t[frames], rtol=0, atol=1e-12)
    np.testing.assert_allclose(res.offsets, traj.offset[frames], rtol=0, atol=1e-12)
    # The graph of step s is built from the window ending at n = START + s.
    np.testing.assert_array_equal(res.steps.n_pp_edges,
                                  2 * pairs_within(traj.pos[ends], spec.pp_cutoff))
    assert res.steps.n_pw_edges.max() > 0
    assert res.steps.n_outside.sum() == 0 and res.steps.overflow.sum() == 0
    assert res.steps.n_snapped.sum() == 0


def test_snap_back_would_move_dem_balls(dem):
    """With snap-back on, the replay departs from the DEM at the first step whose new position
    has phi >= phi_sb on the SDF grid: why replays run with snap-back off. phi_sb = -R (any
    overlap with the wall) makes sure the DEM's contacts reach it in this short run; the
    paper's -4.9 mm (0.1 mm overlap) is reached by harder impacts."""
    traj, spec, grid, motion = dem
    n_steps, phi_sb = 500, -0.005
    table, _, _ = _replay_table(traj, spec, n_steps)
    window0 = initial_window(traj, START, spec.window)
    rollout = make_rollout(spec, replay_predictor(), n_steps, 1, snap_back=True, phi_sb=phi_sb)
    res = jax.device_get(rollout(table, None, window0, motion, grid, traj.t[START]))

    new = np.arange(START + 1, START + n_steps + 1)  # sample reached by each step
    phi = np.asarray(jax.jit(jax.vmap(lambda x, o: query_sdf_grid(grid, x, o)[0]))(
        traj.pos[new], traj.offset[new]))
    expected = (phi >= phi_sb).sum(axis=1)
    first = int(np.flatnonzero(expected)[0])  # the DEM's wall contacts do reach phi_sb
    assert res.steps.n_snapped[first] == expected[first] > 0
    assert res.steps.n_snapped[:first].sum() == 0
    np.testing.assert_allclose(res.positions[:first + 1], traj.pos[START:START + first + 1],
                               rtol=0, atol=1e-12)
    # The balls with phi >= phi_sb are put on phi_sb (to the grid's curvature), the others kept.
    moved = phi[first] >= phi_sb
    phi_after = np.asarray(jax.jit(lambda x, o: query_sdf_grid(grid, x, o)[0])(
        res.positions[first + 1], res.offsets[first + 1]))
    np.testing.assert_allclose(phi_after[moved], phi_sb, rtol=0,
                               atol=1e-9 + 1e-3 * (phi[first][moved] - phi_sb).max())
    np.testing.assert_allclose(res.positions[first + 1][~moved],
                               traj.pos[START + first + 1][~moved], rtol=0, atol=1e-12)


# --------------------------------------------------------------------------------------------
# Snap-back on a planar wall (analytic jar: the floor's phi = -y exactly)


def _circle_offset(rpm, amplitude, t):
    """The circle of docs/conventions.md section 2 in numpy: (A sin 2 pi f t, 0, A cos 2 pi f t),
    f = rpm / 60."""
    angle = 2 * np.pi * rpm / 60 * t
    return np.array([amplitude * np.sin(angle), 0.0, amplitude * np.cos(angle)])


def _floor_case(snap_velocity, n_steps):
    spec = GraphSpec(n_particles=2, window=3, ball_radius=0.005, dt=1e-4, pp_pair_capacity=1)
    jar = JarParams()
    motion = CircleMotion(rpm=300.0, amplitude=0.017)
    t0 = 0.01
    velocities = np.array([[0.0, -0.2, 0.0], [0.05, 0.0, 0.0]])  # ball 0 falls onto the floor
    last = np.array([[0.0, 0.00491, 0.0], [0.0, 0.02, 0.0]]) + _circle_offset(300.0, 0.017, t0)
    positions = last + velocities * spec.dt * np.arange(-spec.window, 1)[:, None, None]
    window0 = Window(positions=positions, offsets=np.zeros((3, 3)),
                     offset_velocities=np.zeros((3, 3)), frequency_hz=np.float64(0.0))
    table = ReplayTable(accel=np.zeros((n_steps, 2, 3)), dE=np.zeros(n_steps))
    rollout = make_rollout(spec, replay_predictor(), n_steps, 1, phi_sb=-0.0049,
                           snap_velocity=snap_velocity, query=analytic_jar_query)
    res = jax.device_get(rollout(table, None, window0, motion, jar, t0))
    window = res.final.window
    fd_velocity = (window.positions[1:] - window.positions[:-1]) / spec.dt  # (W, N, 3)
    return res, fd_velocity, velocities


def test_snap_back_keep_velocity_moves_ball_to_threshold():
    res, fd_velocity, velocities = _floor_case("keep", 3)
    # Each step the falling ball reaches y = 0.0049 - 0.00002 and is put back on phi = phi_sb.
    np.testing.assert_array_equal(res.steps.n_snapped, [1, 1, 1])
    y_rel = res.positions[1:, 0, 1] - res.offsets[1:, 1]
    np.testing.assert_allclose(y_rel, 0.0049, rtol=0, atol=1e-15)
    # Velocity unchanged (the paper's choice): every FD velocity of the window is the initial one.
    np.testing.assert_allclose(fd_velocity, np.broadcast_to(velocities, fd_velocity.shape),
                               rtol=0, atol=1e-10)
    # The other ball flies free.
    np.testing.assert_allclose(res.positions[-1, 1] - res.positions[0, 1],
                               3 * 1e-4 * velocities[1], rtol=0, atol=1e-15)
    assert res.steps.n_outside.sum() == 0


def test_snap_back_position_mode_changes_fd_velocity():
    res, fd_velocity, _ = _floor_case("position", 1)
    assert res.steps.n_snapped[0] == 1
    np.testing.assert_allclose(res.positions[1, 0, 1] - res.offsets[1, 1], 0.0049, atol=1e-15)
    # The newest FD velocity follows the move: (0.0049 - 0.00491) / dt = -0.1 m/s.
    np.testing.assert_allclose(fd_velocity[-1, 0], [0.0, -0.1, 0.0], rtol=0, atol=1e-10)
    np.testing.assert_allclose(fd_velocity[-2, 0], [0.0, -0.2, 0.0], rtol=0, atol=1e-10)


@pytest.mark.parametrize("snap_back", [True, False])
def test_a_ball_outside_the_jar_is_snapped_or_counted_outside(snap_back):
    """A ball whose centre ends a step 1 mm outside the floor (phi > 0): with the snap-back it
    is moved back to phi_sb (snapped, and not outside after the step; it rests there as the jar
    moves, and may be snapped again); without, it is counted outside, and the ball inside the
    jar is neither."""
    spec = GraphSpec(n_particles=2, window=3, ball_radius=0.005, dt=1e-4, pp_pair_capacity=1)
    t0 = 0.01
    last = np.array([[0.0, -0.001, 0.0], [0.0, 0.02, 0.0]]) + _circle_offset(300.0, 0.017, t0)
    positions = np.broadcast_to(last, (spec.window + 1, 2, 3)).copy()
    window0 = Window(positions=positions, offsets=np.zeros((3, 3)),
                     offset_velocities=np.zeros((3, 3)), frequency_hz=np.float64(0.0))
    table = ReplayTable(accel=np.zeros((2, 2, 3)), dE=np.zeros(2))
    rollout = make_rollout(spec, replay_predictor(), 2, 1, snap_back=snap_back, phi_sb=-0.0049,
                           query=analytic_jar_query)
    res = jax.device_get(rollout(table, None, window0, CircleMotion(rpm=300.0, amplitude=0.017),
                                 JarParams(), t0))
    if snap_back:
        assert res.steps.n_snapped[0] == 1 and res.steps.n_snapped.max() == 1
        np.testing.assert_array_equal(res.steps.n_outside, [0, 0])
        assert res.positions[-1, 0, 1] - res.offsets[-1, 1] > 0.0048
    else:
        np.testing.assert_array_equal(res.steps.n_snapped, [0, 0])
        np.testing.assert_array_equal(res.steps.n_outside, [1, 1])


def test_separate_pairs_known_answer():
    radius, limit = 0.005, 5e-5
    positions = jnp.array([[0.0, 0.0, 0.0], [0.009, 0.0, 0.0],  # 1 mm overlap
                           [0.0, 0.03, 0.0],  # far away
                           [0.0, 0.0, 0.05], [0.0, 0.0, 0.05]])  # coincident: no normal
    separate = jax.jit(separate_pairs, static_argnums=(1, 2))  # one compile
    shift, n_pairs = separate(positions, radius, limit)
    shift = np.asarray(shift)
    moved = positions + shift
    assert int(n_pairs) == 1
    np.testing.assert_allclose(np.linalg.norm(moved[1] - moved[0]), 2 * radius - limit,
                               rtol=0, atol=1e-15)
    np.testing.assert_allclose(shift[0], [-0.000475, 0.0, 0.0], rtol=0, atol=1e-15)
    np.testing.assert_allclose(shift[1], -shift[0], rtol=0, atol=1e-15)  # momentum-neutral
    np.testing.assert_array_equal(shift[2:], 0.0)
    # within the allowed overlap nothing moves
    shift, n_pairs = separate(positions.at[1, 0].set(0.00996), radius, limit)
    assert int(n_pairs) == 0 and np.all(np.asarray(shift) == 0.0)


def test_pp_separation_in_the_rollout_caps_the_overlap():
    """Two balls driven into each other: without the separation they pass through each other;
    with it their overlap after every step is at most pp_max_overlap (velocities kept)."""
    spec = GraphSpec(n_particles=2, window=3, ball_radius=0.005, dt=1e-4, pp_pair_capacity=1)
    t0 = 0.01
    centre = np.array([0.0, 0.012, 0.0]) + _circle_offset(300.0, 0.017, t0)
    velocities = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])  # 2 m/s closing speed
    last = centre + np.array([[-0.0052, 0.0, 0.0], [0.0052, 0.0, 0.0]])
    positions = last + velocities * spec.dt * np.arange(-spec.window, 1)[:, None, None]
    window0 = Window(positions=positions, offsets=np.zeros((3, 3)),
                     offset_velocities=np.zeros((3, 3)), frequency_hz=np.float64(0.0))
    n_steps = 8
    table = ReplayTable(accel=np.zeros((n_steps, 2, 3)), dE=np.zeros(n_steps))
    gaps = {}
    for limit in (None, 5e-5):
        rollout = make_rollout(spec, replay_predictor(), n_steps, 1, query=analytic_jar_query,
                               pp_max_overlap=limit)
        res = jax.device_get(rollout(table, None, window0, CircleMotion(rpm=300.0,
                                                                        amplitude=0.017),
                                     JarParams(), t0))
        gaps[limit] = np.linalg.norm(res.positions[:, 1] - res.positions[:, 0], axis=-1)
    assert gaps[None][-1] < 0.009  # free flight: 1.2 mm of overlap after 8 steps
    assert np.all(gaps[5e-5][1:] >= 2 * 0.005 - 5e-5 - 1e-12)
    assert gaps[5e-5][-1] == pytest.approx(2 * 0.005 - 5e-5, abs=1e-12)


# --------------------------------------------------------------------------------------------
# A tiny SGN


def _moments(mean, std):
    return Moments(mean=np.asarray(mean, np.float64), std=np.asarray(std, np.float64))


def _stats(window):
    """Hand-set normalisation scales of the standard case (m/s, m, Hz, m/s^2, J)."""
    return NormStats(
        particle=_moments(np.zeros(7 * window), [0.5, 0.5, 0.5, 0.01, 1.0, 1.0, 1.0] * window),
        wall=_moments([0, 0, 0, 0, 0, 0, 5.0] * window,
                      [0.017, 0.017, 0.017, 0.5, 0.5, 0.5, 1.0] * window),
        pp_edge=_moments(np.zeros(3), [0.01] * 3), pw_edge=_moments(np.zeros(3), [0.005] * 3),
        accel=_moments(np.zeros(3), [0.5] * 3), dissipation=_moments([0.0], [1e-5]))


def _random_biases(params, seed, scale=0.3):
    """flax initialises biases to zero; random ones keep the random network's ReLUs away from
    their kinks (many inputs are exactly 0), so finite differences see a smooth function."""
    keys = iter(jax.random.split(jax.random.PRNGKey(seed), 200))
    return jax.tree_util.tree_map_with_path(
        lambda p, a: a + scale * jax.random.normal(next(keys), a.shape, a.dtype)
        if "bias" in jax.tree_util.keystr(p) else a, params)


def _init(model, stats, window0, motion, sdf, t0, spec, query=None, bias_seed=None):
    """Parameters of ``model`` from the graph of ``window0`` (jitted: eager ops compile one by
    one), with random biases if ``bias_seed`` is given."""

    def init(window):
        graph, _ = build_graph(jar_state_window(window, motion, t0, spec.dt), sdf, spec, query)
        params = init_params(model, normalize_graph(graph, stats), 0)
        return params if bias_seed is None else _random_biases(params, bias_seed)

    return jax.device_get(jax.jit(init)(window0))


# The slow tier (`pytest -m slow`; the default run's time): the rollout's gradient against finite differences; the design study's estimate (tests/test_design.py) keeps a gradient check in the default run.
@pytest.mark.slow
def test_gradients_match_finite_differences():
    """d E(100 steps) / d (rpm, amplitude, straight_length) by jax.grad through the rollout vs
    central finite differences (least-squares slope through E at x0 + j h, j = -5..5).

    Balls are placed so that no edge appears or disappears within the run (checked at every
    evaluation): two on the floor at phi = -5.05 mm (ball-wall edges) 10.5 mm apart (a ball-ball
    edge), two at mid height near the end cap (an edge; their phi depends on the jar length),
    one free. The network runs in float32 and is piecewise linear (ReLU): h = 3e-5 relative is
    small enough to cross few kinks and, with the 11-point fit, large enough to average the
    float32 rounding of dE (relative 6e-8 per step against a signal of ~1e-7 of E)."""
    window = 7
    jar = JarParams()
    centres = np.array([[-0.006, 0.00505, 0.0], [0.0045, 0.00505, 0.0], [0.0295, 0.0235, 0.0],
                        [0.019, 0.0235, 0.0], [-0.02, 0.025, 0.0]])
    n = len(centres)
    spec = GraphSpec(n_particles=n, window=window, ball_radius=0.005, dt=1e-4, pp_pair_capacity=10)
    t0 = 0.0123
    base = CircleMotion(rpm=jnp.float64(300.0), amplitude=jnp.float64(0.017), phase=0.0)
    rng = np.random.default_rng(1)
    v0 = rng.normal(0.0, 0.01, (n, 3))
    v0[:2, 1] = 0.0
    pos = centres + _circle_offset(300.0, 0.017, t0) + v0 * 1e-4 * np.arange(-window, 1)[:, None, None]
    window0 = Window(positions=pos, offsets=np.zeros((window, 3)),
                     offset_velocities=np.zeros((window, 3)), frequency_hz=np.float64(0.0))
    stats = _stats(window)
    model = SGN(hidden=32)
    params = _init(model, stats, window0, base, jar, t0, spec, analytic_jar_query, bias_seed=3)
    rollout = make_rollout(spec, model, 100, 10, query=analytic_jar_query, jit=False)

    def energy(rpm, amplitude, length):
        motion = CircleMotion(rpm=rpm, amplitude=amplitude, phase=0.0)
        res = rollout(params, stats, window0, motion, jar.replace(straight_length=length), t0)
        return res.energy, (res.steps.n_pp_edges, res.steps.n_pw_edges)

    # One compilation serves the gradient and every evaluation.
    value_and_grad = jax.jit(jax.value_and_grad(energy, argnums=(0, 1, 2), has_aux=True))
    x0 = (300.0, 0.017, 0.035)
    (_, (pp0, pw0)), grads = jax.device_get(value_and_grad(*x0))
    assert np.all(pp0 == 4) and np.all(pw0 == 4)  # two pairs, two balls on the floor, all along
    offsets = np.arange(-5, 6)
    for i, name in enumerate(("rpm", "amplitude", "straight_length")):
        h = 3e-5 * x0[i]
        values = []
        for j in offsets:
            x = list(x0)
            x[i] = float(x0[i] + j * h)  # Python floats throughout: one compilation
            (e, (pp, pw)), _ = jax.device_get(value_and_grad(*x))
            assert np.all(pp == 4) and np.all(pw == 4), (name, j)  # the energy is smooth here
            values.append(float(e))
        fd = np.polyfit(offsets * h, values, 1)[0]
        assert abs(float(grads[i])) > 0, name
        assert abs(fd / float(grads[i]) - 1) < 0.02, (name, fd, float(grads[i]))


@pytest.fixture(scope="module")
def tiny(dem):
    """A hidden-16 SGN on the DEM's window, a trace counter and the jitted rollout."""
    traj, spec, grid, motion = dem
    stats = _stats(spec.window)
    model = SGN(hidden=16)
    window0 = initial_window(traj, 100, spec.window)
    params = _init(model, stats, window0, motion, grid, traj.t[100], spec)
    traces = []
    inner = model_predictor(model)

    def counting_predictor(*args):
        traces.append(1)  # runs once per trace, never per step of a compiled rollout
        return inner(*args)

    rollout = make_rollout(spec, counting_predictor, 40, 10)
    return dict(traj=traj, spec=spec, grid=grid, motion=motion, model=model, params=params,
                stats=stats, window0=window0, rollout=rollout, traces=traces)


def _motions(k):
    return [CircleMotion(rpm=jnp.float64(240.0 + 20.0 * i), amplitude=jnp.float64(0.015 + 5e-4 * i),
                         phase=jnp.float64(0.1 * i)) for i in range(k)]


# The slow tier (11-17 s): its twin in the default run is
# tests/test_sweep.py::test_a_sweep_equals_one_ensemble_per_motion (a rollout vmapped over
# motions against one ensemble per motion).
@pytest.mark.slow
def test_vmap_over_motions_matches_separate_calls(tiny):
    from sgn_jax.motion import stack_motions

    t = tiny
    t0 = float(t["traj"].t[100])
    motions = _motions(8)
    args = (t["params"], t["stats"], t["window0"])
    batched = jax.device_get(jax.jit(jax.vmap(t["rollout"], in_axes=(None, None, None, 0, None,
                                                                     None)))(
        *args, stack_motions(motions), t["grid"], t0))
    for i, motion in enumerate(motions):
        single = jax.device_get(t["rollout"](*args, motion, t["grid"], t0))
        # Batched float32 matmuls may round differently; over 40 steps that stays ~1e-7 m.
        np.testing.assert_allclose(batched.positions[i], single.positions, rtol=0, atol=1e-9)
        np.testing.assert_allclose(batched.steps.energy_cum[i], single.steps.energy_cum,
                                   rtol=1e-5)
        np.testing.assert_array_equal(batched.steps.n_pp_edges[i], single.steps.n_pp_edges)
        np.testing.assert_array_equal(batched.steps.n_pw_edges[i], single.steps.n_pw_edges)
        np.testing.assert_allclose(batched.offsets[i], single.offsets, rtol=0, atol=1e-15)
    # The motions differ, so the batch is not one result repeated.
    assert np.ptp(batched.steps.energy_cum[:, -1]) > 0


@pytest.mark.slow
def test_no_recompilation_between_calls_with_the_same_shapes(tiny):
    t = tiny
    rollout, traj = t["rollout"], t["traj"]
    before = len(t["traces"])
    for i, motion in enumerate(_motions(3)):
        start = 100 + 37 * i
        params = jax.tree_util.tree_map(lambda a, i=i: a * np.float32(1.0 + 0.01 * i),
                                        t["params"])
        res = rollout(params, t["stats"], initial_window(traj, start, t["spec"].window), motion,
                      t["grid"], float(traj.t[start]))
        assert np.isfinite(np.asarray(res.positions)).all()
    assert rollout._cache_size() == 1
    assert len(t["traces"]) - before <= 1  # traced at most once (zero if an earlier test did)


@pytest.mark.slow
def test_capacity_tiers_give_the_same_rollout(tiny):
    t = tiny
    spec = t["spec"]
    args = (t["params"], t["stats"], t["window0"], t["motion"], t["grid"], float(t["traj"].t[100]))
    plain = jax.device_get(t["rollout"](*args))
    tiers = (20, 22)  # this window holds 19 to 23 pairs: every branch runs
    tiered = jax.device_get(make_rollout(spec, t["model"], 40, 10, pp_capacity_tiers=tiers)(*args))
    pairs = plain.steps.n_pp_edges // 2
    branch = np.searchsorted(np.array(tiers), pairs)  # 0, 1 or 2 (the full capacity)
    assert set(branch.tolist()) == {0, 1, 2}
    np.testing.assert_allclose(tiered.positions, plain.positions, rtol=0, atol=1e-12)
    np.testing.assert_allclose(tiered.steps.energy_cum, plain.steps.energy_cum, rtol=1e-12)
    np.testing.assert_array_equal(tiered.steps.n_pp_edges, plain.steps.n_pp_edges)
    with pytest.raises(RolloutError, match="pp_capacity_tiers"):
        make_rollout(spec, t["model"], 40, 10, pp_capacity_tiers=(8, 4))


def test_single_rollouts_use_pair_tiers_only_where_they_repay_their_compile():
    """run_rollout's tiers (pair_capacity_tiers): 1/4 and 1/2 of the capacity for a long
    rollout of a kind they speed up; none for a short one (compile-bound: each tier compiles
    the step again), none for a kind without ``capacity_tiers_help`` (the contact kind), and
    only tiers inside (0, capacity). That tiers give the same rollout is checked above."""
    from sgn_jax.pipelines.rollout_run import TIERS_MIN_STEPS, pair_capacity_tiers

    assert pair_capacity_tiers(96, TIERS_MIN_STEPS) == (24, 48)
    assert pair_capacity_tiers(96, 100_000) == (24, 48)
    assert pair_capacity_tiers(96, TIERS_MIN_STEPS - 1) == ()
    assert pair_capacity_tiers(96, 100_000, tiers_help=False) == ()
    assert pair_capacity_tiers(2, 100_000) == (1,)
    assert pair_capacity_tiers(1, 100_000) == ()
    assert 1000 <= TIERS_MIN_STEPS <= 20_000    # about where 1.4 s of compile is repaid


def test_overflow_is_counted_not_hidden(dem):
    """A capacity below the number of ball pairs: the dropped directed edges are reported each
    step (the replay's positions do not depend on the graph)."""
    import dataclasses

    traj, spec, grid, motion = dem
    small = dataclasses.replace(spec, pp_pair_capacity=4)
    table, ends, _ = _replay_table(traj, small, 200)
    for tiers in ((), (2,)):
        res = jax.device_get(make_rollout(small, replay_predictor(), 200, 10, snap_back=False,
                                          pp_capacity_tiers=tiers)(
            table, None, initial_window(traj, START, spec.window), motion, grid, traj.t[START]))
        pairs = pairs_within(traj.pos[ends], spec.pp_cutoff)
        assert pairs.max() > 4
        np.testing.assert_array_equal(res.steps.overflow, 2 * np.maximum(pairs - 4, 0))
        np.testing.assert_array_equal(res.steps.n_pp_edges, 2 * pairs)


# --------------------------------------------------------------------------------------------
# Host level and CLI


@pytest.fixture(scope="module")
def checkpoint(dem, tiny, tmp_path_factory):
    from sgn_jax.records.checkpoint import save_checkpoint

    traj = dem[0]
    cfg = replace_section(traj.config, "model", hidden=16)
    # With the ball-ball separation on (the built-in configs have it off since the contact
    # model became the default): the chunked rollout must carry it as the one call does.
    cfg = replace_section(cfg, "rollout", save_every=10, chunk_steps=50, checkpoint_steps=50,
                          pp_separation=True)
    directory = tmp_path_factory.mktemp("run") / "checkpoints" / "best"
    save_checkpoint(directory, 1, params=jax.device_get(tiny["params"]),
                    norm_stats=tiny["stats"], meta={"config": config_to_dict(cfg)})
    return directory.parent.parent, cfg


@pytest.mark.slow
def test_run_rollout_in_chunks_equals_one_call(dem, tiny, checkpoint):
    from sgn_jax.records.checkpoint import load_trained_model
    from sgn_jax.records.prediction import load_prediction

    traj, spec, grid, motion = dem
    run_dir, cfg = checkpoint
    assert cfg.rollout.pp_separation  # the checkpoint's config separates ball pairs; so must `whole`
    out = run_dir / "pred.npz"
    # 120 steps in chunks of 50: two calls of one compiled chunk and a remainder of 20.
    summary = run_rollout(load_trained_model(run_dir), traj, 20, 0.012, out, progress=False)
    pred = load_prediction(out)
    assert pred.n_steps == 120 and pred.n_frames == 13
    assert pred.meta["init_index"] == 20 and pred.meta["save_every"] == 10
    np.testing.assert_array_equal(pred.pos[0], traj.pos[20])
    assert summary["compile_time_s"] > 0 and summary["steps"] == 120

    whole = make_rollout(spec, tiny["model"], 120, 10,
                         pp_max_overlap=cfg.rollout.pp_max_overlap)(
        tiny["params"], tiny["stats"], initial_window(traj, 20, spec.window), motion, grid,
        traj.t[20])
    np.testing.assert_allclose(pred.pos, whole.positions, rtol=0, atol=1e-12)
    np.testing.assert_allclose(pred.energy_cum, whole.steps.energy_cum, rtol=1e-12)
    np.testing.assert_array_equal(pred.n_pw_edges, whole.steps.n_pw_edges)
    np.testing.assert_allclose(pred.t_step, whole.t_step, rtol=0, atol=1e-12)


# The slow tier (`pytest -m slow`; the default run's time): a coarser model step; the chunked rollout's equality stays in the default run.
@pytest.mark.slow
def test_run_rollout_with_a_coarser_step_starts_from_the_coarsened_record(dem, tiny, checkpoint):
    """A model whose step is 2 dt of the record (a fast tier at 2e-4 s on 1e-4 s data) starts
    from the record's window coarsened by 2: the same rollout as one from ``coarsen(2)``."""
    import dataclasses

    from sgn_jax.records.checkpoint import load_trained_model

    traj, spec, grid, motion = dem
    run_dir, _ = checkpoint
    trained = load_trained_model(run_dir)
    coarse_cfg = replace_section(trained.config, "dem", dt=2 * traj.dt)
    coarse_model = dataclasses.replace(trained, config=coarse_cfg)
    # 0.010 s = 50 coarse steps: one chunk of 50 (the remainder path is the test above's; one
    # compile fewer).
    summary = run_rollout(coarse_model, traj, 40, 0.010, run_dir / "coarse.npz", progress=False)
    assert summary["steps"] == 50
    assert summary["meta"]["init_index"] == 40 and summary["meta"]["dt"] == 2 * traj.dt
    coarse = traj.coarsen(2)
    coarse_spec = dataclasses.replace(spec, dt=2 * traj.dt)
    whole = make_rollout(coarse_spec, tiny["model"], 50, 10,
                         pp_max_overlap=coarse_cfg.rollout.pp_max_overlap)(
        tiny["params"], tiny["stats"], initial_window(coarse, 20, spec.window), motion, grid,
        coarse.t[20])
    np.testing.assert_allclose(summary["arrays"]["pos"], whole.positions, rtol=0, atol=1e-12)
    with pytest.raises(RolloutError, match="cannot be coarsened"):
        run_rollout(coarse_model, traj, 41, 0.012, run_dir / "odd.npz", progress=False)
    # a case config at the record's step runs at the model's (as api.at_surrogate_step);
    # a step that is not a whole fraction of the model's is refused before any work
    from sgn_jax.pipelines.rollout_run import _effective_config

    assert _effective_config(coarse_cfg, trained.config).dem.dt == 2 * traj.dt
    with pytest.raises(RolloutError, match=r"\[dem\] dt"):
        _effective_config(coarse_cfg, replace_section(trained.config, "dem", dt=0.8 * traj.dt))


@pytest.mark.slow
def test_cli_rollout(dem, checkpoint, tmp_path, capsys):
    from sgn_jax.cli import main
    from sgn_jax.config import save_config
    from sgn_jax.motion import motion2
    from sgn_jax.records.prediction import load_prediction

    traj = dem[0]
    run_dir, cfg = checkpoint
    # Override the motion by a config file (Motion 2 as a harmonic series).
    override = replace_section(cfg, "motion", kind="harmonic", base_frequency_hz=5.0,
                               x_sin=(0.017, 0.0), z_cos=(0.0, 0.017))
    save_config(override, tmp_path / "motion2.toml")
    out = tmp_path / "pred.npz"
    code = main(["rollout", "--checkpoint", str(run_dir), "--init", traj.path, "--duration",
                 "0.002", "--out", str(out), "--start-index", "30", "--save-every", "5",
                 "--config", str(tmp_path / "motion2.toml"), "--no-progress"])
    assert code == 0
    line = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert line["steps"] == 20 and line["out"] == str(out)
    pred = load_prediction(out)
    assert pred.n_frames == 5 and pred.config.motion.kind == "harmonic"
    np.testing.assert_allclose(pred.offset, np.asarray(jax.jit(offset)(motion2(), pred.t_pos)),
                               rtol=0, atol=1e-12)

    code = main(["rollout", "--checkpoint", str(run_dir), "--init", traj.path, "--duration",
                 "0.002", "--out", str(tmp_path / "bad.npz"), "--start-index", "3"])
    assert code == 2
    err = capsys.readouterr().err
    assert "start index 3" in err and "7 <= start index" in err
    assert not (tmp_path / "bad.npz").exists()


def test_bad_step_counts_are_refused():
    spec = GraphSpec(n_particles=2, window=3, ball_radius=0.005, dt=1e-4)
    with pytest.raises(RolloutError, match="multiple of save_every"):
        make_rollout(spec, replay_predictor(), 25, 10)
    with pytest.raises(RolloutError, match="checkpoint_steps"):
        make_rollout_advance(spec, replay_predictor(), 40, 10, checkpoint_steps=15)
    with pytest.raises(RolloutError, match="snap_velocity"):
        make_rollout(spec, replay_predictor(), 10, 1, snap_velocity="bounce")


# --------------------------------------------------------------------------------------------
# Memory of long differentiated rollouts (slow: compiles and runs gradients of 10k steps)


_MEMORY_CHILD = textwrap.dedent("""
    import json, resource, sys
    import jax, numpy as np
    sys.path.insert(0, {bench_dir!r})
    from bench_rollout import differentiated_rollout_memory
    print(json.dumps(differentiated_rollout_memory(int(sys.argv[1]), hidden=16)))
""")


@pytest.mark.slow
def test_memory_of_differentiated_rollout_is_bounded():
    from pathlib import Path

    bench_dir = str(Path(__file__).resolve().parent.parent / "benchmarks")
    code = _MEMORY_CHILD.format(bench_dir=bench_dir)
    result = {}
    for steps in (1000, 10000):
        out = subprocess.run([sys.executable, "-c", code, str(steps)], capture_output=True,
                             text=True, check=True)
        result[steps] = json.loads(out.stdout.strip().splitlines()[-1])
    small, large = result[1000], result[10000]
    # Compiled temporary memory: checkpointed chunks keep it flat in the number of steps ...
    assert large["temp_bytes"] < 1.1 * small["temp_bytes"]
    # ... where the same gradient without checkpointing grows about linearly.
    assert large["temp_bytes_unchunked"] > 5 * small["temp_bytes_unchunked"]
    # Peak RSS of the whole process (compile included) barely moves from 1k to 10k steps.
    assert large["peak_rss_mb"] < small["peak_rss_mb"] + 100
    assert np.isfinite(large["grad_norm"]) and large["grad_norm"] > 0


def test_the_init_step_pair_is_the_scan(tiny):
    """Stepping ``init_state`` with ``make_rollout_step`` by hand gives the jitted scan's
    states, energies and step records (the scan is this step): 20 steps by hand against the
    first 20 steps (two frames) of the module's compiled 40-step rollout (no
    compile of its own)."""
    from sgn_jax.surrogate.rollout import init_state, make_rollout_step

    t = tiny
    spec, t0 = t["spec"], float(t["traj"].t[100])
    whole = jax.device_get(t["rollout"](
        t["params"], t["stats"], t["window0"], t["motion"], t["grid"], t0))
    assert whole.steps.energy_cum.shape == (40,)
    step = jax.jit(make_rollout_step(spec, t["model"]))
    state = init_state(t["window0"], t["motion"], t0, spec.dt)
    energies, n_pw = [], []
    for k in range(20):
        state, record = step(t["params"], t["stats"], state, t["motion"], t["grid"], t0)
        energies.append(float(record.energy_cum))
        n_pw.append(int(record.n_pw_edges))
        if k == 9:
            np.testing.assert_allclose(np.asarray(state.window.positions[-1]),
                                       whole.positions[1], rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(state.window.positions[-1]), whole.positions[2],
                               rtol=0, atol=1e-12)
    np.testing.assert_allclose(energies, whole.steps.energy_cum[:20], rtol=1e-6, atol=0)
    assert n_pw == list(whole.steps.n_pw_edges[:20])
    assert int(state.step) == 20
