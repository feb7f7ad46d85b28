#!/usr/bin/env python
"""Calibrate the SPEC 7 state rule on a DEM ensemble: bed vs agitated.

    python experiments/calibrate_states.py [--case standard] [--data data/] [--out runs/states]

For every DEM file ``data/{case}_seed*.npz`` this computes, per run and per 1-s window of
motion, three regime indicators:

- the DEM's mean ball-ball contact count (its contact list: the ground truth of the state);
- the mean ball speed in the jar frame from 1-ms finite differences of ``pos - offset``
  (``sgn_jax.analysis.metrics.jar_frame_speed``, the default rule of ``sgn-jax evaluate``: it reads
  positions only, so it applies to a surrogate's rollout the same way);
- the mean dissipation power (normal + tangential damping, the surrogate's target).

It writes ``OUT/{case}_states.json`` (per-run rows, the gap between the two clusters of the
speed, the threshold in use and whether it separates them) and ``OUT/{case}_states.png``
(speed vs contacts and power vs contacts, one point per 1-s window). The threshold
``sgn_jax.regime.AGITATED_SPEED_M_S`` was chosen from this output (docs/results.md, "States").
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

FRAME_STRIDE = 10  # samples between the frames the speed is computed from (1 ms at 1e-4 s)


def indicators(path: Path, window_s: float | None = None) -> dict:
    """Per-run and per-window indicators (windows of ``window_s``, default
    ``sgn_jax.regime.REGIME_WINDOW_S`` = 1 s)."""
    from sgn_jax.api import load_trajectory
    from sgn_jax.experiment_tools import REGIME_WINDOW_S, jar_frame_speed, pp_contact_counts

    window_s = REGIME_WINDOW_S if window_s is None else window_s

    traj = load_trajectory(path)
    t = np.asarray(traj.t)
    frames = slice(None, None, FRAME_STRIDE)
    speed = jar_frame_speed(t[frames], traj.pos[frames], traj.offset[frames])
    t_speed = t[frames][1:]
    contacts = pp_contact_counts(traj.pp_pairs)
    energy = np.asarray(traj.cumulative_dissipation("normal+tangential", "pp+pw"))
    windows = []
    for start in np.arange(0.0, t[-1] - 1e-9, window_s):
        stop = start + window_s
        in_s = (t_speed > start) & (t_speed <= stop)
        in_t = (t > start) & (t <= stop)
        if not in_s.any():
            continue
        i0, i1 = np.searchsorted(t, [start, stop], side="right") - 1
        windows.append({"t0": float(start), "t1": float(stop),
                        "jar_speed_m_s": float(speed[in_s].mean()),
                        "pp_contacts": float(contacts[in_t].mean()),
                        "power_W": float((energy[i1] - energy[i0]) / (t[i1] - t[i0]))})
    return {"file": str(path), "seed": traj.meta.get("seed"), "n_balls": int(traj.n_balls),
            "jar_speed_m_s": float(speed.mean()), "pp_contacts": float(contacts.mean()),
            "power_W": float((energy[-1] - energy[0]) / (t[-1] - t[0])),
            "windows": windows}


def main(argv: list[str] | None = None) -> int:
    from sgn_jax.experiment_tools import (
        AGITATED_SPEED_M_S,
        REGIME_PP_CONTACTS_PER_BALL,
        git_commit,
        new_figure,
        save_figure,
        write_json,
    )

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--case", default="standard")
    p.add_argument("--data", default="data")
    p.add_argument("--out", default="runs/states")
    p.add_argument("--contacts-threshold", type=float, default=None,
                   help="DEM ball-ball contacts that separate bed (>=) from agitated (default: "
                   "sgn_jax.regime.REGIME_PP_CONTACTS_PER_BALL x balls, 14 for 24 balls)")
    args = p.parse_args(argv)
    files = sorted(Path(args.data).glob(f"{args.case}_seed*.npz"),
                   key=lambda f: int(f.stem.rsplit("seed", 1)[1]))
    if not files:
        print(f"calibrate_states: no {args.data}/{args.case}_seed*.npz; make them with "
              "experiments/generate_data.py", file=sys.stderr)
        return 2
    rows = [indicators(f) for f in files]
    if args.contacts_threshold is None:  # the manifest's regime rule, per ball
        args.contacts_threshold = REGIME_PP_CONTACTS_PER_BALL * rows[0]["n_balls"]
    windows = [w for r in rows for w in r["windows"]]
    bed = [w["jar_speed_m_s"] for w in windows if w["pp_contacts"] >= args.contacts_threshold]
    agitated = [w["jar_speed_m_s"] for w in windows if w["pp_contacts"] < args.contacts_threshold]
    gap = {"bed_min_m_s": min(bed) if bed else None, "bed_max_m_s": max(bed) if bed else None,
           "agitated_min_m_s": min(agitated) if agitated else None,
           "agitated_max_m_s": max(agitated) if agitated else None,
           "midpoint_m_s": 0.5 * (max(bed) + min(agitated)) if bed and agitated else None}
    separates = bool(bed and agitated and max(bed) < AGITATED_SPEED_M_S <= min(agitated))
    result = {"case": args.case, "threshold_in_use_m_s": AGITATED_SPEED_M_S,
              "contacts_threshold": args.contacts_threshold,
              "windows_1s": {"bed": len(bed), "agitated": len(agitated)},
              "speed_gap_1s_windows": gap, "threshold_separates_1s_windows": separates,
              "runs": rows, "commit": git_commit()}
    out = Path(args.out)
    write_json(out / f"{args.case}_states.json", result)

    fig = new_figure(10.0, 4.0, layout="constrained")
    left, right = fig.subplots(1, 2)
    c = np.array([w["pp_contacts"] for w in windows])
    left.scatter(c, [w["jar_speed_m_s"] for w in windows], s=12)
    left.axhline(AGITATED_SPEED_M_S, color="tab:red", ls=":")
    left.axvline(args.contacts_threshold, color="grey", ls=":")
    left.set_xlabel("DEM ball-ball contacts (1-s window mean)")
    left.set_ylabel("mean ball speed in the jar frame (m/s)")
    right.scatter(c, [w["power_W"] for w in windows], s=12)
    right.axvline(args.contacts_threshold, color="grey", ls=":")
    right.set_xlabel("DEM ball-ball contacts (1-s window mean)")
    right.set_ylabel("dissipation power (W)")
    fig.suptitle(f"{args.case}: {len(rows)} DEM runs, {len(windows)} 1-s windows")
    save_figure(fig, out / f"{args.case}_states.png")
    for r in rows:
        print(f"seed {r['seed']:>3}: speed {r['jar_speed_m_s']:.3f} m/s, contacts "
              f"{r['pp_contacts']:5.1f}, power {r['power_W']:.3f} W")
    print(json.dumps({k: result[k] for k in ("windows_1s", "speed_gap_1s_windows",
                                             "threshold_in_use_m_s",
                                             "threshold_separates_1s_windows")}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
