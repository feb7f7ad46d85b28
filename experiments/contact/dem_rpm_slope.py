"""The DEM's answer to the jar speed on the packings the `sgn-jax sensitivity` default uses
(issue 19): P(250 rpm) and P(350 rpm) of the standard case per packing, as
experiments/design/verify_gradients.py measures it on seeds 20-27 (1.5 s of motion, power
over 0.5-1.5 s), so that a surrogate's sensitivity on seeds 100-107 is compared with the DEM
on the SAME packings (paired), not with another 8.

    taskset -c 0 python experiments/contact/dem_rpm_slope.py --seeds 100-103 --out runs/dem_slope/a.jsonl &
    taskset -c 1 python experiments/contact/dem_rpm_slope.py --seeds 104-107 --out runs/dem_slope/b.jsonl

Resumable: a (seed, rpm) already in --out is skipped. Each line: seed, rpm, power_W, ...
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import sgn_jax.api as sj
import sgn_jax.experiment_tools as tools

DURATION, BURN_IN = 1.5, 0.5


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", required=True, help="first-last, e.g. 100-103")
    ap.add_argument("--rpm", default="250,350")
    ap.add_argument("--out", required=True)
    args = ap.parse_args()
    lo, hi = (int(x) for x in args.seeds.split("-"))
    out = Path(args.out)
    done = {(r["seed"], r["rpm"]) for r in tools.read_jsonl(out)}   # a line cut by a kill: redone
    base = sj.load_config("emax_300rpm")
    ensemble = sj.DEMEnsemble()
    for seed in range(lo, hi + 1):
        for rpm in (float(x) for x in args.rpm.split(",")):
            if (seed, rpm) in done:
                continue
            cfg = sj.design_config(base, ["motion.rpm"], [rpm])
            t0 = time.perf_counter()
            result = ensemble.power(cfg, seed, DURATION, BURN_IN)
            result.update(seed=seed, rpm=rpm, wall_s=time.perf_counter() - t0)
            tools.append_jsonl(out, result)   # one line per run: a kill loses at most that run
            print(f"seed {seed} rpm {rpm:g}: {result['power_W']:.4f} W "
                  f"({result['wall_s']:.0f} s)", flush=True)


if __name__ == "__main__":
    main()
