"""SGN training: precomputed graphs, packed static-shape batches, optax Adam, orbax checkpoints.

Pipeline (:func:`train`):

1. Every trajectory is split chronologically (:func:`split_window_ends`) and each window is
   featurized once with :func:`sgn_jax.graph.build_graph` (vmapped, jitted) into a compact
   numpy :class:`GraphDataset` (real edges only). An edge-capacity overflow is an error.
2. Normalisation statistics come from the training split (:mod:`sgn_jax.normalization`);
   the dataset is normalised once (float32).
3. Each epoch shuffles the training samples and packs them greedily into batches of at most
   ``batch_size`` graphs and at most a static number of edges (:class:`BatchPacker`), so every
   batch has the same array shapes and the step compiles once; unused graph slots are masked.
4. Loss (paper Eqs. 28-30): ``alpha * Huber(accel) + beta * Huber(dE)`` (beta =
   ``global_loss_weight``: 1 as in the paper, 0 for the appendix ablation) on normalised
   targets, Huber in Eq. 30's form ``optax.huber_loss(e, delta) / delta`` (= ``huber_loss(delta=2) / 2``), means
   over the real ball components and the real graphs of the batch. Gaussian noise of
   ``noise_std`` is added to the normalised velocity columns of the ball nodes.
5. Adam; learning rate ``lr_init * (lr_final / lr_init) ** progress`` with progress = fraction of
   all epochs done (per step, smooth).
6. After every epoch: validation loss, a row in ``metrics.jsonl`` / ``metrics.csv``,
   ``loss.png``, ``checkpoints/latest`` and, when the validation loss improves,
   ``checkpoints/best``. ``resume=True`` continues from ``checkpoints/latest``.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import math
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import flax.struct
import jax
import jax.numpy as jnp
import jraph
import numpy as np
import optax

import sgn_jax
from sgn_jax.checkpoint import latest_step, restore_checkpoint, save_checkpoint
from sgn_jax.config import config_to_dict, replace_section, save_config
from sgn_jax.envelope import ENVELOPE_PATH, load_envelope
from sgn_jax.errors import SGNJaxError
from sgn_jax.geometry import sdf_grid_from_config
from sgn_jax.graph import (
    GraphError,
    GraphSpec,
    SDFQuery,
    dissipation_per_interval,
    graph_spec_from_config,
    make_graph_builder,
    trajectory_frequency_hz,
    valid_window_ends,
    velocity_columns,
    windows_from_arrays,
)
from sgn_jax.io_utils import atomic_write, git_commit, write_json
from sgn_jax.model import count_params, init_params, make_apply, make_model
from sgn_jax.normalization import NormStats, compute_norm_stats, encode_velocities, stats_to_arrays

# --------------------------------------------------------------------------------------------
# Precomputed graphs


@dataclasses.dataclass
class GraphDataset:
    """Graphs of many windows, node rows fixed (N balls + wall), edges compact (CSR).

    Attributes:
        node_features: (S, N+1, 7W) float32, rows 0..N-1 balls, row N the wall node.
        edge_offsets: (S+1,) int64, edges of sample s are ``edge_offsets[s]:edge_offsets[s+1]``.
        edge_features: (E, 3 or 5) float32; edge_senders, edge_receivers: (E,) int32 local node
            indices (0..N); edge_is_pp: (E,) bool (False: ball-wall edge).
        accel: (S, N, 3) acceleration targets (m/s^2); dissipation: (S,) dE targets (J).
        source: (S,) index of the trajectory; window_end: (S,) sample index n ending the window.
        pp_dropped: directed ball-ball edges lost to the capacity (0 unless overflow).

    Normalised datasets (:func:`normalize_dataset`) hold normalised float32 values instead.
    """

    node_features: np.ndarray
    edge_offsets: np.ndarray
    edge_features: np.ndarray
    edge_senders: np.ndarray
    edge_receivers: np.ndarray
    edge_is_pp: np.ndarray
    accel: np.ndarray
    dissipation: np.ndarray
    source: np.ndarray
    window_end: np.ndarray
    pp_dropped: int = 0

    def __len__(self) -> int:
        return int(self.node_features.shape[0])

    @property
    def n_particles(self) -> int:
        return int(self.node_features.shape[1]) - 1

    @property
    def edges_per_sample(self) -> np.ndarray:
        return np.diff(self.edge_offsets)

    @staticmethod
    def concatenate(parts: Sequence[GraphDataset]) -> GraphDataset:
        parts = [p for p in parts if len(p)]
        if not parts:
            raise GraphError("no samples to concatenate")
        offsets = [parts[0].edge_offsets]
        for p in parts[1:]:
            offsets.append(p.edge_offsets[1:] + offsets[-1][-1])
        cat = lambda name: np.concatenate([getattr(p, name) for p in parts])  # noqa: E731
        return GraphDataset(
            node_features=cat("node_features"), edge_offsets=np.concatenate(offsets),
            edge_features=cat("edge_features"), edge_senders=cat("edge_senders"),
            edge_receivers=cat("edge_receivers"), edge_is_pp=cat("edge_is_pp"),
            accel=cat("accel"), dissipation=cat("dissipation"), source=cat("source"),
            window_end=cat("window_end"), pp_dropped=sum(p.pp_dropped for p in parts))


def random_walk_position_noise(rng: np.random.Generator, n_windows: int, window: int,
                               n_particles: int, velocity_std: float, dt: float
                               ) -> tuple[np.ndarray, np.ndarray]:
    """GNS-style random-walk noise on a position window (Sanchez-Gonzalez et al. 2020).

    The W finite-difference velocities of a window get a random walk ``nu_k = sum_{j<=k}
    eps_j`` with ``eps_j ~ N(0, velocity_std^2 / W)`` (so the last one has std
    ``velocity_std``, m/s); the positions integrate it: ``n_0 = 0``, ``n_k = n_{k-1} + nu_k dt``.

    Returns ``(position_noise (S, W+1, N, 3) m, last_velocity_noise (S, N, 3) m/s)``. A window
    trained with this noise gets the target ``a_true - nu_W / dt``: the next position stays
    the true one shifted by the last position's noise, so the model learns to undo a velocity
    error instead of carrying it on (docs/sgn.md, "Training noise").
    """
    eps = rng.normal(0.0, velocity_std / math.sqrt(window), (n_windows, window, n_particles, 3))
    nu = np.cumsum(eps, axis=1)
    steps = np.cumsum(nu * dt, axis=1)
    noise = np.concatenate([np.zeros((n_windows, 1, n_particles, 3)), steps], axis=1)
    return noise, nu[:, -1]


def featurize_trajectory(traj: Any, spec: GraphSpec, sdf: Any, ends: np.ndarray, *,
                         query: SDFQuery | None = None, frequency_hz: float | None = None,
                         source: int = 0, chunk: int = 1024, progress: bool = False,
                         builder: Callable | None = None, position_noise_std: float = 0.0,
                         noise_seed: int = 0) -> GraphDataset:
    """Featurize the windows of ``traj`` ending at ``ends`` with :func:`build_graph`.

    ``traj`` is a ``sgn_jax.dataset.Trajectory`` (or any object with ``pos``, ``offset``,
    ``offset_vel``, the four dissipation arrays and ``meta``). Chunks of ``chunk`` windows are
    built at once (the last one padded, so one compilation serves all).

    ``position_noise_std`` > 0 (m/s) perturbs every window once with
    :func:`random_walk_position_noise` (seeded by ``(noise_seed, source)``, so a rerun
    featurizes the same noise) and corrects the acceleration targets to match.
    """
    from tqdm.auto import tqdm

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


def split_window_ends(t: np.ndarray, window: int, train_time: float, val_time: float
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Chronological split of a trajectory's window ends (sample times ``t`` (T,), s).

    Training windows: the target step ends at ``t[n+1] <= train_time``. Validation windows lie
    wholly after the training targets: ``t[n-W] >= train_time`` and ``t[n+1] <= train_time +
    val_time``. (Windows straddling train_time are in neither.)
    """
    t = np.asarray(t, np.float64)
    ends = valid_window_ends(len(t), window)
    tol = 1e-9 + 1e-6 * (float(t[1] - t[0]) if len(t) > 1 else 0.0)
    train = ends[t[ends + 1] <= train_time + tol]
    val = ends[(t[ends - window] >= train_time - tol) & (t[ends + 1] <= train_time + val_time + tol)]
    return train, val


