"""The charge-reading surrogate against DEM ensembles of the held-out charges, and the bars.

    python experiments/charges/evaluate.py --model runs/contact_charge/second \
        [--data data/charges_heldout] [--names heldout_00 ...] [--seeds 100 101 ...] \
        [--out runs/charge_eval] [--name heldout] [--dem-reference runs/charge_eval/heldout.json] \
        [--split train] [--model-set friction_sweeps=12] [--separation]
    python experiments/charges/evaluate.py --bars runs/charge_eval/heldout.json

Every complete DEM record ``DATA/NAME/seed_K.npz`` of the held-out charges of
experiments/charges/design.toml is rolled out by ``sgn_jax.api.run_rollout`` from its first
window for the whole record, with the case's config (its charge, jar and motion), the ball-ball
separation OFF (``--separation``: on, at the config's ``[rollout] pp_max_overlap``) and the wall
snap-back as configured (each ball's own threshold), and compared with the DEM over the same
interval by ``rollout_against_dem`` (``sgn_jax.pipelines.rollout_eval``): power (the DEM's
normal + tangential damping against the model's target), mean jar-frame speed, touching
ball-ball and ball-wall contacts per step (each pair's own r_i + r_j), the deepest ball-ball
overlap as a fraction of the pair's smaller radius, balls outside, non-finite runs, the model's
ledger. Resumable (runs already in OUT/NAME.json are kept).

With ``--dem-reference JSON`` (repeatable: earlier evaluations, e.g. of another model on the same
records) a record whose run (``<charge>_seed_<K>``) is in one of them takes the DEM's numbers
from that row and rolls out over that row's interval (its ``steps`` at its ``dt_s``; a row
without ``dt_s`` is refused): the record need only hold its first window,
as a record trimmed by experiments/tools/trim_records.py does (a later file's row wins).

The bars (docs/contact_charge.md): at least 5 of the 6 charges within max(10 %, 2 SE) of the
DEM's mean power, the sixth within 20 %, Spearman >= 0.9 over the six; speed within 15 %,
contacts within 25 %, deepest ball-ball overlap <= 10 % of the smaller radius, 0 outside,
0 non-finite.
"""

from __future__ import annotations

import argparse
import json
import tomllib
from pathlib import Path

import numpy as np

import sgn_jax.api as sj
import sgn_jax.experiment_tools as tools

HERE = Path(__file__).resolve().parent

POWER_BAR, SIXTH_BAR, SPEARMAN_BAR = 0.10, 0.20, 0.9
SPEED_BAR, CONTACTS_BAR, OVERLAP_REL_BAR = 0.15, 0.25, 0.10


def write_json(path: Path, data: dict) -> None:
    with tools.atomic_write(path, "w") as f:
        f.write(json.dumps(data, indent=1))


