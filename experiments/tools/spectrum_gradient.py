"""A design study of a collision statistic, checked against the DEM.

The contact model's `DesignStudy.collision_estimate` of a collision statistic (default the
power delivered by collisions of at least 1e-4 J) and its derivative with respect to the rpm,
by central differences with common packings; beside it the same from DEM ensembles: the same
packings (placement seeds) run at rpm - h, rpm and rpm + h, the statistic over the same
measurement interval (after the burn-in), the difference per packing.

    python experiments/tools/spectrum_gradient.py --config emax_300rpm --step 30 \\
        --seeds 4,5,6,7,8,9,10,11 --data data/collisions/gradient \\
        --out runs/collisions_eval/gradient.json --jobs 2
"""

from __future__ import annotations

import argparse
import concurrent.futures
import json
import math
import subprocess
from pathlib import Path

import sgn_jax.api as sj
import sgn_jax.experiment_tools as tools


def mean_se(values) -> tuple[float, float]:
    return tuple(float(x) for x in tools.mean_and_se(values))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default="emax_300rpm")
    ap.add_argument("--model", default="contact")
    ap.add_argument("--statistic", default="power_above_W")
    ap.add_argument("--threshold", type=float, default=1e-4)
    ap.add_argument("--step", type=float, default=30.0, help="rpm")
    ap.add_argument("--seeds", default="4,5,6,7,8,9,10,11")
    ap.add_argument("--duration", type=float, default=1.5)
    ap.add_argument("--burn-in", type=float, default=0.5)
    ap.add_argument("--data", default="data/collisions/gradient")
    ap.add_argument("--out", default="runs/collisions_eval/gradient.json")
    ap.add_argument("--jobs", type=int, default=2)
    args = ap.parse_args()
    seeds = [int(s) for s in args.seeds.split(",")]
    if len(seeds) < 2:
        raise SystemExit("--seeds: at least two packings")
    cfg = sj.load_config(args.config)
    rpm = float(cfg.motion.rpm)
    data = Path(args.data)
    data.mkdir(parents=True, exist_ok=True)

    # The DEM at rpm - h, rpm, rpm + h: one process per core.
    runs = []
    for label, value in (("minus", rpm - args.step), ("base", rpm), ("plus", rpm + args.step)):
        path = data / f"{label}.toml"
        tools.save_config(sj.replace_section(cfg, "motion", rpm=value), path)
        runs += [(label, seed, path, data / f"{label}_seed{seed}.npz") for seed in seeds]

    def dem(job):
        k, (label, seed, config, out) = job
        if not out.exists():
            subprocess.run(["taskset", "-c", str(k % args.jobs), "sgn-jax", "dem", "--config",
                            str(config), "--seed", str(seed), "--duration", str(args.duration),
                            "--out", str(out), "--no-progress"], check=True,
                           stdout=subprocess.DEVNULL)
        return label, seed, out

    with concurrent.futures.ThreadPoolExecutor(args.jobs) as pool:
        done = list(pool.map(dem, enumerate(runs)))
    dem_value = {}
    for label, seed, out in done:
        table = sj.load_events(out).window(args.burn_in, args.duration)
        stats = tools.collision_statistics(table, threshold=args.threshold)
        dem_value[(label, seed)] = float(stats[args.statistic])
    dem_base = mean_se([dem_value[("base", s)] for s in seeds])
    dem_grad = mean_se([(dem_value[("plus", s)] - dem_value[("minus", s)]) / (2 * args.step)
                        for s in seeds])

    # The surrogate: a design study of the same packings.
    tools.enable_compilation_cache()
    model = tools.load_trained_model(tools.resolve_checkpoint(args.model))
    scfg = sj.at_surrogate_step(cfg, model)
    packings = sj.make_packings(scfg, seeds=seeds)
    study = sj.design_study(model, scfg, ["motion.rpm"], packings, duration=args.duration,
                            burn_in=args.burn_in, n_segments=5)
    est = study.collision_estimate(args.statistic, steps={"motion.rpm": args.step},
                                   threshold=args.threshold)
    g = est["gradient"]["motion.rpm"]
    diff = g["value"] - dem_grad[0]
    result = {"statistic": args.statistic, "threshold_J": args.threshold, "rpm": rpm,
              "step_rpm": args.step, "seeds": seeds, "duration_s": args.duration,
              "burn_in_s": args.burn_in,
              "dem": {"value": dem_base, "gradient_per_rpm": dem_grad},
              "model": {"value": [est["value"], est["se"]],
                        "gradient_per_rpm": [g["value"], g["se"]]},
              "gradient_difference_in_se": diff / math.hypot(g["se"], dem_grad[1])}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=1))
    print(json.dumps(result))


if __name__ == "__main__":
    main()
