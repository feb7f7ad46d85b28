#!/usr/bin/env python
"""The MSE_t of two unrelated DEM runs of the same case: the plateau of a fully decorrelated
prediction, to read the surrogates' MSE_t plateaus against.

    python experiments/reproduce/mse_floor/mse_baseline.py [--case standard] [--data data/] [--out runs/mse_baseline.json]

Pairs consecutive held-out seeds of the case (4-5, 6-7, ...): MSE_t (paper Eq. 33, balls matched
by index) between the two DEM trajectories at the same times from t = 0.7 ms on, every 1 ms, and
its plateau (median over the second half, as ``sgn_jax.analysis.metrics.mse_plateau``).

``--files A.npz B.npz`` compares two given runs instead, e.g. the same packing with the DEM at
two time steps (the chaos floor of any surrogate):

    sgn-jax dem --config experiments/configs/emax_300rpm.toml --seed 4 --duration 5 \
        --dt-dem 4.716981132075472e-07 --out data/chaos/standard_seed4_halfdt.npz
    python experiments/reproduce/mse_floor/mse_baseline.py --files data/standard_seed4.npz \
        data/chaos/standard_seed4_halfdt.npz --out runs/mse_chaos.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

DEFAULT_ENSEMBLES = Path(__file__).resolve().parents[2] / "ensembles.toml"


def main(argv: list[str] | None = None) -> int:
    from sgn_jax.experiment_tools import load_ensembles, mse_plateau, position_mse, write_json

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--case", default="standard")
    p.add_argument("--data", default="data")
    p.add_argument("--out", default="runs/mse_baseline.json")
    p.add_argument("--files", nargs=2, default=None, metavar=("A", "B"))
    args = p.parse_args(argv)
    if args.files:
        pa, pb = (np.load(f)["pos"][7::10] for f in args.files)
        n = min(len(pa), len(pb))
        mse = position_mse(pa[:n], pb[:n])
        result = {"files": args.files, "initial_max_abs_diff_m": float(np.abs(pa[0] - pb[0]).max()),
                  "mse_plateau_m2": mse_plateau(mse),
                  "mse_at_s": {str(t): float(mse[int(round(t * 1000))])
                               for t in (0.1, 0.2, 0.5, 1.0, 2.0) if t * 1000 < n}}
        write_json(args.out, result)
        print(json.dumps(result))
        return 0
    case = load_ensembles(DEFAULT_ENSEMBLES)[args.case]
    seeds = case.eval_seeds
    pairs = []
    for a, b in zip(seeds[0::2], seeds[1::2], strict=False):
        pa = np.load(Path(args.data) / f"{args.case}_seed{a}.npz")["pos"][7::10]
        pb = np.load(Path(args.data) / f"{args.case}_seed{b}.npz")["pos"][7::10]
        n = min(len(pa), len(pb))
        mse = position_mse(pa[:n], pb[:n])
        pairs.append({"seeds": [a, b], "mse_plateau_m2": mse_plateau(mse),
                      "mse_mean_m2": float(mse.mean())})
    values = [p_["mse_plateau_m2"] for p_ in pairs]
    result = {"case": args.case, "pairs": pairs, "mean_plateau_m2": float(np.mean(values)),
              "min_plateau_m2": float(np.min(values)), "max_plateau_m2": float(np.max(values))}
    write_json(args.out, result)
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