def norm_stats_from_dataset(ds: GraphDataset, velocity_encoding: str = "absolute") -> NormStats:
    """Statistics of a (raw, training) dataset, by row type."""
    n = ds.n_particles
    return compute_norm_stats(
        velocity_encoding=velocity_encoding,
        particle=ds.node_features[:, :n].reshape(-1, ds.node_features.shape[-1]),
        wall=ds.node_features[:, n],
        pp_edge=ds.edge_features[ds.edge_is_pp],
        pw_edge=ds.edge_features[~ds.edge_is_pp],
        accel=ds.accel.reshape(-1, 3),
        dissipation=ds.dissipation,
    )


def _norm32(x: np.ndarray, m: Any) -> np.ndarray:
    # The same float32 operations as normalization.normalize_graph, so results are identical.
    return (np.asarray(x, np.float32) - np.asarray(m.mean, np.float32)) / np.asarray(m.std,
                                                                                      np.float32)


def normalize_dataset(ds: GraphDataset, stats: NormStats) -> GraphDataset:
    """A copy of ``ds`` with every feature and target normalised (float32)."""
    n = ds.n_particles
    nodes = np.empty(ds.node_features.shape, np.float32)
    nodes[:, :n] = _norm32(encode_velocities(ds.node_features[:, :n], stats.velocity_encoding),
                           stats.particle)
    nodes[:, n] = _norm32(ds.node_features[:, n], stats.wall)
    edges = np.where(ds.edge_is_pp[:, None], _norm32(ds.edge_features, stats.pp_edge),
                     _norm32(ds.edge_features, stats.pw_edge)).astype(np.float32)
    return dataclasses.replace(
        ds, node_features=nodes, edge_features=edges,
        accel=_norm32(ds.accel, stats.accel),
        dissipation=_norm32(ds.dissipation[:, None], stats.dissipation)[:, 0])


