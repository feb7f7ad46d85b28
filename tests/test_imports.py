"""Smoke test of the jraph API the SGN relies on (jraph 0.0.6.dev0 on current JAX)."""

import jax
import jax.numpy as jnp
import jraph
import numpy as np

import sgn_jax  # noqa: F401


def _graph(n_node: int, n_edge: int, seed: int) -> jraph.GraphsTuple:
    rng = np.random.default_rng(seed)
    return jraph.GraphsTuple(
        nodes=rng.standard_normal((n_node, 4)).astype(np.float32),
        edges=rng.standard_normal((n_edge, 2)).astype(np.float32),
        senders=rng.integers(0, n_node, n_edge).astype(np.int32),
        receivers=rng.integers(0, n_node, n_edge).astype(np.int32),
        n_node=np.array([n_node], np.int32), n_edge=np.array([n_edge], np.int32),
        globals=np.zeros((1, 1), np.float32))


def test_batch_pad_segment_mean_and_graph_network_under_jit():
    g1, g2 = _graph(3, 4, 0), _graph(5, 2, 1)
    batched = jraph.batch([g1, g2])
    assert batched.nodes.shape == (8, 4)
    # Receivers of the second graph are offset by the first graph's node count.
    np.testing.assert_array_equal(batched.receivers[4:], g2.receivers + 3)

    padded = jraph.pad_with_graphs(batched, n_node=11, n_edge=9, n_graph=4)
    assert padded.nodes.shape == (11, 4) and padded.edges.shape == (9, 2)
    assert padded.n_node.tolist() == [3, 5, 3, 0] and padded.n_edge.tolist() == [4, 2, 3, 0]
    mask = np.asarray(jraph.get_node_padding_mask(padded))
    assert mask.tolist() == [True] * 8 + [False] * 3

    @jax.jit
    def mean_by_receiver(g):
        return jraph.segment_mean(g.edges, g.receivers, num_segments=g.nodes.shape[0])

    out = np.asarray(mean_by_receiver(padded))
    r = np.asarray(padded.receivers)
    for node in range(11):
        rows = np.asarray(padded.edges)[r == node]
        expected = rows.mean(axis=0) if len(rows) else np.zeros(2)
        np.testing.assert_allclose(out[node], expected, rtol=1e-6, atol=1e-7)

    net = jraph.GraphNetwork(
        update_edge_fn=lambda e, s, r, g: jnp.concatenate([e, s[:, :1] - r[:, :1]], -1),
        update_node_fn=lambda n, sent, recv, g: n + recv[:, :1],
        update_global_fn=lambda n, e, g: g + jnp.sum(n, axis=-1, keepdims=True),
        aggregate_edges_for_nodes_fn=jraph.segment_sum)
    result = jax.jit(net)(padded)
    assert result.edges.shape == (9, 3)
    assert result.nodes.shape == (11, 4)
    assert result.globals.shape == (4, 1)
    assert np.all(np.isfinite(np.asarray(result.nodes)))
    # Gradients flow through the GraphNetwork (jitted: one program instead of ~50 eager op
    # compiles).
    grad = jax.jit(jax.grad(lambda nodes: jnp.sum(net(padded._replace(nodes=nodes)).globals)))(
        jnp.asarray(padded.nodes))
    assert grad.shape == (11, 4) and np.all(np.isfinite(np.asarray(grad)))
