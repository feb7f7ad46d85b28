"""The ``sgn-jax`` command line.

Each subcommand is registered by a ``_add_<name>`` function below and dispatched to a
``_cmd_<name>`` handler. The handlers that plot import :mod:`sgn_jax.analysis.plots` (matplotlib)
inside the handler, so ``sgn-jax --help`` does not pay for it (orbax is imported where a
checkpoint is read or written). Every error that derives from
:class:`sgn_jax.errors.SGNJaxError` (bad config, bad file, a run that failed) is printed as one
clear line, exit code 2.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import warnings
from pathlib import Path

from sgn_jax import __version__, api
from sgn_jax.analysis.collisions import DEFAULT_THRESHOLD_J
from sgn_jax.analysis.metrics import (
    MetricsWarning,
    compare,
    ensemble_summary,
    motion_warning_lines,
)
from sgn_jax.analysis.metrics import headline as run_headline
from sgn_jax.config import resolve_config
from sgn_jax.errors import EnvelopeWarning, SGNJaxError
from sgn_jax.pipelines.configure import jar_mesh_from_config, mesh_report
from sgn_jax.pipelines.contact_train_run import train_stages
from sgn_jax.pipelines.dem_run import run_dem
from sgn_jax.pipelines.demo import format_report, run_demo
from sgn_jax.pipelines.rollout_run import run_rollout
from sgn_jax.pipelines.spectra import collision_spectra
from sgn_jax.pipelines.studies import check_study_sizes, sensitivity_tasks
from sgn_jax.pipelines.train_run import train
from sgn_jax.pipelines.validation import check_duration, warn_outside_envelope
from sgn_jax.records.cache import enable_compilation_cache
from sgn_jax.records.checkpoint import load_trained_model
from sgn_jax.records.io_utils import atomic_write, write_json
from sgn_jax.records.prediction import load_prediction
from sgn_jax.records.shipped_models import resolve_checkpoint
from sgn_jax.records.trajectory import load_trajectory
from sgn_jax.regime import CLASSIFIERS
from sgn_jax.surrogate.collisions import DEFAULT_CAPACITY


class UserError(SGNJaxError):
    """An error caused by the user's input; printed without a traceback."""


# --------------------------------------------------------------------------------------------
# jar


def _add_jar(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "jar",
        help="write the jar of a config as an STL mesh and print its volume",
        description="Build the jar of CFG as a watertight mesh, write it as STL and print one "
        "JSON line with volume_ml, watertight and the analytic volume.",
    )
    p.add_argument("--config", required=True, help="experiment config: a TOML file or a built-in name (emax_300rpm, motion1, motion2, emax_post_motion1)")
    p.add_argument("--out", required=True, help="output STL file (m units)")
    p.set_defaults(handler=_cmd_jar)


def _cmd_jar(args: argparse.Namespace) -> int:

    cfg = resolve_config(args.config)
    mesh = jar_mesh_from_config(cfg.jar)
    with atomic_write(args.out, "wb") as fh:
        mesh.export(fh, file_type="stl")
    report = mesh_report(mesh, cfg.jar)
    report["out"] = str(Path(args.out))
    print(json.dumps(report))
    return 0


# --------------------------------------------------------------------------------------------
# demo


def _add_demo(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "demo",
        help="DEM vs the trained surrogate on the standard case: energy, MSE, speed, animation",
        description="Run the DEM of the case (settling, then DURATION s of motion), roll the "
        "trained surrogate out for DURATION s from the DEM's first full window, print the "
        "dissipated energy of both and its relative error, the position MSE, the wall-time speed "
        "ratio, balls outside the jar and edge overflows, and write OUT/summary.json, the "
        "comparison plots and OUT/animation.gif.",
    )
    p.add_argument("--out", default="runs/demo", help="output directory (default runs/demo)")
    p.add_argument("--checkpoint", default=None,
                   help="training run directory or checkpoint directory (default: the model "
                   "shipped with the package)")
    p.add_argument("--duration", type=float, default=1.0,
                   help="seconds of motion to compare (default 1.0)")
    p.add_argument("--seed", type=int, default=None,
                   help="DEM placement seed (default: the config's [dem] seed)")
    p.add_argument("--config", default="emax_300rpm",
                   help="built-in config name or TOML path of the case (default emax_300rpm)")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.set_defaults(handler=_cmd_demo)