# --------------------------------------------------------------------------------------------
# Batches


@flax.struct.dataclass
class Batch:
    """A packed batch: graph (normalised features), targets (normalised) and masks.

    ``graph`` has ``max_graphs`` graph slots of N + 1 nodes plus a padding graph of one node;
    ``accel`` (n_node, 3), ``dissipation`` and ``graph_mask`` (n_graph,).
    """

    graph: jraph.GraphsTuple
    accel: jax.Array
    dissipation: jax.Array
    graph_mask: jax.Array


class BatchPacker:
    """Packs samples of a normalised :class:`GraphDataset` into static-shape batches.

    Each batch has ``max_graphs`` graph slots (unused slots are masked out) and
    ``edge_capacity`` edge slots (unused slots are padding edges on the padding node).
    """

    def __init__(self, ds: GraphDataset, max_graphs: int, edge_capacity: int):
        per = ds.edges_per_sample
        if len(per) and per.max() > edge_capacity:
            raise GraphError(f"a sample has {per.max()} edges, more than the batch edge capacity "
                             f"{edge_capacity}")
        self.ds, self.max_graphs, self.edge_capacity = ds, int(max_graphs), int(edge_capacity)
        self.n_particles = ds.n_particles
        n1 = self.n_particles + 1
        self.n_node = self.max_graphs * n1 + 1
        local = np.arange(n1)
        self._particle_row = np.tile(local < self.n_particles, self.max_graphs)
        self._wall_row = np.tile(local == self.n_particles, self.max_graphs)

    def plan(self, order: np.ndarray) -> list[np.ndarray]:
        """Greedy packing of the samples in ``order`` (a list of index arrays, one per batch)."""
        per = self.ds.edges_per_sample[order]
        batches, current, edges = [], [], 0
        for idx, e in zip(order.tolist(), per.tolist(), strict=True):
            if current and (len(current) == self.max_graphs or edges + e > self.edge_capacity):
                batches.append(np.array(current))
                current, edges = [], 0
            current.append(idx)
            edges += e
        if current:
            batches.append(np.array(current))
        return batches

    def make(self, idx: np.ndarray) -> Batch:
        """The batch of samples ``idx`` (at most ``max_graphs``), as numpy arrays."""
        ds, b, n1 = self.ds, self.max_graphs, self.n_particles + 1
        k = len(idx)
        feat_dim = ds.node_features.shape[-1]
        nodes = np.zeros((b * n1 + 1, feat_dim), np.float32)
        nodes[: k * n1] = ds.node_features[idx].reshape(k * n1, feat_dim)
        used_rows = np.arange(b * n1) < k * n1
        particle = np.concatenate([self._particle_row & used_rows, [False]])
        wall = np.concatenate([self._wall_row & used_rows, [False]])

        starts, lens = ds.edge_offsets[idx], ds.edges_per_sample[idx]
        total = int(lens.sum())
        seg = np.repeat(np.arange(k), lens)
        src = starts[seg] + np.arange(total) - np.repeat(np.cumsum(lens) - lens, lens)
        pad_node = b * n1
        cap = self.edge_capacity
        senders = np.full(cap, pad_node, np.int32)
        receivers = np.full(cap, pad_node, np.int32)
        senders[:total] = ds.edge_senders[src] + seg * n1
        receivers[:total] = ds.edge_receivers[src] + seg * n1
        efeat = np.zeros((cap, ds.edge_features.shape[-1]), np.float32)
        efeat[:total] = ds.edge_features[src]
        is_pp = np.zeros(cap, bool)
        is_pp[:total] = ds.edge_is_pp[src]
        is_pw = np.zeros(cap, bool)
        is_pw[:total] = ~ds.edge_is_pp[src]

        n_edge = np.zeros(b + 1, np.int32)
        n_edge[:k] = lens
        n_edge[b] = cap - total
        n_node = np.full(b + 1, n1, np.int32)
        n_node[b] = 1
        accel = np.zeros((b * n1 + 1, 3), np.float32)
        acc_rows = accel[: k * n1].reshape(k, n1, 3)
        acc_rows[:, : self.n_particles] = ds.accel[idx]
        de = np.zeros(b + 1, np.float32)
        de[:k] = ds.dissipation[idx]
        graph = jraph.GraphsTuple(
            nodes={"features": nodes, "particle": particle, "wall": wall},
            edges={"features": efeat, "pp": is_pp, "pw": is_pw},
            senders=senders, receivers=receivers, n_node=n_node, n_edge=n_edge, globals=None)
        return Batch(graph=graph, accel=accel, dissipation=de,
                     graph_mask=np.arange(b + 1) < k)

    def batches(self, order: np.ndarray) -> Iterator[Batch]:
        for idx in self.plan(order):
            yield self.make(idx)


