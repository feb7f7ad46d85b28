"""The SGN model: reference forward pass, equivariance, padding invariance, readout, normalisation."""

import jax
import jax.numpy as jnp
import jraph
import numpy as np
import pytest

import sgn_jax  # noqa: F401
from sgn_jax.config import builtin_config_path, load_config
from sgn_jax.geometry import jar_sdf
from sgn_jax.pipelines.configure import jar_params_from_config
from sgn_jax.pipelines.features import windows_from_trajectory
from sgn_jax.surrogate.graph import GraphSpec, Window, build_graph
from sgn_jax.surrogate.model import count_params, init_params, make_predict
from sgn_jax.surrogate.normalization import (
    compute_norm_stats,
    denormalize_accel,
    denormalize_dissipation,
    normalize_accel,
    normalize_dissipation,
    normalize_graph,
    stats_from_arrays,
    stats_to_arrays,
)
from sgn_jax.surrogate.sgn import SGN
from sgn_jax.testing import random_init_weights, synthetic_trajectory

N, W = 8, 3


@pytest.fixture(scope="module")
def jar():
    return jar_params_from_config(load_config(builtin_config_path("emax_300rpm")).jar)


def analytic_query(params, points, offset):
    x = jnp.asarray(points) - jnp.asarray(offset)
    phi = jar_sdf(params, x)
    grad = jax.vmap(jax.grad(lambda p: jar_sdf(params, p)))(x.reshape(-1, 3)).reshape(x.shape)
    return phi, grad / jnp.linalg.norm(grad, axis=-1, keepdims=True)


GRAPH_SPEC = GraphSpec(n_particles=N, window=W, ball_radius=0.005, dt=1e-4, pp_pair_capacity=16)

# The tests' normalisation of graphs as one program, instead of dozens of eager op compiles;
# test_normalisation_round_trip_... checks normalize_graph itself, called as is.
normalize = jax.jit(normalize_graph)


@pytest.fixture(scope="module")
def windows():
    wins, _, _ = windows_from_trajectory(synthetic_trajectory(40, N, seed=7), W)
    return wins


@pytest.fixture(scope="module")
def builder(jar):
    return jax.jit(lambda w: build_graph(w, jar, GRAPH_SPEC, analytic_query))



def _stats(graphs):
    nodes = np.concatenate([np.asarray(g.nodes["features"]) for g in graphs])
    part = np.concatenate([np.asarray(g.nodes["particle"]) for g in graphs])
    wall = np.concatenate([np.asarray(g.nodes["wall"]) for g in graphs])
    edges = np.concatenate([np.asarray(g.edges["features"]) for g in graphs])
    pp = np.concatenate([np.asarray(g.edges["pp"]) for g in graphs])
    pw = np.concatenate([np.asarray(g.edges["pw"]) for g in graphs])
    rng = np.random.default_rng(0)
    return compute_norm_stats(nodes[part], nodes[wall], edges[pp], edges[pw],
                              rng.normal(0, 30, (100, 3)), rng.uniform(0, 1e-5, 100))


@pytest.fixture(scope="module")
def setup(windows, builder):
    graphs = [builder(jax.tree_util.tree_map(lambda a, k=k: a[k], windows))[0]
              for k in range(0, 30, 3)]
    stats = _stats(graphs)
    model = SGN(hidden=16, mlp_layers=4, interaction_layers=1)
    params = random_init_weights(model, normalize(graphs[0], stats), 1)
    return graphs, stats, model, params


# --------------------------------------------------------------------------------------------


def _np_mlp(p, x, layers=4):
    for i in range(layers):
        x = x @ np.asarray(p[f"dense_{i}"]["kernel"], np.float64) + np.asarray(
            p[f"dense_{i}"]["bias"], np.float64)
        if i < layers - 1:
            x = np.maximum(x, 0)
    return x