def _cmd_demo(args: argparse.Namespace) -> int:
    summary = run_demo(args.out, checkpoint=args.checkpoint, duration=args.duration,
                       seed=args.seed, config=args.config, progress=not args.no_progress,
                       log=lambda msg: print(f"sgn-jax demo: {msg}", file=sys.stderr))
    print(format_report(summary))
    return 0


# --------------------------------------------------------------------------------------------
# train


def _add_train(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "train",
        help="train a surrogate on DEM records (the SGN, or the contact model in stages)",
        description="With [model] kind = 'contact' and [[train.stages]] in the config (the "
        "shipped model's recipe: `--config contact_train`), run the stages in order, each in "
        "OUT/<stage>/, each warm-started from the previous stage's best checkpoint, on the "
        "records its globs match under --data (a folder); OUT/summary.json names the trained "
        "model (docs/training.md). With an SGN config, featurize the --data files with the "
        "config's [graph] rules and SDF grid, split them chronologically ([train] train_time, "
        "val_time), train for [train] epochs, and write metrics.jsonl/.csv, loss.png and orbax "
        "checkpoints (checkpoints/latest, checkpoints/best) to OUT. Prints a JSON summary.",
    )
    p.add_argument("--config", required=True,
                   help="experiment config: a TOML file or a built-in name (contact_train, "
                   "emax_300rpm, motion1, motion2, emax_post_motion1)")
    p.add_argument("--data", required=True,
                   help="staged contact training: the folder the stages' record globs are "
                   "relative to; SGN: record file(s) (.npz, docs/conventions.md section 4), "
                   "comma-separated")
    p.add_argument("--out", required=True, help="run directory")
    p.add_argument("--epochs", type=int, default=None,
                   help="SGN only: total epochs of the run (overrides [train] epochs)")
    p.add_argument("--resume", action="store_true",
                   help="continue the run in OUT from its latest checkpoint (finished stages "
                   "are skipped)")
    p.add_argument("--quiet", action="store_true", help="no progress bars or per-step lines")
    p.set_defaults(handler=_cmd_train)


def _cmd_train(args: argparse.Namespace) -> int:
    if args.epochs is not None and args.epochs < 1:
        raise UserError(f"--epochs must be >= 1, got {args.epochs}")
    cfg = resolve_config(args.config)
    log = (lambda msg: None) if args.quiet else (lambda msg: print(msg, file=sys.stderr))
    if cfg.train.stages:
        if args.epochs is not None:
            raise UserError("--epochs is for an SGN; a staged config sets each stage's steps")
        if not Path(args.data).is_dir():
            raise UserError(f"--data {args.data!r}: a staged config reads its records from a "
                            "folder (its [[train.stages]] records globs are relative to it)")
        summary = train_stages(cfg, args.data, args.out, resume=args.resume,
                               progress=not args.quiet, log=log)
        print(json.dumps({"out": str(Path(args.out)), **summary}))
        return 0
    if cfg.model.kind == "contact":
        raise UserError(f"{args.config}: [model] kind = 'contact' trains in stages; add "
                        "[[train.stages]] (see the built-in config contact_train)")
    paths = [p.strip() for p in args.data.split(",") if p.strip()]
    if not paths:
        raise UserError("--data needs at least one trajectory file")
    trajectories = [load_trajectory(p) for p in paths]
    summary = train(cfg, trajectories, args.out, epochs=args.epochs, resume=args.resume,
                    names=paths, progress=not args.quiet, log=log)
    keys = ("epochs", "best_epoch", "best_loss", "n_train", "n_val", "n_params")
    print(json.dumps({"out": str(Path(args.out)), **{k: summary[k] for k in keys}}))
    return 0


# --------------------------------------------------------------------------------------------
# dem


