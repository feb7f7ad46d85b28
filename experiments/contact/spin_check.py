"""The spins a contact model with spin state carries, against the DEM's (issue 19).

Rolls the model out for ``--duration`` s from each record's window (sample 7) and prints the
mean contact-point speed of the spin, R |w|, over the first, second and last parts of the
rollout, beside the DEM record's over the same samples, under the record's own jar and motion
with the ball-ball separation off (docs/contact.md).

    python experiments/contact/spin_check.py --model runs/contact_t12 \
        data/envelope/heldout_c02_seed4.npz data/envelope/heldout_h00_seed4.npz
"""

from __future__ import annotations

import argparse

import numpy as np

import sgn_jax.api as sj
import sgn_jax.experiment_tools as tools


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", required=True, help="a training run directory (its best checkpoint)")
    ap.add_argument("--duration", type=float, default=1.0)
    ap.add_argument("--every", type=int, default=10, help="steps between compared frames")
    ap.add_argument("records", nargs="+")
    args = ap.parse_args()
    model = tools.load_trained_model(args.model, which="best")
    if not getattr(model.model, "spin", False):
        raise SystemExit(f"{args.model} has no spin state ([model] spin = false)")
    radius = float(model.config.balls.radius)
    start = int(model.config.graph.window)
    for path in args.records:
        traj = sj.load_trajectory(path)
        # The record's own jar and motion (its config), the ball-ball separation off: without
        # the override the rollout ran the model's training config's motion, not the
        # record's (fixed 2026-11-26; the spins this script reported before were of another
        # motion than the DEM's they were compared with).
        cfg = sj.replace_section(traj.config, "rollout", pp_separation=False)
        res = sj.run_rollout(model, traj, start, args.duration, None, cfg,
                             save_every=args.every, progress=False)
        spins = res["arrays"]["omega_model"]
        n = spins.shape[0]
        dem = np.asarray(traj.omega)[start: start + args.every * n: args.every][:n]
        n = min(n, len(dem))
        for lo, hi in ((0, n // 4), (n // 4, n // 2), (n // 2, n)):
            model_speed = radius * np.linalg.norm(spins[lo:hi], axis=-1).mean()
            dem_speed = radius * np.linalg.norm(dem[lo:hi], axis=-1).mean()
            print(f"{path}: frames {lo}-{hi}: R|w| model {model_speed:.4f} m/s, "
                  f"DEM {dem_speed:.4f} m/s")


if __name__ == "__main__":
    main()
