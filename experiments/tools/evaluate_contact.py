#!/usr/bin/env python
"""Free rollouts of a surrogate against DEM ensembles: power, motion and contact checks, and the bars.

    python experiments/tools/evaluate_contact.py --model contact --name heldout \\
        --ensembles experiments/envelope/ensembles.toml --data data/envelope \\
        [--cases heldout_c00,...] [--duration 1.0] [--rollout pp_separation=true] \\
        [--dem-reference JSON] [--out runs/contact_eval]
    python experiments/tools/evaluate_contact.py --bars runs/contact_eval/heldout.json [...]

Every evaluation packing (the seeds that are not training seeds) of every case is rolled out
from the DEM record's first window for ``--duration`` s (default: the whole record), with the
ball-ball separation OFF unless ``--rollout pp_separation=true``, and compared with the DEM over
the same interval. Per case (means over the packings, SE ddof 1):

- power (W): the DEM's target (normal + tangential damping) and its total (all losses), the
  model's reported target (dE) and, for a kind that reports its own ledger, its total;
  signed error of the means and the bar max(10 %, 2 SE) with SE the combined standard error;
- motion: mean jar-frame ball speed, ball-ball and ball-wall contacts touching per step, mean
  ball-ball contact lifetime (steps), deepest ball-ball overlap, snapped ball-steps (%), balls
  outside, non-finite rollouts;
- the model's own energy ledger: jar work + gravity's work - change of kinetic energy against
  the dissipation it reports (relative residual over the rollout).

Writes ``OUT/NAME.json`` (every run and the case summaries) and ``OUT/NAME.md`` (the table and
the bars). Resumable: runs already in the JSON are kept.

**The bars** (printed after the table; ``--bars JSON ...`` prints them for existing result
files): the power error against its bar (held-out and fresh motions: the summary's
max(10 %, 2 SE); Motion 1 and 2: 15 %; the post jar: 20 %; the standard case: max(5 %, 2 SE)),
the mean jar-frame speed (15 %), the touching ball-ball and ball-wall contacts per step (25 %),
the deepest ball-ball overlap (0.5 mm), snapped ball-steps (1 %), balls outside and non-finite
runs (0), and which of them a case misses.

**The DEM's side from an earlier evaluation** (``--dem-reference JSON``). The DEM numbers of a
run (every ``dem_*`` entry: powers, speeds, contact census, deepest overlaps, spins) depend only
on the case, the seed and the DEM, not on the model, so an earlier evaluation's JSON of the
same ensembles (e.g. experiments/reproduce/contact_heldout/expected/heldout.json) holds them for
every packing. With it, ``--data`` needs only each record's first window: the first
milliseconds of the DEM run (``generate_data.py --prefix 0.002``), whose samples are
bit-identical to the first samples of the full run (the same settled packing, the same steps).
The model then rolls out over the reference run's interval (its ``steps`` at its own step
``dt_s``: a model at half the step rolls out twice the steps; ``reference_span``), the DEM's
statistics come from the reference, and the JSON records which reference it used. A reference
row without ``dt_s`` is refused. The full DEM record of 1.5-10
s per packing costs 500-5000x its prefix (docs/contact.md, "Evaluating a candidate").
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import sgn_jax.api as sj
import sgn_jax.experiment_tools as tools


def parse_settings(items):
    out = {}
    for item in items or []:
        key, _, value = item.partition("=")
        value = value.strip()
        out[key.strip()] = (value.lower() == "true" if value.lower() in ("true", "false")
                            else float(value) if value.replace(".", "", 1).replace("e-", "").isdigit()
                            else value)
    return out


def table(summaries):
    lines = ["| case | DEM W (SE) | model W (SE) | error | bar | total err | speed err | pp touch DEM/model | pw touch DEM/model | pp life steps DEM/model | deepest pp um | snapped % | outside | non-finite | ledger | spin R \\|w\\| DEM / model m/s |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for s in summaries:
        lines.append(
            f"| {s['case']} | {s['dem_power_W']:.3f} ({s['dem_power_W_se']:.3f}) | "
            f"{s['model_power_W']:.3f} ({s['model_power_W_se']:.3f}) | {100 * s['power_error']:+.0f} % | "
            f"{100 * s['power_bar']:.0f} % | {100 * s.get('total_power_error', float('nan')):+.0f} % | "
            f"{100 * s['speed_error']:+.0f} % | {s['dem_pp_touching_mean']:.1f} / {s['model_pp_touching_mean']:.1f} | "
            f"{s['dem_pw_touching_mean']:.1f} / {s['model_pw_touching_mean']:.1f} | "
            f"{s['dem_pp_contact_frames_mean']:.0f} / {s['model_pp_contact_frames_mean']:.0f} | "
            f"{1e6 * s['deepest_pp_overlap_m']:.0f} | {100 * s['snapped_fraction']:.2f} | "
            f"{s['outside_ball_steps']} | {s['non_finite_runs']} | {s['ledger_residual']:.1e} | "
            f"{s['dem_spin_speed_m_s']:.3f} / {s['model_spin_speed_m_s']:.3f} |")
    powers = [(s["dem_power_W"], s["model_power_W"]) for s in summaries]
    if len(powers) >= 3:
        from scipy.stats import spearmanr
        rho = spearmanr([p[0] for p in powers], [p[1] for p in powers]).statistic
        lines.append(f"\nSpearman rho over the cases: {rho:.2f}")
    return "\n".join(lines) + "\n"


SPEED_BAR, CONTACTS_BAR, OVERLAP_BAR_M, SNAPPED_BAR = 0.15, 0.25, 5e-4, 0.01


def power_bar(case: str, summary_bar: float) -> float:
    """The power bar of a case: 15 % for Motion 1 and 2, 20 % for the post jar, max(5 %, 2 SE)
    for the standard case, the summary's max(10 %, 2 SE) for any other motion."""
    if case in ("motion1", "motion2"):
        return 0.15
    if case.startswith("post"):
        return 0.20
    if case == "standard":
        return max(0.05, summary_bar)
    return summary_bar


