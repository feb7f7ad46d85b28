"""DEM throughput for the standard case (24 balls, Emax-like jar, 300 rpm).

Measures DEM steps per second of one run and of vmapped batches, for each pair formulation
("neighbour" Verlet list, "pairs" static i<j list, "nxn" dense) and float64 / float32, with
the compile time reported apart. The state is a settled bed (seed 0, 0.5 s at rest) after
0.05 s of motion, so contacts and Verlet-list rebuilds are those of a real run.

Run pinned to one core (the target is >= 50,000 steps/s for one float64 run on one core):

    taskset -c 0 python benchmarks/bench_dem.py [--steps 50000] [--batches 8,32]

Prints a markdown table (for docs/benchmarks.md) and writes JSON to --out.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import sgn_jax
from sgn_jax.config import builtin_config_path, load_config
from sgn_jax.dem.engine import init_state, make_advance
from sgn_jax.pipelines.dem_run import initial_state, setup_from_config
from sgn_jax.records.io_utils import git_commit, write_json


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def _time(fn, repeats: int) -> tuple[float, float]:
    """Best wall and best CPU (process) seconds of ``fn()`` over ``repeats`` calls."""
    best_wall, best_cpu = float("inf"), float("inf")
    for _ in range(repeats):
        w0, c0 = time.perf_counter(), time.process_time()
        jax.block_until_ready(fn())
        best_wall = min(best_wall, time.perf_counter() - w0)
        best_cpu = min(best_cpu, time.process_time() - c0)
    return best_wall, best_cpu


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=50_000, help="DEM steps per timing")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--batches", default="8,32", help="vmapped batch sizes (comma list)")
    parser.add_argument("--modes", default="neighbour,pairs,nxn")
    parser.add_argument("--dtypes", default="float64,float32")
    parser.add_argument("--out", default="benchmarks/results/bench_dem.json")
    args = parser.parse_args()

    cfg = load_config(builtin_config_path("emax_300rpm"))
    setup = setup_from_config(cfg)
    t0 = time.perf_counter()
    state = initial_state(setup, seed=0)
    advance = make_advance(setup.spec, setup.jar.wall_fn)
    state = advance(setup.params, state, int(-state.step))  # settle 0.5 s
    state = advance(setup.params, state, 500 * setup.substeps)  # 0.05 s of motion
    jax.block_until_ready(state.pos)
    prep_s = time.perf_counter() - t0

    rows = []
    for dtype in args.dtypes.split(","):
        for mode in args.modes.split(","):
            spec = dataclasses.replace(setup.spec, pair_mode=mode, dtype=dtype,
                                       collision_capacity=0)  # the ledger: bench_collisions.py
            start = init_state(spec, setup.params, state.pos, state.vel, state.omega,
                               step=int(state.step))
            start = start.replace(pw_history=state.pw_history.astype(dtype))
            adv = make_advance(spec, setup.jar.wall_fn)
            c0 = time.perf_counter()
            compiled = adv.lower(setup.params, start, args.steps).compile()
            compile_s = time.perf_counter() - c0
            wall, cpu = _time(lambda c=compiled, s=start: c(setup.params, s), args.repeats)
            rows.append({"mode": mode, "dtype": dtype, "batch": 1, "compile_s": compile_s,
                         "steps_per_s_wall": args.steps / wall,
                         "steps_per_s_cpu": args.steps / cpu,
                         "system_steps_per_s_wall": args.steps / wall})
            print(json.dumps(rows[-1]))
            for batch in [int(b) for b in args.batches.split(",") if b]:
                # Independent systems: different motion phases of the same settled bed.
                phases = jnp.linspace(0.0, 2 * np.pi, batch, endpoint=False)
                params_b = jax.vmap(
                    lambda ph: setup.params.replace(
                        motion=setup.params.motion.replace(phase=ph)))(phases)
                states_b = jax.tree_util.tree_map(
                    lambda x, b=batch: jnp.broadcast_to(x, (b,) + jnp.shape(x)), start)
                steps_b = max(args.steps // 10, 1000)
                fn = jax.jit(jax.vmap(lambda p, s, n=steps_b, a=adv: a(p, s, n)))
                c0 = time.perf_counter()
                compiled_b = fn.lower(params_b, states_b).compile()
                compile_b = time.perf_counter() - c0
                wall, cpu = _time(lambda c=compiled_b, p=params_b, s=states_b: c(p, s),
                                  args.repeats)
                rows.append({"mode": mode, "dtype": dtype, "batch": batch,
                             "compile_s": compile_b, "steps_per_s_wall": steps_b / wall,
                             "steps_per_s_cpu": steps_b / cpu,
                             "system_steps_per_s_wall": batch * steps_b / wall})
                print(json.dumps(rows[-1]))

    machine = {
        "platform": platform.platform(), "cpu": _cpu_model(), "cpu_count": os.cpu_count(),
        "affinity": sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
        "python": platform.python_version(), "jax": jax.__version__,
    }
    result = {"benchmark": "dem_standard_case", "commit": git_commit(),
              "sgn_jax": sgn_jax.__version__, "machine": machine, "steps": args.steps,
              "state_preparation_s": prep_s, "rows": rows}
    write_json(args.out, result)

    print(f"\nCommit {result['commit']}, {machine['cpu']}, {machine['cpu_count']} CPUs, "
          f"affinity {machine['affinity']}, jax {machine['jax']}, {args.steps} steps per timing\n")
    print("| pair mode | dtype | batch | compile (s) | steps/s per system (wall) | "
          "steps/s (CPU time) | system-steps/s |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['mode']} | {r['dtype']} | {r['batch']} | {r['compile_s']:.1f} | "
              f"{r['steps_per_s_wall']:,.0f} | {r['steps_per_s_cpu']:,.0f} | "
              f"{r['system_steps_per_s_wall']:,.0f} |")


if __name__ == "__main__":
    main()
