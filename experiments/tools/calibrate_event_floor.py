"""The surrogate ledger's force floor (EVENT_FORCE_FRACTION), fitted on training packings.

A contact of the contact model touches in a step when its normal force is at least a fraction
of its reduced mass's weight (docs/collisions.md). This script rolls the model out from DEM
records of training motions and training packings (never the held-out ones) with the collision
ledger on at several fractions, and prints the collision frequency of each against the DEM's
over the same interval; the fraction whose frequency is closest to the DEM's (in log ratio,
summed over the records) is the one the ledger uses.

    python experiments/tools/calibrate_event_floor.py --data data/coll_calib \\
        --fractions 0.02,0.05,0.1,0.2 --out runs/collisions_eval/calibration.json
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

import sgn_jax.api as sj
import sgn_jax.experiment_tools as tools


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", default="contact")
    ap.add_argument("--data", required=True, help="DEM records with collisions (training runs)")
    ap.add_argument("--fractions", default="0.02,0.05,0.1,0.2")
    ap.add_argument("--out", default="runs/collisions_eval/calibration.json")
    args = ap.parse_args()
    tools.enable_compilation_cache()
    model = tools.load_trained_model(tools.resolve_checkpoint(args.model))
    dt = float(model.config.dem.dt)
    window = int(model.config.graph.window)
    fractions = [float(f) for f in args.fractions.split(",")]
    rows = []
    for path in sorted(Path(args.data).glob("*.npz")):
        traj = sj.load_trajectory(path).at_step(dt)
        cfg = sj.replace_section(sj.replace_section(
            tools.config_from_dict(traj.meta["config"]), "rollout", pp_separation=False),
            "dem", dt=dt)
        n_steps = len(traj.t) - 2 - window
        t0 = float(traj.t[window])
        dem = sj.load_events(path).window(t0, t0 + n_steps * dt)
        row = {"record": path.name,
               "dem_frequency": tools.collision_statistics(dem)["frequency_per_ball_hz[all]"]}
        for fraction in fractions:
            res = sj.run_rollout(model, traj, window, n_steps * dt, None, cfg, save_every=1,
                                 progress=False, collisions=True,
                                 collision_force_fraction=fraction)
            table = tools.events_from_arrays(res["arrays"], res["meta"], source="surrogate")
            row[f"model_frequency@{fraction:g}"] = tools.collision_statistics(
                table)["frequency_per_ball_hz[all]"]
            print(json.dumps({"record": path.name, "fraction": fraction,
                              "dem": row["dem_frequency"],
                              "model": row[f"model_frequency@{fraction:g}"]}), flush=True)
        rows.append(row)
    score = {f: sum(abs(math.log(r[f"model_frequency@{f:g}"] / r["dem_frequency"]))
                    for r in rows) for f in fractions}
    best = min(score, key=score.get)
    result = {"records": rows, "score_sum_abs_log_ratio": {f"{k:g}": v for k, v in score.items()},
              "best_fraction": best}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=1))
    print(json.dumps({"best_fraction": best, "scores": result["score_sum_abs_log_ratio"]}))
    print(np.round([[r["dem_frequency"]] + [r[f"model_frequency@{f:g}"] for f in fractions]
                    for r in rows], 1))


if __name__ == "__main__":
    main()