def _add_dem(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "dem",
        help="run the DEM of a config and write a trajectory record (.npz, docs/conventions.md "
        "section 4)",
        description="Place the balls from SEED, settle them with the jar at rest, run DURATION "
        "seconds of motion and write the trajectory. Checkpoints after every chunk go to "
        "OUT.partial/; rerunning the same command resumes from there. Prints one JSON line: "
        "wall time, steps/s, dissipation by kind, ledger residual, balls outside the jar.",
    )
    p.add_argument("--config", required=True, help="experiment config: a TOML file or a built-in name (emax_300rpm, motion1, motion2, emax_post_motion1)")
    p.add_argument("--duration", type=float, default=None,
                   help="seconds of motion (default: [dem] duration)")
    p.add_argument("--out", required=True, help="output trajectory (.npz)")
    p.add_argument("--seed", type=int, default=None, help="placement seed (default: [dem] seed)")
    p.add_argument("--dt-dem", type=float, default=None,
                   help="largest DEM step (s); the step used is dt/k <= this (default: "
                   "[dem] dt_dem_max)")
    p.add_argument("--dtype", choices=("float64", "float32"), default=None,
                   help="DEM precision (default: [dem] dtype)")
    p.add_argument("--no-resume", action="store_true",
                   help="ignore (and delete) an existing OUT.partial/ checkpoint")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(handler=_cmd_dem)


def _cmd_dem(args: argparse.Namespace) -> int:

    cfg = resolve_config(args.config)
    result = run_dem(cfg, duration=args.duration, out_path=args.out, seed=args.seed,
                     dt_dem=args.dt_dem, dtype=args.dtype, resume=not args.no_resume,
                     progress=not args.no_progress)
    print(json.dumps(result.summary, sort_keys=True))
    return 0


# --------------------------------------------------------------------------------------------
# rollout


def _add_rollout(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "rollout",
        help="roll a trained surrogate out from a dataset's window and write a prediction (.npz)",
        description="Start from the window of DATASET ending at sample START_INDEX, run the "
        "trained surrogate for DURATION seconds (jitted lax.scan, [rollout] settings of the trained "
        "config) and write the prediction file read by `sgn-jax evaluate`. --config replaces "
        "the [jar], [motion], [sdf] and [rollout] sections (balls and dt must match). Prints "
        "one JSON line: energy, counts, wall and compile time, ms per step.",
    )
    p.add_argument("--checkpoint", default=None,
                   help="training run directory (its checkpoints/best), checkpoint directory or "
                   "shipped model name (contact, emax_300rpm, envelope); default: the shipped "
                   "default model, contact (docs/contact.md)")
    p.add_argument("--init", required=True, metavar="DATASET",
                   help="trajectory (.npz, docs/conventions.md section 4) that provides the "
                   "initial window")
    p.add_argument("--duration", required=True, type=float, help="seconds of rollout")
    p.add_argument("--out", required=True, help="output prediction file (.npz)")
    p.add_argument("--config", default=None,
                   help="config (TOML) whose [jar], [motion], [sdf], [rollout] override the "
                   "trained model's")
    p.add_argument("--start-index", type=int, default=None,
                   help="dataset sample at the rollout's start (default: the first with a full "
                   "window at the model's step: [graph] window, times the step ratio for a "
                   "record sampled finer than the model, e.g. 1e-4 s data and the 2e-4 s "
                   "shipped contact model)")
    p.add_argument("--save-every", type=int, default=None,
                   help="steps between saved frames (default: [rollout] save_every)")
    p.add_argument("--which", choices=("best", "latest"), default="best",
                   help="which checkpoint of a training run (default: best)")
    p.add_argument("--collisions", action="store_true",
                   help="record the collision ledger (contact model): one event per contact, "
                   "written as the prediction's collision_* arrays (docs/collisions.md)")
    p.add_argument("--collision-capacity", type=int, default=DEFAULT_CAPACITY, metavar="EVENTS",
                   help="events the ledger holds per chunk of [rollout] chunk_steps steps "
                   f"(default {DEFAULT_CAPACITY}); a chunk with more stops with an error")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(handler=_cmd_rollout)


