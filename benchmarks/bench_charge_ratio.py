"""The charge-reading surrogate against our DEM, per charge: one core, the same physical time.

Two tables (compile time apart, best of ``--repeats``):

1. **Held-out charges** (experiments/charges/design.toml): the DEM of each charge's config (its
   own step from the charge, collision ledger on, as ``sgn-jax dem`` runs), placed, settled and
   moved for ``--warm`` s, then ``--dem-steps`` steps timed; the surrogate (``--model``, model
   kind ``contact_charge``) rolled out by ``sgn_jax.api.run_rollout`` from the charge's DEM
   record (DATA/NAME/seed_100.npz) for ``--duration`` s after a first call that compiles.
   Both in seconds of one core per simulated second, and their ratio.
2. **Ball count** (6 mm steel balls, 300 rpm, 24 to 220 balls, as bench_charge_scaling.py): the
   surrogate's time per step and per ball-step, from a 0.03 s DEM run of each count.

    taskset -c 0 python benchmarks/bench_charge_ratio.py --model runs/contact_charge/unroll24 \
        [--markdown docs/benchmarks.md] [--full-rows]

``--full-rows``: each surrogate rollout also with every step on the whole graph (the
single-rollout form's compaction to the rows that may act off, docs/contact.md), and the
speed-up of the compaction, in the same run. ``--model-set KEY=VALUE`` (repeatable): the same
weights with a ``[model]`` key replaced, e.g. ``'rebound_sweeps="free"'``, as the evaluation
scripts' option.

Writes JSON to --out; prints markdown tables (or replaces them in --markdown).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import tempfile
import time
import tomllib
from pathlib import Path

import jax

import sgn_jax
import sgn_jax.api as sj
from sgn_jax.config import builtin_config_path, load_config, replace_section
from sgn_jax.dem.engine import make_advance
from sgn_jax.experiment_tools import with_model_keys
from sgn_jax.pipelines.dem_run import initial_state, setup_from_config
from sgn_jax.records.checkpoint import load_trained_model
from sgn_jax.records.io_utils import git_commit, machine_info, write_json

MARKER_CHARGES, MARKER_COUNTS = "charge-ratio", "charge-surrogate-scaling"
ROOT = Path(__file__).resolve().parent.parent
DESIGN = ROOT / "experiments" / "charges"
COUNTS = (24, 50, 100, 150, 220)


def dem_seconds_per_second(cfg, steps: int, repeats: int, warm: float) -> dict:
    """The DEM of ``cfg``: seconds of this core per simulated second (best of ``repeats``)."""
    setup = setup_from_config(cfg)
    state = initial_state(setup, seed=0)
    advance = make_advance(setup.spec, setup.jar.wall_fn)
    state = advance(setup.params, state, int(-state.step))              # settle
    state = advance(setup.params, state, int(round(warm / setup.dt_dem)))
    compiled = advance.lower(setup.params, state, steps).compile()
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(setup.params, state))
        best = min(best, time.perf_counter() - t0)
    return {"dt_dem_s": setup.dt_dem, "dem_us_per_step": 1e6 * best / steps,
            "dem_s_per_s": best / steps / setup.dt_dem}


def surrogate_seconds_per_second(model, record, cfg, duration: float, repeats: int,
                                 full_rows: bool = False) -> dict:
    """The surrogate's rollout from ``record``: seconds per simulated second, run time only
    (best of ``repeats``; each call's compile is apart, ``run_rollout``'s own timing). With
    ``full_rows`` also the same rollout with every step on the whole graph (the model's
    single-rollout form with ``compact_per_ball = 0``, docs/contact.md):
    ``model_s_per_s_full_rows`` and ``compact_speedup``."""
    dt = float(model.config.dem.dt)

    def best_time(trained) -> float:
        best = float("inf")
        for _ in range(repeats):
            out = sj.run_rollout(trained, record, None, duration, None, cfg, save_every=10,
                                 progress=False)
            best = min(best, 1e-3 * out["ms_per_step"])
        return best

    best = best_time(model)
    row = {"model_dt_s": dt, "model_ms_per_step": 1e3 * best, "model_s_per_s": best / dt}
    if full_rows:
        whole = model.model.for_single_rollout().clone(compact_per_ball=0.0)
        full = best_time(dataclasses.replace(model, model=whole))
        row.update(model_s_per_s_full_rows=full / dt, compact_speedup=full / best)
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", required=True)
    parser.add_argument("--data", default="data/charges_heldout")
    parser.add_argument("--names", nargs="*", default=None)
    parser.add_argument("--counts", type=int, nargs="*", default=list(COUNTS))
    parser.add_argument("--dem-steps", type=int, default=20_000)
    parser.add_argument("--duration", type=float, default=0.5)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--warm", type=float, default=0.02)
    parser.add_argument("--out", default="benchmarks/results/bench_charge_ratio.json")
    parser.add_argument("--markdown", default=None)
    parser.add_argument("--full-rows", action="store_true",
                        help="also time each rollout with every step on the whole graph")
    parser.add_argument("--model-set", action="append", default=[], metavar="KEY=VALUE",
                        help="a [model] key of the checkpoint's config replaced (repeatable)")
    args = parser.parse_args()
    model = with_model_keys(load_trained_model(args.model, which="latest"), args.model_set)
    model_dt = float(model.config.dem.dt)
    design = tomllib.loads((DESIGN / "design.toml").read_text())["heldout"]
    charges = []
    for name in args.names if args.names is not None else sorted(design):
        cfg = load_config(DESIGN / "configs" / f"{name}.toml")
        record = sj.load_trajectory(Path(args.data) / name / "seed_100.npz")
        row = {"charge": name, "label": design[name]["label"], "balls": cfg.balls.n_balls,
               **dem_seconds_per_second(cfg, args.dem_steps, args.repeats, args.warm),
               **surrogate_seconds_per_second(model, record,
                                              replace_section(cfg, "dem", dt=model_dt),
                                              args.duration, args.repeats, args.full_rows)}
        row["ratio"] = row["dem_s_per_s"] / row["model_s_per_s"]
        charges.append(row)
        print(json.dumps(row), flush=True)
    counts = []
    for count in args.counts:
        cfg = replace_section(load_config(builtin_config_path("emax_300rpm")), "balls",
                              count=count, radius=0.003)
        with tempfile.TemporaryDirectory() as tmp:
            sj.run_dem(cfg, duration=0.03, seed=0, out_path=Path(tmp) / "r.npz", progress=False)
            record = sj.load_trajectory(Path(tmp) / "r.npz")
            row = {"balls": count, **surrogate_seconds_per_second(
                model, record, replace_section(cfg, "dem", dt=model_dt), args.duration,
                args.repeats, args.full_rows)}
        row["model_us_per_ball_step"] = 1e3 * row["model_ms_per_step"] / count
        counts.append(row)
        print(json.dumps(row), flush=True)
    machine = {**machine_info(), "affinity": sorted(os.sched_getaffinity(0))}
    result = {"benchmark": "charge_ratio", "commit": git_commit(), "model": args.model,
              "model_set": args.model_set,
              "sgn_jax": sgn_jax.__version__, "machine": machine, "charges": charges,
              "counts": counts}
    write_json(args.out, result)
    head = (f"Commit {result['commit']}, jax {machine['jax']}, affinity {machine['affinity']}, "
            f"model `{args.model}`{''.join(f' {a}' for a in args.model_set)} (`{args.out}`):")
    full_head = " surrogate on the whole graph, s / simulated s | speed-up |" if args.full_rows else ""
    full_rule = "---|---|" if args.full_rows else ""

    def full_cells(r: dict) -> str:
        if not args.full_rows:
            return ""
        return f" {r['model_s_per_s_full_rows']:.2f} | {r['compact_speedup']:.2f}x |"

    lines = [head, "", "| charge | balls | DEM dt (s) | DEM s / simulated s | surrogate s / "
             "simulated s | ratio |" + full_head, "|---|---|---|---|---|---|" + full_rule]
    for r in charges:
        lines.append(f"| {r['label']} | {r['balls']} | {r['dt_dem_s']:.3g} | "
                     f"{r['dem_s_per_s']:.1f} | {r['model_s_per_s']:.2f} | {r['ratio']:.1f}x |"
                     + full_cells(r))
    table_charges = "\n".join(lines)
    lines = [head, "", "| balls (6 mm) | surrogate ms / step | us / ball-step |" + full_head,
             "|---|---|---|" + full_rule]
    for r in counts:
        lines.append(f"| {r['balls']} | {r['model_ms_per_step']:.3f} | "
                     f"{r['model_us_per_ball_step']:.2f} |" + full_cells(r))
    table_counts = "\n".join(lines)
    print(table_charges + "\n\n" + table_counts)
    if args.markdown:
        from markdown_section import replace_section as replace_md  # this folder is on sys.path

        if charges:
            replace_md(args.markdown, MARKER_CHARGES, table_charges)
        if counts:
            replace_md(args.markdown, MARKER_COUNTS, table_counts)


if __name__ == "__main__":
    main()
