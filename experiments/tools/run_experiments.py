#!/usr/bin/env python
"""The paper's protocol for a trained model: rollouts from the held-out packings, evaluation, runtime.

    python experiments/tools/run_experiments.py --model sgn_jax/data/models/emax_300rpm [--name NAME]
        [--cases standard,motion1,motion2,post_motion1] [--jobs 2] [--data data/]
        [--duration S] [--runtime-seconds 2] [--runtime-seed 4] [--skip-runtime]
        [--ensembles experiments/ensembles.toml] [--rollout KEY=VALUE] [--no-pin]

For every case of ``experiments/ensembles.toml`` (or those of ``--cases``) and every held-out
seed S of that case (``seeds`` minus ``train_seeds``), this

1. rolls the model out from the first full window of ``data/{case}_seed{S}.npz`` for as long
   as that DEM reference covers (a whole number of ``[rollout] save_every`` steps), with the
   case's config replacing the model's jar and motion (``sgn-jax rollout --config``), into
   ``OUT/rollouts/{case}_seed{S}.npz``; the rollout's JSON line (energy, edge counts, balls
   outside, wall and compile time, ms per step) goes to ``OUT/rollouts/{case}_seed{S}.json``;
2. compares all rollouts of the case with their DEM references (``sgn-jax evaluate``) into
   ``OUT/eval/{case}/`` (per-run ``run_XX/metrics.json`` and plots, ``ensemble.json`` and
   ``ensemble.png``);

then, unless ``--skip-runtime``, runs the runtime row: ``sgn-jax demo`` with this model on the
standard case (seed ``--runtime-seed``) for ``--runtime-seconds`` of motion, DEM and surrogate
in the same process, pinned to one core, into ``OUT/runtime/``.

Everything is summarised in ``OUT/results.json``: per case the per-run headline numbers (MSE_t
plateau, final relative energy error, Pearson r, balls outside, states), their mean / min /
max, the ensemble metrics (mean dissipation power of DEM and surrogate and the error of the
means, state counts, contact counts), the mean ms per surrogate step; the runtime row; the
model's provenance, the commit and the machine. ``OUT`` is ``runs/experiments/NAME`` (NAME
defaults to the model directory's name).

Rerunning the same command skips rollouts whose prediction file loads (so an interrupted run
continues), and redoes the evaluations and the summary (cheap). Rollouts run in ``--jobs``
processes, process k pinned to the k-th usable core, as the DEM ensemble does.

Exit status: 0 when every rollout and evaluation succeeded, 1 otherwise (the others still
run), 2 for a bad argument.
"""

from __future__ import annotations

import argparse
import json
import shlex
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from sgn_jax.api import CheckpointError
from sgn_jax.experiment_tools import (
    CLASSIFIERS,
    EnsembleError,
    ExperimentError,
    case_config,
    case_result,
    git_commit,
    last_json_line,
    load_ensembles,
    load_trained_model,
    machine_info,
    parse_rollout_settings,
    plot_case_curves,
    prediction_ok,
    rollout_duration,
    select_cases,
    sgn_jax_command,
    usable_cores,
    write_json,
)

HERE = Path(__file__).resolve().parent
DEFAULT_ENSEMBLES = HERE.parent / "ensembles.toml"
POLL_S = 1.0

# The planning (rollout_duration, parse_rollout_settings, case_config) and summary
# (case_result, plot_case_curves) steps live in sgn_jax.pipelines.experiments and
# sgn_jax.analysis.plots, shared with experiments/reproduce/envelope_heldout/evaluate_model.py; they are imported
# above from sgn_jax.api.


# --------------------------------------------------------------------------------------------
# Running


