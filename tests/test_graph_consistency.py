"""Training and the rollout featurize the same window into the same graph.

The rollout is run with the replay ("cheating") predictor on a short real DEM trajectory, snap-back
off: fed the DEM's finite-difference accelerations it reproduces the DEM positions to float64
rounding, so the window it assembles at step j must be the dataset's window ending at sample
START + j. The graphs the rollout builds are compared with the graphs the training code path
builds for the same windows from the dataset file
(:func:`sgn_jax.pipelines.features.windows_from_trajectory` +
:func:`sgn_jax.surrogate.graph.make_graph_builder`, and the compact rows of
:func:`sgn_jax.pipelines.features.featurize_trajectory`, what training actually stores).

What the comparison covers on the rollout side: the slide order of the window, the integration
of the newest position, the time at which the jar offset and offset velocity of each new slot are
taken (the rollout recomputes them from the motion at ``t0 + (step + 1) dt``; training reads the
DEM's recorded ``offset`` / ``offset_vel``), the rotational frequency (from the motion vs from the
dataset's config), and how ``build_graph`` is called inside the scan.

Tolerance: integer arrays and masks must be equal. The float32 features are compared with
``|a - b| <= 2**-23 |b| + 1e-10`` (SI units). The float64 positions of the replay differ from the
DEM's by rounding only (a few ulp of |x| ~ 0.04 m, ~1e-17 m, accumulating to < 1e-15 m over 20
steps), so in float64 the velocities (differences over dt = 1e-4 s) differ by < 1e-11 m/s, the
phi, normal and edge features by less; the jar state is the same motion evaluated at the same
float64 times (~1e-18 m apart). Casting to float32 can turn such a difference into at most one
float32 ulp (<= 2**-23 relative) for a value next to a rounding boundary; 1e-10 covers values
near zero, where the float64 difference is not negligible against the float32 ulp. A
one-sample error in the jar time changes offsets by A omega dt ~ 5e-5 m and offset velocities by
A omega^2 dt ~ 2e-3 m/s, a wrong velocity stencil changes velocities by ~a dt ~ 1e-3 m/s: six
orders of magnitude above this tolerance. (On this machine the graphs come out bit-identical.)
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import sgn_jax  # noqa: F401  (x64)
from sgn_jax.config import replace_section
from sgn_jax.pipelines.configure import (
    graph_spec_from_config,
    motion_from_config,
    sdf_grid_from_config,
)
from sgn_jax.pipelines.features import featurize_trajectory, windows_from_trajectory
from sgn_jax.pipelines.rollout_run import initial_window
from sgn_jax.surrogate.graph import (
    build_graph,
    dissipation_per_interval,
    make_graph_builder,
    targets_from_arrays,
)
from sgn_jax.surrogate.rollout import ReplayTable, make_rollout, replay_predictor

START = 12  # window end of the rollout's first step (>= W = 7)
STEPS = 20  # > W: the final window holds no slot of the initial (dataset) window
FEATURE_RTOL = 2.0**-23  # one float32 ulp, relative
FEATURE_ATOL = 1e-10  # SI units; bounds the float64 rounding differences (module docstring)


@pytest.fixture(scope="module")
def dem(standard_dem_file):
    """A short real DEM trajectory of the standard case: 0.05 s settling, then motion (the
    session's run shared with tests/test_rollout.py, conftest.py; the tests use its first
    START + STEPS + 2 samples), saved and loaded back as training reads it."""
    from sgn_jax.config import builtin_config_path, load_config
    from sgn_jax.records.trajectory import load_trajectory

    traj = load_trajectory(standard_dem_file)
    want = replace_section(load_config(builtin_config_path("emax_300rpm")), "dem",
                           settle_time=0.05)
    assert (traj.config.jar, traj.config.balls, traj.config.dem.settle_time) == (
        want.jar, want.balls, want.dem.settle_time)
    assert len(traj.pos) >= START + STEPS + 2  # the training window at START + STEPS has a target
    spec = graph_spec_from_config(traj.config)
    return traj, spec, sdf_grid_from_config(traj.config), motion_from_config(traj.config.motion)


@pytest.fixture(scope="module")
def rollout_graphs(dem):
    """``{j: graph}`` for j = 0 .. STEPS: the graph the rollout built at step j (window ending at
    sample START + j), and for j = STEPS the graph of the rollout's final window."""
    traj, spec, grid, motion = dem
    ends = START + np.arange(STEPS)
    accel, de = targets_from_arrays(traj.pos, dissipation_per_interval(traj), ends, spec.dt)
    table = ReplayTable(accel=jnp.asarray(accel), dE=jnp.asarray(de))
    replay = replay_predictor()
    captured = {}

    def capture(step, graph):
        captured[int(step)] = jax.tree_util.tree_map(np.array, graph)

    def capturing_replay(params, stats, graph, step):
        # The graph handed to the predictor inside the jitted scan, copied out to the host.
        jax.debug.callback(capture, step, graph)
        return replay(params, stats, graph, step)

    rollout = make_rollout(spec, capturing_replay, STEPS, STEPS, snap_back=False)
    result = jax.device_get(rollout(table, None, initial_window(traj, START, spec.window), motion,
                                    grid, traj.t[START]))
    assert sorted(captured) == list(range(STEPS))

    # The rollout does not return the graph its next step would build, so the last graph is
    # rebuilt from ``result.final.window`` with the same build_graph. This still tests the
    # rollout's window assembly: with STEPS > W every slot of that window (positions, jar
    # offsets, offset velocities) was appended by the rollout's own step (integration, motion at
    # t_{n+1}, slide_window), and its frequency came from the motion in init_state; only the
    # featurizer call is ours.
    final, _ = jax.jit(lambda window: build_graph(window, grid, spec))(result.final.window)
    captured[STEPS] = jax.tree_util.tree_map(np.array, final)
    return captured, result


