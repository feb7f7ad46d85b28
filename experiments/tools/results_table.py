#!/usr/bin/env python
"""Print the markdown tables of docs/results.md from ``results.json`` files.

    python experiments/tools/results_table.py runs/experiments/NAME/results.json [...]

One table per results file (a model): a row per case with the paper's per-trajectory metrics
over the held-out packings (MSE_t plateau, final cumulative-energy error signed and absolute,
Pearson r: mean and range), the ensemble metrics of docs/conventions.md section 7 (mean
dissipation power of DEM and surrogate, the error of the ensemble means, agitated runs of DEM
and surrogate), balls outside the jar and ms per surrogate step; then the runtime row. Numbers only come from the files.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path


def _fmt(value, spec: str) -> str:
    return "n/a" if value is None else format(value, spec)


def _signed_errors(case: dict) -> list[float]:
    out = []
    for run in case["runs"]:
        pred, ref = run.get("energy_pred_J"), run.get("energy_ref_J")
        if pred is not None and ref:
            out.append((pred - ref) / ref)
    return out


def table(results: dict) -> str:
    lines = [
        "| case | runs | MSE_t plateau (m²) mean [min, max] | final energy error, signed mean "
        "[min, max] | mean abs | Pearson r mean [min] | power DEM (W) | power SGN (W) | "
        "error of ensemble means | agitated DEM / SGN | balls outside | ms/step |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, case in results["cases"].items():
        mse, r = case["mse_plateau_m2"], case["pearson_r"]
        signed = _signed_errors(case)
        ens = case["ensemble"]
        power = ens["power"]
        states = ens["states"]
        lines.append(
            f"| {name} | {len(case['runs'])} | {_fmt(mse['mean'], '.2e')} "
            f"[{_fmt(mse['min'], '.1e')}, {_fmt(mse['max'], '.1e')}] | "
            + (f"{100 * sum(signed) / len(signed):+.1f} % [{100 * min(signed):+.0f}, "
               f"{100 * max(signed):+.0f}] % | " if signed else "n/a | ")
            + f"{100 * case['abs_energy_relative_error_final']['mean']:.1f} % | "
            f"{_fmt(r['mean'], '.4f')} [{_fmt(r['min'], '.3f')}] | "
            f"{_fmt(power['ref_W']['mean'], '.3f')} ± {_fmt(power['ref_W']['std'], '.3f')} | "
            f"{_fmt(power['pred_W']['mean'], '.3f')} ± {_fmt(power['pred_W']['std'], '.3f')} | "
            f"{100 * power['relative_error_of_means']:.1f} % | "
            f"{states['ref']['agitated']['count']} / {states['pred']['agitated']['count']} | "
            f"{case['balls_outside_total']} | {_fmt(case['ms_per_step']['mean'], '.2f')} |")
    rt = results.get("runtime")
    if rt:
        s = rt["speed"]
        lines += ["", f"Runtime ({rt['seconds_of_motion']:g} s of motion, seed {rt['seed']}, "
                  f"one core, same process): DEM {s['dem_s_per_sim_s']:.2f} s and SGN "
                  f"{s['sgn_s_per_sim_s']:.2f} s of wall time per simulated second, ratio "
                  f"{_fmt(s.get('ratio'), '.2f')}x (compile: DEM {s['dem_compile_s']:.1f} s, "
                  f"SGN {s['sgn_compile_s']:.1f} s; settling apart)."]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    paths = (argv if argv is not None else sys.argv[1:])
    if not paths:
        print(__doc__, file=sys.stderr)
        return 2
    for path in paths:
        results = json.loads(Path(path).read_text())
        print(f"### {results['model']} ({path}, commit {results['commit']})\n")
        print(table(results))
        print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
