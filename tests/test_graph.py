"""The SGN featurizer: edge rules, both directions, overflow, features, integrator consistency."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import sgn_jax  # noqa: F401
from sgn_jax.config import builtin_config_path, load_config
from sgn_jax.geometry import jar_sdf, query_sdf_grid
from sgn_jax.pipelines.configure import jar_params_from_config, sdf_grid_from_config
from sgn_jax.pipelines.features import windows_from_trajectory
from sgn_jax.surrogate.graph import (
    GraphError,
    GraphSpec,
    Window,
    build_graph,
    slide_window,
    true_indices,
    velocity_columns,
)
from sgn_jax.surrogate.train import split_window_ends
from sgn_jax.testing import synthetic_trajectory

R = 0.005
DT = 1e-4


@pytest.fixture(scope="module")
def grid():
    return sdf_grid_from_config(load_config(builtin_config_path("emax_300rpm")))


@pytest.fixture(scope="module")
def jar():
    return jar_params_from_config(load_config(builtin_config_path("emax_300rpm")).jar)


def analytic_query(params, points, offset):
    """The exact jar SDF and its unit normal (the featurizer accepts any such query)."""
    x = jnp.asarray(points) - jnp.asarray(offset)
    phi = jar_sdf(params, x)
    grad = jax.vmap(jax.grad(lambda p: jar_sdf(params, p)))(x.reshape(-1, 3)).reshape(x.shape)
    return phi, grad / jnp.linalg.norm(grad, axis=-1, keepdims=True)


# The tests' own evaluations of the exact SDF (the expected values), as one program per shape
# instead of ~60 eager compiles of its ops; the featurizer calls analytic_query
# inside its own programs.
reference_query = jax.jit(analytic_query)


def _spec(n, window=3, pairs=64):
    return GraphSpec(n_particles=n, window=window, ball_radius=R, dt=DT, pp_pair_capacity=pairs)


def _window(positions, offsets=None, window=3, freq=5.0):
    positions = np.asarray(positions, np.float64)
    if positions.ndim == 2:  # static balls: the same positions in every slot
        positions = np.repeat(positions[None], window + 1, axis=0)
    offsets = np.zeros((window, 3)) if offsets is None else np.asarray(offsets, np.float64)
    return Window(positions=positions, offsets=offsets,
                  offset_velocities=np.full((window, 3), 0.25), frequency_hz=np.array(freq))


def _edge_set(graph):
    """Real edges as {(sender, receiver): feature}, split by kind."""
    s, r = np.asarray(graph.senders), np.asarray(graph.receivers)
    f = np.asarray(graph.edges["features"], np.float64)
    pp = {(a, b): f[i] for i, (a, b) in enumerate(zip(s, r, strict=True)) if graph.edges["pp"][i]}
    pw = {(a, b): f[i] for i, (a, b) in enumerate(zip(s, r, strict=True)) if graph.edges["pw"][i]}
    return pp, pw


def _random_balls(n, seed):
    """Ball centres in the jar (jar frame = lab frame at zero offset), some pairs close, some
    balls near the floor and the side walls."""
    rng = np.random.default_rng(seed)
    pts = []
    while len(pts) < n:
        # The first five balls straddle the ball-wall threshold on the floor (phi = -y there).
        y = rng.uniform(0.0049, 0.0055) if len(pts) < 5 else rng.uniform(0.0045, 0.02)
        p = np.array([rng.uniform(-0.03, 0.03), y, rng.uniform(-0.012, 0.012)])
        if all(np.linalg.norm(p - q) > 1.9 * R for q in pts):
            pts.append(p)
    return np.array(pts)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_edges_follow_the_rules_in_both_directions(jar, seed):
    n = 16
    x = _random_balls(n, seed)
    offset = np.array([0.004, 0.0, -0.003])
    win = _window(x + offset, offsets=np.tile(offset, (3, 1)))
    spec = _spec(n)
    graph, counts = jax.jit(lambda w: build_graph(w, jar, spec, analytic_query))(win)
    pp, pw = _edge_set(graph)

    # Expected by brute force from the same SDF and the rules of docs/conventions.md section 5.
    phi, normal = (np.asarray(a, np.float64) for a in reference_query(jar, x + offset, offset))
    d = np.linalg.norm(x[:, None] - x[None], axis=-1)
    expected_pp = {(j, i) for i in range(n) for j in range(n)
                   if i != j and d[i, j] <= 2 * R + spec.pp_skin}
    walled = [b for b in range(n) if phi[b] >= spec.phi_pw]
    expected_pw = {(n, b) for b in walled} | {(b, n) for b in walled}
    assert expected_pp and walled and len(walled) < n, "test configuration must exercise rules"
    assert set(pp) == expected_pp
    assert set(pw) == expected_pw
    for (s, r), f in pp.items():
        np.testing.assert_allclose(f, x[s] - x[r], atol=1e-9)  # float32 of x_s - x_r
    for (s, r), f in pw.items():
        b = s if r == n else r
        np.testing.assert_allclose(f, phi[b] * normal[b], rtol=1e-6, atol=1e-10)
    assert int(counts.n_pp) == len(expected_pp) and int(counts.n_pw) == len(expected_pw)
    assert int(counts.pp_dropped) == 0

    # jraph layout: real edges first, the rest are padding edges on the padding node n + 1.
    n_real = len(pp) + len(pw)
    assert graph.n_node.tolist() == [n + 1, 1]
    assert graph.n_edge.tolist() == [n_real, spec.edge_capacity - n_real]
    assert np.all(np.asarray(graph.senders[n_real:]) == n + 1)
    assert np.all(np.asarray(graph.receivers[n_real:]) == n + 1)
    assert graph.nodes["particle"].tolist() == [True] * n + [False, False]
    assert graph.nodes["wall"].tolist() == [False] * n + [True, False]


def test_pp_capacity_overflow_is_counted_and_pairs_stay_bidirectional(grid):
    # A row of 6 touching balls on the floor: 5 close pairs.
    x = np.array([[-0.025 + k * 0.0102, 0.012, 0.0] for k in range(6)])
    spec = _spec(6, pairs=2)
    # jitted: one program per spec instead of ~160 eager compiles
    graph, counts = jax.jit(build_graph, static_argnums=2)(_window(x), grid, spec)
    assert int(counts.n_pp) == 10
    assert int(counts.pp_dropped) == 6
    pp, _ = _edge_set(graph)
    assert len(pp) == 4
    for s, r in pp:
        assert (r, s) in pp
        np.testing.assert_allclose(pp[(s, r)], -pp[(r, s)])

    roomy, counts = jax.jit(build_graph, static_argnums=2)(_window(x), grid, _spec(6, pairs=5))
    assert int(counts.pp_dropped) == 0 and len(_edge_set(roomy)[0]) == 10


def test_node_features_velocities_sdf_and_wall(jar):
    traj = synthetic_trajectory(40, 6, seed=3)
    w = 4
    wins, _, _ = windows_from_trajectory(traj, w)
    k = 11  # a window in the middle
    win = jax.tree_util.tree_map(lambda a: a[k], wins)
    n_end = w + k  # sample index that ends this window
    graph, _ = jax.jit(lambda win: build_graph(win, jar, _spec(6, window=w), analytic_query))(win)
    feats = np.asarray(graph.nodes["features"], np.float64)
    for slot in range(w):
        j = n_end - w + 1 + slot  # sample of this slot
        v = (traj.pos[j] - traj.pos[j - 1]) / DT
        phi, normal = reference_query(jar, traj.pos[j], traj.offset[j])
        cols = slice(7 * slot, 7 * slot + 7)
        np.testing.assert_allclose(feats[:6, cols][:, :3], v, rtol=1e-6, atol=1e-7)
        np.testing.assert_allclose(feats[:6, cols][:, 3], phi, rtol=1e-6, atol=1e-9)
        np.testing.assert_allclose(feats[:6, cols][:, 4:], normal, rtol=1e-6, atol=1e-7)
        wall = feats[6, cols]
        np.testing.assert_allclose(wall[:3], traj.offset[j], rtol=1e-6)
        np.testing.assert_allclose(wall[3:6], traj.offset_vel[j], rtol=1e-6, atol=1e-7)
        assert wall[6] == 5.0
    assert np.all(feats[7] == 0)  # padding node
    assert velocity_columns(w).tolist() == [0, 1, 2, 7, 8, 9, 14, 15, 16, 21, 22, 23]


def test_default_query_is_the_sdf_grid(grid):
    traj = synthetic_trajectory(12, 6, seed=6)
    wins, _, _ = windows_from_trajectory(traj, 3)
    win = jax.tree_util.tree_map(lambda a: a[2], wins)
    spec = _spec(6)
    default, _ = jax.jit(lambda w: build_graph(w, grid, spec))(win)
    explicit, _ = jax.jit(lambda w: build_graph(w, grid, spec, query_sdf_grid))(win)
    for a, b in zip(jax.tree_util.tree_leaves(default), jax.tree_util.tree_leaves(explicit),
                    strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    phi = np.asarray(default.nodes["features"][:6, 3::7])
    assert np.all((phi < 0) & (phi > -0.03))  # the balls are inside the cavity


def test_targets_replay_the_trajectory_with_the_integrator():
    """a_n and dE_n fed to v += a dt, x += v dt, E += dE reproduce positions and energy."""
    traj = synthetic_trajectory(60, 5, seed=4)
    w = 7
    wins, accel, de = windows_from_trajectory(traj, w)
    first_end = w  # windows end at samples w .. T-2, in order
    x = traj.pos[first_end].copy()
    v = (traj.pos[first_end] - traj.pos[first_end - 1]) / DT
    cum = np.cumsum(np.sum([traj.diss_pp_normal, traj.diss_pp_tangential, traj.diss_pw_normal,
                            traj.diss_pw_tangential], axis=0))
    energy = cum[first_end]
    for s in range(len(accel)):
        v = v + accel[s] * DT
        x = x + v * DT
        energy = energy + de[s]
        n_next = first_end + s + 1
        np.testing.assert_allclose(x, traj.pos[n_next], rtol=0, atol=1e-12)
        np.testing.assert_allclose(energy, cum[n_next], rtol=1e-12)
    # The velocity feature of the newest slot is the integrator's velocity.
    np.testing.assert_allclose(np.asarray(wins.positions[0, -1] - wins.positions[0, -2]) / DT,
                               (traj.pos[w] - traj.pos[w - 1]) / DT)


def test_build_graph_inside_lax_scan_matches_direct_calls(jar):
    traj = synthetic_trajectory(30, 6, seed=5)
    w = 3
    spec = _spec(6, window=w)
    wins, _, _ = windows_from_trajectory(traj, w)
    first = jax.tree_util.tree_map(lambda a: jnp.asarray(a[0]), wins)
    steps = 8
    new_pos = jnp.asarray(traj.pos[w + 1: w + 1 + steps])
    new_off = jnp.asarray(traj.offset[w + 1: w + 1 + steps])
    new_vel = jnp.asarray(traj.offset_vel[w + 1: w + 1 + steps])

    def body(carry, xs):
        win, dropped = carry
        win = slide_window(win, *xs)
        graph, counts = build_graph(win, jar, spec, analytic_query)
        return (win, dropped + counts.pp_dropped), (graph.edges["features"], counts.n_pw)

    (_, dropped), (edge_feats, n_pw) = jax.jit(
        lambda c: jax.lax.scan(body, c, (new_pos, new_off, new_vel)))((first, jnp.int32(0)))
    assert int(dropped) == 0
    # The direct calls: build_graph on each dataset window, outside any scan (jitted on its
    # own, one program instead of ~70 eager compiles).
    direct_call = jax.jit(lambda win: build_graph(win, jar, spec, analytic_query))
    for s in range(steps):
        direct, counts = direct_call(jax.tree_util.tree_map(lambda a, s=s: a[s + 1], wins))
        np.testing.assert_allclose(np.asarray(edge_feats[s]),
                                   np.asarray(direct.edges["features"]), rtol=1e-6, atol=1e-12)
        assert int(n_pw[s]) == int(counts.n_pw)


def test_bad_window_shape_is_a_clear_error(grid):
    win = _window(np.zeros((4, 3)), window=3)
    with pytest.raises(GraphError, match="W \\+ 1 positions"):
        build_graph(win.replace(positions=win.positions[1:]), grid, _spec(4))


@pytest.mark.parametrize("size", [1, 5, 12])
def test_true_indices_are_each_rows_nonzero(size):
    """true_indices (one cumsum and one scatter for all rows) gives per row what jnp.nonzero
    gives: the first ``size`` True indices in order, then the fill value."""
    mask = np.random.default_rng(size).random((3, 12)) < np.array([[0.2], [0.7], [0.0]])
    got = np.asarray(jax.jit(true_indices, static_argnums=(1, 2))(jnp.asarray(mask), size, 12))
    for k in range(3):
        (want,) = jnp.nonzero(mask[k], size=size, fill_value=12)
        np.testing.assert_array_equal(got[k], np.asarray(want))


def test_chronological_split():
    t = np.arange(100) * DT
    train, val = split_window_ends(t, 7, train_time=50 * DT, val_time=30 * DT)
    assert train.min() == 7 and t[train.max() + 1] == pytest.approx(50 * DT)
    assert t[val.min() - 7] == pytest.approx(50 * DT)
    assert t[val.max() + 1] == pytest.approx(80 * DT)
    assert np.intersect1d(train, val).size == 0
