"""The DEM's collision statistics at two time steps: the events are a property of the physics,
not of the step.

Takes the same packings run at the DEM's step and at half of it (`sgn-jax dem --dt-dem`) and
prints, per statistic, the ensemble mean and standard error of each and their difference in
units of its standard error (sqrt(SE1^2 + SE2^2)); the dissipated-energy spectrum per decade
likewise. The runs of one packing part within a second (chaos), so the comparison is between
ensembles, not run by run.

    python experiments/tools/compare_collision_steps.py --a 'data/envelope/heldout_c01_seed[4-7].npz' \\
        --b 'data/halfstep/heldout_c01_seed*.npz' --out runs/collisions_eval/halfstep.json
"""

from __future__ import annotations

import argparse
import glob
import json
import math
from pathlib import Path

import numpy as np

import sgn_jax.api as sj
import sgn_jax.experiment_tools as tools

SCALARS = ("frequency_per_ball_hz[all]", "frequency_per_ball_hz[ball-ball]",
           "frequency_per_ball_hz[ball-wall]", "mean_stress_energy_J[all]", "normal_share[all]",
           "power_W[all]", "power_above_W", "impact_speed_median_m_s[all]")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--a", required=True, help="records at the DEM's step (glob)")
    ap.add_argument("--b", required=True, help="the same packings at half the step (glob)")
    ap.add_argument("--out", required=True)
    args = ap.parse_args()
    sets = {}
    for name, pattern in (("a", args.a), ("b", args.b)):
        paths = sorted(glob.glob(pattern))
        if len(paths) < 2:
            raise SystemExit(f"--{name} {pattern!r} matches {len(paths)} records; need >= 2")
        tables = [sj.load_events(p) for p in paths]
        sets[name] = {"paths": paths, "ens": tools.ensemble_statistics(tables),
                      "events": [int(np.sum(t.new)) for t in tables]}
    a, b = sets["a"]["ens"], sets["b"]["ens"]
    rows = []
    for stat in SCALARS:
        ma, sa, mb, sb = (float(x) for x in (a.mean[stat], a.se[stat], b.mean[stat], b.se[stat]))
        z = (mb - ma) / math.hypot(sa, sb)
        rows.append({"statistic": stat, "a": [ma, sa], "b": [mb, sb], "z": z})
    decades = tools.decade_comparison(a, b)
    for row in decades:
        if row["power_relative_difference"] is None:
            continue
        lo, hi = np.searchsorted(a.edges, row["lo_J"]), np.searchsorted(a.edges, row["hi_J"])
        pa = np.asarray(a.mean["dissipation_power_W"])[lo:hi].sum()
        pb = np.asarray(b.mean["dissipation_power_W"])[lo:hi].sum()
        # the per-packing decade sums' SE is not kept per decade: bound it by the bins' SE sum
        sa = float(np.sqrt(np.sum(np.asarray(a.se["dissipation_power_W"])[lo:hi] ** 2)))
        sb = float(np.sqrt(np.sum(np.asarray(b.se["dissipation_power_W"])[lo:hi] ** 2)))
        rows.append({"statistic": f"power in [{row['lo_J']:.0e}, {row['hi_J']:.0e}) J",
                     "a": [float(pa), sa], "b": [float(pb), sb],
                     "z": float((pb - pa) / math.hypot(sa, sb))})
    result = {"a": sets["a"]["paths"], "b": sets["b"]["paths"],
              "events_a": sets["a"]["events"], "events_b": sets["b"]["events"], "rows": rows}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=1))
    print("| statistic | dt | dt/2 | difference / SE |\n|---|---|---|---|")
    for r in rows:
        print(f"| {r['statistic']} | {r['a'][0]:.4g} ({r['a'][1]:.2g}) | "
              f"{r['b'][0]:.4g} ({r['b'][1]:.2g}) | {r['z']:+.1f} |")


if __name__ == "__main__":
    main()
