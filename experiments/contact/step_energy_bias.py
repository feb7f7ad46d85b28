#!/usr/bin/env python
"""The energy a contact model's step gives the balls beyond the DEM's, teacher-forced.

    python experiments/contact/step_energy_bias.py --model runs/contact_dt2e \\
        --record data/envelope/train_c00_seed1000.npz [--stride 10]

For windows ending at every ``--stride``-th sample n of a DEM record (coarsened to the model's
step), the model's step from the DEM's own window and spins gives v_{n+1} and w_{n+1}; against
the DEM's next velocities and spins, the extra kinetic energy sum_i m/2 (|v_i|^2 - |v_DEM,i|^2)
+ I/2 (|w_i|^2 - |w_DEM,i|^2), summed over the windows and divided by the time they span, is a
power (W): the energy the model's step would inject (> 0) or take out (< 0) where the DEM's
does not, in the DEM's own states. Printed per class of ball (touching a wall and a ball, a
wall only, a ball only, neither, by the DEM's positions), beside the squared-error heating
m/2 sum |v - v_DEM|^2 per time and the DEM's target power over the record (docs/contact.md,
"One step", item 8: for contact_dt2e it is negative on agitated circles whose free rollouts
are too fast; the cause was the bed, not the step's energy).
"""

from __future__ import annotations

import argparse
import json
import math

import jax
import jax.numpy as jnp
import numpy as np

import sgn_jax.api as sj
import sgn_jax.experiment_tools as tools
from sgn_jax.api import graph_spec_from_config
from sgn_jax.experiment_tools import Window, build_graph, surrogate_walls_from_config

CLASSES = ("neither", "wall_only", "ball_only", "wall_and_ball")
DAMPING = ("diss_pp_normal", "diss_pp_tangential", "diss_pw_normal", "diss_pw_tangential")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", required=True, help="a contact model with spin (run or checkpoint)")
    ap.add_argument("--record", required=True, help="a DEM record (.npz) of the model's jar")
    ap.add_argument("--stride", type=int, default=10, help="samples between windows")
    args = ap.parse_args()

    sur = tools.load_trained_model(tools.resolve_checkpoint(args.model))
    cfg, net, params = sur.config, sur.model, sur.params
    if not getattr(net, "spin", False):
        raise SystemExit(f"{args.model} is not a contact model with spin state")
    spec = graph_spec_from_config(cfg)
    sdf, query = surrogate_walls_from_config(cfg)
    traj = sj.load_trajectory(args.record).at_step(spec.dt)
    pos, off = np.asarray(traj.pos, np.float64), np.asarray(traj.offset, np.float64)
    offv, omega = np.asarray(traj.offset_vel, np.float64), np.asarray(traj.omega, np.float64)
    w, n, dt = spec.window, spec.n_particles, spec.dt
    radius = float(cfg.balls.radius)
    mass = float(cfg.balls.density) * 4 / 3 * math.pi * radius ** 3
    inertia = 0.4 * mass * radius ** 2

    @jax.jit
    def step(p, o, ov, spins):
        window = Window(positions=p, offsets=o, offset_velocities=ov,
                        frequency_hz=jnp.zeros(()), spins=spins)
        graph, _ = build_graph(window, sdf, spec, query)
        terms = net.apply({"params": params}, graph, method=type(net).step_terms)
        return terms["dv"][:n], terms["dw"][:n]

    samples = np.arange(w + 1, len(pos) - 2, args.stride)
    extra = dict.fromkeys(CLASSES, 0.0)
    heating = 0.0
    for s in samples:
        dv, dw = step(pos[s - w: s + 1], off[s - w + 1: s + 1], offv[s - w + 1: s + 1], omega[s])
        v_model = (pos[s] - pos[s - 1]) / dt + np.asarray(dv)
        v_dem = (pos[s + 1] - pos[s]) / dt
        w_model, w_dem = omega[s] + np.asarray(dw), omega[s + 1]
        per_ball = (0.5 * mass * (np.sum(v_model ** 2, -1) - np.sum(v_dem ** 2, -1))
                    + 0.5 * inertia * (np.sum(w_model ** 2, -1) - np.sum(w_dem ** 2, -1)))
        x = pos[s]
        dist = np.linalg.norm(x[:, None] - x[None], axis=-1) + np.eye(n)   # not itself
        on_ball = (dist < 2 * radius + 1e-6).any(1)
        phi, _ = query(sdf, jnp.asarray(x), jnp.asarray(off[s]))
        on_wall = np.asarray(phi) > -radius - 1e-6
        cls = np.where(on_wall & on_ball, 3, np.where(on_wall, 1, np.where(on_ball, 2, 0)))
        for c, name in enumerate(CLASSES):
            extra[name] += float(np.sum(per_ball[cls == c]))
        heating += 0.5 * mass * float(np.sum((v_model - v_dem) ** 2))
    span = len(samples) * dt
    target = sum(float(np.sum(np.asarray(traj[k]))) for k in DAMPING) / (len(pos) * dt)
    print(json.dumps({"model": args.model, "record": args.record, "windows": int(len(samples)),
                      "extra_power_W": sum(extra.values()) / span,
                      **{f"extra_power_{k}_W": v / span for k, v in extra.items()},
                      "squared_error_heating_W": heating / span,
                      "dem_target_power_W": target}, indent=1))


if __name__ == "__main__":
    main()
