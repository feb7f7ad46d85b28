#!/usr/bin/env python
"""The motion-general table: a model's ensemble-mean powers against the DEM's, per motion, with the bars.

    python experiments/reproduce/envelope_heldout/report.py --experiment runs/experiments/NAME [...]
        [--out runs/experiments/NAME/report.json] [--markdown]

Reads the ``results.json`` of one or more ``experiments/tools/run_experiments.py`` runs of the same
model and rollout settings (e.g. one over ``experiments/envelope/ensembles.toml``'s held-out
motions and one over ``experiments/ensembles.toml``'s Motion 1, Motion 2, post jar and
standard case) and writes one JSON with, per case:

- the DEM's and the surrogate's mean dissipation power over the held-out packings with their
  standard errors (SE = sample std / sqrt(n)), and the signed relative error of the means;
- the bar (held-out envelope motions 10 %, Motion 1 and 2 15 %, post jar 20 %,
  standard case 5 %), widened to 2 DEM standard errors where that is larger, and whether it is
  met; whether 2 SE of the DEM stays under 15 % of its mean (enough packings);
- the motion checks: the mean ball speed in the jar frame (DEM vs SGN), the deepest ball-ball
  overlap over every compared frame of every run, balls outside, and runs that are missing
  (a rollout that failed, e.g. went non-finite);

and over the held-out envelope motions the Spearman rank correlation of the surrogate's means
with the DEM's. ``--markdown`` prints the table for docs/results.md.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np
from scipy.stats import spearmanr

from sgn_jax.experiment_tools import write_json

BARS = {"motion1": 0.15, "motion2": 0.15, "post_motion1": 0.20, "standard": 0.05}
HELDOUT_BAR = 0.10
SPEARMAN_BAR = 0.9
OVERLAP_BAR_M = 0.5e-3
SPEED_BAR = 0.20
SE_ENOUGH = 0.15


def bar_of(case: str) -> float:
    return BARS.get(case, HELDOUT_BAR)


def _mean_se(values: list[float]) -> tuple[float | None, float | None]:
    v = np.asarray([x for x in values if x is not None and math.isfinite(x)], np.float64)
    if v.size == 0:
        return None, None
    se = float(v.std(ddof=1) / math.sqrt(v.size)) if v.size > 1 else None
    return float(v.mean()), se


def case_row(case: dict[str, Any]) -> dict[str, Any]:
    name = case["case"]
    ens = case["ensemble"]
    runs = ens["runs"]
    ref = [r["power_ref_W"] for r in runs]
    pred = [r["power_pred_W"] for r in runs]
    ref_mean, ref_se = _mean_se(ref)
    pred_mean, pred_se = _mean_se(pred)
    rel = (pred_mean - ref_mean) / ref_mean if ref_mean and pred_mean is not None else None
    bar = bar_of(name)
    tol = max(bar, 2 * ref_se / ref_mean) if ref_se and ref_mean else bar
    overlaps, speeds_pred, speeds_ref = [], [], []
    for run in case["runs"]:
        metrics = json.loads(Path(run["metrics"]).read_text())
        for check in metrics["motion"]["checks"]:
            if check["name"] == "overlap" and check["sgn"] is not None:
                overlaps.append(check["sgn"] * 1e-6)
    for r in runs:
        speeds_pred.append(r["jar_speed_pred_mean_m_s"])
        speeds_ref.append(r["jar_speed_ref_mean_m_s"])
    sp, sr = _mean_se(speeds_pred)[0], _mean_se(speeds_ref)[0]
    speed_rel = (sp - sr) / sr if sp is not None and sr else None
    deepest = max(overlaps) if overlaps else None
    return {
        "case": name, "description": case.get("description"), "n_runs": len(runs),
        "n_seeds": len(case["seeds"]),
        "dem_power_W": ref_mean, "dem_power_se_W": ref_se,
        "sgn_power_W": pred_mean, "sgn_power_se_W": pred_se,
        "relative_error_of_means": rel, "bar": bar, "tolerance_used": tol,
        "meets_bar": None if rel is None else abs(rel) <= tol,
        "dem_2se_over_mean": (2 * ref_se / ref_mean) if ref_se and ref_mean else None,
        "enough_packings": (2 * ref_se / ref_mean < SE_ENOUGH) if ref_se and ref_mean else None,
        "jar_speed_dem_m_s": sr, "jar_speed_sgn_m_s": sp, "jar_speed_relative": speed_rel,
        "speed_ok": None if speed_rel is None else abs(speed_rel) <= SPEED_BAR,
        "deepest_overlap_m": deepest,
        "overlap_ok": None if deepest is None else deepest <= OVERLAP_BAR_M,
        "balls_outside_total": case["balls_outside_total"],
        "missing_runs": len(case["seeds"]) - len(runs),
        "mse_plateau_m2_mean": case["mse_plateau_m2"]["mean"],
    }


def report(experiments: list[Path]) -> dict[str, Any]:
    rows, meta = [], []
    for exp in experiments:
        results = json.loads((exp / "results.json").read_text())
        meta.append({"experiment": str(exp), "model": results.get("model"),
                     "rollout_settings": results.get("rollout_settings"),
                     "commit": results.get("commit")})
        cases = results["cases"]
        for case in (cases.values() if isinstance(cases, dict) else cases):
            rows.append(case_row(case))
    held = [r for r in rows if r["case"].startswith("heldout_")]
    rho = None
    if len(held) >= 3:
        rho = float(spearmanr([r["dem_power_W"] for r in held],
                              [r["sgn_power_W"] for r in held]).statistic)
    return {"experiments": meta, "cases": rows,
            "heldout_spearman_rho": rho,
            "heldout_spearman_ok": None if rho is None else rho >= SPEARMAN_BAR,
            "all_bars_met": all(r["meets_bar"] for r in rows) if rows else None}


def markdown(rep: dict[str, Any]) -> str:
    def f(x, scale=1.0, fmt=".3f"):
        return "-" if x is None else format(x * scale, fmt)

    lines = ["| case | DEM W (SE) | SGN W (SE) | error | bar (used) | met | speed DEM/SGN m/s | "
             "deepest overlap um | outside | missing |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rep["cases"]:
        lines.append(
            f"| {r['case']} | {f(r['dem_power_W'])} ({f(r['dem_power_se_W'])}) | "
            f"{f(r['sgn_power_W'])} ({f(r['sgn_power_se_W'])}) | "
            f"{f(r['relative_error_of_means'], 100, '+.0f')} % | "
            f"{f(r['bar'], 100, '.0f')} ({f(r['tolerance_used'], 100, '.0f')}) % | "
            f"{'yes' if r['meets_bar'] else 'no'} | "
            f"{f(r['jar_speed_dem_m_s'])} / {f(r['jar_speed_sgn_m_s'])} | "
            f"{f(r['deepest_overlap_m'], 1e6, '.0f')} | {r['balls_outside_total']} | "
            f"{r['missing_runs']} |")
    lines.append("")
    lines.append(f"Spearman rho over the held-out envelope motions: "
                 f"{f(rep['heldout_spearman_rho'], 1.0, '.2f')} (bar {SPEARMAN_BAR})")
    return "\n".join(lines)


def ablation_row(rep: dict[str, Any]) -> dict[str, Any]:
    """One line of the ablation table: a report over the held-out envelope motions, condensed."""
    rows = [r for r in rep["cases"] if r["relative_error_of_means"] is not None]
    errs = [abs(r["relative_error_of_means"]) for r in rows]
    speeds = [abs(r["jar_speed_relative"]) for r in rows if r["jar_speed_relative"] is not None]
    overlaps = [r["deepest_overlap_m"] for r in rows if r["deepest_overlap_m"] is not None]
    return {"experiment": rep["experiments"][0]["experiment"] if rep["experiments"] else None,
            "cases": len(rows), "bars_met": sum(bool(r["meets_bar"]) for r in rows),
            "mean_abs_power_error": float(np.mean(errs)) if errs else None,
            "max_abs_power_error": float(np.max(errs)) if errs else None,
            "spearman_rho": rep["heldout_spearman_rho"],
            "mean_abs_speed_error": float(np.mean(speeds)) if speeds else None,
            "deepest_overlap_m": max(overlaps) if overlaps else None,
            "balls_outside_total": sum(r["balls_outside_total"] for r in rows),
            "missing_runs": sum(r["missing_runs"] for r in rep["cases"])}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--experiment", action="append", required=True, type=Path)
    p.add_argument("--out", type=Path, default=None)
    p.add_argument("--markdown", action="store_true")
    p.add_argument("--ablation", action="store_true",
                   help="one condensed row per --experiment (each its own report) instead")
    args = p.parse_args(argv)
    for exp in args.experiment:
        if not (exp / "results.json").is_file():
            print(f"report: error: {exp / 'results.json'} does not exist; run "
                  "experiments/reproduce/envelope_heldout/evaluate_model.py first", file=sys.stderr)
            return 2
    if args.ablation:
        rows = [ablation_row(report([exp])) for exp in args.experiment]
        if args.out:
            write_json(args.out, {"ablation": rows})
        for r in rows:
            print(json.dumps(r))
        return 0
    rep = report(args.experiment)
    if args.out:
        write_json(args.out, rep)
    print(markdown(rep) if args.markdown else json.dumps(rep, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
