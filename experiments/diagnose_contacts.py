#!/usr/bin/env python
"""Why rollouts lose ball-ball separation: one-step contact accuracy vs rollout overlaps.

    python experiments/diagnose_contacts.py --model sgn_jax/data/models/emax_300rpm \\
        --data data/standard_seed0.npz --prediction runs/experiments/standard_1traj/rollouts/standard_seed4.npz \\
        --reference data/standard_seed4.npz [--out runs/diagnose/1traj.json]

Two numbers side by side:

1. **One step, in distribution.** For DEM windows (first 4.5 s of ``--data``, every 7th
   window end that has a ball-ball contact in the DEM contact list, up to 600) the model's
   predicted relative normal acceleration of each contacting pair, (a_j - a_i) . n_ij, against
   the DEM's (finite differences, SPEC 5), binned by the DEM overlap 2R - |x_j - x_i|: median
   of both and their correlation.
2. **Rollout, out of distribution.** The distribution of ball-ball overlaps in the rollout's
   saved frames (``--prediction``) against the DEM reference's frames at the same times: pairs
   overlapping per frame, pairs overlapping by more than 50 um / 1 mm, and the largest overlap.

Writes the JSON to ``--out`` and prints it.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

BINS_M = (0.0, 1e-6, 5e-6, 2e-5, 1e-3)


def pair_overlaps(pos: np.ndarray, radius: float) -> np.ndarray:
    """(P, N, 3) -> (P, N(N-1)/2) overlaps 2R - |x_j - x_i| (m; negative = gap)."""
    iu = np.triu_indices(pos.shape[1], 1)
    d = np.linalg.norm(pos[:, iu[0]] - pos[:, iu[1]], axis=-1)
    return 2.0 * radius - d


def overlap_stats(overlap: np.ndarray) -> dict:
    return {"overlapping_pairs_per_frame": float((overlap > 0).sum(1).mean()),
            "pairs_over_50um_per_frame": float((overlap > 5e-5).sum(1).mean()),
            "pairs_over_1mm_per_frame": float((overlap > 1e-3).sum(1).mean()),
            "max_overlap_m": float(overlap.max())}


def one_step(model_dir: str, data: str, train_time: float = 4.5, stride: int = 7,
             limit: int = 600) -> dict:
    import jax

    from sgn_jax.api import graph_spec_from_config, load_trajectory, sdf_grid_from_config
    from sgn_jax.experiment_tools import build_graph, load_trained_model, windows_from_trajectory

    trained = load_trained_model(model_dir)
    cfg = trained.config
    traj = load_trajectory(data)
    spec, grid = graph_spec_from_config(cfg), sdf_grid_from_config(cfg)
    radius = cfg.balls.radius
    pp = np.asarray(traj.pp_pairs)
    last = int(np.searchsorted(np.asarray(traj.t), train_time))
    ends = np.array([n for n in range(spec.window, min(last, len(pp) - 1), stride)
                     if (pp[n, :, 0] >= 0).any()])[:limit]
    wins, accel, _ = windows_from_trajectory(traj, spec.window, ends=ends)
    predict = trained.predict_fn()

    @jax.jit
    def accel_of(win):
        graph, _ = build_graph(win, grid, spec)
        return predict(trained.params, trained.norm_stats, graph)[0][:spec.n_particles]

    pred = np.asarray(jax.lax.map(accel_of, wins))
    rows = []
    for k, n in enumerate(ends):
        pos = np.asarray(traj.pos[n])
        for i, j in pp[n]:
            if i < 0:
                continue
            dvec = pos[j] - pos[i]
            dist = float(np.linalg.norm(dvec))
            normal = dvec / dist
            rows.append((2 * radius - dist, (accel[k, j] - accel[k, i]) @ normal,
                         (pred[k, j] - pred[k, i]) @ normal))
    rows = np.asarray(rows)
    bins = []
    for lo, hi in zip(BINS_M[:-1], BINS_M[1:], strict=True):
        sel = rows[(rows[:, 0] >= lo) & (rows[:, 0] < hi)]
        if len(sel) < 3:
            continue
        bins.append({"overlap_um": [lo * 1e6, hi * 1e6], "n": int(len(sel)),
                     "dem_median_m_s2": float(np.median(sel[:, 1])),
                     "sgn_median_m_s2": float(np.median(sel[:, 2])),
                     "correlation": float(np.corrcoef(sel[:, 1], sel[:, 2])[0, 1])})
    return {"windows": int(len(ends)), "contacts": int(len(rows)),
            "max_dem_overlap_m": float(rows[:, 0].max()), "bins": bins}


def main(argv: list[str] | None = None) -> int:
    from sgn_jax.api import load_prediction, load_trajectory
    from sgn_jax.experiment_tools import align, write_json

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--model", required=True)
    p.add_argument("--data", required=True, help="a training trajectory (one-step check)")
    p.add_argument("--prediction", required=True, help="a rollout prediction file")
    p.add_argument("--reference", required=True, help="the DEM run of that rollout")
    p.add_argument("--out", default=None)
    args = p.parse_args(argv)
    result = {"model": args.model, "one_step": one_step(args.model, args.data)}
    pred, ref = load_prediction(args.prediction), load_trajectory(args.reference)
    al = align(pred, ref)
    radius = float(ref.meta["ball_radius"])
    result["rollout"] = {
        "prediction": args.prediction,
        "sgn": overlap_stats(pair_overlaps(np.asarray(pred.pos)[al.frame_index], radius)),
        "dem": overlap_stats(pair_overlaps(ref.pos[al.frame_ref_index], radius)),
    }
    if args.out:
        write_json(Path(args.out), result)
    print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