def batch_edge_capacity(edges_per_sample: np.ndarray, max_graphs: int, multiple: int = 16) -> int:
    """Static edge capacity of a batch: the mean load plus 4 standard deviations of a sum of
    ``max_graphs`` samples (at least the largest sample), rounded up to ``multiple``. Batches
    whose samples would exceed it are closed early by the packer (fewer graphs, same shapes)."""
    e = np.asarray(edges_per_sample, np.float64)
    if e.size == 0:
        return multiple
    cap = max(e.max(), max_graphs * e.mean() + 4.0 * math.sqrt(max_graphs) * e.std(), 1.0)
    return int(math.ceil(cap / multiple) * multiple)


# --------------------------------------------------------------------------------------------
# Loss and steps


def huber_eq30(error: jax.Array, delta: float) -> jax.Array:
    """Paper Eq. 30: e^2 / (2 delta) if |e| < delta else |e| - delta / 2
    (= ``optax.huber_loss(e, delta=delta) / delta``)."""
    return optax.huber_loss(error, delta=delta) / delta


@flax.struct.dataclass
class TrainState:
    """Parameters, optimiser state and the number of steps taken."""

    params: Any
    opt_state: Any
    step: jax.Array


def make_optimizer(lr_init: float) -> optax.GradientTransformation:
    """Adam whose learning rate is a hyperparameter set at every step (see :func:`lr_at`)."""
    return optax.inject_hyperparams(optax.adam)(learning_rate=lr_init)


def lr_at(progress: float, lr_init: float, lr_final: float) -> float:
    """Exponential decay: ``lr_init`` at progress 0, ``lr_final`` at progress 1."""
    return float(lr_init * (lr_final / lr_init) ** min(max(progress, 0.0), 1.0))


def loss_sums(apply: Callable, params: Any, batch: Batch, delta: float
              ) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
    """Summed Huber losses and their counts: (node_sum, node_count, global_sum, global_count)."""
    accel, de = apply(params, batch.graph)
    particle = batch.graph.nodes["particle"].astype(jnp.float32)
    node = jnp.sum(huber_eq30(accel - batch.accel, delta) * particle[:, None])
    glob = jnp.sum(huber_eq30(de - batch.dissipation, delta) * batch.graph_mask)
    return node, 3.0 * jnp.sum(particle), glob, jnp.sum(batch.graph_mask.astype(jnp.float32))


def add_velocity_noise(graph: jraph.GraphsTuple, key: jax.Array, std: float,
                       window: int) -> jraph.GraphsTuple:
    """Gaussian noise of ``std`` on the normalised velocity columns of the ball nodes."""
    x = graph.nodes["features"]
    cols = np.zeros(x.shape[-1], np.float32)
    cols[velocity_columns(window)] = 1.0
    mask = graph.nodes["particle"][:, None].astype(x.dtype) * jnp.asarray(cols)
    noise = std * jax.random.normal(key, x.shape, x.dtype) * mask
    return graph._replace(nodes={**graph.nodes, "features": x + noise})