def charge_bars(summaries: list[dict]) -> tuple[str, bool]:
    """A markdown table of the bars per charge and the verdict over all of them."""
    lines = ["| charge | balls | DEM W (SE) | model W (SE) | power (bar) | speed | pp contacts | "
             "pw contacts | deepest pp / smaller r | outside | non-finite | misses |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    within, loose, other = 0, 0, True
    for s in summaries:
        bar = max(POWER_BAR, s["power_bar"])
        miss = []
        if abs(s["power_error"]) <= bar:
            within += 1
        elif abs(s["power_error"]) <= SIXTH_BAR:
            loose += 1
            miss.append(f"power {s['power_error']:+.1%} (<= 20 %)")
        else:
            miss.append(f"power {s['power_error']:+.1%}")
        miss += tools.motion_misses(s, SPEED_BAR, CONTACTS_BAR)
        if not s["model_deepest_pp_overlap_rel"] <= OVERLAP_REL_BAR:
            miss.append(f"overlap {s['model_deepest_pp_overlap_rel']:.1%}")
        if s["outside_ball_steps"] or s["non_finite_runs"]:
            miss.append("outside or non-finite")
        other &= not any(not m.startswith("power") for m in miss)
        lines.append(
            f"| {s['case']} | {s['n_balls']} | {s['dem_power_W']:.3f} ({s['dem_power_W_se']:.3f}) | "
            f"{s['model_power_W']:.3f} ({s['model_power_W_se']:.3f}) | "
            f"{s['power_error']:+.1%} ({bar:.0%}) | {s['speed_error']:+.1%} | "
            f"{s['pp_touching_error']:+.1%} | {s['pw_touching_error']:+.1%} | "
            f"{s['model_deepest_pp_overlap_rel']:.1%} | {s['outside_ball_steps']} | "
            f"{s['non_finite_runs']} | {', '.join(miss) or '-'} |")
    rho = float("nan")
    if len(summaries) >= 3:
        from scipy.stats import spearmanr
        rho = float(spearmanr([s["dem_power_W"] for s in summaries],
                              [s["model_power_W"] for s in summaries]).statistic)
    n = len(summaries)
    power_ok = n >= 6 and within >= n - 1 and within + loose == n
    verdict = power_ok and other and rho >= SPEARMAN_BAR
    lines.append(f"\n{within} of {n} charges within max(10 %, 2 SE), {loose} more within 20 %; "
                 f"Spearman {rho:.2f} (bar 0.9); all bars met: {verdict}")
    return "\n".join(lines) + "\n", verdict


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bars", nargs="+", default=None, metavar="JSON")
    ap.add_argument("--model")
    ap.add_argument("--data", default="data/charges_heldout")
    ap.add_argument("--names", nargs="*", default=None)
    ap.add_argument("--split", choices=("heldout", "train"), default="heldout",
                    help="the design's held-out charges (the bars) or its training charges "
                         "(free rollouts of the training records: a check of a model choice "
                         "that leaves the held-out charges unseen)")
    ap.add_argument("--seeds", type=int, nargs="*", default=None)
    ap.add_argument("--model-set", action="append", default=[], metavar="KEY=VALUE",
                    help="a [model] key of the checkpoint's config replaced, e.g. "
                         "friction_sweeps=12 (repeatable; the same weights)")
    ap.add_argument("--separation", action="store_true",
                    help="roll out with the ball-ball separation on (the config's "
                         "[rollout] pp_max_overlap); off by default, the model's own setting")
    ap.add_argument("--out", default="runs/charge_eval")
    ap.add_argument("--name", default="heldout")
    ap.add_argument("--dem-reference", action="append", default=[], metavar="JSON",
                    help="an earlier evaluation whose rows give the DEM's numbers and the steps")
    args = ap.parse_args()
    if args.bars:
        for path in args.bars:
            print(f"{path}:\n" + charge_bars(json.loads(Path(path).read_text())["summaries"])[0])
        return
    if not args.model:
        ap.error("--model required (or --bars)")
    tools.enable_compilation_cache()
    model = tools.load_model_to_evaluate(args.model, args.model_set)
    model_dt = float(model.config.dem.dt)
    window = int(model.config.graph.window)
    refs = {}
    for path in args.dem_reference:
        refs.update(json.loads(Path(path).read_text())["runs"])
    design = tomllib.loads((HERE / "design.toml").read_text())[args.split]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    json_path = out / f"{args.name}.json"
    done = json.loads(json_path.read_text()) if json_path.exists() else {"runs": {}}
    summaries = []
    for name in args.names or sorted(design):
        cfg = sj.load_config(HERE / "configs" / f"{name}.toml")
        cfg = sj.replace_section(cfg, "rollout", pp_separation=bool(args.separation))
        cfg = sj.replace_section(cfg, "dem", dt=model_dt)
        records = sorted((Path(args.data) / name).glob("seed_*.npz"))
        if args.seeds:
            records = [r for r in records if int(r.stem.split("_")[1]) in args.seeds]
        runs = []
        for path in records:
            key = f"{name}_{path.stem}"
            if key not in done["runs"]:
                traj = sj.load_trajectory(path).at_step(model_dt)
                ref = refs.get(key)
                if ref is not None:   # the DEM's side and the interval from the reference
                    try:
                        duration = tools.reference_span(ref, model_dt, f"--dem-reference {key}")
                    except ValueError as exc:
                        raise SystemExit(str(exc)) from None
                else:
                    duration = (len(traj.t) - 2 - window) * model_dt
                    duration = round(duration / model_dt / 10) * 10 * model_dt
                    if not duration > 0:
                        raise SystemExit(f"{path} holds {len(traj.t)} samples at "
                                         f"{model_dt:g} s: too few to compare with the DEM; "
                                         "give an evaluation of it with --dem-reference")
                row = tools.rollout_against_dem(model, cfg, traj, duration, window, dem_ref=ref)
                row["n_balls"] = int(np.shape(traj.pos)[1])
                done["runs"][key] = row
                write_json(json_path, done)
                print(json.dumps({"run": key, **{k: row.get(k) for k in (
                    "dem_power_W", "model_power_W", "dem_speed_m_s", "model_speed_m_s",
                    "model_deepest_pp_overlap_rel", "outside_ball_steps", "wall_s")}}),
                    flush=True)
            runs.append(done["runs"][key])
        if runs:
            summary = tools.summarize_runs(name, runs)
            summary["n_balls"] = runs[0]["n_balls"]
            summary["label"] = design[name]["label"]
            summaries.append(summary)
    done["summaries"] = summaries
    done["model"] = str(args.model)
    if args.model_set:
        done["model_set"] = list(args.model_set)
    if args.dem_reference:
        done["dem_reference"] = [str(p) for p in args.dem_reference]
    write_json(json_path, done)
    text, _ = charge_bars(summaries)
    (out / f"{args.name}.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
