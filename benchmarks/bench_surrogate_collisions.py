"""The surrogate collision ledger's cost: the shipped contact model's rollout with it off and on.

The standard case (24 balls, 300 rpm, the model's step 2e-4 s), the first window of a DEM
packing (seed 0), advanced ``--steps`` surrogate steps by the jitted rollout in the model's
single-rollout form (as ``run_rollout``) with ``collisions`` off and on; the timings
alternate, best of ``--repeats`` each, compile time apart. Also checks that the events add up
to the model's ledger.

    taskset -c 0 python benchmarks/bench_surrogate_collisions.py [--steps 5000] [--repeats 3]

Prints one JSON line.
"""

from __future__ import annotations

import argparse
import json
import time

import jax
import numpy as np

import sgn_jax as sj
from sgn_jax.pipelines.configure import graph_spec_from_config, surrogate_walls_from_config
from sgn_jax.surrogate.rollout import init_state, make_rollout_advance, single_rollout_model


def rollout_cost(steps: int = 5000, repeats: int = 3, capacity: int = 20000,
                 checkpoint: str | None = None) -> dict:
    """ms per step with the ledger off and on (best of ``repeats``), the slowdown and the
    events' closure against the model's ledger, for the shipped model ``checkpoint`` (default:
    the default model)."""
    trained = sj.load_surrogate(checkpoint)
    cfg = sj.at_surrogate_step(sj.load_config("emax_300rpm"), trained)
    packings = sj.make_packings(cfg, seeds=[0])
    window = jax.tree_util.tree_map(lambda a: np.asarray(a)[0], packings.windows)
    spec = graph_spec_from_config(cfg, n_particles=int(cfg.balls.count))
    sdf, query = surrogate_walls_from_config(cfg)
    motion = sj.motion_from_config(cfg.motion)
    model, _ = single_rollout_model(trained.model)
    t0 = float(packings.t0)
    runs = {}
    for mode, on in (("off", False), ("on", True)):
        advance = make_rollout_advance(spec, model, steps, 10, query=query, snap_back=True,
                                       checkpoint_steps=steps, collisions=on,
                                       collision_capacity=capacity)
        state = init_state(window, motion, t0, spec.dt, capacity if on else 0)
        start = time.perf_counter()
        compiled = advance.lower(trained.params, None, state, motion, sdf, t0).compile()
        runs[mode] = (compiled, state, time.perf_counter() - start)
    best = {mode: float("inf") for mode in runs}
    result = None
    for _ in range(repeats):
        for mode, (compiled, state, _) in runs.items():
            start = time.perf_counter()
            out = jax.block_until_ready(compiled(trained.params, None, state, motion, sdf, t0))
            best[mode] = min(best[mode], time.perf_counter() - start)
            if mode == "on":
                result = out
    events = jax.device_get(result).collision_arrays()
    ledger = float(np.sum(result.steps.diss_pp) + np.sum(result.steps.diss_pw))
    ms = {mode: 1e3 * best[mode] / steps for mode in best}
    return {"steps": steps, "ms_per_step_off": ms["off"], "ms_per_step_on": ms["on"],
            "slowdown": ms["on"] / ms["off"] - 1.0,
            "compile_s_off": runs["off"][2], "compile_s_on": runs["on"][2],
            "events": int(events["collision_ball"].size),
            "events_energy_J": float(events["collision_energy"].sum()), "ledger_J": ledger}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=5000)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    print(json.dumps(rollout_cost(args.steps, args.repeats), sort_keys=True))


if __name__ == "__main__":
    main()
