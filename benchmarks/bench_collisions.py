"""The collision ledger's cost: DEM steps per second with and without it, on one core.

The standard case (24 balls, 300 rpm), a settled bed after 0.05 s of motion (seed 0), advanced
``--steps`` DEM steps by the jitted scan with the ledger off (``collision_capacity = 0``) and
on; the timings alternate, best of ``--repeats`` each, compile time apart. The same for the
rollouts of the shipped contact models ``contact``, ``contact_rebound`` (2e-4 s steps) and
``contact_collisions`` (1e-4 s), collisions off / on, ``--rollout-steps`` steps each
(benchmarks/bench_surrogate_collisions.py).

    taskset -c 0 python benchmarks/bench_collisions.py [--steps 50000] [--markdown docs/benchmarks.md]

Writes JSON to --out; prints a markdown table (or replaces it in --markdown).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time

import jax

import sgn_jax
from sgn_jax.config import builtin_config_path, load_config
from sgn_jax.dem.engine import init_state, make_advance
from sgn_jax.pipelines.dem_run import initial_state, setup_from_config
from sgn_jax.records.io_utils import git_commit, machine_info, write_json

CAP = 8192  # events the buffer holds: more than the timed steps close
MARKER = "collision-ledger-cost"


def _best(fn, repeats: int) -> float:
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        best = min(best, time.perf_counter() - t0)
    return best


def dem_rows(steps: int, repeats: int) -> list[dict]:
    cfg = load_config(builtin_config_path("emax_300rpm"))
    setup = setup_from_config(cfg)
    state = initial_state(setup, seed=0)
    advance = make_advance(setup.spec, setup.jar.wall_fn)
    state = advance(setup.params, state, int(-state.step))
    state = advance(setup.params, state, 500 * setup.substeps)
    runs = {}
    for capacity in (0, CAP):
        spec = dataclasses.replace(setup.spec, collision_capacity=capacity)
        start = init_state(spec, setup.params, state.pos, state.vel, state.omega,
                           step=int(state.step))
        start = start.replace(pw_history=state.pw_history, pp_history=state.pp_history,
                              pairs=state.pairs)
        adv = make_advance(spec, setup.jar.wall_fn)
        t0 = time.perf_counter()
        compiled = adv.lower(setup.params, start, steps).compile()
        runs[capacity] = (compiled, start, time.perf_counter() - t0)
    best = {c: float("inf") for c in runs}
    for _ in range(repeats):  # alternate, so that a busy spell hits both
        for c, (compiled, start, _) in runs.items():
            best[c] = min(best[c], _best(lambda c_=compiled, s=start: c_(setup.params, s), 1))
    events = int(runs[CAP][0](setup.params, runs[CAP][1]).collisions.buffer.count)
    off, on = best[0], best[CAP]
    return [{"what": "DEM, standard case", "steps": steps, "off_s": off, "on_s": on,
             "off_steps_per_s": steps / off, "on_steps_per_s": steps / on,
             "slowdown": on / off - 1, "compile_off_s": runs[0][2],
             "compile_on_s": runs[CAP][2], "events": events}]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=50_000)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--rollout-steps", type=int, default=5000)
    parser.add_argument("--out", default="benchmarks/results/bench_collisions.json")
    parser.add_argument("--markdown", default=None,
                        help="replace the table between this script's markers in this file")
    args = parser.parse_args()
    rows = dem_rows(args.steps, args.repeats)
    from bench_surrogate_collisions import rollout_cost  # this folder is on sys.path

    for name in ("contact", "contact_rebound", "contact_collisions"):
        r = rollout_cost(args.rollout_steps, args.repeats, checkpoint=name)
        rows.append({"what": f"`{name}` rollout, standard case", "steps": r["steps"],
                     "off_s": r["ms_per_step_off"] * 1e-3 * r["steps"],
                     "on_s": r["ms_per_step_on"] * 1e-3 * r["steps"],
                     "off_steps_per_s": 1e3 / r["ms_per_step_off"],
                     "on_steps_per_s": 1e3 / r["ms_per_step_on"], "slowdown": r["slowdown"],
                     "compile_off_s": r["compile_s_off"], "compile_on_s": r["compile_s_on"],
                     "events": r["events"]})
    machine = {**machine_info(), "affinity": sorted(os.sched_getaffinity(0))}
    result = {"benchmark": "collision_ledger_cost", "commit": git_commit(),
              "sgn_jax": sgn_jax.__version__, "machine": machine, "rows": rows}
    write_json(args.out, result)
    lines = [f"Commit {result['commit']}, jax {machine['jax']}, affinity {machine['affinity']} "
             f"(`{args.out}`):", "",
             "| run | steps timed | ledger off (steps/s) | ledger on (steps/s) | slowdown | "
             "compile off / on (s) | events |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['what']} | {r['steps']:,} | {r['off_steps_per_s']:,.0f} | "
                     f"{r['on_steps_per_s']:,.0f} | {100 * r['slowdown']:+.1f} % | "
                     f"{r['compile_off_s']:.1f} / {r['compile_on_s']:.1f} | {r['events']} |")
    table = "\n".join(lines)
    print(json.dumps(rows))
    print(table)
    if args.markdown:
        from markdown_section import replace_section  # this folder is on sys.path

        replace_section(args.markdown, MARKER, table)


if __name__ == "__main__":
    main()
