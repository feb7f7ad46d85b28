#!/usr/bin/env python
"""The first milliseconds of the DEM evaluation runs: the records a candidate model's free
rollouts start from, when the DEM's statistics come from an earlier evaluation
(``evaluate_contact.py --dem-reference``; docs/contact.md, "Evaluating a candidate").

    python experiments/contact/dem_prefixes.py --ensembles experiments/envelope/ensembles.toml \
        --out data/prefix [--cases heldout_c00,...] [--duration 0.002] [--jobs 2]

For every evaluation seed of every selected case (its seeds that are not training seeds)
this runs ``sgn-jax dem --config CONFIG --duration D --seed S --out OUT/{case}_seed{S}.npz``:
the same settled packing and the same DEM steps as the full run, so the samples are the full
record's first ones, bit for bit (a settled packing is cached, so the cases of one jar share
it). ``--duration`` must cover the first window at the model's step (7 windows of 2e-4 s:
1.4 ms; default 2 ms). A file already there is kept. Exits 1 when a run failed.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import sgn_jax.experiment_tools as tools


def jobs_of(ensembles: str, cases: str | None, out: Path, duration: float) -> list[list[str]]:
    jobs = []
    for case in tools.select_cases(tools.load_ensembles(ensembles), cases):
        for seed in (s for s in case.seeds if s not in case.train_seeds):
            path = out / f"{case.name}_seed{seed}.npz"
            if path.exists():
                continue
            jobs.append(["sgn-jax", "dem", "--config", str(case.config_path), "--duration",
                         f"{duration:g}", "--seed", str(seed), "--out", str(path),
                         "--no-progress"])
    return jobs


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ensembles", required=True)
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--cases", default=None)
    ap.add_argument("--duration", type=float, default=0.002)
    ap.add_argument("--jobs", type=int, default=2)
    args = ap.parse_args(argv)
    if not 0 < args.duration <= 0.05:
        ap.error(f"--duration {args.duration}: a prefix of a few ms (0 < D <= 0.05 s)")
    args.out.mkdir(parents=True, exist_ok=True)
    jobs = jobs_of(args.ensembles, args.cases, args.out, args.duration)
    print(f"{len(jobs)} prefix runs to {args.out}", flush=True)

    def run(cmd: list[str]) -> int:
        proc = subprocess.run(cmd, capture_output=True, text=True)
        print(("ok   " if proc.returncode == 0 else "FAIL ") + cmd[-2], flush=True)
        if proc.returncode:
            print(proc.stderr[-2000:], file=sys.stderr)
        return proc.returncode

    with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        codes = list(pool.map(run, jobs))
    return 1 if any(codes) else 0


if __name__ == "__main__":
    raise SystemExit(main())
