"""A first look at the charge-conditioned contact model on held-out charges (one packing each).

    python experiments/charges/probe_rollout.py runs/contact_charge/second \
        data/charges_heldout/heldout_03/seed_100.npz [more records ...]

Rolls the checkpoint (model kind ``contact_charge``, its latest step) out from each DEM record's
first window, with the record's charge (``Window.charge``), for the record's 2.5 s, and prints
one JSON line per record: the mean power of the model's dissipation target and of the DEM's
normal + tangential damping over (0.5 s, end]. One packing per record: a probe of whether the
model runs and what it does, not an ensemble result (the rollout drivers do not take this kind
yet, docs/contact_charge.md).
"""

from __future__ import annotations

import dataclasses
import json
import sys

import jax.numpy as jnp
import numpy as np

import sgn_jax.api as sj
from sgn_jax.experiment_tools import (
    Window,
    ball_charge,
    charge_from_config,
    config_from_dict,
    load_trained_model,
    model_predictor,
    surrogate_walls_from_config,
)

BURN_IN_S = 0.5
# The wall snap-back's threshold ([graph] phi_sb = -4.9 mm) is a 5 mm ball's, not each ball's:
# off here, so smaller balls touching the wall are not pushed off it at every step.
SNAP_BACK = False


def probe(model, path: str) -> dict:
    cfg = model.config
    dt = float(cfg.dem.dt)
    record = sj.load_trajectory(path)
    record_cfg = config_from_dict(record.meta["config"])
    every = int(round(dt / float(record.meta["dt"])))   # the record's samples per model step
    pos = np.asarray(record.pos)[::every]
    off = np.asarray(record.offset)[::every]
    off_vel = np.asarray(record.offset_vel)[::every]
    t = np.asarray(record.t)[::every]
    n, w = pos.shape[1], cfg.graph.window
    spec = dataclasses.replace(sj.graph_spec_from_config(cfg, n_particles=n),
                               pp_pair_capacity=max(1, cfg.graph.pp_edges_per_particle * n // 2))
    charge = ball_charge(charge_from_config(record_cfg), n_balls=n, classes=3,
                         radii=record.meta.get("ball_radii"), masses=record.meta.get("ball_masses"))
    spins = jnp.asarray(np.asarray(record.omega)[::every][w - 1]) if model.model.spin else None
    window = Window(positions=jnp.asarray(pos[:w + 1]), offsets=jnp.asarray(off[:w]),
                    offset_velocities=jnp.asarray(off_vel[:w]), frequency_hz=jnp.zeros(()),
                    spins=spins, charge=charge)
    sdf, query = surrogate_walls_from_config(cfg)
    steps = int(round(float(t[-1]) / dt)) - w
    steps -= steps % 10
    rollout = sj.make_rollout(spec, model_predictor(model.model), steps, 10, query=query,
                              snap_back=SNAP_BACK)
    result = rollout(model.params, model.norm_stats, window,
                     sj.motion_from_config(record_cfg.motion), sdf, float(t[w]))
    energy, t_step = np.asarray(result.steps.dE), np.asarray(result.t_step)
    kept = t_step > BURN_IN_S
    span = float(t_step[kept][-1]) - BURN_IN_S
    arrays = record.arrays
    dem = sum(np.asarray(arrays[f"diss_{c}_{k}"]) for c in ("pp", "pw")
              for k in ("normal", "tangential"))
    t_dem = np.asarray(record.t)
    in_window = (t_dem > BURN_IN_S) & (t_dem <= float(t_step[kept][-1]))
    p_model = float(energy[kept].sum()) / span
    p_dem = float(dem[in_window].sum()) / span
    steps_out = result.steps
    return {"record": path, "n_balls": n, "model_W": p_model, "dem_W": p_dem,
            "relative": p_model / p_dem - 1,
            "model_pp_W": float(np.asarray(steps_out.diss_pp)[kept].sum()) / span,
            "model_pw_W": float(np.asarray(steps_out.diss_pw)[kept].sum()) / span,
            "edge_overflow_steps": int(np.sum(np.asarray(steps_out.overflow) > 0)),
            "max_outside": int(np.max(np.asarray(steps_out.n_outside))),
            "snapped_ball_steps": int(np.sum(np.asarray(steps_out.n_snapped))),
            "finite": bool(np.all(np.isfinite(np.asarray(result.positions))))}


def main() -> None:
    model = load_trained_model(sys.argv[1], which="latest")
    for path in sys.argv[2:]:
        print(json.dumps(probe(model, path)), flush=True)


if __name__ == "__main__":
    main()
