"""The SDF graph network (SGN, paper section 2.2.1) as a ``flax.linen`` module.

Encoder-processor-decoder on the padded graphs of :mod:`sgn_jax.graph` (normalised features):

- Encoders (4-layer ReLU MLPs, width ``hidden``): ``particle_encoder`` for ball nodes and
  ``wall_encoder`` for the wall node (different quantities in the same columns, so separate
  MLPs, as the paper allows); one ``edge_encoder`` shared by ball-ball and ball-wall edges whose
  input is the normalised 3-vector plus a one-hot edge type [is_pp, is_pw], so the encoder can
  tell the two separately normalised kinds apart at the cost of one MLP per edge, not two.
- ``interaction_layers`` interaction layers: message ``psi_e([h_r, h_s, h_e])`` on each real edge
  (sender s -> receiver r), mean over the incoming real edges of each node (count clamped at 1,
  so a node without edges gets a zero message), update ``h_r <- psi_v([h_r, m_r])`` (replaces h,
  no residual, as in the paper). Edge embeddings are not updated. The first linear layer of
  ``psi_e`` is split into receiver, sender and edge blocks, the node blocks applied once per
  node and gathered: the same function as a dense layer on the concatenation, fewer FLOPs.
- Decoder ``MLP_d`` -> 3 normalised acceleration components per ball (zero on other rows).
- Global readout: mean of the final embeddings of the balls with at least one incident real
  edge in their graph (a zero vector if there is none), then an MLP -> normalised dE per graph.

Padding is handled with the boolean masks of the graph (jraph's ``zero_out_padding`` is broken
on current JAX): padding edges carry no message, padding nodes are never read by a real node.
All computation is in ``float32`` (parameters and activations).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import jraph

from sgn_jax.normalization import (
    NormStats,
    denormalize_accel,
    denormalize_dissipation,
    normalize_graph,
)

DTYPE = jnp.float32


class MLP(nn.Module):
    """``layers`` dense layers, ReLU between them, linear output of width ``out``."""

    hidden: int
    out: int
    layers: int = 4

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        for i in range(self.layers - 1):
            x = nn.relu(nn.Dense(self.hidden, dtype=DTYPE, param_dtype=DTYPE, name=f"dense_{i}")(x))
        return nn.Dense(self.out, dtype=DTYPE, param_dtype=DTYPE, name=f"dense_{self.layers - 1}")(x)


def masked_mean_by_segment(values: jax.Array, mask: jax.Array, segment_ids: jax.Array,
                           num_segments: int) -> tuple[jax.Array, jax.Array]:
    """Mean of ``values`` (E, D) rows with ``mask`` (E,) per segment; empty segments give 0.

    Returns ``(mean (num_segments, D), count (num_segments,))``.
    """
    w = mask.astype(values.dtype)
    total = jax.ops.segment_sum(values * w[:, None], segment_ids, num_segments=num_segments)
    count = jax.ops.segment_sum(w, segment_ids, num_segments=num_segments)
    return total / jnp.maximum(count, 1.0)[:, None], count


class InteractionLayer(nn.Module):
    """One message-passing layer (paper Eqs. 24-26) with mean aggregation."""

    hidden: int
    layers: int = 4

    @nn.compact
    def __call__(self, h_node: jax.Array, h_edge: jax.Array, senders: jax.Array,
                 receivers: jax.Array, edge_mask: jax.Array) -> jax.Array:
        n_node = h_node.shape[0]
        dense = lambda name, bias=True: nn.Dense(  # noqa: E731
            self.hidden, use_bias=bias, dtype=DTYPE, param_dtype=DTYPE, name=name)
        # First layer of psi_e on [h_receiver, h_sender, h_edge], split by block.
        z = (dense("message_in_receiver")(h_node)[receivers]
             + dense("message_in_sender", bias=False)(h_node)[senders]
             + dense("message_in_edge", bias=False)(h_edge))
        z = nn.relu(z)
        for i in range(1, self.layers - 1):
            z = nn.relu(dense(f"message_{i}")(z))
        messages = dense(f"message_{self.layers - 1}")(z)
        aggregated, _ = masked_mean_by_segment(messages, edge_mask, receivers, n_node)
        return MLP(self.hidden, self.hidden, self.layers, name="node_update")(
            jnp.concatenate([h_node, aggregated], axis=-1))


def node_graph_index(graph: jraph.GraphsTuple) -> jax.Array:
    """(n_node_total,) index of the graph each node belongs to (static total length)."""
    n_total = graph.nodes["features"].shape[0]
    n_graph = graph.n_node.shape[0]
    return jnp.repeat(jnp.arange(n_graph), graph.n_node, total_repeat_length=n_total)


class SGN(nn.Module):
    """The SGN. ``__call__(graph) -> (accel_norm (n_node, 3), dE_norm (n_graph,))``.

    ``graph`` is a normalised graph (:func:`sgn_jax.normalization.normalize_graph`) with the
    layout of :mod:`sgn_jax.graph`, possibly batched with ``jraph.batch`` and padded.
    """

    hidden: int = 256
    mlp_layers: int = 4
    interaction_layers: int = 1

    @nn.compact
    def __call__(self, graph: jraph.GraphsTuple) -> tuple[jax.Array, jax.Array]:
        x = jnp.asarray(graph.nodes["features"], DTYPE)
        is_particle = graph.nodes["particle"]
        is_pp, is_pw = graph.edges["pp"], graph.edges["pw"]
        edge_mask = is_pp | is_pw
        mlp = lambda out, name: MLP(self.hidden, out, self.mlp_layers, name=name)  # noqa: E731

        # The wall encoder runs only on the wall rows: at most one per graph, so a static-size
        # gather of n_graph rows instead of all n_node rows; unused slots point past the end
        # and their results are dropped by the scatter.
        n_graph, n_rows = graph.n_node.shape[0], x.shape[0]
        wall_rows = jnp.nonzero(graph.nodes["wall"], size=n_graph, fill_value=n_rows)[0]
        h = mlp(self.hidden, "particle_encoder")(x)
        h_wall = mlp(self.hidden, "wall_encoder")(jnp.take(x, wall_rows, axis=0, mode="clip"))
        h = h.at[wall_rows].set(h_wall, mode="drop")
        e_in = jnp.concatenate([jnp.asarray(graph.edges["features"], DTYPE),
                                is_pp[:, None].astype(DTYPE), is_pw[:, None].astype(DTYPE)], -1)
        h_edge = mlp(self.hidden, "edge_encoder")(e_in)

        for layer in range(self.interaction_layers):
            h = InteractionLayer(self.hidden, self.mlp_layers, name=f"interaction_{layer}")(
                h, h_edge, graph.senders, graph.receivers, edge_mask)

        accel = mlp(3, "decoder")(h)
        accel = jnp.where(is_particle[:, None], accel, 0.0)

        # Global readout over balls with >= 1 incident real edge (either direction).
        n_node = x.shape[0]
        w = edge_mask.astype(DTYPE)
        degree = (jax.ops.segment_sum(w, graph.receivers, num_segments=n_node)
                  + jax.ops.segment_sum(w, graph.senders, num_segments=n_node))
        active = is_particle & (degree > 0)
        pooled, _ = masked_mean_by_segment(h, active, node_graph_index(graph),
                                           graph.n_node.shape[0])
        de = mlp(1, "global_readout")(pooled)[:, 0]
        return accel, de


def make_model(model_cfg: Any) -> SGN:
    """An :class:`SGN` from a ``[model]`` config section (:class:`sgn_jax.config.ModelConfig`)."""
    return SGN(hidden=model_cfg.hidden, mlp_layers=model_cfg.mlp_layers,
               interaction_layers=model_cfg.interaction_layers)


def init_params(model: SGN, example_graph: jraph.GraphsTuple, seed: int | jax.Array = 0) -> Any:
    """Initial parameters (flax default init: LeCun-normal kernels, zero biases)."""
    key = jax.random.PRNGKey(seed) if isinstance(seed, int) else seed
    return model.init(key, example_graph)["params"]


def make_apply(model: SGN) -> Callable[[Any, jraph.GraphsTuple], tuple[jax.Array, jax.Array]]:
    """Pure ``apply(params, normalised_graph) -> (accel_norm, dE_norm)``."""

    def apply(params: Any, graph: jraph.GraphsTuple) -> tuple[jax.Array, jax.Array]:
        return model.apply({"params": params}, graph)

    return apply


def make_predict(model: SGN) -> Callable[[Any, NormStats, jraph.GraphsTuple],
                                         tuple[jax.Array, jax.Array]]:
    """Pure ``predict(params, stats, raw_graph) -> (accel (n_node, 3) m/s^2, dE (n_graph,) J)``.

    Normalises the raw graph of :func:`sgn_jax.graph.build_graph`, applies the network and
    de-normalises (float32). Rows other than balls are zero in ``accel``; for a single window
    ``accel[:N]`` are the balls and ``dE[0]`` is the step's dissipation. Jittable, and
    differentiable in the parameters and the raw features.
    """

    def predict(params: Any, stats: NormStats, graph: jraph.GraphsTuple):
        accel_n, de_n = model.apply({"params": params}, normalize_graph(graph, stats, DTYPE))
        accel = jnp.where(graph.nodes["particle"][:, None], denormalize_accel(accel_n, stats), 0.0)
        return accel, denormalize_dissipation(de_n, stats)

    return predict


def count_params(params: Any) -> int:
    return int(sum(p.size for p in jax.tree_util.tree_leaves(params)))