@pytest.fixture(scope="module")
def training_graphs(dem):
    """The padded graphs (leading axis j = 0 .. STEPS) of the dataset windows ending at samples
    START + j, built as training builds them, and the jitted builder that made them."""
    traj, spec, grid, _ = dem
    windows, _, _ = windows_from_trajectory(traj, spec.window, ends=START + np.arange(STEPS + 1))
    builder = make_graph_builder(None, spec)
    graphs, counts = jax.device_get(builder(jax.tree_util.tree_map(jnp.asarray, windows), grid))
    assert np.all(counts.pp_dropped == 0)
    return graphs, builder


def _assert_same_graph(rollout_graph, training_graph, label):
    for name in ("senders", "receivers", "n_node", "n_edge"):
        np.testing.assert_array_equal(getattr(rollout_graph, name), getattr(training_graph, name),
                                      err_msg=f"{label}: {name}")
    for part in ("nodes", "edges"):
        ours, theirs = getattr(rollout_graph, part), getattr(training_graph, part)
        # The rollout's graph also hands the model the balls' spins (nodes["spin"]: rollout
        # state, which a kind with spin reads and the SGN does not); everything else is the
        # training featurizer's.
        extra = {"spin"} if part == "nodes" else set()
        assert set(theirs) <= set(ours) <= set(theirs) | extra, label
        for key in theirs:
            if key == "features":
                assert ours[key].dtype == theirs[key].dtype == np.float32, (label, part)
                np.testing.assert_allclose(ours[key], theirs[key], rtol=FEATURE_RTOL,
                                           atol=FEATURE_ATOL, err_msg=f"{label}: {part} {key}")
            else:
                np.testing.assert_array_equal(ours[key], theirs[key],
                                              err_msg=f"{label}: {part} {key}")


def test_final_rollout_window_gives_the_training_graph(dem, rollout_graphs, training_graphs):
    """The window the rollout holds after STEPS steps featurizes like the dataset window ending
    at sample START + STEPS."""
    traj, spec, _, _ = dem
    graphs, result = rollout_graphs
    training, _ = training_graphs
    # The premise: the replay reproduced the DEM positions of the window to float64 rounding.
    window_samples = slice(START + STEPS - spec.window, START + STEPS + 1)
    np.testing.assert_allclose(result.final.window.positions, traj.pos[window_samples], rtol=0,
                               atol=1e-15)
    last = jax.tree_util.tree_map(lambda a: a[STEPS], training)
    _assert_same_graph(graphs[STEPS], last, f"final window (sample {START + STEPS})")


def test_every_rollout_step_graph_is_the_training_graph(rollout_graphs, training_graphs):
    """Each graph the rollout fed to its predictor inside the scan is the training graph of the
    same window; the edge sets change along the run (pairs and wall contacts come and go)."""
    graphs, _ = rollout_graphs
    training, _ = training_graphs
    for j in range(STEPS):
        one = jax.tree_util.tree_map(lambda a, j=j: a[j], training)
        _assert_same_graph(graphs[j], one, f"step {j} (window ending at sample {START + j})")
    n_real = training.n_edge[:, 0]
    n_pp = training.edges["pp"].sum(axis=1)
    assert n_pp.min() > 0 and (n_real - n_pp).min() > 0  # ball-ball and ball-wall edges
    assert len(set(n_pp.tolist())) > 1 and len(set((n_real - n_pp).tolist())) > 1


def test_training_dataset_rows_are_the_rollout_graphs(dem, rollout_graphs, training_graphs):
    """What training stores (featurize_trajectory's compact rows: N + 1 node rows, real edges
    only) is the rollout's graph without its padding."""
    traj, spec, grid, _ = dem
    graphs, _ = rollout_graphs
    _, builder = training_graphs
    n = spec.n_particles
    ends = START + np.arange(STEPS + 1)
    ds = featurize_trajectory(traj, spec, grid, ends, chunk=len(ends), builder=builder)
    np.testing.assert_array_equal(ds.window_end, ends)
    for j in range(STEPS + 1):
        graph = graphs[j]
        label = f"window ending at sample {START + j}"
        real = graph.edges["pp"] | graph.edges["pw"]
        rows = slice(ds.edge_offsets[j], ds.edge_offsets[j + 1])
        np.testing.assert_allclose(graph.nodes["features"][: n + 1], ds.node_features[j],
                                   rtol=FEATURE_RTOL, atol=FEATURE_ATOL, err_msg=label)
        np.testing.assert_allclose(graph.edges["features"][real], ds.edge_features[rows],
                                   rtol=FEATURE_RTOL, atol=FEATURE_ATOL, err_msg=label)
        np.testing.assert_array_equal(graph.senders[real], ds.edge_senders[rows], err_msg=label)
        np.testing.assert_array_equal(graph.receivers[real], ds.edge_receivers[rows],
                                      err_msg=label)
        np.testing.assert_array_equal(graph.edges["pp"][real], ds.edge_is_pp[rows], err_msg=label)