def make_train_step(apply: Callable, tx: optax.GradientTransformation, train_cfg: Any,
                    window: int) -> Callable:
    """Jitted ``step(state, batch, lr, key) -> (state, sums)``; ``sums`` as in :func:`loss_sums`."""
    alpha, delta, noise = train_cfg.node_loss_weight, train_cfg.huber_delta, train_cfg.noise_std
    beta = train_cfg.global_loss_weight

    def loss_fn(params, batch, key):
        if noise > 0:
            batch = batch.replace(graph=add_velocity_noise(batch.graph, key, noise, window))
        sums = loss_sums(apply, params, batch, delta)
        node = sums[0] / jnp.maximum(sums[1], 1.0)
        glob = sums[2] / jnp.maximum(sums[3], 1.0)
        return alpha * node + beta * glob, jnp.stack(sums)

    def step(state: TrainState, batch: Batch, lr: jax.Array, key: jax.Array):
        grads, sums = jax.grad(loss_fn, has_aux=True)(state.params, batch, key)
        opt_state = state.opt_state
        opt_state = opt_state._replace(
            hyperparams={**opt_state.hyperparams, "learning_rate": jnp.asarray(lr, jnp.float32)})
        updates, opt_state = tx.update(grads, opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        return TrainState(params=params, opt_state=opt_state, step=state.step + 1), sums

    return jax.jit(step, donate_argnums=(0,))


def make_eval_step(apply: Callable, train_cfg: Any) -> Callable:
    """Jitted ``eval(params, batch) -> sums`` (no noise)."""
    delta = train_cfg.huber_delta
    return jax.jit(lambda params, batch: jnp.stack(loss_sums(apply, params, batch, delta)))


def losses_from_sums(sums: np.ndarray, alpha: float, beta: float = 1.0) -> dict[str, float]:
    """Exact means over all real components / graphs: node, global and total loss."""
    node = float(sums[0] / max(sums[1], 1.0))
    glob = float(sums[2] / max(sums[3], 1.0))
    return {"loss": alpha * node + beta * glob, "node": node, "global": glob}


def evaluate(eval_step: Callable, params: Any, packer: BatchPacker, alpha: float,
             beta: float = 1.0) -> dict[str, float]:
    """Loss over a whole dataset, in chronological order (weights as in the training loss)."""
    total = jnp.zeros(4, jnp.float32)
    for batch in packer.batches(np.arange(len(packer.ds))):
        total = total + eval_step(params, batch)
    return losses_from_sums(np.asarray(total, np.float64), alpha, beta)


# --------------------------------------------------------------------------------------------
# Metrics files


METRIC_FIELDS = ("epoch", "step", "lr", "train_loss", "train_node", "train_global", "val_loss",
                 "val_node", "val_global", "epoch_seconds", "samples_per_second", "batches",
                 "best")


def write_metrics(out_dir: Path, history: list[dict[str, Any]]) -> None:
    """``metrics.jsonl`` and ``metrics.csv`` (rewritten atomically) and ``loss.png``."""
    with atomic_write(out_dir / "metrics.jsonl", "w") as fh:
        for row in history:
            fh.write(json.dumps(row, sort_keys=True) + "\n")
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=METRIC_FIELDS, extrasaction="ignore")
    writer.writeheader()
    writer.writerows(history)
    with atomic_write(out_dir / "metrics.csv", "w") as fh:
        fh.write(buf.getvalue())
    plot_losses(history, out_dir / "loss.png")


def read_metrics(out_dir: Path) -> list[dict[str, Any]]:
    path = out_dir / "metrics.jsonl"
    if not path.is_file():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def plot_losses(history: list[dict[str, Any]], path: Path) -> None:
    """Training and validation losses against epoch (log scale), written atomically as PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not history:
        return
    ep = [r["epoch"] for r in history]
    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    for key, style, label in (("train_loss", "-", "train (total)"),
                              ("val_loss", "-", "validation (total)"),
                              ("train_node", ":", "train node"), ("val_node", ":", "val node"),
                              ("train_global", "--", "train global"),
                              ("val_global", "--", "val global")):
        y = [r.get(key) for r in history]
        if all(v is not None and math.isfinite(v) and v > 0 for v in y):
            ax.plot(ep, y, style, label=label, marker="o" if len(ep) < 30 else None, ms=3)
    ax.set_yscale("log")
    ax.set_xlabel("epoch")
    ax.set_ylabel("Huber loss (normalised)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    with atomic_write(path, "wb") as fh:
        fig.savefig(fh, format="png", dpi=120)
    plt.close(fig)


# --------------------------------------------------------------------------------------------
# The training loop


class TrainingError(SGNJaxError, RuntimeError):
    """A training run cannot start or continue (inconsistent data, config or output dir)."""


def check_trajectory_matches(traj: Any, cfg: Any, name: str) -> None:
    """The data must have the config's dt, ball count and ball radius."""
    meta = getattr(traj, "meta", None) or {}
    n = np.asarray(traj.pos).shape[1]
    problems = []
    if n != cfg.balls.count:
        problems.append(f"{n} balls, config [balls] count = {cfg.balls.count}")
    if "dt" in meta and not math.isclose(float(meta["dt"]), cfg.dem.dt, rel_tol=1e-9):
        problems.append(f"dt = {meta['dt']}, config [dem] dt = {cfg.dem.dt}")
    if "ball_radius" in meta and not math.isclose(float(meta["ball_radius"]), cfg.balls.radius,
                                                  rel_tol=1e-9):
        problems.append(f"ball radius {meta['ball_radius']}, config {cfg.balls.radius}")
    saved = meta.get("config") if isinstance(meta, dict) else None
    if isinstance(saved, dict) and "jar" in saved:
        if saved["jar"] != config_to_dict(cfg)["jar"]:
            problems.append(f"jar {saved['jar']}, config [jar] {config_to_dict(cfg)['jar']} "
                            "(the featurizer would use the wrong SDF)")
    if problems:
        raise TrainingError(f"{name} does not match the config: " + "; ".join(problems))


