"""The DEM's cost against the ball count: one core, 6 mm steel balls in the Emax jar, 300 rpm.

For each ball count (24 to 220 balls of 6 mm, 1.7 % to 20 % of the jar's volume) the balls are
placed (seed 0), settled for ``--settle`` s and moved for ``--warm`` s; then ``--steps`` DEM
steps of the jitted scan (collision ledger on, as ``sgn-jax dem`` runs) are timed, best of
``--repeats``, compile time apart. The table gives the time per step, per simulated second, per
ball-step and per contact-step (the mean number of touching ball-ball and ball-wall contacts
over the timed steps, counted at its end and start), and the neighbour list's rebuilds, for
each neighbour search (``--searches``: all pairs, the cell list; the same run either way).

    taskset -c 0 python benchmarks/bench_charge_scaling.py [--markdown docs/benchmarks.md]

Writes JSON to --out; prints a markdown table (or replaces it in --markdown).
"""

from __future__ import annotations

import argparse
import json
import os
import time

import jax
import numpy as np

import sgn_jax
from sgn_jax.config import builtin_config_path, load_config, replace_section
from sgn_jax.dem.engine import contact_overlaps, make_advance
from sgn_jax.pipelines.dem_run import initial_state, setup_from_config
from sgn_jax.records.io_utils import git_commit, machine_info, write_json

MARKER = "charge-scaling"
COUNTS = (24, 50, 100, 150, 220)


def _contacts(setup, state) -> int:
    ov = contact_overlaps(setup.spec, setup.jar.wall_fn, setup.params, state)
    return int(np.sum(np.asarray(ov.pp_overlap) > 0) + np.sum(np.asarray(ov.pw_overlap) > 0))


def row(count: int, radius: float, steps: int, repeats: int, settle: float, warm: float,
        search: str) -> dict:
    cfg = load_config(builtin_config_path("emax_300rpm"))
    cfg = replace_section(cfg, "balls", count=count, radius=radius)
    cfg = replace_section(cfg, "dem", settle_time=settle, neighbour_search=search)
    setup = setup_from_config(cfg)
    state = initial_state(setup, seed=0)
    advance = make_advance(setup.spec, setup.jar.wall_fn)
    state = advance(setup.params, state, int(-state.step))              # settle
    state = advance(setup.params, state, int(round(warm / setup.dt_dem)))
    t0 = time.perf_counter()
    compiled = advance.lower(setup.params, state, steps).compile()
    compile_s = time.perf_counter() - t0
    best, final = float("inf"), None
    for _ in range(repeats):
        t0 = time.perf_counter()
        final = jax.block_until_ready(compiled(setup.params, state))
        best = min(best, time.perf_counter() - t0)
    contacts = 0.5 * (_contacts(setup, state) + _contacts(setup, final))
    per_step = best / steps
    return {"balls": count, "search": search, "radius_m": radius, "dt_dem_s": setup.dt_dem, "steps": steps,
            "us_per_step": 1e6 * per_step, "s_per_simulated_s": per_step / setup.dt_dem,
            "ns_per_ball_step": 1e9 * per_step / count,
            "contacts": contacts,
            "ns_per_contact_step": 1e9 * per_step / max(contacts, 1.0),
            "rebuilds_per_1000_steps": 1000 * int(final.pairs.rebuilds - state.pairs.rebuilds)
            / steps,
            "pair_slots": setup.spec.n_pair_slots, "compile_s": compile_s,
            "overflow": bool(final.pairs.overflow)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--counts", type=int, nargs="+", default=list(COUNTS))
    parser.add_argument("--radius", type=float, default=0.003)
    parser.add_argument("--steps", type=int, default=20_000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--settle", type=float, default=0.1)
    parser.add_argument("--warm", type=float, default=0.02)
    parser.add_argument("--searches", nargs="+", default=["all_pairs", "cells"],
                        choices=("all_pairs", "cells"))
    parser.add_argument("--out", default="benchmarks/results/bench_charge_scaling.json")
    parser.add_argument("--markdown", default=None,
                        help="replace the table between this script's markers in this file")
    args = parser.parse_args()
    rows = []
    for count in args.counts:
        for search in args.searches:
            rows.append(row(count, args.radius, args.steps, args.repeats, args.settle,
                            args.warm, search))
            print(json.dumps(rows[-1]), flush=True)
    machine = {**machine_info(), "affinity": sorted(os.sched_getaffinity(0))}
    result = {"benchmark": "charge_scaling", "commit": git_commit(),
              "sgn_jax": sgn_jax.__version__, "machine": machine, "rows": rows}
    write_json(args.out, result)
    lines = [f"Commit {result['commit']}, jax {machine['jax']}, affinity {machine['affinity']}, "
             f"balls of radius {args.radius * 1e3:g} mm, 300 rpm (`{args.out}`):", "",
             "| balls | search | dt_dem (s) | us / step | s / simulated s | contacts | "
             "ns / ball-step | ns / contact-step | rebuilds / 1000 steps | compile (s) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['balls']} | {r['search']} | {r['dt_dem_s']:.3g} | "
                     f"{r['us_per_step']:.1f} | "
                     f"{r['s_per_simulated_s']:.1f} | {r['contacts']:.0f} | "
                     f"{r['ns_per_ball_step']:.0f} | {r['ns_per_contact_step']:.0f} | "
                     f"{r['rebuilds_per_1000_steps']:.1f} | {r['compile_s']:.1f} |")
    table = "\n".join(lines)
    print(table)
    if args.markdown:
        from markdown_section import replace_section  # this folder is on sys.path

        replace_section(args.markdown, MARKER, table)


if __name__ == "__main__":
    main()
