"""Normalisation statistics of the SGN inputs and targets (docs/conventions.md section 5).

Mean and standard deviation per feature column, from the training split only, kept separately
for the ball nodes, the wall node, ball-ball edges, ball-wall edges, the acceleration targets and
the dissipation target. ``x_norm = (x - mean) / std``.

Constant columns: a column whose spread is below ``CONSTANT_RTOL * |mean|`` (or exactly zero)
gets ``std = 1``, so it normalises to (nearly) zero and is never amplified. The wall node's
rotational frequency and the out-of-plane jar axis are such columns for a single circular
motion: they carry no information then, by construction. A group with no rows at all (e.g. no
ball-ball edge in the training data) gets mean 0 and std 1.

Velocity encoding: with ``velocity_encoding = "differences"`` the ball velocity columns are
re-expressed (:func:`encode_velocities`) before the statistics are taken and before every
normalisation; the raw graph features are unchanged.

:class:`NormStats` is a ``flax.struct`` pytree of float64 arrays, saved with every checkpoint.
"""

from __future__ import annotations

from typing import Any

import flax.struct
import jax
import jax.numpy as jnp
import jraph
import numpy as np

from sgn_jax.errors import SGNJaxError

VELOCITY_ENCODINGS = ("absolute", "differences")
"""How the ball velocity columns enter the network (see :func:`encode_velocities`)."""

CONSTANT_RTOL = 1e-6
"""A column with std <= CONSTANT_RTOL * |mean| (or std == 0) counts as constant (std := 1)."""


class NormalizationError(SGNJaxError, ValueError):
    """Statistics cannot be computed or applied (wrong shapes, non-finite data)."""


@flax.struct.dataclass
class Moments:
    """Per-column ``mean`` and ``std`` (both (D,) float64; ``std > 0``)."""

    mean: jax.Array
    std: jax.Array


@flax.struct.dataclass
class NormStats:
    """All normalisation statistics of an SGN (fields are :class:`Moments`).

    ``particle`` and ``wall`` have 7 W columns, ``pp_edge``, ``pw_edge`` and ``accel`` 3,
    ``dissipation`` 1. ``velocity_encoding`` (static) says whether the ``particle`` statistics
    are of the raw columns ("absolute") or of the :func:`encode_velocities` ones.
    """

    particle: Moments
    wall: Moments
    pp_edge: Moments
    pw_edge: Moments
    accel: Moments
    dissipation: Moments
    velocity_encoding: str = flax.struct.field(pytree_node=False, default="absolute")


