"""Dataset trajectory -> graph windows and training samples (the host side of the featurizer).

The featurizer itself is :func:`sgn_jax.surrogate.graph.build_graph` (pure, used by training and by
the rollout). This module reads a trajectory record: its positions, jar offsets, dissipation and the
config stored in its metadata. The rotational-frequency feature comes from the motion object the
config describes (:func:`sgn_jax.pipelines.configure.motion_from_config`, then
:func:`sgn_jax.motion.frequency_hz`), the same function the rollout applies to its live motion.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from sgn_jax.config import MotionConfig, config_from_dict
from sgn_jax.motion import Motion, frequency_hz
from sgn_jax.pipelines.configure import motion_from_config
from sgn_jax.surrogate.graph import (
    GraphError,
    GraphSpec,
    SDFQuery,
    Window,
    dissipation_per_interval,
    make_graph_builder,
    targets_from_arrays,
    valid_window_ends,
    windows_from_arrays,
)
from sgn_jax.surrogate.train import GraphDataset, random_walk_position_noise


def trajectory_motion(traj: Any) -> Motion:
    """The jar motion of a trajectory, built from the ``[motion]`` config in ``meta['config']``
    (a :class:`sgn_jax.config.Config`, its dict form, or a :class:`MotionConfig`)."""
    meta = getattr(traj, "meta", None) or {}
    cfg = meta.get("config") if isinstance(meta, dict) else None
    motion_cfg = cfg if isinstance(cfg, MotionConfig) else None
    if cfg is not None and motion_cfg is None:
        section = cfg.get("motion") if isinstance(cfg, dict) else getattr(cfg, "motion", None)
        if isinstance(section, dict):
            motion_cfg = config_from_dict(section, MotionConfig)
        elif isinstance(section, MotionConfig):
            motion_cfg = section
    if motion_cfg is None:
        raise GraphError("trajectory meta has no motion config; pass frequency_hz explicitly")
    return motion_from_config(motion_cfg)


def trajectory_frequency_hz(traj: Any, default: float | None = None) -> float:
    """The rotational frequency (Hz) of a trajectory's motion: ``default`` if given, else
    :func:`sgn_jax.motion.frequency_hz` of :func:`trajectory_motion` (as in the rollout)."""
    if default is not None:
        return float(default)
    return float(frequency_hz(trajectory_motion(traj)))


def windows_from_trajectory(traj: Any, window: int, dt: float | None = None,
                            frequency_hz: float | None = None, ends: np.ndarray | None = None
                            ) -> tuple[Window, np.ndarray, np.ndarray]:
    """Training windows and targets of a trajectory
    (``sgn_jax.records.trajectory.Trajectory``-like).

    ``traj`` needs ``pos`` (T, N, 3), ``offset`` and ``offset_vel`` (T, 3), the four
    ``diss_{pp,pw}_{normal,tangential}`` (T,) arrays and ``meta`` (with ``dt`` and ``config``
    unless ``dt`` / ``frequency_hz`` are passed). ``ends`` defaults to every valid window end.

    Returns ``(windows, accel (S, N, 3), dE (S,))`` as float64 numpy arrays.
    """
    pos = np.asarray(traj.pos, np.float64)
    meta = getattr(traj, "meta", None) or {}
    if dt is None:
        if "dt" not in meta:
            raise GraphError("trajectory meta has no 'dt'; pass dt explicitly")
        dt = float(meta["dt"])
    freq = trajectory_frequency_hz(traj, frequency_hz)
    if ends is None:
        ends = valid_window_ends(len(pos), window)
    wins = windows_from_arrays(pos, traj.offset, traj.offset_vel, freq, ends, window)
    accel, de = targets_from_arrays(pos, dissipation_per_interval(traj), ends, dt)
    return wins, accel, de


def featurize_trajectory(traj: Any, spec: GraphSpec, sdf: Any, ends: np.ndarray, *,
                         query: SDFQuery | None = None, frequency_hz: float | None = None,
                         source: int = 0, chunk: int = 1024, progress: bool = False,
                         builder: Callable | None = None, position_noise_std: float = 0.0,
                         noise_seed: int = 0) -> GraphDataset:
    """Featurize the windows of ``traj`` ending at ``ends`` with :func:`build_graph`.

    ``traj`` is a ``sgn_jax.records.trajectory.Trajectory`` (or any object with ``pos``, ``offset``,
    ``offset_vel``, the four dissipation arrays and ``meta``). Chunks of ``chunk`` windows are
    built at once (the last one padded, so one compilation serves all).

    ``position_noise_std`` > 0 (m/s) perturbs every window once with
    :func:`random_walk_position_noise` (seeded by ``(noise_seed, source)``, so a rerun
    featurizes the same noise) and corrects the acceleration targets to match.
    """
    n, w = spec.n_particles, spec.window
    pos = np.asarray(traj.pos, np.float64)
    if pos.ndim != 3 or pos.shape[1:] != (n, 3):
        raise GraphError(f"trajectory positions have shape {pos.shape}, expected (T, {n}, 3)")
    freq = trajectory_frequency_hz(traj, frequency_hz)
    diss = dissipation_per_interval(traj)
    ends = np.asarray(ends, np.int64)
    builder = builder or make_graph_builder(query, spec)
    parts: list[dict[str, np.ndarray]] = []
    dropped = 0
    noise_rng = np.random.default_rng([noise_seed, source]) if position_noise_std > 0 else None
    last_velocity_noise = []
    starts = range(0, len(ends), chunk)
    for start in tqdm(starts, desc="featurize", unit="chunk", disable=not progress, leave=False):
        e = ends[start:start + chunk]
        padded = np.concatenate([e, np.full(chunk - len(e), e[-1])]) if len(e) < chunk else e
        wins = windows_from_arrays(pos, traj.offset, traj.offset_vel, freq, padded, w)
        if noise_rng is not None:
            noise, nu_last = random_walk_position_noise(noise_rng, len(padded), w, n,
                                                        position_noise_std, spec.dt)
            wins = wins.replace(positions=wins.positions + noise)
            last_velocity_noise.append(nu_last[:len(e)])
        graphs, counts = builder(jax.tree_util.tree_map(jnp.asarray, wins), sdf)
        graphs, counts = jax.device_get((graphs, counts))
        k = len(e)
        real = (graphs.edges["pp"] | graphs.edges["pw"])[:k]  # (k, E_cap), a prefix per row
        parts.append(dict(
            node_features=np.asarray(graphs.nodes["features"][:k, : n + 1]),
            n_edges=real.sum(axis=1),
            edge_features=np.asarray(graphs.edges["features"][:k][real]),
            edge_senders=np.asarray(graphs.senders[:k][real], np.int32),
            edge_receivers=np.asarray(graphs.receivers[:k][real], np.int32),
            edge_is_pp=np.asarray(graphs.edges["pp"][:k][real]),
        ))
        dropped += int(np.sum(counts.pp_dropped[:k]))
    cat = lambda name: np.concatenate([p[name] for p in parts])  # noqa: E731
    accel = (pos[ends + 1] - 2.0 * pos[ends] + pos[ends - 1]) / spec.dt**2
    if last_velocity_noise:
        accel = accel - np.concatenate(last_velocity_noise) / spec.dt
    return GraphDataset(
        node_features=cat("node_features"),
        edge_offsets=np.concatenate([[0], np.cumsum(cat("n_edges"))]).astype(np.int64),
        edge_features=cat("edge_features"), edge_senders=cat("edge_senders"),
        edge_receivers=cat("edge_receivers"), edge_is_pp=cat("edge_is_pp"),
        accel=accel, dissipation=diss[ends + 1], source=np.full(len(ends), source, np.int32),
        window_end=ends, pp_dropped=dropped)