def _cmd_rollout(args: argparse.Namespace) -> int:

    if args.save_every is not None and args.save_every < 1:
        raise UserError(f"--save-every must be >= 1, got {args.save_every}")
    if args.collision_capacity < 1:
        raise UserError(f"--collision-capacity must be >= 1 events, got "
                        f"{args.collision_capacity}")
    check_duration(args.duration, "--duration")
    checkpoint = resolve_checkpoint(args.checkpoint)
    trained = load_trained_model(checkpoint, which=args.which)
    override = resolve_config(args.config) if args.config else None
    if override is not None:
        warn_outside_envelope(override, trained.config, trained.meta)
    traj = load_trajectory(args.init)
    summary = run_rollout(trained, traj, args.start_index, args.duration, args.out, override,
                          save_every=args.save_every, progress=not args.no_progress,
                          checkpoint_path=str(checkpoint), collisions=args.collisions,
                          collision_capacity=args.collision_capacity)
    summary.pop("arrays")
    summary.pop("meta")
    print(json.dumps(summary, sort_keys=True))
    return 0


# --------------------------------------------------------------------------------------------
# evaluate


def _add_evaluate(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "evaluate",
        help="compare rollout predictions with DEM references (metrics and plots of "
        "docs/conventions.md sections 6 and 7)",
        description="Compare each rollout prediction with its DEM reference trajectory: position "
        "MSE_t, cumulative-energy error and Pearson r, balls outside, overflow, regime "
        "indicators. One pair writes OUT/metrics.json and the plots; several pairs write "
        "OUT/run_XX/ for each and OUT/ensemble.json + ensemble.png (docs/conventions.md "
        "section 7). Prints one JSON line with the headline numbers.",
    )
    p.add_argument("--prediction", required=True, nargs="+", metavar="FILE",
                   help="prediction .npz file(s) written by the rollout")
    p.add_argument("--reference", required=True, nargs="+", metavar="DATASET",
                   help="DEM trajectory .npz file(s), one per prediction, same order")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--classify-by", choices=CLASSIFIERS, default="speed",
                   help="state rule (docs/conventions.md section 7): mean ball speed in the jar "
                   "frame (default), ball pairs within the skin per ball, or dissipation power")
    p.add_argument("--threshold", type=float, default=None,
                   help="state threshold: m/s (speed, default 0.16), pairs per ball "
                   "(contacts, default 0.75) or W (power, required)")
    p.set_defaults(handler=_cmd_evaluate)


def _cmd_evaluate(args: argparse.Namespace) -> int:
    # deferred: sgn_jax.analysis.plots imports matplotlib, which the other commands do not need
    from sgn_jax.analysis.plots import plot_ensemble, plot_run

    if len(args.prediction) != len(args.reference):
        raise UserError(f"got {len(args.prediction)} --prediction file(s) but "
                        f"{len(args.reference)} --reference file(s); give one reference per "
                        "prediction, in the same order")
    if args.classify_by == "power" and args.threshold is None:
        raise UserError("--classify-by power needs --threshold W")
    out = Path(args.out)
    several = len(args.prediction) > 1
    summaries, headline = [], []
    for i, (pred_path, ref_path) in enumerate(zip(args.prediction, args.reference, strict=True)):
        run_dir = out / f"run_{i:02d}" if several else out
        prediction, reference = load_prediction(pred_path), load_trajectory(ref_path)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", MetricsWarning)
            comparison = compare(prediction, reference, classify_by=args.classify_by,
                                 threshold=args.threshold)
        for warning in caught:
            print(f"sgn-jax evaluate: warning: {warning.message}", file=sys.stderr)
        summary = comparison.summary
        # The motion checks (metrics.motion_warnings): the energy can agree by accident.
        for line in motion_warning_lines(summary["motion"]["warnings"]):
            print(f"sgn-jax evaluate: {pred_path}: {line}" if several
                  else f"sgn-jax evaluate: {line}", file=sys.stderr)
        summary["warnings"] = [str(w.message) for w in caught]
        summary["plots"] = plot_run(comparison, prediction, reference, run_dir)
        write_json(run_dir / "metrics.json", summary)
        summaries.append(summary)
        headline.append({"metrics": str(run_dir / "metrics.json"), **run_headline(summary)})
    if not several:
        print(json.dumps(headline[0]))
        return 0
    ensemble = ensemble_summary(summaries, classify_by=args.classify_by,
                                threshold=args.threshold, labels=[str(p) for p in args.prediction])
    ensemble["plot"] = str(plot_ensemble(ensemble, out / "ensemble.png"))
    write_json(out / "ensemble.json", ensemble)
    print(json.dumps({
        "ensemble": str(out / "ensemble.json"),
        "n_runs": ensemble["n_runs"],
        "power_pred_W": ensemble["power"]["pred_W"]["mean"],
        "power_ref_W": ensemble["power"]["ref_W"]["mean"],
        "power_relative_error_of_means": ensemble["power"]["relative_error_of_means"],
        "agitated_pred": ensemble["states"]["pred"]["agitated"]["count"],
        "agitated_ref": ensemble["states"]["ref"]["agitated"]["count"],
        "runs": headline,
    }))
    return 0


