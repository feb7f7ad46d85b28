"""Benchmark: SGN training throughput (samples/s) on this machine, compile time apart.

Uses synthetic normalised graphs of the standard case's shape (24 balls + wall, window 7) with a
chosen mean number of directed edges per graph (ball-ball + ball-wall), packed exactly as in
training (:class:`sgn_jax.surrogate.train.BatchPacker`), and times the jitted training step.

    python benchmarks/bench_train.py                      # hidden 256 and 128, batch 32
    python benchmarks/bench_train.py --hidden 256 --batch 16 32 64 --edges 60 100 --seconds 20

Prints one JSON line per configuration and, with --markdown, the table that replaces the one of
docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

import sgn_jax  # noqa: F401  (enables x64 before any array is made)
from sgn_jax.config import ModelConfig, TrainConfig
from sgn_jax.records.io_utils import machine_info
from sgn_jax.surrogate.model import count_params, init_params, make_apply, make_model
from sgn_jax.surrogate.train import (
    BatchPacker,
    GraphDataset,
    TrainState,
    batch_edge_capacity,
    make_optimizer,
    make_train_step,
)


def synthetic_dataset(n_samples: int, n_particles: int, window: int, mean_edges: float,
                      seed: int = 0) -> GraphDataset:
    """Random normalised graphs; edges per graph ~ Poisson(mean_edges), 2/3 ball-ball."""
    rng = np.random.default_rng(seed)
    f = 7 * window
    n_edges = np.maximum(rng.poisson(mean_edges, n_samples), 0)
    total = int(n_edges.sum())
    return GraphDataset(
        node_features=rng.standard_normal((n_samples, n_particles + 1, f), np.float32),
        edge_offsets=np.concatenate([[0], np.cumsum(n_edges)]).astype(np.int64),
        edge_features=rng.standard_normal((total, 3), np.float32),
        edge_senders=rng.integers(0, n_particles + 1, total).astype(np.int32),
        edge_receivers=rng.integers(0, n_particles, total).astype(np.int32),
        edge_is_pp=rng.random(total) < 2 / 3,
        accel=rng.standard_normal((n_samples, n_particles, 3), np.float32),
        dissipation=rng.standard_normal(n_samples, np.float32),
        source=np.zeros(n_samples, np.int32), window_end=np.arange(n_samples))


def time_train_steps(step, state, packer, plan, seconds: float, count=len
                     ) -> tuple[float, int, int, float]:
    """Run ``step`` over ``plan``'s packed batches for ``seconds`` after one compiling call.

    ``count(group)`` is the samples of one planned step (``len`` for a ``BatchPacker`` plan; a
    sum over sub-batches for a ``ShardedPacker``). Returns ``(compile_s, samples, steps,
    elapsed_s)``.
    """
    import jax

    key = jax.random.PRNGKey(0)
    t0 = time.perf_counter()
    state, sums = step(state, packer.make(plan[0]), np.float32(1e-4), key)
    jax.block_until_ready(sums)
    compile_s = time.perf_counter() - t0

    samples, steps, i = 0, 0, 1
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        group = plan[i % len(plan)]
        state, sums = step(state, packer.make(group), np.float32(1e-4), key)
        samples += count(group)
        steps += 1
        i += 1
    jax.block_until_ready(state.params)
    return compile_s, samples, steps, time.perf_counter() - t0


def bench(hidden: int, batch: int, mean_edges: float, seconds: float, n_particles: int = 24,
          window: int = 7) -> dict:
    import jax.numpy as jnp

    ds = synthetic_dataset(4096, n_particles, window, mean_edges)
    cap = batch_edge_capacity(ds.edges_per_sample, batch)
    packer = BatchPacker(ds, batch, cap)
    model = make_model(ModelConfig(hidden=hidden))
    tcfg = TrainConfig(batch_size=batch)
    tx = make_optimizer(tcfg.lr_init)
    example = packer.make(np.arange(batch))
    params = init_params(model, example.graph, 0)
    state = TrainState(params=params, opt_state=tx.init(params), step=jnp.asarray(0, jnp.int64))
    step = make_train_step(make_apply(model), tx, tcfg, window)
    plan = packer.plan(np.random.default_rng(1).permutation(len(ds)))
    compile_s, samples, steps, elapsed = time_train_steps(step, state, packer, plan, seconds)
    rate = samples / elapsed
    return {"hidden": hidden, "batch_graphs": batch, "mean_edges_per_graph": mean_edges,
            "batch_edge_capacity": cap, "n_params": count_params(params),
            "compile_s": round(compile_s, 2), "steps": steps,
            "samples_per_s": round(rate, 1), "ms_per_step": round(1e3 * elapsed / steps, 2),
            "epoch_45000_s": round(45000 / rate, 1)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--hidden", type=int, nargs="+", default=[256, 128])
    p.add_argument("--batch", type=int, nargs="+", default=[32])
    p.add_argument("--edges", type=float, nargs="+", default=[100.0],
                   help="mean directed edges per graph (ball-ball + ball-wall)")
    p.add_argument("--seconds", type=float, default=20.0, help="timed seconds per configuration")
    p.add_argument("--markdown", action="store_true",
                   help="also print the table, to replace the one of docs/benchmarks.md")
    args = p.parse_args()

    machine = machine_info()
    print(json.dumps(machine))
    rows = []
    for hidden in args.hidden:
        for batch in args.batch:
            for edges in args.edges:
                row = bench(hidden, batch, edges, args.seconds)
                print(json.dumps(row), flush=True)
                rows.append(row)
    if args.markdown:
        lines = ["", "## SGN training throughput (`benchmarks/bench_train.py`)",
                 "", f"Machine: {machine['platform']}, {machine['cpu_count']} CPUs, backend "
                 f"{machine['backend']}, jax {machine['jax']}, commit {machine['commit']}. "
                 "Synthetic graphs of the standard case (24 balls + wall, window 7), edges per "
                 "graph ~ Poisson(mean), packed as in training; float32; compile time apart; "
                 f"{args.seconds:.0f} s timed per row; load average {machine['load_average']}.",
                 "", "| hidden | graphs/batch | mean edges/graph | edge capacity | params | "
                 "compile (s) | ms/step | samples/s | 45,000-sample epoch (s) |",
                 "|---|---|---|---|---|---|---|---|---|"]
        for r in rows:
            lines.append(f"| {r['hidden']} | {r['batch_graphs']} | {r['mean_edges_per_graph']:.0f} "
                         f"| {r['batch_edge_capacity']} | {r['n_params']:,} | {r['compile_s']} | "
                         f"{r['ms_per_step']} | {r['samples_per_s']} | {r['epoch_45000_s']} |")
        print("\n".join(lines))


if __name__ == "__main__":
    main()
