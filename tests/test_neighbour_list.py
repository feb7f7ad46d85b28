"""The rollout's neighbour list: the ball pairs within reach plus a skin, carried from step to
step, give the graph of all pairs edge for edge (docs/rollout.md, "Neighbour list")."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sgn_jax.dem.charge import BallClass, Charge, Material
from sgn_jax.surrogate.contact_charge import ball_charge
from sgn_jax.surrogate.graph import GraphSpec, Window, build_graph, neighbour_pairs
from sgn_jax.surrogate.rollout import (
    RolloutError,
    RolloutState,
    _refresh_neighbours,
    check_neighbours,
    empty_neighbour_list,
    init_state,
    make_rollout_advance,
)

DT, W, SKIN = 1e-4, 3, 1e-3
STEEL = Material("steel", young=2.05e9, poisson=0.235, restitution=0.3, friction=0.3,
                 rolling_friction=0.045)
# 30 balls of 10 mm and 30 of 6 mm, the last 4 absent (padding of a smaller charge)
MIX = Charge(classes=(BallClass(30, 0.005, 7700.0, STEEL), BallClass(26, 0.003, 7700.0, STEEL)),
             wall=STEEL)
N = 60
GRAPH_SPEC = GraphSpec(n_particles=N, window=W, ball_radius=0.005, dt=DT, pp_skin=1.5e-3,
                 phi_pw=-0.006, pp_pair_capacity=200, contact_features=True)


def no_walls(sdf, points, offset):
    """Every ball far from any wall (the ball-ball edges are what is tested)."""
    del sdf, offset
    return jnp.full(points.shape[:1], -1.0), jnp.broadcast_to(jnp.array([0.0, 1.0, 0.0]),
                                                              points.shape)


def window_at(x: np.ndarray) -> Window:
    """A window whose W + 1 positions are ``x`` (balls at rest), with MIX's charge."""
    return Window(positions=jnp.asarray(np.broadcast_to(x, (W + 1, N, 3)).copy()),
                  offsets=jnp.zeros((W, 3)), offset_velocities=jnp.zeros((W, 3)),
                  frequency_hz=jnp.asarray(5.0), spins=jnp.zeros((N, 3)),
                  charge=ball_charge(MIX, n_balls=N))


def packing(seed: int) -> np.ndarray:
    """(N, 3) m: 60 centres in a 45 mm box, many of them within reach of each other."""
    return np.random.default_rng(seed).uniform(-0.0225, 0.0225, (N, 3))


def brute_force_pairs(x: np.ndarray, radius: np.ndarray, present: np.ndarray, reach_extra: float):
    pairs = []
    for i in range(N):
        for j in range(i + 1, N):
            if present[i] and present[j] and np.linalg.norm(x[j] - x[i]) <= (
                    radius[i] + radius[j] + GRAPH_SPEC.pp_skin + reach_extra):
                pairs.append((i, j))
    return np.asarray(pairs, np.int32)


@jax.jit
def graph_of(window, candidates=None):
    """``build_graph`` of ``window`` (jitted: eager it dispatches op by op)."""
    return build_graph(window, None, GRAPH_SPEC, no_walls, candidates)


def assert_same_graph(a, b):
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_the_list_holds_the_pairs_within_reach_and_skin_in_all_pairs_order():
    x = packing(0)
    charge = ball_charge(MIX, n_balls=N)
    pairs, found = neighbour_pairs(jnp.asarray(x), GRAPH_SPEC, charge, SKIN, 10 * N)
    expected = brute_force_pairs(x, np.asarray(charge.radius), np.asarray(charge.present), SKIN)
    assert int(found) == len(expected) > 20
    np.testing.assert_array_equal(np.asarray(pairs[:len(expected)]), expected)
    assert np.all(np.asarray(pairs[len(expected):]) == N)        # unused rows


