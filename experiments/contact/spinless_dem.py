"""Does spin set the motion response at the standard point? The DEM without rotation.

docs/contact.md's diagnosis of the contact model (issue 19): its power at the standard point
answers the jar speed 1.8-2.1x as strongly as the DEM's (P(350 rpm) +50-65 %), and the suspect
is rolling, which a model without spin cannot represent. This script tests the suspect in the
DEM itself: the same ensemble as issue 11's verification (seeds 20-27, 1.5 s of motion, power
over (0.5, 1.5] s, settled with the full physics), run with the balls' moment of inertia
multiplied by ``--inertia-factor`` (1e6: the balls cannot turn, so every tangential contact
slides or sticks, as in a spinless surrogate). If the spinless DEM over-responds as the model
does, spin is the missing state; if it answers as the full DEM, it is not.

    python experiments/contact/spinless_dem.py --rpm 250 350 --workers 2

Results: one JSON line per run in ``runs/spinless/worker*.jsonl`` (resumable: runs already
logged are skipped), the table on stdout.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

import sgn_jax.api as sj
from sgn_jax.experiment_tools import append_jsonl, read_jsonl

OUT = Path("runs/spinless")
SEEDS = tuple(range(20, 28))   # issue 11's DEM ensemble (experiments/design/verify_gradients.py)
DURATION, BURN_IN = 1.5, 0.5


@dataclasses.dataclass
class FrozenSpinEnsemble(sj.DEMEnsemble):
    """A DEMEnsemble whose powered runs (not the settling) have the inertia scaled."""

    inertia_factor: float = 1.0e6
    _frozen: bool = False

    def _run(self, setup, state, n_samples):
        if self._frozen and self.inertia_factor != 1.0:
            params = setup.params.replace(inertia=setup.params.inertia * self.inertia_factor)
            setup = dataclasses.replace(setup, params=params)
            # balls that cannot turn: no spin (set at every chunk; with factor 1 nothing changes)
            state = state.replace(omega=0.0 * state.omega)
        return super()._run(setup, state, n_samples)

    def power(self, cfg, seed, duration, burn_in):
        # Settle first with the full physics (and cache it as any DEMEnsemble does); only then
        # freeze, so that power()'s own settled() call finds the packing in memory and only
        # the powered run is spinless.
        self.settled(cfg, seed)
        self._frozen = True
        try:
            return super().power(cfg, seed, duration, burn_in)
        finally:
            self._frozen = False


def jobs(rpms, factor):
    return [(rpm, factor, seed) for rpm in rpms for seed in SEEDS]


def key(job):
    return f"{job[0]}|{job[1]:g}|{job[2]}"


def worker(index, of, rpms, factor):
    done = {r["key"] for p in OUT.glob("worker*.jsonl") for r in read_jsonl(p)}
    todo = [j for i, j in enumerate(jobs(rpms, factor)) if i % of == index and key(j) not in done]
    ens = FrozenSpinEnsemble(inertia_factor=factor)
    base = sj.load_config("emax_300rpm")
    t_start = time.perf_counter()
    for n, job in enumerate(todo, 1):
        rpm, _, seed = job
        cfg = sj.design_config(base, ["motion.rpm"], [float(rpm)])
        res = ens.power(cfg, seed, DURATION, BURN_IN)
        res.update(key=key(job), rpm=rpm, inertia_factor=factor)
        append_jsonl(OUT / f"worker{index}.jsonl", res)
        rate = (time.perf_counter() - t_start) / n
        print(f"[worker {index}] {n}/{len(todo)} {key(job)}: {res['power_W']:.4f} W; "
              f"ETA {rate * (len(todo) - n) / 60:.1f} min", flush=True)


def report():
    rows = [r for p in sorted(OUT.glob("worker*.jsonl")) for r in read_jsonl(p)]
    groups = {}
    for r in rows:
        groups.setdefault((r["inertia_factor"], r["rpm"]), []).append(r)
    print("| inertia factor | rpm | packings | P W (SE) | ball-ball contacts per step |")
    print("|---|---|---|---|---|")
    for (factor, rpm), rs in sorted(groups.items()):
        mean, se = sj.ensemble_mean([r["power_W"] for r in rs])
        print(f"| {factor:g} | {rpm} | {len(rs)} | {mean:.4f} ({se:.4f}) | "
              f"{np.mean([r['mean_pp_contacts'] for r in rs]):.2f} |")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rpm", type=float, nargs="+", default=[250.0, 350.0])
    ap.add_argument("--inertia-factor", type=float, default=1.0e6)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--index", type=int, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    OUT.mkdir(parents=True, exist_ok=True)
    if args.index is not None:
        worker(args.index, args.workers, args.rpm, args.inertia_factor)
        return
    procs = []
    for i in range(args.workers):
        cmd = [sys.executable, __file__, "--rpm", *map(str, args.rpm), "--inertia-factor",
               str(args.inertia_factor), "--workers", str(args.workers), "--index", str(i)]
        if args.workers > 1 and os.path.exists("/usr/bin/taskset"):
            cmd = ["taskset", "-c", str(i % os.cpu_count()), *cmd]
        procs.append(subprocess.Popen(cmd))
    if any(p.wait() for p in procs):
        sys.exit("a worker failed")
    report()


if __name__ == "__main__":
    main()
