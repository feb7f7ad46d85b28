"""Draw the charge-envelope design: training and held-out charges (docs/charge.md).

    python experiments/charges/design.py [--out experiments/charges/design.toml]

Training charges: a Latin hypercube over the whole envelope (sgn_jax/data/charge_envelope.toml),
each held to at most --max-train-balls balls (the fill is lowered where a draw holds more), so
that the large charges are left for the held-out set. Held-out charges: a second hypercube
(another seed) whose rows are constrained as the charge issue asks: rows 0 and 1 mixtures,
row 2 at least 150 balls (small balls, high fill), row 3 a density <= 3,000 kg/m^3, row 4 a
restitution >= 0.7, row 5 free. Writes the design as TOML (one table per charge) and one config
per charge under experiments/charges/configs/.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import tomli_w

import sgn_jax.api as sj
from sgn_jax.experiment_tools import (
    check_dem_config,
    jar_volume,
    latin_hypercube_charges,
    load_charge_envelope,
    save_config,
)

HERE = Path(__file__).resolve().parent


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--train", type=int, default=12)
    parser.add_argument("--max-train-balls", type=int, default=60)
    parser.add_argument("--seed", type=int, default=35)
    parser.add_argument("--out", default=str(HERE / "design.toml"))
    args = parser.parse_args()
    env = load_charge_envelope()
    base = sj.load_config("emax_300rpm")
    volume = float(jar_volume(sj.jar_params_from_config(base.jar)))
    share = env.mixture_share
    train = latin_hypercube_charges(env, args.train, args.seed, volume, prefix="train",
                                    max_balls=args.max_train_balls)
    # Held out: unit sub-ranges of the design dimensions (see the module docstring). Row 2:
    # diameter 6-7 mm and fill 16-20 % (150+ balls of one size); row 3: density 2,600-3,000;
    # row 4: restitution 0.7-0.8.
    span = lambda lo, hi, bounds: ((lo - bounds[0]) / (bounds[1] - bounds[0]),  # noqa: E731
                                   (hi - bounds[0]) / (bounds[1] - bounds[0]))
    constraints = {
        0: {"mixture": (0.0, share)},
        1: {"mixture": (0.0, share)},
        2: {"mixture": (share, 1.0), "diameter": span(0.006, 0.007, env.diameter),
            "fill": span(0.16, 0.20, env.fill)},
        3: {"density": span(2600.0, 3000.0, env.density)},
        4: {"restitution": span(0.7, 0.8, env.restitution)},
    }
    heldout = latin_hypercube_charges(env, 6, args.seed + 1, volume, prefix="heldout",
                                      constraints=constraints)
    doc = {"envelope": "sgn_jax/data/charge_envelope.toml", "seed": args.seed,
           "max_train_balls": args.max_train_balls, "jar_volume_ml": volume * 1e6,
           "train": {}, "heldout": {}}
    configs = HERE / "configs"
    configs.mkdir(exist_ok=True)
    for split, rows in (("train", train), ("heldout", heldout)):
        for row in rows:
            cfg = row.apply(base, env)
            check_dem_config(cfg, warn=False)  # every charge must be a valid DEM run
            save_config(cfg, configs / f"{row.name}.toml")
            doc[split][row.name] = {**row.to_dict(), "n_balls": row.n_balls,
                                    "fill": round(row.fill(volume), 4), "label": row.label()}
            print(f"{row.name}: {row.label()} ({row.n_balls} balls, fill "
                  f"{100 * row.fill(volume):.1f} %)")
    Path(args.out).write_text(tomli_w.dumps(doc))


if __name__ == "__main__":
    main()
