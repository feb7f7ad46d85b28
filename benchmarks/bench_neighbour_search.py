"""Benchmark: one Verlet-list build, all pairs (O(N^2)) against the cell list (O(N)).

Balls of 6 mm diameter are placed without overlap by random sequential addition in a cube
sized for the volume fraction (default 0.3), the skin is the DEM's default 1 mm and the list
has the engine's default 8 * N / 2 slots. Each builder is jitted and compiled apart; the time
is the median of repeated warm calls. The cell grid comes from ``cell_grid_for`` over the cube.

Prints a Markdown table (N, all-pairs us, cells us, ratio) with the machine and commit.

Usage: taskset -c 1 python benchmarks/bench_neighbour_search.py [--fraction 0.3] [--reach 1]
       [--repeats 50] [--sizes 24 50 100 220 500 1000]
"""

from __future__ import annotations

import argparse
import functools
import math
import time

import jax
import jax.numpy as jnp
import numpy as np

import sgn_jax  # noqa: F401  (enables x64)
from sgn_jax.dem.cells import build_pairs_all, build_pairs_cells, cell_grid_for
from sgn_jax.records.io_utils import machine_info

RADIUS = 0.003
SKIN = 0.001
SLOTS_PER_BALL = 8  # DEMSpec.neighbour_capacity's default


def packed_balls(n: int, fraction: float, seed: int = 0) -> tuple[np.ndarray, float]:
    """N non-overlapping balls (random sequential addition) with centres in a cube [0, side)^3 whose
    volume makes the balls fill ``fraction`` of it."""
    side = (n * 4 / 3 * math.pi * RADIUS**3 / fraction) ** (1 / 3)
    rng = np.random.default_rng(seed)
    pos = np.empty((n, 3))
    placed = 0
    while placed < n:
        x = rng.uniform(0.0, side, 3)
        if placed == 0 or np.min(np.sum((pos[:placed] - x) ** 2, axis=1)) >= (2 * RADIUS) ** 2:
            pos[placed] = x
            placed += 1
    return pos, side


def compiled(fn, *args):
    """(the compiled fn, compile s)."""
    start = time.perf_counter()
    out = jax.jit(fn).lower(*args).compile()
    return out, time.perf_counter() - start


def median_us(fn, *args, repeats: int) -> float:
    """Median warm call, us."""
    jax.block_until_ready(fn(*args))
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - start)
    return float(np.median(times)) * 1e6


def bench(n: int, fraction: float, reach: int, repeats: int) -> dict:
    pos_np, side = packed_balls(n, fraction)
    pos = jnp.asarray(pos_np)
    radius, skin, origin = jnp.asarray(RADIUS), jnp.asarray(SKIN), jnp.zeros(3)
    n_slots = max(1, min(n * (n - 1) // 2, math.ceil(SLOTS_PER_BALL * n / 2)))
    grid = cell_grid_for([0.0, 0.0, 0.0], [side] * 3, 2 * RADIUS + SKIN, RADIUS, n, reach=reach)
    all_fn, all_compile = compiled(functools.partial(build_pairs_all, n_slots), pos, radius, skin)
    cells_fn, cells_compile = compiled(functools.partial(build_pairs_cells, grid, n_slots),
                                       pos, radius, skin, origin)
    ref = all_fn(pos, radius, skin)
    got = cells_fn(pos, radius, skin, origin)
    same = all(np.array_equal(a, b) for a, b in zip(ref, got[:4], strict=True))
    if not same or bool(got[4]) or int(ref[3]) > n_slots:
        raise RuntimeError(f"N={n}: the cell list disagrees with all pairs or overflowed")
    return {"n": n, "candidates": int(ref[3]), "dims": grid.dims,
            "capacity": grid.cell_capacity,
            "all_us": median_us(all_fn, pos, radius, skin, repeats=repeats),
            "cells_us": median_us(cells_fn, pos, radius, skin, origin, repeats=repeats),
            "all_compile_s": all_compile, "cells_compile_s": cells_compile}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--fraction", type=float, default=0.3)
    parser.add_argument("--reach", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=50)
    parser.add_argument("--sizes", type=int, nargs="+", default=[24, 50, 100, 220, 500, 1000])
    args = parser.parse_args()

    rows = [bench(n, args.fraction, args.reach, args.repeats) for n in args.sizes]
    machine = machine_info()
    print(f"## Neighbour search: all pairs vs cell list (6 mm balls, volume fraction "
          f"{args.fraction}, skin {SKIN * 1e3:g} mm, reach {args.reach})\n")
    print("| N | candidates | cells (dims, capacity) | all-pairs us | cells us | "
          "all-pairs / cells | compile all-pairs / cells s |")
    print("|---:|---:|---|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {r['n']} | {r['candidates']} | {'x'.join(map(str, r['dims']))}, "
              f"{r['capacity']} | {r['all_us']:.1f} | {r['cells_us']:.1f} | "
              f"{r['all_us'] / r['cells_us']:.2f} | {r['all_compile_s']:.2f} / "
              f"{r['cells_compile_s']:.2f} |")
    print(f"\nMedian of {args.repeats} warm calls of one jitted build (compile apart). "
          f"Commit {machine['commit']}, {machine['processor']}, {machine['cores_used']} of "
          f"{machine['cpu_count']} cores, load {machine['load_average']}, jax {machine['jax']} "
          f"({machine['backend']}), {machine['date']}.")


if __name__ == "__main__":
    main()
