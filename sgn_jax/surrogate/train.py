"""SGN training: precomputed graphs, packed static-shape batches, optax Adam, orbax checkpoints.

Pipeline (:func:`train`):

1. Every trajectory is split chronologically (:func:`split_window_ends`) and each window is
   featurized once with :func:`sgn_jax.surrogate.graph.build_graph` (vmapped, jitted) into a compact
   numpy :class:`GraphDataset` (real edges only). An edge-capacity overflow is an error.
2. Normalisation statistics come from the training split (:mod:`sgn_jax.surrogate.normalization`);
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

import dataclasses
import math
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import flax.struct
import jax
import jax.numpy as jnp
import jraph
import numpy as np
import optax

from sgn_jax.errors import SGNJaxError
from sgn_jax.surrogate.graph import (
    GraphError,
    valid_window_ends,
    velocity_columns,
)
from sgn_jax.surrogate.normalization import NormStats, compute_norm_stats, encode_velocities

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


class ShardedPacker:
    """Packs steps of ``n_shards`` static-shape sub-batches, one per device (data parallel).

    ``base`` packs each sub-batch (its ``max_graphs`` and ``edge_capacity`` are per device).
    :meth:`plan` packs greedily as :meth:`BatchPacker.plan` and groups ``n_shards`` consecutive
    sub-batches into one step (the last step's missing sub-batches are empty: every graph slot
    masked); :meth:`make` stacks them on a new leading axis of length ``n_shards``, the axis
    that :func:`make_train_step` splits over the devices. A step holds the samples of all its
    sub-batches, up to ``n_shards * base.max_graphs`` graphs.
    """

    def __init__(self, base: BatchPacker, n_shards: int):
        if n_shards < 1:
            raise ValueError(f"n_shards must be >= 1, got {n_shards}")
        self.base, self.n_shards = base, int(n_shards)
        self.ds = base.ds

    def plan(self, order: np.ndarray) -> list[list[np.ndarray]]:
        subs = self.base.plan(order)
        empty = np.zeros(0, np.int64)
        steps = [subs[i:i + self.n_shards] for i in range(0, len(subs), self.n_shards)]
        return [s + [empty] * (self.n_shards - len(s)) for s in steps]

    def make(self, group: Sequence[np.ndarray]) -> Batch:
        if len(group) != self.n_shards:
            raise ValueError(f"a step has {self.n_shards} sub-batches, got {len(group)}")
        parts = [self.base.make(np.asarray(idx, np.int64)) for idx in group]
        return jax.tree_util.tree_map(lambda *a: np.stack(a), *parts)

    def batches(self, order: np.ndarray) -> Iterator[Batch]:
        for group in self.plan(order):
            yield self.make(group)


def step_samples(group: np.ndarray | Sequence[np.ndarray]) -> int:
    """Samples in one planned step of :meth:`BatchPacker.plan` or :meth:`ShardedPacker.plan`."""
    if isinstance(group, np.ndarray):
        return len(group)
    return sum(len(idx) for idx in group)


# --------------------------------------------------------------------------------------------
# Devices

BATCH_AXIS = "batch"


@dataclasses.dataclass(frozen=True)
class DataParallel:
    """Data-parallel placement over a 1-D :class:`jax.sharding.Mesh` (axis ``"batch"``).

    Parameters and optimiser state are replicated on every device; a stacked batch of
    :class:`ShardedPacker` (leading axis = one sub-batch per device) is split over the devices.
    Build one with :meth:`over`.
    """

    mesh: jax.sharding.Mesh

    @classmethod
    def over(cls, devices: int | Sequence[Any] | None = None) -> DataParallel:
        """Over the first ``devices`` local devices (an int), the given devices, or all."""
        available = jax.local_devices()
        if devices is None:
            chosen = available
        elif isinstance(devices, int):
            if not 1 <= devices <= len(available):
                raise ValueError(f"asked for {devices} devices, {len(available)} available "
                                 f"({available[0].platform}); on CPU set XLA_FLAGS="
                                 "--xla_force_host_platform_device_count=N before JAX starts")
            chosen = available[:devices]
        else:
            chosen = list(devices)
        return cls(jax.sharding.Mesh(np.array(chosen), (BATCH_AXIS,)))

    @property
    def n_devices(self) -> int:
        return int(self.mesh.devices.size)

    @property
    def replicated(self) -> jax.sharding.NamedSharding:
        return jax.sharding.NamedSharding(self.mesh, jax.sharding.PartitionSpec())

    @property
    def split(self) -> jax.sharding.NamedSharding:
        """Leading axis split over the devices (stacked batches)."""
        return jax.sharding.NamedSharding(self.mesh, jax.sharding.PartitionSpec(BATCH_AXIS))

    def replicate(self, tree: Any) -> Any:
        """``tree`` (parameters, optimiser or train state) copied onto every device."""
        return jax.device_put(tree, self.replicated)

    def shard_batch(self, batch: Batch) -> Batch:
        """A stacked batch (leading axis ``n_devices``) with sub-batch d on device d."""
        return jax.device_put(batch, self.split)


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


def _set_lr(opt_state: Any, lr: jax.Array) -> Any:
    return opt_state._replace(
        hyperparams={**opt_state.hyperparams, "learning_rate": jnp.asarray(lr, jnp.float32)})


def make_train_step(apply: Callable, tx: optax.GradientTransformation, train_cfg: Any,
                    window: int, sharding: DataParallel | None = None) -> Callable:
    """Jitted ``step(state, batch, lr, key) -> (state, sums)``; ``sums`` as in :func:`loss_sums`.

    ``sharding`` None: one device, ``batch`` one :class:`Batch` of :class:`BatchPacker`.

    ``sharding`` a :class:`DataParallel` over D devices: ``batch`` a stacked batch of a
    :class:`ShardedPacker` (leading axis D), sub-batch d on device d; ``state`` replicated
    (:meth:`DataParallel.replicate`). Each device computes the summed losses of its sub-batch
    and their gradients, scaled by the step's total counts (summed over the devices first, so
    the loss is the mean over all the step's real components and graphs, as on one device);
    the gradients and sums are summed over the devices (``psum``) and every device applies the
    same optimiser update (the parameters stay replicated). The update equals the one-device update on a batch of the same
    samples up to float32 summation order; with ``noise_std > 0`` device d draws its noise
    with ``fold_in(key, d)`` (same distribution, other numbers than one device).
    """
    alpha, delta, noise = train_cfg.node_loss_weight, train_cfg.huber_delta, train_cfg.noise_std
    beta = train_cfg.global_loss_weight

    def scaled_loss(params, batch, key, node_count, graph_count):
        if noise > 0:
            batch = batch.replace(graph=add_velocity_noise(batch.graph, key, noise, window))
        sums = loss_sums(apply, params, batch, delta)
        node = sums[0] / jnp.maximum(node_count, 1.0)
        glob = sums[2] / jnp.maximum(graph_count, 1.0)
        return alpha * node + beta * glob, jnp.stack(sums)

    def update(state: TrainState, grads: Any, lr: jax.Array) -> TrainState:
        opt_state = _set_lr(state.opt_state, lr)
        updates, opt_state = tx.update(grads, opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        return TrainState(params=params, opt_state=opt_state, step=state.step + 1)

    if sharding is None:
        def loss_fn(params, batch, key):
            if noise > 0:
                batch = batch.replace(graph=add_velocity_noise(batch.graph, key, noise, window))
            sums = loss_sums(apply, params, batch, delta)
            node = sums[0] / jnp.maximum(sums[1], 1.0)
            glob = sums[2] / jnp.maximum(sums[3], 1.0)
            return alpha * node + beta * glob, jnp.stack(sums)

        def step(state: TrainState, batch: Batch, lr: jax.Array, key: jax.Array):
            grads, sums = jax.grad(loss_fn, has_aux=True)(state.params, batch, key)
            return update(state, grads, lr), sums

        return jax.jit(step, donate_argnums=(0,))

    P = jax.sharding.PartitionSpec

    def local_step(state: TrainState, batch: Batch, lr: jax.Array, key: jax.Array):
        batch = jax.tree_util.tree_map(lambda a: a[0], batch)  # this device's sub-batch
        key = jax.random.fold_in(key, jax.lax.axis_index(BATCH_AXIS))
        particle = batch.graph.nodes["particle"].astype(jnp.float32)
        node_count = jax.lax.psum(3.0 * jnp.sum(particle), BATCH_AXIS)
        graph_count = jax.lax.psum(jnp.sum(batch.graph_mask.astype(jnp.float32)), BATCH_AXIS)
        # The parameters are replicated (device-invariant) and the loss varies per device, so
        # shard_map inserts an implicit pvary whose transpose is a psum: the gradient comes out
        # already summed over the devices (a psum here would count it D times).
        grads, sums = jax.grad(scaled_loss, has_aux=True)(state.params, batch, key,
                                                           node_count, graph_count)
        sums = jax.lax.psum(sums, BATCH_AXIS)
        return update(state, grads, lr), sums

    sharded = jax.shard_map(local_step, mesh=sharding.mesh,
                            in_specs=(P(), P(BATCH_AXIS), P(), P()), out_specs=(P(), P()))
    rep, split = sharding.replicated, sharding.split
    return jax.jit(sharded, donate_argnums=(0,), in_shardings=(rep, split, rep, rep),
                   out_shardings=(rep, rep))


def make_eval_step(apply: Callable, train_cfg: Any,
                   sharding: DataParallel | None = None) -> Callable:
    """Jitted ``eval(params, batch) -> sums`` (no noise). With ``sharding``, ``batch`` is a
    stacked batch of a :class:`ShardedPacker` and the sums are summed over the devices."""
    delta = train_cfg.huber_delta
    if sharding is None:
        return jax.jit(lambda params, batch: jnp.stack(loss_sums(apply, params, batch, delta)))
    P = jax.sharding.PartitionSpec

    def local(params, batch):
        batch = jax.tree_util.tree_map(lambda a: a[0], batch)
        return jax.lax.psum(jnp.stack(loss_sums(apply, params, batch, delta)), BATCH_AXIS)

    sharded = jax.shard_map(local, mesh=sharding.mesh, in_specs=(P(), P(BATCH_AXIS)),
                            out_specs=P())
    return jax.jit(sharded, in_shardings=(sharding.replicated, sharding.split),
                   out_shardings=sharding.replicated)


def losses_from_sums(sums: np.ndarray, alpha: float, beta: float = 1.0) -> dict[str, float]:
    """Exact means over all real components / graphs: node, global and total loss."""
    node = float(sums[0] / max(sums[1], 1.0))
    glob = float(sums[2] / max(sums[3], 1.0))
    return {"loss": alpha * node + beta * glob, "node": node, "global": glob}


def evaluate(eval_step: Callable, params: Any, packer: BatchPacker | ShardedPacker,
             alpha: float, beta: float = 1.0) -> dict[str, float]:
    """Loss over a whole dataset, in chronological order (weights as in the training loss)."""
    total = jnp.zeros(4, jnp.float32)
    for batch in packer.batches(np.arange(len(packer.ds))):
        total = total + eval_step(params, batch)
    return losses_from_sums(np.asarray(total, np.float64), alpha, beta)


# --------------------------------------------------------------------------------------------
# Metrics files


# --------------------------------------------------------------------------------------------
# The training loop


class TrainingError(SGNJaxError, RuntimeError):
    """A training run cannot start or continue (inconsistent data, config or output dir)."""


# --------------------------------------------------------------------------------------------
# Synthetic data (tests, benchmarks, smoke runs)


