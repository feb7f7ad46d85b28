"""The SDF graph network (SGN, paper section 2.2.1) as a ``flax.linen`` module.

Encoder-processor-decoder on the padded graphs of :mod:`sgn_jax.surrogate.graph` (normalised
features):

- Encoders (4-layer ReLU MLPs, width ``hidden``): ``particle_encoder`` for ball nodes and
  ``wall_encoder`` for the wall node (different quantities in the same columns, so separate
  MLPs, as the paper allows); one ``edge_encoder`` shared by ball-ball and ball-wall edges whose
  input is the normalised 3-vector plus a one-hot edge type [is_pp, is_pw], so the encoder can
  tell the two separately normalised kinds apart at the cost of one MLP per edge, not two.
- ``interaction_layers`` interaction layers: message ``psi_e([h_r, h_s, h_e])`` on each real edge
  (sender s -> receiver r), mean over the incoming real edges of each node (count clamped at 1,
  so a node without edges gets a zero message), update ``h_r <- psi_v([h_r, m_r])`` (replaces h,
  no residual, as in the paper). Edge embeddings are not updated.
- Decoder ``MLP_d`` -> 3 normalised acceleration components per ball (zero on other rows).
- Global readout: mean of the final embeddings of the balls with at least one incident real
  edge in their graph (a zero vector if there is none), then an MLP -> normalised dE per graph.

Exact restructurings for speed (the same function and parameters as the straightforward
network, up to float32 rounding; ``tests/test_model.py`` checks both against a reference):

1. The first layer of ``psi_e`` is split into receiver, sender and edge blocks; the node blocks
   run once per node and are gathered per edge instead of a 3*hidden-wide matmul per edge.
2. The edge encoder's output layer is linear and feeds only the edge block of each message
   layer, so the two are one linear map: ``(z W4 + b4) Wc = z (W4 Wc) + b4 Wc``. The product
   ``W4 Wc`` costs as much as ``hidden`` edge rows per call, so by default it is used when the
   graph has more edge slots than ``interaction_layers * hidden`` (training batches). In a
   rollout without capacity tiers XLA hoists the product out of the ``lax.scan`` (the
   parameters are loop constants), so fusing always pays there (``fuse_edge_output=True``);
   inside the ``lax.switch`` of capacity tiers it is not hoisted and is paid every step.
3. The message MLP's output layer is linear and the aggregation is a mean, so the layer runs
   after the mean, once per node: ``mean_e(z_e W + b) = mean_e(z_e) W + b [count > 0]``.

Per edge slot this leaves the edge encoder's first three layers and two hidden x hidden
message layers (plus the edge block), against seven hidden x hidden matmuls before.

Padding is handled with the boolean masks of the graph (jraph's ``zero_out_padding`` is broken
on current JAX): padding edges carry no message, padding nodes are never read by a real node.
All computation is in ``float32`` (parameters and activations).

The kind "sgn" of the model registry (:mod:`sgn_jax.surrogate.model`, the default
``[model] kind``): :func:`make_sgn` builds it from a ``[model]`` section and is registered
at the end of this module.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp
import jraph

from sgn_jax.surrogate.model import (
    DEFAULT_MODEL_KIND,
    DTYPE,
    MLP,
    ModelKindError,
    masked_mean_by_segment,
    node_graph_index,
    register_model,
)


class DenseParams(nn.Module):
    """The parameters of an ``nn.Dense(features)`` on ``in_features`` inputs, not applied.

    Same names, shapes, dtypes and initialisers (LeCun-normal kernel, zero bias) as
    ``nn.Dense``, created in the same order, so the parameter tree and its initial values are
    those of the dense layer it stands for; used where a layer is fused with another one.
    Returns ``(kernel (in_features, features), bias (features,) or None)``.
    """

    features: int
    use_bias: bool = True

    @nn.compact
    def __call__(self, in_features: int) -> tuple[jax.Array, jax.Array | None]:
        kernel = self.param("kernel", nn.initializers.lecun_normal(),
                            (in_features, self.features), DTYPE)
        bias = (self.param("bias", nn.initializers.zeros_init(), (self.features,), DTYPE)
                if self.use_bias else None)
        return kernel, bias


class EdgeEmbedding(NamedTuple):
    """The edge encoder's output ``h_e = hidden @ kernel + bias``, kept factored.

    ``hidden`` (E, H) is the last ReLU activation of the encoder, ``kernel`` (H, H) and ``bias``
    (H,) its linear output layer; ``h_edge`` (E, H) is the product, or None when every
    interaction layer fuses the output layer into its message layer instead.
    """

    hidden: jax.Array
    kernel: jax.Array
    bias: jax.Array
    h_edge: jax.Array | None


class EdgeEncoder(nn.Module):
    """``MLP`` with its linear output layer returned as parameters (see :class:`EdgeEmbedding`).

    Same parameter tree as ``MLP(hidden, hidden, layers)``.
    """

    hidden: int
    layers: int = 4

    @nn.compact
    def __call__(self, x: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        for i in range(self.layers - 1):
            x = nn.relu(nn.Dense(self.hidden, dtype=DTYPE, param_dtype=DTYPE, name=f"dense_{i}")(x))
        kernel, bias = DenseParams(self.hidden, name=f"dense_{self.layers - 1}")(x.shape[-1])
        return x, kernel, bias


class InteractionLayer(nn.Module):
    """One message-passing layer (paper Eqs. 24-26) with mean aggregation.

    ``psi_e``'s first layer is split into receiver, sender and edge blocks (node blocks once per
    node, gathered per edge); its edge block is fused with the edge encoder's output layer when
    ``edge.h_edge`` is None; its output layer runs after the mean, once per node.
    """

    hidden: int
    layers: int = 4

    @nn.compact
    def __call__(self, h_node: jax.Array, edge: EdgeEmbedding, senders: jax.Array,
                 receivers: jax.Array, edge_mask: jax.Array) -> jax.Array:
        n_node = h_node.shape[0]
        dense = lambda name, bias=True: nn.Dense(  # noqa: E731
            self.hidden, use_bias=bias, dtype=DTYPE, param_dtype=DTYPE, name=name)
        edge_kernel, _ = DenseParams(self.hidden, use_bias=False, name="message_in_edge")(
            edge.kernel.shape[-1])
        at_receiver = dense("message_in_receiver")(h_node)
        if edge.h_edge is None:
            # (z W4 + b4) Wc = z (W4 Wc) + b4 Wc; the constant goes on the receiver's rows.
            edge_term = edge.hidden @ (edge.kernel @ edge_kernel)
            at_receiver = at_receiver + edge.bias @ edge_kernel
        else:
            edge_term = edge.h_edge @ edge_kernel
        z = nn.relu(at_receiver[receivers]
                    + dense("message_in_sender", bias=False)(h_node)[senders] + edge_term)
        for i in range(1, self.layers - 1):
            z = nn.relu(dense(f"message_{i}")(z))
        # The output layer is linear and the mean is linear: apply it to the mean (once per
        # node); a node without incoming edges gets a zero message, not the bias.
        mean_z, count = masked_mean_by_segment(z, edge_mask, receivers, n_node)
        aggregated = jnp.where((count > 0)[:, None],
                               dense(f"message_{self.layers - 1}")(mean_z), 0.0)
        return MLP(self.hidden, self.hidden, self.layers, name="node_update")(
            jnp.concatenate([h_node, aggregated], axis=-1))


class SGN(nn.Module):
    """The SGN. ``__call__(graph) -> (accel_norm (n_node, 3), dE_norm (n_graph,))``.

    ``graph`` is a normalised graph (:func:`sgn_jax.surrogate.normalization.normalize_graph`) with
    the layout of :mod:`sgn_jax.surrogate.graph`, possibly batched with ``jraph.batch`` and padded.
    """

    hidden: int = 256
    mlp_layers: int = 4
    interaction_layers: int = 1
    # Fuse the edge encoder's output layer into the message layers (see the module docstring):
    # None chooses by FLOPs from the static edge count; True/False force it (same function).
    fuse_edge_output: bool | None = None

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
        z_edge, out_kernel, out_bias = EdgeEncoder(self.hidden, self.mlp_layers,
                                                   name="edge_encoder")(e_in)
        # Fusing the encoder's output layer into the L message layers costs L kernel products
        # (L H^3) and saves one H x H matmul per edge slot (E H^2): worth it when E > L H.
        fuse = (self.fuse_edge_output if self.fuse_edge_output is not None
                else e_in.shape[0] > self.interaction_layers * self.hidden)
        h_edge = None if fuse else z_edge @ out_kernel + out_bias
        edge = EdgeEmbedding(z_edge, out_kernel, out_bias, h_edge)

        for layer in range(self.interaction_layers):
            h = InteractionLayer(self.hidden, self.mlp_layers, name=f"interaction_{layer}")(
                h, edge, graph.senders, graph.receivers, edge_mask)

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


def make_sgn(model_cfg: Any) -> SGN:
    """An :class:`SGN` from a ``[model]`` config section (the factory of kind "sgn")."""
    if getattr(model_cfg, "spin", False):
        raise ModelKindError("[model] spin = true: the SGN has no spin state; spin is for kind "
                             "'contact' (set [model] kind = \"contact\" or spin = false)")
    if getattr(model_cfg, "overlap_limit", 0.0) or getattr(model_cfg, "overlap_law_factor", 0.0):
        raise ModelKindError(f"[model] overlap_limit = {model_cfg.overlap_limit}: the SGN has no "
                             "contact law to limit; it is for kind 'contact' (set [model] kind = "
                             "\"contact\" or overlap_limit = 0)")
    return SGN(hidden=model_cfg.hidden, mlp_layers=model_cfg.mlp_layers,
               interaction_layers=model_cfg.interaction_layers)


register_model(DEFAULT_MODEL_KIND, make_sgn,
               description="the SDF graph network of the paper (section 2.2.1)")