def prepare_datasets(trajectories: Sequence[Any], cfg: Any, sdf: Any, *,
                     query: SDFQuery | None = None, names: Sequence[str] | None = None,
                     progress: bool = True) -> tuple[GraphDataset, GraphDataset | None, GraphSpec]:
    """Featurize the training and validation windows of all trajectories (raw, compact)."""
    spec = graph_spec_from_config(cfg)
    names = names or [f"trajectory {i}" for i in range(len(trajectories))]
    builder = make_graph_builder(query, spec)
    train_parts, val_parts = [], []
    for i, (traj, name) in enumerate(zip(trajectories, names, strict=True)):
        check_trajectory_matches(traj, cfg, name)
        t = np.asarray(traj.t, np.float64)
        tr, va = split_window_ends(t, spec.window, cfg.train.train_time, cfg.train.val_time)
        stride = cfg.train.window_stride
        tr, va = tr[::stride], va[::stride]
        if len(tr) == 0:
            raise TrainingError(f"{name}: no training window with t <= train_time = "
                                f"{cfg.train.train_time} s (the data cover {t[-1]:.4g} s)")
        # Noise on the training windows only: validation measures the clean one-step error.
        for ends, parts, noise in ((tr, train_parts, cfg.train.position_noise_std),
                                   (va, val_parts, 0.0)):
            if len(ends):
                parts.append(featurize_trajectory(traj, spec, sdf, ends, source=i,
                                                  builder=builder, progress=progress,
                                                  position_noise_std=noise,
                                                  noise_seed=cfg.train.seed))
    train_ds = GraphDataset.concatenate(train_parts)
    val_ds = GraphDataset.concatenate(val_parts) if val_parts else None
    dropped = train_ds.pp_dropped + (val_ds.pp_dropped if val_ds else 0)
    if dropped:
        raise GraphError(
            f"{dropped} directed ball-ball edges exceeded the graph capacity of "
            f"{spec.pp_capacity} per graph; raise [graph] pp_edges_per_particle "
            f"(now {cfg.graph.pp_edges_per_particle})")
    return train_ds, val_ds, spec


