#!/usr/bin/env python
"""How a contact model answers one clean impact, against the DEM's contact law.

    python experiments/contact/impact_response.py --model contact [--out runs/contact_eval]

Two head-on impacts at approach speeds 0.05-6 m/s (the envelope's violent orbits reach 3-5
m/s relative):

- **ball on wall**: one ball falls straight onto the floor of a still jar (gravity on);
- **ball on ball**: two balls approach each other along x in the middle of a still jar
  (gravity on for both, so it cancels in their relative motion).

For each, the model's free rollout (no snap-back, no separation) gives the coefficient of
restitution (rebound / approach normal speed, measured 1.5 ms after the contact ends) and the
deepest overlap; the DEM's law (Hertz with the damping of restitution e, SPEC section 3) gives
the same two numbers by integrating the 1-D normal contact at 1e-7 s. The DEM's e is the
config's restitution for every speed (that is how the damping is chosen); its deepest overlap
grows like v^(4/5).

A model whose e grows with speed is too lively in violent motions (more agitation, more power,
deeper overlaps); one whose overlap grows faster than v^(4/5) lets hard impacts through.
Writes OUT/impact_NAME.json and prints a table.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import sgn_jax.api as sj
import sgn_jax.experiment_tools as tools
from sgn_jax.api import make_rollout
from sgn_jax.experiment_tools import GraphSpec, Window, model_predictor

SPEEDS = (0.05, 0.2, 0.5, 1.0, 2.0, 3.0, 4.0, 6.0)


def dem_impact(cfg, speed: float, wall: bool) -> tuple[float, float]:
    """(restitution, deepest overlap m) of a 1-D head-on contact with the DEM's normal force
    (``sj.head_on_normal_force``: Hertz spring and damping, not clipped), explicit at 1e-7 s."""
    laws = tools.dem_params_from_config(cfg)
    law = jax.tree_util.tree_map(float, laws.pw if wall else laws.pp)
    m, dt = law.mass_eff, 1e-7
    d, v, deepest = 0.0, speed, 0.0          # overlap and its rate (approach > 0)
    while True:
        v -= float(tools.head_on_normal_force(law, d, v)) / m * dt
        d += v * dt
        deepest = max(deepest, d)
        if d < 0:
            return -v / speed, deepest


def model_impact(model, speed: float, wall: bool, steps: int = 400) -> tuple[float, float]:
    """(restitution, deepest overlap m) of the model's free rollout of the same impact."""
    cfg = model.config
    r, dt = cfg.balls.radius, cfg.dem.dt
    n = 1 if wall else 2
    spec = GraphSpec(n_particles=n, window=cfg.graph.window, ball_radius=r, dt=dt,
                     pp_skin=cfg.graph.pp_skin, phi_pw=cfg.graph.phi_pw, pp_pair_capacity=4,
                     wall_patches=cfg.graph.wall_patches)
    still = sj.replace_section(cfg, "motion", kind="circle", rpm=300.0, amplitude=0.0)
    w = spec.window
    slots = np.arange(w + 1) - w                       # ..., -1, 0: the newest slot is 0
    gap0 = 1.5 * speed * dt + 2e-6                     # contact within the first steps
    if wall:
        direction = np.array([[0.0, -1.0, 0.0]])
        start = np.array([[0.0, r + gap0, 0.0]])
    else:
        direction = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
        centre_y = 0.02
        start = np.array([[-r - gap0 / 2, centre_y, 0.0], [r + gap0 / 2, centre_y, 0.0]])
    rel_speed = speed / (1 if wall else 2)             # each ball moves at half the approach
    pos = start[None] + rel_speed * direction[None] * (slots[:, None, None] * dt)
    window = Window(positions=jnp.asarray(pos), offsets=jnp.zeros((w, 3)),
                    offset_velocities=jnp.zeros((w, 3)), frequency_hz=jnp.asarray(5.0))
    run = make_rollout(spec, model_predictor(model.model), steps, 1, snap_back=False,
                       query=tools.analytic_jar_query)
    res = run(model.params, model.norm_stats, window, sj.motion_from_config(still.motion),
              sj.jar_params_from_config(cfg.jar), 0.0)
    traj = np.concatenate([pos, np.asarray(res.positions)])
    if wall:
        gap = traj[:, 0, 1] - r
        normal_speed = np.diff(traj[:, 0, 1]) / dt           # + away from the floor
    else:
        gap = (traj[:, 1, 0] - traj[:, 0, 0]) - 2 * r
        normal_speed = np.diff(traj[:, 1, 0] - traj[:, 0, 0]) / dt
    touching = np.flatnonzero(gap < 0)
    if len(touching) == 0:
        return float("nan"), 0.0
    end = touching[-1] + 15                                    # 1.5 ms after the last overlap
    if end >= len(normal_speed):
        return float("nan"), float(-gap.min())
    g_correction = 9.81 * (end - touching[-1]) * dt if wall else 0.0  # gravity's slowing
    return float((normal_speed[end] + g_correction) / speed), float(-gap.min())


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", default="contact", help="shipped name or checkpoint folder")
    ap.add_argument("--name", default=None)
    ap.add_argument("--out", type=Path, default=Path("runs/contact_eval"))
    args = ap.parse_args()
    model = sj.load_surrogate(args.model)
    name = args.name or Path(args.model).name
    rows = []
    print(f"{'contact':8} {'v m/s':>6} {'e DEM':>6} {'e model':>8} {'overlap DEM um':>15} "
          f"{'model um':>9}")
    for wall in (True, False):
        for v in SPEEDS:
            e_dem, d_dem = dem_impact(model.config, v, wall)
            e_mod, d_mod = model_impact(model, v, wall)
            kind = "pw" if wall else "pp"
            rows.append({"kind": kind, "speed": v, "e_dem": e_dem, "e_model": e_mod,
                         "overlap_dem_m": d_dem, "overlap_model_m": d_mod})
            print(f"{kind:8} {v:6.2f} {e_dem:6.3f} {e_mod:8.3f} {d_dem * 1e6:15.1f} "
                  f"{d_mod * 1e6:9.1f}", flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / f"impact_{name}.json"
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps({"model": args.model, "rows": rows}, indent=1))
    tmp.replace(path)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