def run_pinned(jobs: list[tuple[str, list[str], Path]], n_jobs: int, pin: bool
               ) -> dict[str, int]:
    """Run ``(name, argv, log)`` jobs, at most ``n_jobs`` at a time, each pinned to one core.

    Returns the exit status of each job by name. stdout and stderr go to the job's log.
    """
    cores = usable_cores()[:max(1, n_jobs)]
    free = list(cores)
    pending = list(jobs)
    active: dict[int, tuple[str, subprocess.Popen, Any, float]] = {}
    status: dict[str, int] = {}
    while pending or active:
        while pending and free:
            name, argv, log = pending.pop(0)
            core = free.pop(0)
            full = (["taskset", "-c", str(core)] if pin else []) + argv
            log.parent.mkdir(parents=True, exist_ok=True)
            fh = log.open("w")
            fh.write("$ " + shlex.join(full) + "\n")
            fh.flush()
            print(f"start {name} on core {core}", flush=True)
            active[core] = (name, subprocess.Popen(full, stdout=fh, stderr=subprocess.STDOUT),
                            fh, time.perf_counter())
        time.sleep(POLL_S)
        for core, (name, proc, fh, t0) in list(active.items()):
            rc = proc.poll()
            if rc is None:
                continue
            fh.close()
            status[name] = rc
            print(f"{'done' if rc == 0 else 'FAILED'} {name} (exit {rc}, "
                  f"{time.perf_counter() - t0:.0f} s)", flush=True)
            del active[core]
            free.append(core)
    return status


