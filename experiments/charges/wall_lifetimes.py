"""How long the balls' wall contacts last: a DEM record of a charge against the charge model's
free rollout from the record's first window over the same interval.

    sgn-jax dem --config experiments/charges/configs/heldout_01.toml --duration 1.0 --seed 100 \
        --out runs/h01_dem_seed100.npz
    python experiments/charges/wall_lifetimes.py --record runs/h01_dem_seed100.npz \
        --config experiments/charges/configs/heldout_01.toml [--model contact_charge] \
        [--model-set 'friction_sweep_contacts="wall"'] [--duration 0.9] [--out runs/wall_life.json]

Prints one JSON line each for the DEM and the model (``sgn_jax.experiment_tools.
wall_contact_lifetimes`` at the model's step: balls touching the wall per step, the number of
touching runs, their mean length and histogram in steps, the wall-time fraction of the charge's
larger and smaller balls) and writes both to ``--out``. One packing: a lead, not an ensemble.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

import sgn_jax.api as sj
import sgn_jax.experiment_tools as tools


def summary(label: str, pos, offset, jar, radius) -> dict:
    out = tools.wall_contact_lifetimes(pos, offset, jar, radius)
    fraction = out.pop("pw_fraction_per_ball")
    larger = radius > radius.mean()
    out.update(label=label, steps=int(len(pos)),
               wall_fraction_larger=float(fraction[larger].mean()) if larger.any() else None,
               wall_fraction_smaller=float(fraction[~larger].mean()))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--record", required=True, help="a DEM record of the charge (sgn-jax dem)")
    ap.add_argument("--config", required=True, help="the charge's config")
    ap.add_argument("--model", default="contact_charge")
    ap.add_argument("--model-set", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--duration", type=float, default=0.9, help="s of rollout (default 0.9)")
    ap.add_argument("--out", default="runs/wall_life.json")
    args = ap.parse_args()
    model = tools.load_model_to_evaluate(args.model, args.model_set)
    cfg = sj.replace_section(sj.load_config(args.config), "dem", dt=float(model.config.dem.dt))
    record = sj.load_trajectory(args.record)
    res = sj.run_rollout(model, record, None, args.duration, None, cfg, save_every=1,
                         progress=False)
    arrays, radius = res["arrays"], np.asarray(res["meta"]["ball_radii"], np.float64)
    jar = sj.jar_params_from_config(cfg.jar)
    dem = record.at_step(float(cfg.dem.dt))
    first = int(np.argmin(np.abs(np.asarray(dem.t) - float(np.asarray(arrays["t_pos"])[0]))))
    steps = np.asarray(arrays["pos"]).shape[0]
    rows = [summary("dem", np.asarray(dem.pos)[first:first + steps],
                    np.asarray(dem.offset)[first:first + steps], jar, radius),
            summary(f"{args.model} {' '.join(args.model_set)}".strip(), arrays["pos"],
                    arrays["offset"], jar, radius)]
    for row in rows:
        print(json.dumps(row), flush=True)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps({"record": args.record, "config": args.config,
                                          "model_set": args.model_set, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