# --------------------------------------------------------------------------------------------
# sensitivity


def _add_sensitivity(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "sensitivity",
        help="design sensitivity: ensemble-mean dissipation power and its gradient w.r.t. "
        "named design parameters (surrogate)",
        description="Settle PACKINGS DEM packings (seeds FIRST_SEED..; with a jar.* parameter "
        "the DEM makes them in every evaluated jar, --start), roll the surrogate out "
        "for DURATION s from each under the config's jar and motion, and estimate the "
        "ensemble-mean dissipation power over (BURN_IN, DURATION] and its gradient with respect "
        "to each --param (default: the ensemble central difference with common packings, "
        "step --step or 10 % of the value; docs/design.md). A charge parameter (balls.*: a "
        "surrogate that reads the charge, e.g. --checkpoint contact_charge) is the "
        "central difference of surrogate ensembles at theta -+ h, each side with DEM packings "
        "of its own charge from the same seeds. --dem adds the DEM's ensemble central "
        "difference of each parameter at the same two points. Writes "
        "OUT/sensitivity.json and OUT/sensitivity.png (power vs each parameter around the point "
        "with the gradient's tangent); the last line of stdout is the JSON result: power_W, "
        "power_se_W, gradient (W per unit), gradient_se (and dem with --dem).",
    )
    p.add_argument("--config", required=True,
                   help="built-in config name (emax_300rpm, motion1, ...) or TOML path")
    p.add_argument("--param", required=True, action="append", metavar="NAME",
                   help="design parameter, repeatable: motion.rpm, motion.amplitude, "
                   "motion.phase, motion.base_frequency_hz, motion.scale, motion.x_sin[0] (any "
                   "harmonic coefficient), jar.straight_length, jar.radius, jar.height, "
                   "jar.post_radius; charge parameters (difference estimator, a model that "
                   "reads the charge, one ball class): balls.radius_fill (ball radius at the "
                   "config's filling, the count follows), balls.radius_count (at its ball "
                   "count), balls.density, balls.restitution, balls.friction (of the balls' "
                   "material)")
    p.add_argument("--duration", type=float, default=1.5,
                   help="seconds of surrogate rollout per packing (default 1.5)")
    p.add_argument("--burn-in", type=float, default=0.5,
                   help="seconds before the power is averaged (default 0.5)")
    p.add_argument("--packings", type=int, default=8, help="DEM packings (default 8)")
    p.add_argument("--first-seed", type=int, default=100,
                   help="first DEM placement seed (default 100: never used for training)")
    p.add_argument("--estimator", choices=("difference", "horizon"), default="difference",
                   help="gradient estimator (default difference; horizon: truncated-horizon "
                   "autodiff, docs/design.md)")
    p.add_argument("--step", action="append", default=[], metavar="NAME=H",
                   help="difference step of a parameter in its unit, repeatable (default: 10 %% "
                   "of its value)")
    p.add_argument("--horizon", type=int, default=10,
                   help="steps of each gradient horizon (horizon estimator; default 10)")
    p.add_argument("--segments", type=int, default=8,
                   help="gradient horizons per packing (horizon estimator; default 8)")
    p.add_argument("--checkpoint", default=None,
                   help="training run or checkpoint directory (default: the shipped model)")
    p.add_argument("--separation", choices=("config", "on", "off"), default="config",
                   help="ball-ball separation in the rollout (default: the config's)")
    p.add_argument("--no-curve", action="store_true",
                   help="skip the power evaluations at theta +- h (faster; no curve points)")
    p.add_argument("--start", choices=("auto", "packing", "dem", "settle"), default="auto",
                   help="where the rollouts start: packing (the DEM's packings of the config's "
                   "jar), dem (the DEM makes each packing in every evaluated jar: a DEM settle "
                   "per packing and jar), settle (the same placement settled by the "
                   "surrogate); default auto: dem when a jar.* parameter is studied, else "
                   "packing (docs/design.md)")
    p.add_argument("--dem", action="store_true",
                   help="also the DEM's ensemble central difference of each parameter at the "
                   "same two points, seeds, duration and burn-in (2 x PACKINGS DEM runs per "
                   "parameter)")
    p.add_argument("--out", default="runs/sensitivity", help="output directory")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(handler=_cmd_sensitivity)