def train(cfg: Any, trajectories: Sequence[Any], out_dir: str | Path, *, sdf: Any = None,
          query: SDFQuery | None = None, epochs: int | None = None, resume: bool = False,
          names: Sequence[str] | None = None, progress: bool = True,
          log: Callable[[str], None] = print) -> dict[str, Any]:
    """Train an SGN on ``trajectories`` and write the run to ``out_dir``.

    Args:
        cfg: the experiment :class:`sgn_jax.config.Config` ([graph], [model], [train]).
        trajectories: ``sgn_jax.dataset.Trajectory`` objects (or look-alikes).
        out_dir: run directory (config.toml, metrics, loss.png, checkpoints/).
        sdf, query: the jar SDF for :func:`sgn_jax.graph.build_graph` (default: the config's
            SDF grid and ``query_sdf_grid``).
        epochs: overrides ``cfg.train.epochs`` (total epochs of the run, also when resuming).
        resume: continue from ``out_dir/checkpoints/latest``; without it an existing run in
            ``out_dir`` is an error.

    Returns:
        a summary dict (epochs done, best validation loss and epoch, timings, capacities).
    """
    from tqdm.auto import tqdm

    if epochs is not None:
        cfg = replace_section(cfg, "train", epochs=int(epochs))
    tcfg = cfg.train
    out_dir = Path(out_dir)
    ckpt_latest, ckpt_best = out_dir / "checkpoints" / "latest", out_dir / "checkpoints" / "best"
    existing = latest_step(ckpt_latest)
    if existing is not None and not resume:
        raise TrainingError(f"{out_dir} already holds a training run (epoch {existing}); pass "
                            "--resume to continue it or choose another --out")
    if resume and existing is None:
        log(f"no checkpoint in {ckpt_latest}; starting a new run")
    if sdf is None:
        sdf = sdf_grid_from_config(cfg)

    t0 = time.perf_counter()
    train_raw, val_raw, spec = prepare_datasets(trajectories, cfg, sdf, query=query, names=names,
                                                progress=progress)
    featurize_s = time.perf_counter() - t0

    model = make_model(cfg.model)
    apply = make_apply(model)
    tx = make_optimizer(tcfg.lr_init)
    restored = None
    if existing is not None:
        restored = restore_checkpoint(ckpt_latest)
        saved_cfg = restored.meta.get("config", {})
        for section in ("graph", "model", "balls"):
            if saved_cfg.get(section) != config_to_dict(cfg).get(section):
                raise TrainingError(
                    f"cannot resume: the [{section}] section differs from the run in {out_dir} "
                    f"(saved {saved_cfg.get(section)}, now {config_to_dict(cfg).get(section)})")
        stats = restored.norm_stats
    else:
        stats = norm_stats_from_dataset(train_raw, cfg.model.velocity_encoding)
    train_ds = normalize_dataset(train_raw, stats)
    val_ds = normalize_dataset(val_raw, stats) if val_raw is not None else None
    del train_raw, val_raw

    max_graphs = tcfg.batch_size
    per = train_ds.edges_per_sample
    capacity = batch_edge_capacity(per, max_graphs)
    if val_ds is not None:
        capacity = max(capacity, int(math.ceil(val_ds.edges_per_sample.max() / 16) * 16))
    train_packer = BatchPacker(train_ds, max_graphs, capacity)
    val_packer = BatchPacker(val_ds, max_graphs, capacity) if val_ds is not None else None

    example = train_packer.make(np.arange(min(max_graphs, len(train_ds))))
    params = init_params(model, example.graph, tcfg.seed)
    opt_state = tx.init(params)
    history: list[dict[str, Any]] = []
    start_epoch = 0
    if restored is not None:
        full = restore_checkpoint(ckpt_latest, opt_state_like=opt_state)
        params, opt_state = full.params, full.opt_state
        start_epoch = int(full.meta["epoch"])
        history = [r for r in read_metrics(out_dir) if r["epoch"] <= start_epoch]
        log(f"resuming {out_dir} after epoch {start_epoch}")
    state = TrainState(params=jax.tree_util.tree_map(jnp.asarray, params),
                       opt_state=jax.tree_util.tree_map(jnp.asarray, opt_state),
                       step=jnp.asarray(history[-1]["step"] if history else 0, jnp.int64))
    del params, opt_state

    out_dir.mkdir(parents=True, exist_ok=True)
    save_config(cfg, out_dir / "config.toml")
    write_json(out_dir / "norm_stats.json",
               {**stats_to_arrays(stats), "velocity_encoding": stats.velocity_encoding})
    info = {
        "n_train": len(train_ds), "n_val": len(val_ds) if val_ds is not None else 0,
        "n_params": count_params(state.params), "max_graphs_per_batch": max_graphs,
        "batch_edge_capacity": capacity, "mean_edges_per_sample": float(per.mean()),
        "max_edges_per_sample": int(per.max()), "featurize_seconds": featurize_s,
        "graph_spec": dataclasses.asdict(spec), "git_commit": git_commit(),
        "sgn_jax_version": sgn_jax.__version__,
    }
    write_json(out_dir / "run_info.json", info)
    log(f"train {info['n_train']} / validation {info['n_val']} windows, "
        f"{info['n_params']:,} parameters, batches of <= {max_graphs} graphs and <= {capacity} "
        f"edges (mean {per.mean():.1f} edges per graph)")

    train_step = make_train_step(apply, tx, tcfg, spec.window)
    eval_step = make_eval_step(apply, tcfg)
    base_key = jax.random.PRNGKey(tcfg.seed)
    alpha, beta = tcfg.node_loss_weight, tcfg.global_loss_weight
    best = min((r["val_loss"] if r["val_loss"] is not None else r["train_loss"]
                for r in history), default=math.inf)
    meta_base = {"config": config_to_dict(cfg), "info": info}
    if tcfg.envelope:
        path = ENVELOPE_PATH if tcfg.envelope == "default" else Path(tcfg.envelope)
        meta_base["envelope"] = load_envelope(path).to_meta()

    epoch_bar = tqdm(range(start_epoch, tcfg.epochs), desc="epochs", unit="epoch",
                     disable=not progress, initial=start_epoch, total=tcfg.epochs)
    for epoch in epoch_bar:
        t_epoch = time.perf_counter()
        order = np.random.default_rng([tcfg.seed, epoch]).permutation(len(train_ds))
        plan = train_packer.plan(order)
        sums = jnp.zeros(4, jnp.float32)
        lr = tcfg.lr_init
        step_bar = tqdm(plan, desc=f"epoch {epoch + 1}", unit="batch", leave=False,
                        disable=not progress)
        step_no = int(state.step)
        for i, idx in enumerate(step_bar):
            lr = lr_at((epoch + i / len(plan)) / tcfg.epochs, tcfg.lr_init, tcfg.lr_final)
            # Noise keys depend only on (seed, global step): a resumed run draws the same noise.
            key = jax.random.fold_in(base_key, step_no)
            step_no += 1
            state, batch_sums = train_step(state, train_packer.make(idx), np.float32(lr), key)
            sums = sums + batch_sums
        train_loss = losses_from_sums(np.asarray(sums, np.float64), alpha, beta)
        val_loss = (evaluate(eval_step, state.params, val_packer, alpha, beta)
                    if val_packer is not None else None)
        seconds = time.perf_counter() - t_epoch
        score = val_loss["loss"] if val_loss is not None else train_loss["loss"]
        improved = score < best
        best = min(best, score)
        row = {"epoch": epoch + 1, "step": int(state.step), "lr": lr,
               "train_loss": train_loss["loss"], "train_node": train_loss["node"],
               "train_global": train_loss["global"],
               "val_loss": val_loss["loss"] if val_loss else None,
               "val_node": val_loss["node"] if val_loss else None,
               "val_global": val_loss["global"] if val_loss else None,
               "epoch_seconds": seconds, "samples_per_second": len(train_ds) / seconds,
               "batches": len(plan), "best": improved}
        history.append(row)
        meta = {**meta_base, "epoch": epoch + 1, "global_step": int(state.step),
                "train_loss": train_loss["loss"], "val_loss": row["val_loss"]}
        save_checkpoint(ckpt_latest, epoch + 1, params=state.params, norm_stats=stats,
                        opt_state=state.opt_state, meta=meta, keep=2)
        if improved:
            save_checkpoint(ckpt_best, epoch + 1, params=state.params, norm_stats=stats,
                            meta=meta, keep=1)
        write_metrics(out_dir, history)
        epoch_bar.set_postfix(train=f"{train_loss['loss']:.4g}",
                              val=f"{row['val_loss']:.4g}" if val_loss else "-")
        log(json.dumps({k: row[k] for k in ("epoch", "train_loss", "val_loss", "lr",
                                             "epoch_seconds")}))
    summary = {
        "epochs": len(history), "best_loss": best,
        "best_epoch": next((r["epoch"] for r in reversed(history) if r["best"]), None),
        "final": history[-1] if history else None, **info,
    }
    write_json(out_dir / "summary.json", summary)
    return summary


