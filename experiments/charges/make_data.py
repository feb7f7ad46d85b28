"""DEM ensembles of the charge design (experiments/charges/design.toml), resumable.

    python experiments/charges/make_data.py --split train --seeds 0 1 2 --duration 1.5 \
        [--out data/charges] [--names train_00 train_03]

One record per (charge, seed) at OUT/NAME/seed_K.npz (``sgn-jax dem`` of the charge's config,
separation of the settle cache and the record as usual); a record that exists is skipped and a
killed run resumes from its last chunk. Prints one JSON line per record (wall time, steps/s,
mean power) and the progress with an ETA.
"""

from __future__ import annotations

import argparse
import json
import time
import tomllib
from pathlib import Path

import sgn_jax.api as sj

HERE = Path(__file__).resolve().parent


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--split", choices=("train", "heldout"), required=True)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--duration", type=float, default=1.5)
    parser.add_argument("--names", nargs="*", default=None)
    parser.add_argument("--out", default="data/charges")
    args = parser.parse_args()
    design = tomllib.loads((HERE / "design.toml").read_text())[args.split]
    names = args.names or sorted(design)
    jobs = [(name, seed) for seed in args.seeds for name in names]  # every charge early
    todo = [(n, s) for n, s in jobs if not (Path(args.out) / n / f"seed_{s}.npz").exists()]
    print(f"{len(jobs)} records, {len(jobs) - len(todo)} done, {len(todo)} to run", flush=True)
    t_start = time.perf_counter()
    for k, (name, seed) in enumerate(todo):
        cfg = sj.load_config(HERE / "configs" / f"{name}.toml")
        out = Path(args.out) / name / f"seed_{seed}.npz"
        out.parent.mkdir(parents=True, exist_ok=True)
        t0 = time.perf_counter()
        run = sj.run_dem(cfg, duration=args.duration, seed=seed, out_path=out, progress=False)
        wall = time.perf_counter() - t0
        done = time.perf_counter() - t_start
        eta = done / (k + 1) * (len(todo) - k - 1)
        print(json.dumps({"name": name, "seed": seed, "n_balls": cfg.balls.n_balls,
                          "wall_s": round(wall, 1),
                          "power_W": run.summary.get("mean_dissipation_power_W"),
                          "balls_outside": run.summary.get("balls_outside"),
                          "progress": f"{k + 1}/{len(todo)}", "eta_min": round(eta / 60, 1)}),
              flush=True)


if __name__ == "__main__":
    main()