def _cmd_sensitivity(args: argparse.Namespace) -> int:
    from tqdm.auto import tqdm

    # deferred: sgn_jax.analysis.plots imports matplotlib, which the other commands do not need
    from sgn_jax.analysis.plots import plot_sensitivity

    check_study_sizes(args.duration, args.burn_in, args.packings)
    steps = {}
    for item in args.step:
        name, _, value = item.partition("=")
        try:
            steps[name.strip()] = float(value)
        except ValueError:
            raise UserError(f"--step {item!r}: use NAME=H, e.g. motion.rpm=30") from None
    cfg = api.load_config(args.config)
    total = sensitivity_tasks(args.param, args.packings, args.start, args.estimator,
                              not args.no_curve, args.dem)
    separation = {"config": None, "on": True, "off": False}[args.separation]
    with tqdm(total=total, desc="sensitivity", unit="task", disable=args.no_progress,
              dynamic_ncols=True, file=sys.stderr) as bar:
        def progress(stage: str) -> None:  # called after each packing and evaluation
            bar.set_postfix_str(stage)
            bar.update(1)

        result = api.sensitivity(
            cfg, args.param, duration=args.duration, burn_in=args.burn_in,
            packings=args.packings, first_seed=args.first_seed, checkpoint=args.checkpoint,
            horizon=args.horizon, n_segments=args.segments, curve=not args.no_curve,
            estimator=args.estimator, steps=steps or None,
            separation=separation, start=args.start, dem=args.dem, progress=progress)
    out = Path(args.out)
    result["plot"] = str(plot_sensitivity(result, out / "sensitivity.png"))
    result["config"] = str(args.config)
    write_json(out / "sensitivity.json", result)
    line = {k: result[k] for k in ("power_W", "power_se_W", "gradient", "gradient_se",
                                   "units", "timing_s", "plot")}
    if "dem" in result:   # the DEM's difference beside the surrogate's, per parameter
        line["dem"] = {name: {k: d[k] for k in ("h", "central_difference",
                                                 "central_difference_se")}
                       for name, d in result["dem"].items()}
    line["json"] = str(out / "sensitivity.json")
    print(json.dumps(line))
    return 0


# --------------------------------------------------------------------------------------------
# charge-sweep


def _add_charge_sweep(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "charge-sweep",
        help="power against ball diameter or filling, from DEM ensembles and a surrogate "
        "that reads the charge (docs/charge.md)",
        description="For each --values entry, run PACKINGS DEM packings (seeds FIRST_SEED..) "
        "of the config's jar and motion with one ball size: --parameter diameter (m) at the "
        "config's filling (--hold fill, the count follows) or ball count (--hold count), or "
        "--parameter fill (the balls' volume fraction of the jar) at the config's diameter. "
        "Averages the power over (BURN_IN, DURATION]: the normal + tangential damping (the "
        "surrogates' target) and every dissipation kind, and the specific power per kg of "
        "balls, with standard errors over the packings. --surrogate DIR (a model that reads the "
        "charge) rolls the same DEM packings out with the surrogate for the same duration and "
        "burn-in, its power beside the DEM's (--no-dem: the surrogate only). Prints a table "
        "and, last, one JSON line; writes OUT/charge_sweep.json and OUT/charge_sweep.png.",
    )
    p.add_argument("--config", required=True,
                   help="built-in config name (emax_300rpm, ...) or TOML path, one ball class")
    p.add_argument("--parameter", required=True, choices=("diameter", "fill"))
    p.add_argument("--values", required=True, type=float, nargs="+",
                   help="diameters (m) or fillings (fractions, e.g. 0.1 0.15 0.2)")
    p.add_argument("--hold", choices=("fill", "count"), default="fill",
                   help="a diameter sweep at the config's filling (default) or ball count")
    p.add_argument("--packings", type=int, default=4, help="DEM packings per point (default 4)")
    p.add_argument("--first-seed", type=int, default=100,
                   help="first DEM placement seed (default 100)")
    p.add_argument("--duration", type=float, default=1.5,
                   help="seconds of motion per packing (default 1.5)")
    p.add_argument("--burn-in", type=float, default=0.5,
                   help="seconds before the power is averaged (default 0.5)")
    p.add_argument("--surrogate", default=None, metavar="MODEL",
                   help="a model that reads the charge (model kind contact_charge): the shipped "
                   "contact_charge, or a training run or checkpoint directory; its power at "
                   "every point beside the DEM's")
    p.add_argument("--no-dem", action="store_true",
                   help="with --surrogate: the surrogate's ensembles only (the DEM settles the "
                   "packings, nothing more)")
    p.add_argument("--out", default="runs/charge_sweep", help="output directory")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(handler=_cmd_charge_sweep)