def _reference_forward(params, graph):
    """Paper Eqs. 22-27 and the readout, written out edge by edge in float64 numpy."""
    g = jax.tree_util.tree_map(np.asarray, graph)
    x = g.nodes["features"].astype(np.float64)
    part = g.nodes["particle"]
    h = np.where(part[:, None], _np_mlp(params["particle_encoder"], x),
                 _np_mlp(params["wall_encoder"], x))
    real = np.flatnonzero(g.edges["pp"] | g.edges["pw"])
    e_in = np.concatenate([g.edges["features"], g.edges["pp"][:, None], g.edges["pw"][:, None]],
                          -1).astype(np.float64)
    he = _np_mlp(params["edge_encoder"], e_in)
    n_layers = sum(1 for name in params if name.startswith("interaction_"))
    for layer in range(n_layers):
        p = params[f"interaction_{layer}"]
        # psi_e as one dense layer on the concatenation [h_receiver, h_sender, h_edge].
        k0 = np.concatenate([p["message_in_receiver"]["kernel"], p["message_in_sender"]["kernel"],
                             p["message_in_edge"]["kernel"]]).astype(np.float64)
        b0 = np.asarray(p["message_in_receiver"]["bias"], np.float64)
        agg = np.zeros_like(h)
        count = np.zeros(len(h))
        for e in real:
            s, r = g.senders[e], g.receivers[e]
            z = np.maximum(np.concatenate([h[r], h[s], he[e]]) @ k0 + b0, 0)
            for i in (1, 2):
                z = np.maximum(z @ p[f"message_{i}"]["kernel"] + p[f"message_{i}"]["bias"], 0)
            agg[r] += z @ p["message_3"]["kernel"] + p["message_3"]["bias"]
            count[r] += 1
        agg /= np.maximum(count, 1)[:, None]
        h = _np_mlp(p["node_update"], np.concatenate([h, agg], -1))
    accel = _np_mlp(params["decoder"], h) * part[:, None]
    touched = set(g.senders[real]) | set(g.receivers[real])
    active = [i for i in np.flatnonzero(part) if i in touched]
    pooled = h[active].mean(axis=0) if active else np.zeros(h.shape[1])
    return accel, _np_mlp(params["global_readout"], pooled)[0]


def test_model_matches_a_reference_implementation(setup):
    graphs, stats, model, params = setup
    checked_edges = 0
    apply = jax.jit(model.apply)
    for graph in graphs[:4]:
        g = normalize(graph, stats)
        accel, de = apply({"params": params}, g)
        ref_accel, ref_de = _reference_forward(params, g)
        np.testing.assert_allclose(np.asarray(accel), ref_accel, rtol=2e-4, atol=2e-5)
        np.testing.assert_allclose(float(de[0]), ref_de, rtol=2e-4, atol=2e-5)
        checked_edges += int(g.n_edge[0])
    assert checked_edges > 10


def _with_random_biases(params, seed):
    """``params`` with N(0, 0.1) biases (init gives zeros), so every bias path is exercised
    (drawn in numpy: no eager op compiles)."""
    rng = np.random.default_rng(seed)
    leaves, tree = jax.tree_util.tree_flatten_with_path(params)
    return jax.tree_util.tree_unflatten(tree, [
        (0.1 * rng.standard_normal(leaf.shape)).astype(leaf.dtype)
        if "bias" in jax.tree_util.keystr(path) else leaf
        for path, leaf in leaves])


def _random_graph(graph, seed, n_real):
    """``graph`` with random node and edge features, random senders and receivers (balls and
    the wall node) and ``n_real`` real edges of both kinds: a graph that no layout assumption
    of the model can be exact on by accident."""
    rng = np.random.default_rng(seed)
    e_cap, n_rows = graph.senders.shape[0], graph.nodes["features"].shape[0]
    ids = np.arange(e_cap)
    return graph._replace(
        nodes=dict(graph.nodes, features=jnp.asarray(
            rng.normal(size=graph.nodes["features"].shape), jnp.float32)),
        edges=dict(graph.edges, features=jnp.asarray(rng.normal(size=(e_cap, 3)), jnp.float32),
                   pp=jnp.asarray(ids < n_real // 2), pw=jnp.asarray((ids >= n_real // 2)
                                                                    & (ids < n_real))),
        senders=jnp.asarray(rng.integers(0, n_rows - 1, e_cap), jnp.int32),
        receivers=jnp.asarray(rng.integers(0, n_rows - 1, e_cap), jnp.int32))


