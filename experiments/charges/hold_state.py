"""Does a surrogate keep the DEM's state of a charge? One DEM packing against the model started
from its first window, block by block.

    python experiments/charges/hold_state.py --config experiments/charges/configs/heldout_05.toml \
        --seed 105 [--model contact_charge] [--duration 2.4] [--block 0.2] \
        [--out runs/hold_state] [--model-set friction_sweeps=12]

Runs the DEM of the config (its charge, jar and motion; samples at the model's step) for
``--duration`` s from placement seed ``--seed`` (``sgn_jax.api.run_dem``; resumed if the record
exists), rolls the model out from the record's first window with the ball-ball separation off,
and prints, per ``--block`` s, the DEM's and the model's power (normal + tangential damping),
touching ball-ball and ball-wall contacts per step and mean jar-frame speed. A charge that splits
between a bed and an agitated state (docs/conventions.md section 7) shows here whether the model
holds the DEM's bed or leaves it, and when. Writes OUT/<case>_seed_<K>.json.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

import sgn_jax.api as sj
from sgn_jax.experiment_tools import (
    DAMPING,
    contact_census,
    jar_frame_speed,
    with_model_keys,
    write_json,
)


def block_rows(t: np.ndarray, pos: np.ndarray, off: np.ndarray, power_per_step: np.ndarray,
               jar, radius, dt: float, block: int) -> list[dict]:
    """Per block of ``block`` steps: mean power (W), contacts per step, jar-frame speed (m/s)
    of frames ``pos`` (S + 1, N, 3) with ``power_per_step`` (S,) J per step."""
    rows = []
    for b in range(len(power_per_step) // block):
        frames = slice(b * block, (b + 1) * block + 1)
        census = contact_census(pos[frames], off[frames], jar, radius)
        rows.append({"t0_s": float(t[b * block] - t[0]),
                     "power_W": float(np.sum(power_per_step[b * block:(b + 1) * block]))
                     / (block * dt),
                     "pp_contacts": float(census["pp_touching_mean"]),
                     "pw_contacts": float(census["pw_touching_mean"]),
                     "speed_m_s": float(np.mean(jar_frame_speed(t[frames], pos[frames],
                                                                off[frames])))})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", required=True)
    ap.add_argument("--seed", type=int, required=True)
    ap.add_argument("--model", default="contact_charge")
    ap.add_argument("--duration", type=float, default=2.4)
    ap.add_argument("--block", type=float, default=0.2)
    ap.add_argument("--out", default="runs/hold_state")
    ap.add_argument("--model-set", action="append", default=[], metavar="KEY=VALUE",
                    help="a [model] key of the model's config replaced, e.g. friction_sweeps=12")
    args = ap.parse_args()
    sj.enable_compilation_cache()
    model = with_model_keys(sj.load_surrogate(args.model), args.model_set)
    dt = float(model.config.dem.dt)
    window = int(model.config.graph.window)
    cfg = sj.load_config(args.config)
    cfg = sj.replace_section(sj.replace_section(cfg, "dem", dt=dt), "rollout",
                             pp_separation=False)
    block = int(round(args.block / dt))
    n_steps = int(round(args.duration / dt)) // block * block
    if n_steps < block:
        ap.error(f"--duration {args.duration} s holds no whole --block of {args.block} s")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    stem = f"{cfg.case.name}_seed_{args.seed}"
    record = out / f"{stem}_dem.npz"
    if not record.exists():
        sj.run_dem(cfg, duration=(n_steps + window + 1) * dt, seed=args.seed, out_path=record,
                   progress=True)
    traj = sj.load_trajectory(record).at_step(dt)
    result = sj.run_rollout(model, traj, window, n_steps * dt, None, cfg, save_every=1,
                            progress=True)
    a = result["arrays"]
    jar = sj.jar_params_from_config(cfg.jar)
    radius = (np.asarray(result["meta"]["ball_radii"], np.float64)   # a charge-reading kind
              if "ball_radii" in result["meta"] else float(cfg.balls.radius))
    frames = slice(window, window + n_steps + 1)
    dem_power = sum(np.asarray(traj[k][window + 1:window + n_steps + 1]) for k in DAMPING)
    dem = block_rows(np.asarray(traj.t[frames]), np.asarray(traj.pos[frames]),
                     np.asarray(traj.offset[frames]), dem_power, jar, radius, dt, block)
    mod = block_rows(np.asarray(a["t_pos"]), np.asarray(a["pos"]), np.asarray(a["offset"]),
                     np.asarray(a["dE"]), jar, radius, dt, block)
    print(f"{stem}, model {args.model}: per {args.block:g} s block, DEM / model")
    print("   t (s)   power (W)        ball-ball / step   ball-wall / step   speed (m/s)")
    for d, m in zip(dem, mod, strict=True):
        print(f"  {d['t0_s']:5.2f}   {d['power_W']:6.2f} / {m['power_W']:6.2f}   "
              f"{d['pp_contacts']:6.1f} / {m['pp_contacts']:5.1f}     "
              f"{d['pw_contacts']:6.1f} / {m['pw_contacts']:5.1f}     "
              f"{d['speed_m_s']:5.3f} / {m['speed_m_s']:5.3f}")
    summary = {"config": str(args.config), "seed": args.seed, "model": args.model,
               "model_set": list(args.model_set), "dt_s": dt, "block_s": block * dt, "dem": dem, "model_blocks": mod}
    write_json(out / f"{stem}.json", summary)
    print(json.dumps({"json": str(out / f"{stem}.json")}))


if __name__ == "__main__":
    main()
