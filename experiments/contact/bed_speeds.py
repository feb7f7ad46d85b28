#!/usr/bin/env python
"""How a contact model's bed moves: jar-frame ball speeds of free rollouts against the DEM.

    python experiments/contact/bed_speeds.py --model runs/contact_dt2e \\
        --records train_c03_seed1030,train_c10_seed1102 [--data data/envelope] \\
        [--duration 1.0] [--physics friction_sweeps=6]

Each record (``DATA/NAME.npz``, its motion's config ``experiments/envelope/configs/CASE.toml``)
is rolled out from its first window for ``--duration`` s with the ball-ball separation off; the
jar-frame speed of every ball-step of the model and of the DEM over the same interval is pooled
over the records. Printed: speed quantiles, the share of ball-steps slower than 5, 10 and 20
cm/s, and the same for the ball-steps that touch a wall (centre within R + 20 um of it) and for
the others. A bed that creeps where the DEM's holds shows as too few slow wall-touching
ball-steps (docs/contact.md, "One step", item 8). ``--physics KEY=VALUE`` changes the model's
:class:`sgn_jax.surrogate.contact.ContactPhysics` for the run (no retraining).
"""

from __future__ import annotations

import argparse
import dataclasses
import json

import jax.numpy as jnp
import numpy as np

import sgn_jax.api as sj
import sgn_jax.experiment_tools as tools

QUANTILES = (0.1, 0.25, 0.5, 0.75, 0.9, 0.99)
SLOW = (0.05, 0.1, 0.2)


def touching_wall(pos, offsets, jar, radius):
    """(S, N) bool: ball centres within R + 20 um of a wall."""
    flat = jnp.asarray(pos.reshape(-1, 3))
    off = jnp.asarray(np.repeat(offsets, pos.shape[1], axis=0))
    phi, _ = tools.analytic_jar_query(jar, flat, off)
    return np.asarray(phi).reshape(pos.shape[:2]) > -radius - 2e-5


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", required=True)
    ap.add_argument("--records", required=True, help="comma-separated record names")
    ap.add_argument("--data", default="data/envelope")
    ap.add_argument("--duration", type=float, default=1.0)
    ap.add_argument("--physics", action="append", default=[], metavar="KEY=VALUE")
    args = ap.parse_args()

    model = tools.load_trained_model(tools.resolve_checkpoint(args.model))
    if args.physics:
        changes = {k: type(getattr(model.model.physics, k))(float(v))
                   for k, v in (item.split("=", 1) for item in args.physics)}
        model = dataclasses.replace(model, model=model.model.clone(
            physics=dataclasses.replace(model.model.physics, **changes)))
    dt, window = float(model.config.dem.dt), int(model.config.graph.window)
    radius = float(model.config.balls.radius)
    n = int(round(args.duration / dt))
    pooled = {"model": ([], []), "dem": ([], [])}
    for name in args.records.split(","):
        case = name.rsplit("_seed", 1)[0]
        cfg = sj.load_config(f"experiments/envelope/configs/{case}.toml")
        cfg = sj.replace_section(sj.replace_section(cfg, "rollout", pp_separation=False),
                                 "dem", dt=dt)
        traj = sj.load_trajectory(f"{args.data}/{name}.npz").at_step(dt)
        res = sj.run_rollout(model, traj, window, n * dt, None, cfg, save_every=1,
                             progress=False)
        jar = sj.jar_params_from_config(cfg.jar)
        sl = slice(window, window + n + 1)
        for who, pos, off in (("model", np.asarray(res["arrays"]["pos"]),
                               np.asarray(res["arrays"]["offset"])),
                              ("dem", np.asarray(traj.pos[sl]), np.asarray(traj.offset[sl]))):
            speed = np.linalg.norm(np.diff(pos - off[:, None], axis=0), axis=-1) / dt
            pooled[who][0].append(speed.ravel())
            pooled[who][1].append(touching_wall(pos[1:], off[1:], jar, radius).ravel())
    out = {"model": args.model, "records": args.records.split(","), "physics": args.physics}
    for who, (speeds, walls) in pooled.items():
        s, w = np.concatenate(speeds), np.concatenate(walls)
        out[who] = {"mean_m_s": float(s.mean()),
                    "quantiles_m_s": dict(zip(map(str, QUANTILES),
                                              np.quantile(s, QUANTILES).round(4).tolist(),
                                              strict=True)),
                    "wall_touching_share": float(w.mean()),
                    **{f"slow_{v}": float(np.mean(s < v)) for v in SLOW},
                    **{f"slow_{v}_wall": float(np.mean(s[w] < v)) for v in SLOW},
                    **{f"slow_{v}_free": float(np.mean(s[~w] < v)) for v in SLOW}}
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