@pytest.mark.parametrize("fuse", [True, False])
def test_restructured_forward_equals_the_straightforward_one(setup, fuse):
    """The split, fused and post-mean layers of the model vs the concatenation, edge by edge,
    in float64 (hidden 64, two interaction layers, non-zero biases), on built graphs and on
    random graphs, with the encoder's output layer fused and not (same function)."""
    graphs, stats, _, _ = setup
    model = SGN(hidden=64, mlp_layers=4, interaction_layers=2, fuse_edge_output=fuse)
    params = _with_random_biases(random_init_weights(model, normalize(graphs[0], stats), 5), 6)
    apply = jax.jit(model.apply)
    cases = [normalize(graphs[k], stats) for k in (1, 5)]
    cases += [_random_graph(cases[0], seed, n) for seed, n in ((1, 20), (2, 31))]
    for g in cases:
        accel, de = apply({"params": params}, g)
        ref_accel, ref_de = _reference_forward(params, g)
        assert np.linalg.norm(ref_accel) > 1e-2
        rel = np.linalg.norm(np.asarray(accel, np.float64) - ref_accel) / np.linalg.norm(ref_accel)
        assert rel < 1e-5, rel
        assert abs(float(de[0]) - ref_de) < 1e-5 * max(abs(ref_de), 1.0), (float(de[0]), ref_de)


def test_checkpoint_from_before_the_restructuring_predicts_the_same():
    """tests/data/sgn_checkpoint_v1 was saved, with its predictions, by the model code of
    commit 66433cc (straightforward edge encoder and message MLP; made by
    tests/data/make_sgn_checkpoint_v1.py). It restores into today's model and predicts the same
    up to float32 rounding."""
    import json
    from pathlib import Path

    from sgn_jax.records.checkpoint import restore_checkpoint
    from sgn_jax.testing import synthetic_trajectory as trajectory

    directory = Path(__file__).parent / "data" / "sgn_checkpoint_v1"
    expected = json.loads((directory / "expected_predictions.json").read_text())
    restored = restore_checkpoint(directory)
    model = SGN(**expected["model"])
    spec = GraphSpec(n_particles=6, window=3, ball_radius=0.005, dt=1e-4, pp_pair_capacity=8)

    def sphere(_, points, offset):
        d = jnp.asarray(points) - jnp.asarray(offset) - jnp.array([0.0, 0.02, 0.0])
        r = jnp.linalg.norm(d, axis=-1)
        return r - 0.03, d / r[..., None]

    wins, _, _ = windows_from_trajectory(trajectory(20, 6, seed=2), 3)
    predict = jax.jit(make_predict(model))
    build = jax.jit(lambda win: build_graph(win, None, spec, sphere)[0])
    for case in expected["predictions"]:
        win = jax.tree_util.tree_map(lambda a, k=case["window"]: a[k], wins)
        graph = build(win)
        assert int(graph.n_edge[0]) == case["n_edge"] > 0
        accel, de = predict(restored.params, restored.norm_stats, graph)
        want = np.asarray(case["accel"])
        rel = np.linalg.norm(np.asarray(accel, np.float64) - want) / np.linalg.norm(want)
        assert rel < 1e-5, rel
        np.testing.assert_allclose(np.asarray(de, np.float64), case["dE"], rtol=1e-5)


def test_mlps_have_four_layers_of_the_hidden_width():
    model = SGN(hidden=256)
    spec = GraphSpec(n_particles=24, window=7, ball_radius=0.005, dt=1e-4, pp_pair_capacity=4)
    graph = jax.eval_shape(lambda: _empty_graph(spec))
    params = jax.eval_shape(lambda g: init_params(model, g, 0), graph)
    enc = params["particle_encoder"]
    assert [enc[f"dense_{i}"]["kernel"].shape for i in range(4)] == [(49, 256), (256, 256),
                                                                   (256, 256), (256, 256)]
    assert params["decoder"]["dense_3"]["kernel"].shape == (256, 3)
    assert params["global_readout"]["dense_3"]["kernel"].shape == (256, 1)
    assert params["interaction_0"]["node_update"]["dense_0"]["kernel"].shape == (512, 256)
    assert all(leaf.dtype == jnp.float32 for leaf in jax.tree_util.tree_leaves(params))
    assert 1.5e6 < count_params(params) < 2.0e6