def misses(s: dict) -> list[str]:
    """The bars a case summary misses (an empty list when it meets them all)."""
    out = []
    bar = power_bar(s["case"], s["power_bar"])
    if abs(s["power_error"]) > bar:
        out.append(f"power {s['power_error']:+.1%} (bar {bar:.0%})")
    out += tools.motion_misses(s, SPEED_BAR, CONTACTS_BAR)
    if s["deepest_pp_overlap_m"] > OVERLAP_BAR_M:
        out.append(f"overlap {s['deepest_pp_overlap_m'] * 1e3:.2f} mm")
    if s["snapped_fraction"] > SNAPPED_BAR:
        out.append(f"snapped {s['snapped_fraction']:.2%}")
    if s["outside_ball_steps"] or s["non_finite_runs"]:
        out.append("outside or non-finite")
    return out


def bars_table(summaries) -> str:
    """A markdown table: per case the power error with its bar, speed, contacts, the deepest
    ball-ball overlap and the bars it misses."""
    lines = ["| case | power (bar) | speed | pp contacts | pw contacts | deepest pp overlap | "
             "misses |", "|---|---|---|---|---|---|---|"]
    for s in summaries:
        bar = power_bar(s["case"], s["power_bar"])
        lines.append(
            f"| {s['case']} | {s['power_error']:+.1%} ({bar:.0%}) | {s['speed_error']:+.1%} | "
            f"{s['pp_touching_error']:+.1%} | {s['pw_touching_error']:+.1%} | "
            f"{s['deepest_pp_overlap_m'] * 1e3:.2f} mm | {', '.join(misses(s)) or '-'} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bars", nargs="+", default=None, metavar="JSON",
                    help="print the bars of these result files (nothing is run)")
    ap.add_argument("--model")
    ap.add_argument("--which", default="best", choices=("best", "latest"),
                    help="the training run's checkpoint (a run without validation has only "
                    "latest)")
    ap.add_argument("--name")
    ap.add_argument("--ensembles")
    ap.add_argument("--data")
    ap.add_argument("--cases", default=None)
    ap.add_argument("--seeds", default=None, help="comma-separated subset of the eval seeds")
    ap.add_argument("--duration", type=float, default=None)
    ap.add_argument("--rollout", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--model-set", action="append", default=[], metavar="KEY=VALUE",
                    help="a [model] key of the checkpoint's config replaced (the same weights)")
    ap.add_argument("--out", default="runs/contact_eval")
    ap.add_argument("--dem-reference", default=None, metavar="JSON",
                    help="an earlier evaluation's JSON of the same ensembles: the DEM's numbers "
                    "of each run from it, and --data need only hold each record's first window")
    args = ap.parse_args()
    if args.bars:
        for path in args.bars:
            print(f"{path}:\n" + bars_table(json.loads(Path(path).read_text())["summaries"]))
        return
    missing = [f"--{k}" for k in ("model", "name", "ensembles", "data") if not getattr(args, k)]
    if missing:
        ap.error(f"{', '.join(missing)} required (or --bars)")
    reference = None
    if args.dem_reference:
        if args.duration is not None:
            ap.error("--duration with --dem-reference: the reference's steps set the duration")
        reference = json.loads(Path(args.dem_reference).read_text())["runs"]

    tools.enable_compilation_cache()
    model = tools.with_model_keys(
        tools.load_trained_model(tools.resolve_checkpoint(args.model), which=args.which),
        args.model_set)
    settings = {"pp_separation": False, **parse_settings(args.rollout)}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    json_path = out / f"{args.name}.json"
    done = json.loads(json_path.read_text()) if json_path.exists() else {"runs": {}}
    cases = tools.select_cases(tools.load_ensembles(args.ensembles), args.cases)
    summaries = []
    for case in cases:
        cfg = sj.replace_section(sj.load_config(case.config_path), "rollout", **settings)
        # The model's own step (a model at 2e-4 s is compared with the DEM record coarsened to
        # it; the record's dissipation sums over each coarse step).
        model_dt = float(model.config.dem.dt)
        cfg = sj.replace_section(cfg, "dem", dt=model_dt)
        seeds = [s for s in case.seeds if s not in case.train_seeds]
        if args.seeds:
            seeds = [s for s in seeds if str(s) in args.seeds.split(",")]
        runs = []
        for seed in seeds:
            key = f"{case.name}_seed{seed}"
            path = Path(args.data) / f"{key}.npz"
            if key in done["runs"]:
                runs.append(done["runs"][key])
                continue
            if not path.exists():
                print(f"missing {path}; skipped")
                continue
            traj = sj.load_trajectory(path).at_step(model_dt)
            window = int(model.config.graph.window)
            dem_ref = None
            if reference is not None:
                dem_ref = reference.get(key)
                if dem_ref is None:
                    raise SystemExit(f"--dem-reference {args.dem_reference} has no run {key}")
                if len(traj.t) < window + 1:
                    raise SystemExit(f"{path}: {len(traj.t)} samples at {model_dt} s, fewer "
                                     f"than the first window's {window + 1}")
                try:   # the reference's interval, whatever step its model had
                    duration = tools.reference_span(dem_ref, float(cfg.dem.dt),
                                                    f"--dem-reference {args.dem_reference}, {key}")
                except ValueError as exc:
                    raise SystemExit(str(exc)) from None
            else:
                duration = args.duration or (len(traj.t) - 2 - window) * float(cfg.dem.dt)
            duration = round(duration / float(cfg.dem.dt)) * float(cfg.dem.dt)
            row = tools.rollout_against_dem(model, cfg, traj, duration, window, dem_ref)
            done["runs"][key] = row
            runs.append(row)
            json_path.write_text(json.dumps(done, indent=1))
            print(json.dumps({"run": key, **{k: row.get(k) for k in (
                "dem_power_W", "model_power_W", "model_total_power_W", "dem_speed_m_s",
                "model_speed_m_s", "snapped_fraction", "outside_ball_steps", "wall_s")}}), flush=True)
        if runs:
            summaries.append(tools.summarize_runs(case.name, runs))
    done["summaries"] = summaries
    done["model"] = str(args.model)
    if args.model_set:
        done["model_set"] = list(args.model_set)
    done["settings"] = settings
    if args.dem_reference:
        done["dem_reference"] = args.dem_reference
    json_path.write_text(json.dumps(done, indent=1))
    report = table(summaries) + "\n" + bars_table(summaries)
    (out / f"{args.name}.md").write_text(report)
    print(report)


if __name__ == "__main__":
    main()