def encode_velocities(features: Any, encoding: str) -> Any:
    """Re-express the velocity columns of ball features (..., 7W) (numpy or jax).

    "absolute": unchanged (the paper). "differences": slot k < W-1 holds ``v_k - v_{k+1}``
    (minus the acceleration of the next slot times dt), the newest slot keeps ``v_{W-1}``. The
    same information (an invertible linear map), but the acceleration history, which lives in
    differences of nearly equal velocities (0.01 m/s against 0.5 m/s), becomes a column of its
    own after standardisation instead of a 1e-2 fraction of one, and the acceleration loss
    falls faster (docs/sgn.md).
    """
    if encoding == "absolute":
        return features
    if encoding != "differences":
        raise NormalizationError(f"velocity encoding must be one of {VELOCITY_ENCODINGS}, "
                                 f"got {encoding!r}")
    xp = jnp if isinstance(features, jax.Array) else np
    shape = features.shape
    slots = features.reshape(shape[:-1] + (shape[-1] // 7, 7))
    v = slots[..., :3]
    dv = xp.concatenate([v[..., :-1, :] - v[..., 1:, :], v[..., -1:, :]], axis=-2)
    return xp.concatenate([dv, slots[..., 3:]], axis=-1).reshape(shape)


NORM_GROUPS = ("particle", "wall", "pp_edge", "pw_edge", "accel", "dissipation")


def moments(rows: np.ndarray, n_columns: int | None = None, name: str = "features") -> Moments:
    """Column mean and (population) std of ``rows`` (M, D) in float64, constant columns guarded.

    ``n_columns`` is needed when ``rows`` may be empty (then mean 0, std 1).
    """
    rows = np.asarray(rows, np.float64)
    if rows.ndim == 1:
        rows = rows[:, None]
    if rows.ndim != 2:
        raise NormalizationError(f"{name}: expected rows of shape (M, D), got {rows.shape}")
    d = rows.shape[1] if n_columns is None else n_columns
    if rows.shape[1] != d:
        raise NormalizationError(f"{name}: expected {d} columns, got {rows.shape[1]}")
    if rows.shape[0] == 0:
        return Moments(mean=np.zeros(d), std=np.ones(d))
    if not np.all(np.isfinite(rows)):
        raise NormalizationError(f"{name}: non-finite values in the training data")
    mean = rows.mean(axis=0)
    std = rows.std(axis=0)
    constant = (std == 0) | (std <= CONSTANT_RTOL * np.abs(mean))
    std = np.where(constant, 1.0, std)
    return Moments(mean=mean, std=std)


def compute_norm_stats(particle: np.ndarray, wall: np.ndarray, pp_edge: np.ndarray,
                       pw_edge: np.ndarray, accel: np.ndarray, dissipation: np.ndarray,
                       velocity_encoding: str = "absolute") -> NormStats:
    """Statistics from rows of raw training data.

    Args:
        particle: (M_p, 7W) ball-node features; wall: (M_w, 7W) wall-node features.
        pp_edge, pw_edge: (M, 3) or (M, 5) features of real ball-ball / ball-wall edges.
        accel: (M_p, 3) acceleration targets (m/s^2); dissipation: (S,) dE targets (J).
        velocity_encoding: see :func:`encode_velocities`; the ball statistics are of the
            encoded columns.
    """
    f = np.asarray(particle).shape[-1]
    e = np.asarray(pp_edge).shape[-1]  # 3, or 5 with GraphSpec.contact_features
    particle = encode_velocities(np.asarray(particle), velocity_encoding)
    return NormStats(
        velocity_encoding=velocity_encoding,
        particle=moments(particle, f, "particle"),
        wall=moments(wall, f, "wall"),
        pp_edge=moments(np.reshape(pp_edge, (-1, e)), e, "pp_edge"),
        pw_edge=moments(np.reshape(pw_edge, (-1, e)), e, "pw_edge"),
        accel=moments(np.reshape(accel, (-1, 3)), 3, "accel"),
        dissipation=moments(np.reshape(dissipation, (-1, 1)), 1, "dissipation"),
    )


def _norm(x: jax.Array, m: Moments, dtype: Any) -> jax.Array:
    return ((x - jnp.asarray(m.mean, dtype)) / jnp.asarray(m.std, dtype)).astype(dtype)


def _denorm(x: jax.Array, m: Moments, dtype: Any) -> jax.Array:
    return (x * jnp.asarray(m.std, dtype) + jnp.asarray(m.mean, dtype)).astype(dtype)


def normalize_graph(graph: jraph.GraphsTuple, stats: NormStats,
                    dtype: Any = jnp.float32) -> jraph.GraphsTuple:
    """Normalise node and edge features by row type; padding rows become exactly zero."""
    nodes, edges = graph.nodes, graph.edges
    x = jnp.asarray(nodes["features"], dtype)
    part, wall = nodes["particle"][:, None], nodes["wall"][:, None]
    x = jnp.where(part, _norm(encode_velocities(x, stats.velocity_encoding), stats.particle,
                              dtype),
                  jnp.where(wall, _norm(x, stats.wall, dtype), jnp.zeros_like(x)))
    e = jnp.asarray(edges["features"], dtype)
    pp, pw = edges["pp"][:, None], edges["pw"][:, None]
    e = jnp.where(pp, _norm(e, stats.pp_edge, dtype),
                  jnp.where(pw, _norm(e, stats.pw_edge, dtype), jnp.zeros_like(e)))
    return graph._replace(nodes={**nodes, "features": x}, edges={**edges, "features": e})


def normalize_accel(accel: jax.Array, stats: NormStats, dtype: Any = jnp.float32) -> jax.Array:
    """(..., 3) m/s^2 -> normalised."""
    return _norm(jnp.asarray(accel, dtype), stats.accel, dtype)


def denormalize_accel(accel_norm: jax.Array, stats: NormStats,
                      dtype: Any = jnp.float32) -> jax.Array:
    """Normalised (..., 3) -> m/s^2."""
    return _denorm(jnp.asarray(accel_norm, dtype), stats.accel, dtype)


def normalize_dissipation(de: jax.Array, stats: NormStats, dtype: Any = jnp.float32) -> jax.Array:
    """(...,) J -> normalised."""
    return _norm(jnp.asarray(de, dtype)[..., None], stats.dissipation, dtype)[..., 0]


def denormalize_dissipation(de_norm: jax.Array, stats: NormStats,
                            dtype: Any = jnp.float32) -> jax.Array:
    """Normalised (...,) -> J."""
    return _denorm(jnp.asarray(de_norm, dtype)[..., None], stats.dissipation, dtype)[..., 0]


def stats_to_arrays(stats: NormStats) -> dict[str, dict[str, np.ndarray]]:
    """Plain nested dict of float64 numpy arrays (for checkpoints and JSON)."""
    return {g: {"mean": np.asarray(getattr(stats, g).mean, np.float64),
                "std": np.asarray(getattr(stats, g).std, np.float64)} for g in NORM_GROUPS}


def stats_from_arrays(data: dict[str, Any], velocity_encoding: str = "absolute") -> NormStats:
    """Inverse of :func:`stats_to_arrays` (plus the encoding, kept apart because it is not an
    array); checks that every group is present and std > 0."""
    if velocity_encoding not in VELOCITY_ENCODINGS:
        raise NormalizationError(f"velocity encoding must be one of {VELOCITY_ENCODINGS}, "
                                 f"got {velocity_encoding!r}")
    missing = [g for g in NORM_GROUPS if g not in data]
    if missing:
        raise NormalizationError(f"normalisation statistics lack group(s) {missing}")
    groups = {}
    for g in NORM_GROUPS:
        mean = np.asarray(data[g]["mean"], np.float64)
        std = np.asarray(data[g]["std"], np.float64)
        if mean.shape != std.shape or not np.all(np.isfinite(mean)) or not np.all(std > 0):
            raise NormalizationError(f"normalisation statistics of {g!r} are invalid "
                                     "(shape mismatch, non-finite mean or std <= 0)")
        groups[g] = Moments(mean=mean, std=std)
    return NormStats(**groups, velocity_encoding=velocity_encoding)
