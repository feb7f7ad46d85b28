#!/usr/bin/env python
"""Roll a model out on the held-out packings of some cases and compare with the DEM, in one
process.

    python experiments/reproduce/envelope_heldout/evaluate_model.py --model envelope --name envelope_sepoff \\
        --ensembles experiments/envelope/ensembles.toml --data data/envelope \\
        [--cases heldout_c00,...] [--rollout pp_separation=false] [--duration S]

Does what ``experiments/tools/run_experiments.py`` does (the same files under
``runs/experiments/NAME``: ``rollouts/{case}_seed{S}.npz/.json``, ``eval/{case}/run_XX/
metrics.json``, ``eval/{case}/ensemble.json`` and ``curves.png``, ``results.json``), but loads
the model once and runs every rollout in this process with ``sgn_jax.pipelines.rollout_run.run_rollout``
and every comparison with ``sgn_jax.analysis.metrics.evaluate``. A ``sgn-jax rollout`` process can spend
over a minute starting and compiling on a loaded 2-core CPU; here the compiled programs are reused (JAX's persistent cache) and only the first rollout of a shape
compiles. A rollout that goes non-finite is recorded as failed (``failed`` in results.json; its
case then counts it as a missing run) instead of stopping the others. Resumable: finished
rollouts are skipped.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

from sgn_jax.api import (
    RolloutError,
    ensemble_summary,
    evaluate,
    load_config,
    load_trajectory,
    run_rollout,
)
from sgn_jax.experiment_tools import (
    case_config,
    case_result,
    enable_compilation_cache,
    git_commit,
    load_ensembles,
    load_trained_model,
    machine_info,
    parse_rollout_settings,
    plot_case_curves,
    prediction_ok,
    resolve_checkpoint,
    rollout_duration,
    select_cases,
    write_json,
)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--model", required=True, help="run dir, checkpoint dir or shipped name")
    p.add_argument("--name", required=True)
    p.add_argument("--out-root", default="runs/experiments")
    p.add_argument("--ensembles", required=True)
    p.add_argument("--cases", default=None)
    p.add_argument("--data", required=True)
    p.add_argument("--duration", type=float, default=None)
    p.add_argument("--rollout", action="append", default=[], metavar="KEY=VALUE")
    args = p.parse_args(argv)
    enable_compilation_cache()
    cases = select_cases(load_ensembles(args.ensembles), args.cases)
    settings = parse_rollout_settings(args.rollout)
    checkpoint = resolve_checkpoint(args.model)
    trained = load_trained_model(checkpoint)
    cfg = trained.config
    window, dt, save_every = cfg.graph.window, cfg.dem.dt, cfg.rollout.save_every
    out = Path(args.out_root) / args.name
    data = Path(args.data)
    failed: dict[str, str] = {}
    results_path = out / "results.json"
    previous = json.loads(results_path.read_text()) if results_path.is_file() else {}
    failed.update(previous.get("failed_rollouts", {}))
    t_start = time.perf_counter()
    results: dict = {"cases": dict(previous.get("cases", {}))}
    for case in cases:
        seeds = case.eval_seeds
        override_path = case_config(case, settings, out)
        # The case config describes the DEM run (its [dem] dt is the records' sampling); the
        # rollout takes only [jar], [motion], [sdf] and [rollout] from it, and keeps the
        # model's own step (a fast tier may step 2e-4 s on 1e-4 s records).
        override = dataclasses.replace(load_config(override_path), dem=cfg.dem)
        preds, refs, ok_seeds = [], [], []
        for seed in seeds:
            ref = data / f"{case.name}_seed{seed}.npz"
            pred = out / "rollouts" / f"{case.name}_seed{seed}.npz"
            stem = f"{case.name}_seed{seed}"
            if stem in failed:
                continue
            if not prediction_ok(pred):
                traj = load_trajectory(ref)
                # A model with a coarser step than the record's (an integer factor) starts at
                # its first full window of coarse samples: record sample window * factor.
                start = window * max(1, round(dt / traj.dt))
                duration = (args.duration if args.duration is not None
                            else rollout_duration(ref, start, dt, save_every))
                t0 = time.perf_counter()
                try:
                    summary = run_rollout(trained, traj, start, duration, pred, override,
                                          progress=False, checkpoint_path=str(checkpoint))
                except RolloutError as exc:
                    failed[stem] = str(exc)
                    print(f"FAILED {stem}: {exc}", flush=True)
                    continue
                summary.pop("arrays")
                summary.pop("meta")
                write_json(out / "rollouts" / f"{stem}.json", summary)
                print(f"done {stem}: {time.perf_counter() - t0:.1f} s "
                      f"({summary['ms_per_step']:.3f} ms/step, compile "
                      f"{summary['compile_time_s']:.1f} s)", flush=True)
            preds.append(pred)
            refs.append(ref)
            ok_seeds.append(seed)
        if not ok_seeds:
            continue
        eval_dir = out / "eval" / case.name
        summaries = []
        for i, (pred, ref) in enumerate(zip(preds, refs, strict=True)):
            summary = evaluate(pred, ref)
            write_json(eval_dir / f"run_{i:02d}" / "metrics.json", summary)
            summaries.append(summary)
        write_json(eval_dir / "ensemble.json",
                   ensemble_summary(summaries, labels=[f"seed {s}" for s in ok_seeds]))
        # case_result reads the files above; seeds that failed are missing runs
        row = case_result(case, ok_seeds, out)
        row["seeds"] = list(seeds)
        row["failed_seeds"] = [s for s in seeds if s not in ok_seeds]
        row["curves_plot"] = str(plot_case_curves(
            f"{case.name}: {len(ok_seeds)} held-out packings, model {args.model}", preds, refs,
            [f"seed {s}" for s in ok_seeds], eval_dir / "curves.png"))
        results["cases"][case.name] = row
        print(f"evaluated {case.name}: DEM {row['ensemble']['power']['ref_W']['mean']:.4g} W, "
              f"SGN {row['ensemble']['power']['pred_W']['mean']:.4g} W", flush=True)
        results.update({"model": args.model, "checkpoint": str(checkpoint),
                        "rollout_settings": settings, "failed_rollouts": failed,
                        "command": " ".join(sys.argv), "commit": git_commit(),
                        "machine": machine_info(),
                        "wall_time_s": time.perf_counter() - t_start})
        write_json(results_path, results)
    print(json.dumps({"results": str(results_path), "failed": sorted(failed)}))
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