@pytest.mark.slow
def test_a_graph_from_the_list_is_the_all_pairs_graph_until_a_ball_moves_half_the_skin():
    x = packing(1)
    charge = ball_charge(MIX, n_balls=N)
    pairs, _ = neighbour_pairs(jnp.asarray(x), GRAPH_SPEC, charge, SKIN, 10 * N)
    graph_all, counts_all = graph_of(window_at(x))
    graph_list, counts_list = graph_of(window_at(x), pairs)
    assert int(counts_all.n_pp) > 20
    assert_same_graph(graph_all, graph_list)
    # every ball moved by up to half the skin in a random direction: the old list still holds
    # every pair within reach
    step = np.random.default_rng(2).normal(size=(N, 3))
    moved = x + 0.499 * SKIN * step / np.linalg.norm(step, axis=-1, keepdims=True)
    graph_all, counts_all = graph_of(window_at(moved))
    graph_list, counts_list = graph_of(window_at(moved), pairs)
    assert_same_graph(graph_all, graph_list)
    assert int(counts_list.n_pp) == int(counts_all.n_pp)


def test_the_list_is_rebuilt_once_a_ball_has_moved_half_the_skin_and_overflow_is_refused():
    x = packing(3)
    window = window_at(x)
    nl = _refresh_neighbours(empty_neighbour_list(window, 10 * N, SKIN), window, GRAPH_SPEC)
    np.testing.assert_array_equal(np.asarray(nl.reference), x)     # the first step builds it
    assert not bool(nl.overflow)
    small = x.copy()
    small[5] += [0.4 * SKIN, 0.0, 0.0]
    kept = _refresh_neighbours(nl, window_at(small), GRAPH_SPEC)
    np.testing.assert_array_equal(np.asarray(kept.reference), x)   # kept
    far = x.copy()
    far[5] += [0.6 * SKIN, 0.0, 0.0]
    rebuilt = _refresh_neighbours(nl, window_at(far), GRAPH_SPEC)
    np.testing.assert_array_equal(np.asarray(rebuilt.reference), far)
    # a list too small for the packing: the flag stays set and the host refuses the run
    tiny = _refresh_neighbours(empty_neighbour_list(window, 3, SKIN), window, GRAPH_SPEC)
    assert bool(tiny.overflow)
    with pytest.raises(RolloutError, match="neighbour list of 3 ball pairs overflowed"):
        check_neighbours(RolloutState(window=window, step=jnp.zeros((), jnp.int32),
                                      energy=jnp.zeros(()), neighbours=tiny))
    with pytest.raises(RolloutError, match="capacity >= 1 and skin > 0"):
        empty_neighbour_list(window, 10, 0.0)


@pytest.mark.slow
def test_a_rollout_with_the_list_is_the_all_pairs_rollout_bit_for_bit():
    """30 steps of balls flying apart from a dense start (the list is rebuilt on the way)
    under a predictor that pushes every ball-ball edge's receiver away from its sender."""
    from sgn_jax.motion import CircleMotion

    def predictor(params, stats, graph, step):
        del params, stats, step
        push = jnp.where(graph.edges["pp"][:, None], -graph.edges["features"][:, :3], 0.0)
        accel = jax.ops.segment_sum(push.astype(jnp.float64), graph.receivers, N + 2) * 2e4
        return accel, jnp.zeros(())

    x = packing(4) * 0.6
    x_prev = x - DT * np.random.default_rng(5).normal(scale=0.5, size=(N, 3))
    window = window_at(x)
    window = window.replace(positions=window.positions.at[:-1].set(x_prev))
    motion = CircleMotion(rpm=jnp.asarray(300.0), amplitude=jnp.asarray(0.017), phase=jnp.asarray(0.0))
    advance = make_rollout_advance(GRAPH_SPEC, predictor, 30, 1, query=no_walls, snap_back=False)
    state = init_state(window, motion, 0.0, DT)
    plain = advance(None, None, state, motion, None, 0.0)
    listed = advance(None, None, state.replace(
        neighbours=empty_neighbour_list(state.window, 10 * N, SKIN)), motion, None, 0.0)
    assert float(np.max(np.abs(np.asarray(plain.positions[-1]) - x))) > SKIN   # it moved
    np.testing.assert_array_equal(np.asarray(listed.positions), np.asarray(plain.positions))
    assert not bool(listed.final.neighbours.overflow)
