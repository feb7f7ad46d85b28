"""A surrogate's `sgn-jax sensitivity` answer to the jar speed against the DEM's on the SAME
packings (paired; docs/results.md section 12, "Paired, on the same packings").

    python experiments/contact/paired_slope.py runs/sens_contact_t16/sensitivity.json \
        runs/sens20_contact_t16/sensitivity.json [...]

For each sensitivity JSON (``--param motion.rpm --step motion.rpm=50``, its per-packing
gradients and seeds), the DEM's per-packing central differences on the same seeds: seeds
100-107 from ``experiments/contact/results/dem_rpm_slope_seeds100-107.jsonl``
(experiments/contact/dem_rpm_slope.py), seeds 20-27 from issue 11's
``experiments/design/results/dem_powers.jsonl`` (the standard point's rpm lines). Prints the
ratio of the mean slopes and the paired difference (surrogate minus DEM, mean and SE over the
packings), in W/rpm.
"""

from __future__ import annotations

import argparse
import json

import numpy as np

import sgn_jax.api as sj
import sgn_jax.experiment_tools as tools

DEM_FILES = ("experiments/contact/results/dem_rpm_slope_seeds100-107.jsonl",
             "experiments/design/results/dem_powers.jsonl")
STEP_RPM = 50.0


def dem_slopes() -> dict[int, float]:
    """Per seed: (P(300 + h) - P(300 - h)) / 2h of the DEM, h = 50 rpm."""
    sides: dict[int, dict[int, float]] = {}
    for line in tools.read_jsonl(DEM_FILES[0]):
        sides.setdefault(line["seed"], {})[1 if line["rpm"] > 300 else -1] = line["power_W"]
    for line in tools.read_jsonl(DEM_FILES[1]):
        if line.get("point") == "standard" and line.get("param") == "motion.rpm":
            sides.setdefault(line["seed"], {})[int(line["side"])] = line["power_W"]
    return {seed: (s[1] - s[-1]) / (2 * STEP_RPM) for seed, s in sides.items() if len(s) == 2}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sensitivity", nargs="+", help="sensitivity.json files")
    args = ap.parse_args()
    dem = dem_slopes()
    print("| sensitivity | seeds | surrogate / DEM | paired difference (SE) W/rpm |")
    print("|---|---|---|---|")
    for path in args.sensitivity:
        with open(path) as fh:
            sens = json.load(fh)
        seeds, model = sens["seeds"], sens["gradient_per_packing"]["motion.rpm"]
        missing = [s for s in seeds if s not in dem]
        if missing:
            raise SystemExit(f"{path}: no DEM lines for seeds {missing}")
        ref = np.array([dem[s] for s in seeds])
        diff_mean, diff_se = sj.ensemble_mean(np.asarray(model) - ref)
        print(f"| {path} | {seeds[0]}-{seeds[-1]} | {np.mean(model) / ref.mean():.2f} | "
              f"{diff_mean:+.2e} ({diff_se:.2e}) |")


if __name__ == "__main__":
    main()