def _empty_graph(spec):
    far = np.array([[-0.02 + 0.012 * (k % 4), 0.015 + 0.012 * (k // 4), 0.0]
                    for k in range(spec.n_particles)])
    win = Window(positions=np.repeat(far[None], spec.window + 1, 0),
                 offsets=np.zeros((spec.window, 3)), offset_velocities=np.zeros((spec.window, 3)),
                 frequency_hz=np.array(5.0))
    # jitted: one program instead of ~80 eager compiles
    return jax.jit(lambda win: build_graph(win, None, spec, lambda _, p, o: (
        jnp.full(p.shape[:-1], -0.02), jnp.zeros(p.shape) + 1 / 3**0.5))[0])(win)


def test_permutation_equivariance(setup, windows, builder):
    graphs, stats, model, params = setup
    predict = jax.jit(make_predict(model))
    perm = np.random.default_rng(3).permutation(N)
    for k in (4, 17):
        win = jax.tree_util.tree_map(lambda a, k=k: a[k], windows)
        permuted = win.replace(positions=win.positions[:, perm])
        g1, c1 = builder(win)
        g2, c2 = builder(permuted)
        assert int(c1.n_pp) == int(c2.n_pp) and int(c1.n_pw) == int(c2.n_pw)
        assert int(c1.n_pp) + int(c1.n_pw) > 0
        a1, e1 = predict(params, stats, g1)
        a2, e2 = predict(params, stats, g2)
        np.testing.assert_allclose(np.asarray(a2[:N]), np.asarray(a1[:N])[perm], rtol=1e-4,
                                   atol=1e-4)
        np.testing.assert_allclose(float(e2[0]), float(e1[0]), rtol=1e-5, atol=1e-12)


@pytest.mark.slow
def test_padding_and_batching_do_not_change_real_outputs(setup):
    graphs, stats, model, params = setup
    apply = jax.jit(model.apply)
    g1, g2 = normalize(graphs[1], stats), normalize(graphs[5], stats)
    a1, e1 = apply({"params": params}, g1)
    a2, e2 = apply({"params": params}, g2)
    # Extra padding: 13 more nodes, 40 more edges, 3 more (empty) graphs, with garbage
    # features on the padding rows (masks are False there).
    n_node = int(np.sum(g1.n_node)) + 13
    n_edge = int(np.sum(g1.n_edge)) + 40
    padded = jraph.pad_with_graphs(jax.device_get(g1), n_node, n_edge, n_graph=5)
    feats = np.array(padded.nodes["features"])
    feats[g1.nodes["features"].shape[0]:] = 7.0
    padded = padded._replace(nodes={**padded.nodes, "features": feats})
    ap, ep = apply({"params": params}, padded)
    np.testing.assert_allclose(np.asarray(ap[:N]), np.asarray(a1[:N]), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(float(ep[0]), float(e1[0]), rtol=1e-5, atol=1e-7)
    assert np.all(np.asarray(ap[N:]) == 0)

    both = jraph.batch([jax.device_get(g1), jax.device_get(g2)])
    ab, eb = apply({"params": params}, both)
    off = g1.nodes["features"].shape[0]
    np.testing.assert_allclose(np.asarray(ab[:N]), np.asarray(a1[:N]), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(np.asarray(ab[off:off + N]), np.asarray(a2[:N]), rtol=1e-5,
                               atol=1e-6)
    np.testing.assert_allclose(np.asarray(eb)[[0, 2]], [float(e1[0]), float(e2[0])], rtol=1e-5)


def test_global_readout_gets_a_zero_vector_when_no_ball_has_an_edge(setup):
    _, stats, model, params = setup
    spec = GraphSpec(n_particles=N, window=W, ball_radius=0.005, dt=1e-4, pp_pair_capacity=4)
    graph = _empty_graph(spec)
    assert int(graph.n_edge[0]) == 0
    apply = jax.jit(model.apply)
    _, de = apply({"params": params}, normalize(graph, stats))
    # MLP of the zero vector, whatever the node features are.
    zero = model.hidden * [0.0]
    expected = _np_mlp(params["global_readout"], np.array(zero))[0]
    np.testing.assert_allclose(float(de[0]), expected, rtol=1e-5, atol=1e-7)
    shifted = graph._replace(nodes={**graph.nodes,
                                    "features": graph.nodes["features"] + 0.37})
    _, de2 = apply({"params": params}, normalize(shifted, stats))
    assert float(de2[0]) == float(de[0])
    # ... while a graph with edges reads its balls out.
    _, de3 = apply({"params": params}, normalize(setup[0][2], stats))
    assert float(de3[0]) != pytest.approx(expected, rel=1e-3)


# --------------------------------------------------------------------------------------------
# Normalisation


def test_normalisation_round_trip_and_constant_columns(setup):
    graphs, stats, _, _ = setup
    rng = np.random.default_rng(5)
    accel = rng.normal(3.0, 40.0, (50, 3)).astype(np.float32)
    de = rng.uniform(0, 2e-5, 50).astype(np.float32)
    np.testing.assert_allclose(np.asarray(denormalize_accel(normalize_accel(accel, stats),
                                                            stats)), accel, rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(np.asarray(denormalize_dissipation(
        normalize_dissipation(de, stats), stats)), de, rtol=1e-4, atol=1e-10)

    # The training rows come out standardised, by row type.
    norm = [normalize_graph(g, stats) for g in graphs]
    part = np.concatenate([np.asarray(g.nodes["features"])[np.asarray(g.nodes["particle"])]
                           for g in norm])
    varying = np.asarray(stats.particle.std) != 1.0
    np.testing.assert_allclose(part.mean(0)[varying], 0, atol=1e-4)
    np.testing.assert_allclose(part.std(0)[varying], 1, rtol=1e-3)
    # Constant wall columns (frequency, y offset, y velocity) are not amplified: std 1, value 0.
    wall = np.concatenate([np.asarray(g.nodes["features"])[np.asarray(g.nodes["wall"])]
                           for g in norm])
    freq_cols = np.arange(6, 7 * W, 7)
    assert np.all(np.asarray(stats.wall.std)[freq_cols] == 1.0)
    np.testing.assert_array_equal(wall[:, freq_cols], 0.0)
    np.testing.assert_array_equal(wall[:, np.arange(1, 7 * W, 7)], 0.0)  # offset y
    # Padding rows are exactly zero.
    pad = np.asarray(norm[0].nodes["features"])[N + 1]
    assert np.all(pad == 0)
    real = np.asarray(norm[0].edges["pp"] | norm[0].edges["pw"])
    assert np.all(np.asarray(norm[0].edges["features"])[~real] == 0)

    # Stats survive a plain-array round trip exactly; a broken std is refused.
    again = stats_from_arrays(stats_to_arrays(stats))
    for a, b in zip(jax.tree_util.tree_leaves(again), jax.tree_util.tree_leaves(stats),
                    strict=True):
        np.testing.assert_array_equal(a, b)
    bad = stats_to_arrays(stats)
    bad["pp_edge"]["std"][0] = 0.0
    with pytest.raises(ValueError, match="pp_edge"):
        stats_from_arrays(bad)


def test_velocity_difference_encoding():
    from sgn_jax.surrogate.normalization import encode_velocities

    rng = np.random.default_rng(2)
    x = rng.normal(size=(5, 7 * W))
    enc = encode_velocities(x, "differences")
    v = x.reshape(5, W, 7)[..., :3]
    e = enc.reshape(5, W, 7)
    np.testing.assert_allclose(e[:, :-1, :3], v[:, :-1] - v[:, 1:])
    np.testing.assert_array_equal(e[:, -1, :3], v[:, -1])
    np.testing.assert_array_equal(e[..., 3:], x.reshape(5, W, 7)[..., 3:])
    # Invertible: the velocities are the cumulative sums from the newest slot backwards.
    back = np.cumsum(e[:, ::-1, :3], axis=1)[:, ::-1]
    np.testing.assert_allclose(back, v, atol=1e-12)
    np.testing.assert_allclose(np.asarray(encode_velocities(jnp.asarray(x), "differences")), enc,
                               atol=1e-12)
    assert encode_velocities(x, "absolute") is x
    with pytest.raises(ValueError, match="velocity encoding"):
        encode_velocities(x, "relative")


def test_nearly_constant_column_is_not_amplified():
    from sgn_jax.surrogate.normalization import moments

    rows = np.stack([np.full(100, 5.0) + 1e-12 * np.arange(100), np.linspace(-1, 1, 100)], 1)
    m = moments(rows)
    assert m.std[0] == 1.0 and m.std[1] == pytest.approx(np.linspace(-1, 1, 100).std())
    empty = moments(np.zeros((0, 3)), 3)
    assert np.all(empty.mean == 0) and np.all(empty.std == 1)
