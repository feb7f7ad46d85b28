"""Benchmark: training throughput (samples/s), one device against data-parallel over D devices.

Synthetic normalised graphs of the standard case's shape (:func:`bench_train.synthetic_dataset`,
24 balls + wall, window 7), the same samples per step either way: one device packs
``batch`` graphs per step (:class:`sgn_jax.surrogate.train.BatchPacker`), D devices pack D
sub-batches of ``batch / D`` graphs (:class:`sgn_jax.surrogate.train.ShardedPacker`) and run
``make_train_step(..., sharding=DataParallel.over(D))``. Compile time apart.

On a CPU the devices are host devices (``XLA_FLAGS=--xla_force_host_platform_device_count=D``,
set by this script before JAX starts): they share the machine's cores, so the numbers say what
the data-parallel path costs, not what D accelerators would give.

    python benchmarks/bench_train_sharded.py --devices 2 --seconds 10
    python benchmarks/bench_train_sharded.py --out benchmarks/results/train_sharded.json

Prints one JSON line per device count (and writes them all to ``--out``).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path


def bench(n_devices: int, hidden: int, batch: int, mean_edges: float, seconds: float,
          n_particles: int = 24, window: int = 7) -> dict:
    import jax
    import jax.numpy as jnp
    import numpy as np
    from bench_train import synthetic_dataset, time_train_steps

    from sgn_jax.config import ModelConfig, TrainConfig
    from sgn_jax.surrogate.model import init_params, make_apply, make_model
    from sgn_jax.surrogate.train import (
        BatchPacker,
        DataParallel,
        ShardedPacker,
        TrainState,
        batch_edge_capacity,
        make_optimizer,
        make_train_step,
    )

    ds = synthetic_dataset(4096, n_particles, window, mean_edges)
    per_device = batch // n_devices
    cap = batch_edge_capacity(ds.edges_per_sample, per_device)
    packer = BatchPacker(ds, per_device, cap)
    model = make_model(ModelConfig(hidden=hidden))
    tcfg = TrainConfig(batch_size=batch)
    tx = make_optimizer(tcfg.lr_init)
    params = init_params(model, packer.make(np.arange(per_device)).graph, 0)
    state = TrainState(params=params, opt_state=tx.init(params), step=jnp.asarray(0, jnp.int64))
    strategy = None
    if n_devices > 1:
        strategy = DataParallel.over(n_devices)
        packer = ShardedPacker(packer, n_devices)
        state = strategy.replicate(jax.tree_util.tree_map(np.asarray, state))
    step = make_train_step(make_apply(model), tx, tcfg, window, sharding=strategy)
    plan = packer.plan(np.random.default_rng(1).permutation(len(ds)))
    count = (lambda g: len(g)) if strategy is None else (lambda g: sum(len(i) for i in g))
    compile_s, samples, steps, elapsed = time_train_steps(step, state, packer, plan, seconds,
                                                          count)
    return {"devices": n_devices, "platform": jax.devices()[0].platform, "hidden": hidden,
            "graphs_per_step": batch, "graphs_per_device": per_device,
            "edge_capacity_per_device": cap, "mean_edges_per_graph": mean_edges,
            "compile_s": round(compile_s, 2), "steps": steps,
            "samples_per_s": round(samples / elapsed, 1),
            "ms_per_step": round(1e3 * elapsed / steps, 2)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--devices", type=int, default=2, help="D: compare 1 and D devices")
    p.add_argument("--hidden", type=int, default=128)
    p.add_argument("--batch", type=int, default=32, help="graphs per step (a multiple of D)")
    p.add_argument("--edges", type=float, default=100.0, help="mean directed edges per graph")
    p.add_argument("--seconds", type=float, default=10.0, help="timed seconds per device count")
    p.add_argument("--out", type=Path, default=None, help="also write the rows as JSON here")
    args = p.parse_args()
    if args.batch % args.devices:
        p.error(f"--batch {args.batch} is not a multiple of --devices {args.devices}")

    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_force_host_platform_device_count" not in flags:
        os.environ["XLA_FLAGS"] = (
            f"{flags} --xla_force_host_platform_device_count={args.devices}").strip()
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import jax

    import sgn_jax  # noqa: F401  (enables x64 before any array is made)
    from sgn_jax.records.io_utils import machine_info

    if len(jax.devices()) < args.devices:
        p.error(f"{len(jax.devices())} devices, --devices {args.devices}")
    rows = [{"machine": machine_info()}]
    print(json.dumps(rows[0]), flush=True)
    for n in (1, args.devices):
        row = bench(n, args.hidden, args.batch, args.edges, args.seconds)
        print(json.dumps(row), flush=True)
        rows.append(row)
    one, many = rows[1]["samples_per_s"], rows[2]["samples_per_s"]
    rows.append({"speedup": round(many / one, 3)})
    print(json.dumps(rows[-1]))
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