# --------------------------------------------------------------------------------------------
# Synthetic data (tests, benchmarks, smoke runs)


@dataclasses.dataclass
class SyntheticTrajectory:
    """A SPEC-4-like trajectory (only what the featurizer reads): smooth random ball motions
    inside the standard jar, which moves on the standard circle. Not physical: for tests."""

    t: np.ndarray
    pos: np.ndarray
    offset: np.ndarray
    offset_vel: np.ndarray
    diss_pp_normal: np.ndarray
    diss_pp_tangential: np.ndarray
    diss_pw_normal: np.ndarray
    diss_pw_tangential: np.ndarray
    meta: dict[str, Any]


def synthetic_trajectory(n_samples: int = 64, n_particles: int = 8, *, dt: float = 1e-4,
                         radius: float = 0.005, frequency_hz: float = 5.0,
                         amplitude: float = 0.017, seed: int = 0) -> SyntheticTrajectory:
    """Balls wobbling (0.3 mm, 20-60 Hz) about fixed jar-frame centres while the jar circles.

    Half of the balls sit in a row on the floor (centre height just above R, so ball-wall edges
    come and go; neighbours 0.6-1.4 mm apart, so ball-ball edges too); the others float higher,
    spaced so that some pairs cross the ball-ball cutoff. Dissipation: random smooth, >= 0,
    first sample 0.
    """
    rng = np.random.default_rng(seed)
    t = np.arange(n_samples) * dt
    w = 2 * np.pi * frequency_hz
    offset = np.stack([amplitude * np.sin(w * t), 0 * t, amplitude * np.cos(w * t)], -1)
    offset_vel = np.stack([amplitude * w * np.cos(w * t), 0 * t, -amplitude * w * np.sin(w * t)],
                          -1)
    n_floor = (n_particles + 1) // 2
    centres = []
    x = -0.03
    for _ in range(n_floor):
        centres.append([x, radius + 1e-4, rng.uniform(-0.005, 0.005) * 0.2])
        x += 2 * radius + rng.uniform(0.6e-3, 1.4e-3)
    x = -0.025
    for _ in range(n_particles - n_floor):
        centres.append([x, 0.022 + rng.uniform(-1e-3, 1e-3), rng.uniform(-0.004, 0.004)])
        x += 2 * radius + rng.uniform(1.0e-3, 2.5e-3)
    centres = np.asarray(centres)
    amp = rng.uniform(1e-4, 3e-4, (n_particles, 3))
    freq = rng.uniform(20.0, 60.0, (n_particles, 3)) * 2 * np.pi
    phase = rng.uniform(0, 2 * np.pi, (n_particles, 3))
    wobble = amp * np.sin(freq * t[:, None, None] + phase)
    pos = centres[None] + offset[:, None, :] + wobble
    diss = [np.abs(rng.normal(0, 1e-5)) * (1 + np.sin(rng.uniform(50, 200) * t
                                                     + rng.uniform(0, 6))) for _ in range(4)]
    for d in diss:
        d[0] = 0.0
    meta = {"dt": dt, "ball_radius": radius, "n_balls": n_particles,
            "config": {"motion": {"kind": "circle", "rpm": 60.0 * frequency_hz,
                                  "amplitude": amplitude, "phase": 0.0}}}
    return SyntheticTrajectory(t=t, pos=pos, offset=offset, offset_vel=offset_vel,
                               diss_pp_normal=diss[0], diss_pp_tangential=diss[1],
                               diss_pw_normal=diss[2], diss_pw_tangential=diss[3], meta=meta)