def _cmd_charge_sweep(args: argparse.Namespace) -> int:
    from tqdm.auto import tqdm

    check_study_sizes(args.duration, args.burn_in, args.packings)
    if args.no_dem and args.surrogate is None:
        raise UserError("--no-dem needs --surrogate DIR (a model that reads the charge)")
    cfg = api.load_config(args.config)
    dem = not args.no_dem
    runs = len(args.values) * args.packings * (int(dem) + int(args.surrogate is not None))
    with tqdm(total=runs, desc="charge sweep", unit="run",
              disable=args.no_progress, dynamic_ncols=True, file=sys.stderr) as bar:
        def progress(stage: str) -> None:  # after each packing: rate and ETA from tqdm
            bar.set_postfix_str(stage)
            bar.update(1)

        result = api.charge_sweep(cfg, args.parameter, args.values, hold=args.hold,
                                  packings=args.packings, first_seed=args.first_seed,
                                  duration=args.duration, burn_in=args.burn_in,
                                  surrogate=args.surrogate, dem=dem, progress=progress)
    out = Path(args.out)
    result["plot"] = str(api.plot_charge_sweep(result, out / "charge_sweep.png"))
    result["config"] = str(args.config)
    write_json(out / "charge_sweep.json", result)
    # (key, SE key, column title, format) of the columns this sweep has
    columns = [c for c in (("power_W", "power_se_W", "DEM power W", ".4f"),
                           ("power_total_W", "power_total_se_W", "DEM all kinds W", ".4f"),
                           ("specific_W_per_kg", "specific_se_W_per_kg", "DEM W/kg", ".3f"),
                           ("surrogate_power_W", "surrogate_power_se_W", "surrogate W", ".4f"),
                           ("surrogate_specific_W_per_kg", "surrogate_specific_se_W_per_kg",
                            "surrogate W/kg", ".3f"))
               if c[0] in result["points"][0]]
    print(f"{'value':>10} {'balls':>6} {'fill %':>7} "
          + " ".join(f"{title:>20}" for _, _, title, _ in columns))
    for p in result["points"]:
        cells = " ".join(f"{format(p[key], fmt):>10} +- {format(p[se], fmt):<6}"
                         for key, se, _, fmt in columns)
        print(f"{p['value']:>10.4g} {p['n_balls']:>6d} {100 * p['fill']:>7.1f} {cells}")
    keys = ("value", "n_balls", "fill") + tuple(k for c in columns for k in c[:2])
    line = {"parameter": result["parameter"], "hold": result["hold"],
            "simulator": result["simulator"],
            "points": [{k: p[k] for k in keys} for p in result["points"]],
            "plot": result["plot"], "json": str(out / "charge_sweep.json")}
    print(json.dumps(line))
    return 0


# --------------------------------------------------------------------------------------------
# spectra