# --------------------------------------------------------------------------------------------
# Main


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model", required=True,
                   help="training run directory (its checkpoints/best) or checkpoint directory")
    p.add_argument("--name", default=None, help="experiment name (default: the model's name)")
    p.add_argument("--out-root", default="runs/experiments",
                   help="where OUT=ROOT/NAME goes (default runs/experiments)")
    p.add_argument("--ensembles", default=str(DEFAULT_ENSEMBLES), help="ensembles file")
    p.add_argument("--cases", default=None, help="comma-separated cases (default: all)")
    p.add_argument("--data", default="data", help="folder of the DEM files (default data/)")
    p.add_argument("--jobs", type=int, default=1, help="parallel rollouts, one per core")
    p.add_argument("--duration", type=float, default=None,
                   help="seconds of each rollout (default: all the reference covers)")
    p.add_argument("--runtime-seconds", type=float, default=2.0,
                   help="seconds of motion of the runtime row (default 2)")
    p.add_argument("--runtime-seed", type=int, default=4,
                   help="placement seed of the runtime row (default 4, held out)")
    p.add_argument("--skip-runtime", action="store_true", help="no runtime row")
    p.add_argument("--no-pin", action="store_true", help="do not pin processes with taskset")
    p.add_argument("--rollout", action="append", default=[], metavar="KEY=VALUE",
                   help="set a [rollout] field of every case's config for these rollouts, e.g. "
                   "pp_separation=false (the paper's rollout); repeatable. The configs used "
                   "are written to OUT/configs/")
    p.add_argument("--classify-by", choices=CLASSIFIERS, default=None,
                   help="passed to sgn-jax evaluate (default: its own)")
    p.add_argument("--threshold", type=float, default=None, help="passed to sgn-jax evaluate")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        cases = select_cases(load_ensembles(args.ensembles), args.cases)
        settings = parse_rollout_settings(args.rollout)
        if args.jobs < 1:
            raise ExperimentError(f"--jobs must be >= 1, got {args.jobs}")
        try:
            trained = load_trained_model(args.model)
        except CheckpointError as exc:
            raise ExperimentError(str(exc)) from exc
    except (EnsembleError, ExperimentError) as exc:
        print(f"run_experiments: error: {exc}", file=sys.stderr)
        return 2
    cfg = trained.config
    window, dt, save_every = cfg.graph.window, cfg.dem.dt, cfg.rollout.save_every
    model = Path(args.model)
    name = args.name or (model.name if model.name not in ("best", "latest", "checkpoints")
                         else model.parent.name)
    out = Path(args.out_root) / name
    data = Path(args.data)
    cli = sgn_jax_command()
    t_start = time.perf_counter()

    # 1. rollouts
    jobs, plan = [], {}
    for case in cases:
        seeds = case.eval_seeds
        plan[case.name] = seeds
        for seed in seeds:
            ref = data / f"{case.name}_seed{seed}.npz"
            if not ref.is_file():
                print(f"run_experiments: error: {ref} is missing; make it with "
                      f"`python experiments/tools/generate_data.py --cases {case.name}`",
                      file=sys.stderr)
                return 2
            pred = out / "rollouts" / f"{case.name}_seed{seed}.npz"
            if prediction_ok(pred):
                print(f"skip  {pred.name}: done")
                continue
            duration = (args.duration if args.duration is not None
                        else rollout_duration(ref, window, dt, save_every))
            argv_ = [*cli, "rollout", "--checkpoint", str(model), "--init", str(ref),
                     "--duration", repr(duration), "--config",
                     str(case_config(case, settings, out)),
                     "--out", str(pred), "--no-progress"]
            jobs.append((pred.stem, argv_, out / "logs" / f"rollout_{pred.stem}.log"))
    status = run_pinned(jobs, args.jobs, pin=not args.no_pin)
    failed = [n for n, rc in status.items() if rc != 0]
    # the rollout's JSON line, also for rollouts of an earlier, interrupted call of this script
    for case in cases:
        for seed in plan[case.name]:
            stem = f"{case.name}_seed{seed}"
            log = out / "logs" / f"rollout_{stem}.log"
            if (out / "rollouts" / f"{stem}.json").is_file() or stem in failed \
                    or not log.is_file() or not (out / "rollouts" / f"{stem}.npz").is_file():
                continue
            line = last_json_line(log, key="ms_per_step")
            if line is not None:
                write_json(out / "rollouts" / f"{stem}.json", line)

    # 2. evaluation per case
    results: dict[str, Any] = {"cases": {}}
    for case in cases:
        seeds = plan[case.name]
        preds = [out / "rollouts" / f"{case.name}_seed{s}.npz" for s in seeds]
        if not all(p.is_file() for p in preds):
            print(f"run_experiments: {case.name}: rollouts missing, not evaluated",
                  file=sys.stderr)
            failed.append(f"eval {case.name}")
            continue
        refs = [data / f"{case.name}_seed{s}.npz" for s in seeds]
        argv_ = [*cli, "evaluate", "--prediction", *map(str, preds), "--reference",
                 *map(str, refs), "--out", str(out / "eval" / case.name)]
        if args.classify_by:
            argv_ += ["--classify-by", args.classify_by]
        if args.threshold is not None:
            argv_ += ["--threshold", repr(args.threshold)]
        print(f"evaluate {case.name} ({len(seeds)} runs)", flush=True)
        proc = subprocess.run(argv_, capture_output=True, text=True)
        log = out / "logs" / f"evaluate_{case.name}.log"
        log.parent.mkdir(parents=True, exist_ok=True)
        log.write_text("$ " + shlex.join(argv_) + "\n" + proc.stdout + proc.stderr)
        if proc.returncode != 0:
            print(f"run_experiments: evaluate {case.name} failed; see {log}", file=sys.stderr)
            failed.append(f"eval {case.name}")
            continue
        results["cases"][case.name] = case_result(case, seeds, out)
        results["cases"][case.name]["curves_plot"] = str(plot_case_curves(
            f"{case.name}: {len(seeds)} held-out packings, model {model}", preds, refs,
            [f"seed {s}" for s in seeds], out / "eval" / case.name / "curves.png"))

    # 3. runtime row: DEM and surrogate for the same physical time, same process, one core
    if not args.skip_runtime:
        rt_dir = out / "runtime"
        argv_ = [*cli, "demo", "--checkpoint", str(model), "--seed", str(args.runtime_seed),
                 "--duration", repr(args.runtime_seconds), "--out", str(rt_dir),
                 "--no-progress"]
        status = run_pinned([("runtime", argv_, out / "logs" / "runtime.log")], 1,
                            pin=not args.no_pin)
        summary_path = rt_dir / "summary.json"
        if status.get("runtime") == 0 and summary_path.is_file():
            summary = json.loads(summary_path.read_text())
            results["runtime"] = {"seconds_of_motion": args.runtime_seconds,
                                  "seed": args.runtime_seed, "pinned_to_one_core": not args.no_pin,
                                  "speed": summary["speed"], "summary": str(summary_path)}
        else:
            failed.append("runtime")

    results.update({
        "model": str(model),
        "rollout_settings": settings,
        "model_config_window": window,
        "dt_ml": dt,
        "commit": git_commit(),
        "machine": machine_info(),
        "command": shlex.join([sys.executable, *sys.argv]),
        "wall_time_s": time.perf_counter() - t_start,
        "failed": failed,
    })
    write_json(out / "results.json", results)
    print(json.dumps({"results": str(out / "results.json"), "failed": failed,
                      **{c: {"mse_plateau_mean": r["mse_plateau_m2"]["mean"],
                             "energy_err_mean": r["energy_relative_error_final"]["mean"],
                             "power_err_of_means":
                                 r["ensemble"]["power"]["relative_error_of_means"],
                             "balls_outside": r["balls_outside_total"]}
                         for c, r in results["cases"].items()}}))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
