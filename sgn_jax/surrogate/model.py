"""The surrogate's model registry, the contract every model kind honours, and what the kinds share.

A model kind is a ``flax.linen`` module with one contract: ``module.apply({"params": p}, graph)``
on a normalised, possibly batched and padded graph of :mod:`sgn_jax.surrogate.graph` returns
``(accel_norm (n_node, 3), dE_norm (n_graph,))`` in float32. Everything downstream (the loss, the
jitted steps, :func:`make_predict`, :func:`sgn_jax.surrogate.rollout.model_predictor`, the
checkpoints) uses only that contract.

``[model] kind`` names a registered :class:`ModelFactory`; :func:`make_model` builds the module of
a config section through it, so training and checkpoint loading work for any registered kind.
Each kind is one file beside this one that registers itself at import
(:func:`register_model`): :mod:`sgn_jax.surrogate.sgn`, the paper's SGN, is the default kind
"sgn". Importing :mod:`sgn_jax.surrogate` (which any import of a surrogate module does) imports
the built-in kinds; docs/sgn.md, "Adding a surrogate model".

Shared by the kinds: :class:`MLP`, :func:`masked_mean_by_segment`, :func:`node_graph_index`
(building blocks, float32), :func:`init_params`, :func:`make_apply`, :func:`make_predict`
(normalise, apply, de-normalise) and :func:`count_params`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import jraph

from sgn_jax.errors import SGNJaxError
from sgn_jax.surrogate.normalization import (
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


def node_graph_index(graph: jraph.GraphsTuple) -> jax.Array:
    """(n_node_total,) index of the graph each node belongs to (static total length)."""
    n_total = graph.nodes["features"].shape[0]
    n_graph = graph.n_node.shape[0]
    return jnp.repeat(jnp.arange(n_graph), graph.n_node, total_repeat_length=n_total)


def make_model(model_cfg: Any) -> nn.Module:
    """The flax module of a ``[model]`` config section (:class:`sgn_jax.config.ModelConfig`),
    built by the factory registered for its ``kind`` (default "sgn": an
    :class:`sgn_jax.surrogate.sgn.SGN`)."""
    return model_factory(model_kind(model_cfg)).build(model_cfg)


def init_params(model: nn.Module, example_graph: jraph.GraphsTuple,
                seed: int | jax.Array = 0) -> Any:
    """Initial parameters (flax default init: LeCun-normal kernels, zero biases)."""
    key = jax.random.PRNGKey(seed) if isinstance(seed, int) else seed
    return model.init(key, example_graph)["params"]


def make_apply(model: nn.Module) -> Callable[[Any, jraph.GraphsTuple], tuple[jax.Array, jax.Array]]:
    """Pure ``apply(params, normalised_graph) -> (accel_norm, dE_norm)``."""

    def apply(params: Any, graph: jraph.GraphsTuple) -> tuple[jax.Array, jax.Array]:
        return model.apply({"params": params}, graph)

    return apply


def make_predict(model: nn.Module) -> Callable[[Any, NormStats, jraph.GraphsTuple],
                                         tuple[jax.Array, jax.Array]]:
    """Pure ``predict(params, stats, raw_graph) -> (accel (n_node, 3) m/s^2, dE (n_graph,) J)``.

    Normalises the raw graph of :func:`sgn_jax.surrogate.graph.build_graph`, applies the network and
    de-normalises (float32). Rows other than balls are zero in ``accel``; for a single window
    ``accel[:N]`` are the balls and ``dE[0]`` is the step's dissipation. Jittable, and
    differentiable in the parameters and the raw features.
    """

    if getattr(model, "takes_raw_graph", False):
        # A physics-scaled kind (e.g. the contact model) reads the raw graph and returns
        # physical units itself; the statistics are not used.
        def predict_raw(params: Any, stats: NormStats, graph: jraph.GraphsTuple):
            del stats
            return model.apply({"params": params}, graph)

        return predict_raw

    def predict(params: Any, stats: NormStats, graph: jraph.GraphsTuple):
        accel_n, de_n = model.apply({"params": params}, normalize_graph(graph, stats, DTYPE))
        accel = jnp.where(graph.nodes["particle"][:, None], denormalize_accel(accel_n, stats), 0.0)
        return accel, denormalize_dissipation(de_n, stats)

    return predict


def count_params(params: Any) -> int:
    return int(sum(p.size for p in jax.tree_util.tree_leaves(params)))


# --------------------------------------------------------------------------------------------
# The model registry: [model] kind -> how to build, initialise, apply and predict


DEFAULT_MODEL_KIND = "sgn"


class ModelKindError(SGNJaxError, ValueError):
    """A ``[model] kind`` names no registered model, or a kind is registered twice."""


@dataclasses.dataclass(frozen=True)
class ModelFactory:
    """How training, checkpoints and rollouts make and use one kind of surrogate.

    The contract of a surrogate module: ``module.apply({"params": p}, graph)`` on a normalised,
    possibly batched and padded graph of :mod:`sgn_jax.surrogate.graph` returns ``(accel_norm
    (n_node, 3), dE_norm (n_graph,))``, float32, like :class:`sgn_jax.surrogate.sgn.SGN`. Everything
    downstream (the loss, the jitted steps, :func:`make_predict`,
    :func:`sgn_jax.surrogate.rollout.model_predictor`) only uses that contract, so a new kind needs
    nothing but ``build``.

    Attributes:
        kind: the name in ``[model] kind``.
        build: ``build(model_cfg) -> flax module`` from the ``[model]`` section (its ``hidden``,
            ``mlp_layers``, ``interaction_layers``; the section's ``velocity_encoding`` is used
            by the featurizer, not the module).
        init: ``init(module, example_graph, seed) -> params`` (default :func:`init_params`:
            flax's own initialisation).
        description: one line for listings and error messages.
        builds_from: "model" (``build(cfg.model)``) or "config" (``build(cfg)``).
        node_walls: whether the kind reads the nearest-wall phi and normal of the node
            features (``GraphSpec.node_walls``); a kind that does not saves W SDF queries per
            graph (the contact kind: its walls are its ball-wall edges).
        takes_charge: whether the kind reads each ball's radius, mass and material from the
            window's charge (``Window.charge``), so that it runs any charge: sizes, counts,
            materials and mixtures (the charge-conditioned contact kind). Every other kind
            knows the one charge it was trained on.
    """

    kind: str
    build: Callable[[Any], nn.Module]
    init: Callable[[nn.Module, jraph.GraphsTuple, Any], Any] = init_params
    description: str = ""
    builds_from: str = "model"
    node_walls: bool = True
    takes_charge: bool = False

    def build_model(self, cfg: Any) -> nn.Module:
        """The module of a whole experiment config: ``build(cfg.model)``, or ``build(cfg)``
        for a kind registered with ``builds_from="config"`` (one that needs the balls, the
        step or gravity, e.g. the contact-impulse model)."""
        return self.build(cfg if self.builds_from == "config" else cfg.model)

    def init_params(self, model: nn.Module, example_graph: jraph.GraphsTuple,
                    seed: int | jax.Array = 0) -> Any:
        return self.init(model, example_graph, seed)

    def make_apply(self, model: nn.Module) -> Callable:
        """Pure ``apply(params, normalised_graph) -> (accel_norm, dE_norm)``."""
        return make_apply(model)

    def make_predict(self, model: nn.Module) -> Callable:
        """Pure ``predict(params, stats, raw_graph) -> (accel m/s^2, dE J)``."""
        return make_predict(model)


_REGISTRY: dict[str, ModelFactory] = {}


def register_model(kind: str, build: Callable[[Any], nn.Module], *,
                   init: Callable[[nn.Module, jraph.GraphsTuple, Any], Any] | None = None,
                   description: str = "", replace: bool = False,
                   builds_from: str = "model", node_walls: bool = True,
                   takes_charge: bool = False) -> ModelFactory:
    """Register a surrogate kind: ``[model] kind = "<kind>"`` then builds it with ``build``.

    ``build(model_cfg)`` returns a flax module honouring the contract of :class:`ModelFactory`.
    Registering a kind that exists is an error unless ``replace=True``. Registration is per
    process: a checkpoint of a kind defined outside sgn-jax loads only after the module that
    registers it has been imported. ``node_walls=False``: the kind never reads the node
    features' wall columns, so its graphs skip them (:class:`ModelFactory`).
    ``takes_charge=True``: the kind reads the window's charge and runs any charge
    (:class:`ModelFactory`). Returns the factory.
    """
    if not isinstance(kind, str) or not kind:
        raise ModelKindError(f"a model kind must be a non-empty string, got {kind!r}")
    if kind in _REGISTRY and not replace:
        raise ModelKindError(f"model kind {kind!r} is already registered "
                             "(pass replace=True to override it)")
    if builds_from not in ("model", "config"):
        raise ModelKindError(f"builds_from must be 'model' or 'config', got {builds_from!r}")
    factory = ModelFactory(kind=kind, build=build, init=init or init_params,
                           description=description, builds_from=builds_from,
                           node_walls=bool(node_walls), takes_charge=bool(takes_charge))
    _REGISTRY[kind] = factory
    return factory


def unregister_model(kind: str) -> None:
    """Remove a registered kind (tests; "sgn" cannot be removed)."""
    if kind == DEFAULT_MODEL_KIND:
        raise ModelKindError(f"the built-in model kind {kind!r} cannot be unregistered")
    _REGISTRY.pop(kind, None)


def registered_models() -> tuple[str, ...]:
    """The registered kinds, sorted."""
    return tuple(sorted(_REGISTRY))


def model_factory(kind: str) -> ModelFactory:
    """The factory of a registered kind; :class:`ModelKindError` listing the kinds if none."""
    try:
        return _REGISTRY[kind]
    except KeyError:
        raise ModelKindError(
            f"unknown model kind {kind!r}; registered kinds: {', '.join(registered_models())} "
            "(register a new one with sgn_jax.surrogate.model.register_model)") from None


def model_kind(model_cfg: Any) -> str:
    """The ``kind`` of a ``[model]`` section; "sgn" for objects without one."""
    return getattr(model_cfg, "kind", DEFAULT_MODEL_KIND)