def _add_spectra(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "spectra",
        help="collision statistics and spectra from DEM and/or surrogate records",
        description="Read the collision events of DEM trajectory records (--dem) and/or rollout "
        "prediction records (--surrogate), one record per packing, and report per source the "
        "ensemble mean and standard error of: collisions per ball per second by pair kind, "
        "dissipated power and specific power (W/kg of balls), mean stress energy, the "
        "normal/tangential split, the impact-speed distribution, the power at or above "
        "--threshold, and the log-binned spectra of the dissipated energy and of the stress "
        "energy per collision (4 bins a decade, 1e-10 to 1e-1 J). Prints a table, then one "
        "JSON line (or writes it to --json), and draws one figure per statistic into OUT, "
        "DEM and surrogate overlaid (docs/collisions.md).",
    )
    p.add_argument("--dem", nargs="+", default=[], metavar="FILE",
                   help="DEM trajectory records (.npz) written with the collision ledger; "
                   "glob patterns allowed")
    p.add_argument("--surrogate", nargs="+", default=[], metavar="FILE",
                   help="rollout prediction records (.npz) written with collisions on; glob "
                   "patterns allowed")
    p.add_argument("--threshold", type=float, default=DEFAULT_THRESHOLD_J, metavar="J",
                   help="energy threshold of the power above it, J (default 1e-4 J: a 10 mm "
                   "steel ball pair approaching at 0.32 m/s; docs/collisions.md)")
    p.add_argument("--threshold-by", choices=("dissipated", "stress"), default="dissipated",
                   help="the threshold bounds each collision's dissipated energy (default) or "
                   "its stress energy 0.5 m* v_n^2")
    p.add_argument("--window", nargs=2, type=float, default=None, metavar=("START", "END"),
                   help="only collisions that begin in [START, END) s of motion time count "
                   "(default: each record whole)")
    p.add_argument("--out", default="runs/spectra", help="folder of the figures (default "
                   "runs/spectra)")
    p.add_argument("--no-plots", action="store_true", help="draw no figures")
    p.add_argument("--json", default=None, metavar="FILE",
                   help="write the JSON line to FILE instead of stdout")
    p.set_defaults(handler=_cmd_spectra)


def _cmd_spectra(args: argparse.Namespace) -> int:
    if not args.dem and not args.surrogate:
        raise UserError("give DEM records (--dem FILE ...) and/or surrogate records "
                        "(--surrogate FILE ...)")
    if not (math.isfinite(args.threshold) and args.threshold > 0):
        raise UserError(f"--threshold must be an energy > 0 J, got {args.threshold!r}")
    if args.window is not None and not args.window[1] > args.window[0]:
        raise UserError(f"--window {args.window[0]:g} {args.window[1]:g}: END must be after "
                        "START")
    if args.json is not None and Path(args.json).is_dir():
        raise UserError(f"--json {args.json!r} is a folder; name a file")
    result = collision_spectra(args.dem, args.surrogate, threshold=args.threshold,
                               threshold_by=args.threshold_by,
                               window=tuple(args.window) if args.window else None)
    line = result.to_json()
    if not args.no_plots:
        line["figures"] = {k: str(v) for k, v in result.plot(args.out).items()}
    print(result.table())
    text = json.dumps(line, sort_keys=True)
    if args.json is not None:
        with atomic_write(args.json, "w") as fh:
            fh.write(text + "\n")
    else:
        print(text)
    return 0


# --------------------------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="sgn-jax",
        description="Differentiable SDF graph-network surrogate and DEM engine for ball mills.",
    )
    parser.add_argument("--version", action="version", version=f"sgn-jax {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, fn in sorted(globals().items()):
        if name.startswith("_add_") and callable(fn):
            fn(sub)
    return parser


def _show_warnings_as_lines(command: str) -> None:
    """Envelope and data warnings as one ``sgn-jax CMD: warning: ...`` line each on stderr
    (not Python's file:line form), every time they occur."""
    def show(message, category, filename, lineno, file=None, line=None):  # noqa: ARG001
        print(f"sgn-jax {command}: warning: {message}", file=sys.stderr)

    warnings.showwarning = show
    warnings.simplefilter("always", EnvelopeWarning)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "handler", None):
        parser.print_help()
        return 0
    enable_compilation_cache()  # sgn_jax.records.cache: a second run reuses compiled programs
    _show_warnings_as_lines(args.command)
    user_errors = (SGNJaxError, FileNotFoundError)
    try:
        return int(args.handler(args) or 0)
    except user_errors as exc:
        print(f"sgn-jax {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"sgn-jax {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
