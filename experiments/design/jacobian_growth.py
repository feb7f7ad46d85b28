"""Where the surrogate's long-horizon gradients explode: the tangent of the rollout with respect to
rpm, step by step, with and without the wall snap-back and the ball-ball separation.

    python experiments/design/jacobian_growth.py [--packings 4] [--steps 2000]

For each packing (DEM seeds 100.., the standard case, settled, first window) the surrogate rolls
out ``--steps`` steps at 300 rpm and ``jax.jvp`` carries the tangent d(state)/d(rpm) along (the
packing anchored in the jar frame, as in sgn_jax.design). Per saved frame (every 10 steps) it
records the norm of d(ball positions, jar frame)/d rpm (m/rpm) and of d(cumulative energy)/d rpm
(J/rpm), and per step whether a snap-back or a ball-ball separation fired. Three rollouts:
"shipped" (snap-back + separation, the shipped config), "paper" (snap-back only), "free"
(neither). Writes runs/design/jacobian_growth.json and .png: the tangent's growth vs time, the
fitted exponential rate, and the per-frame growth factor with and without a snap or separation
in that frame.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import sgn_jax.api as sj
from sgn_jax.api import (
    RolloutState,
    graph_spec_from_config,
    jar_params_from_config,
    motion_from_config,
)
from sgn_jax.experiment_tools import (
    analytic_jar_query,
    anchored_window,
    apply_parameters,
    atomic_write,
    make_rollout_advance,
    model_predictor,
)

OUT = Path("runs/design")
SAVE_EVERY = 10
VARIANTS = {"shipped": (True, 5e-5), "paper": (True, None), "free": (False, None)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--packings", type=int, default=4)
    p.add_argument("--steps", type=int, default=1000)
    args = p.parse_args()
    cfg = sj.load_config("emax_300rpm")
    model = sj.load_surrogate()
    packings = sj.make_packings(cfg, range(100, 100 + args.packings))
    spec = graph_spec_from_config(dataclasses.replace(model.config, balls=cfg.balls, dem=cfg.dem),
                                  n_particles=cfg.balls.count)
    motion0 = motion_from_config(cfg.motion)
    jar = jar_params_from_config(cfg.jar)
    dt = float(cfg.dem.dt)
    names = ("motion.rpm",)
    results = {"steps": args.steps, "save_every": SAVE_EVERY, "dt": dt, "variants": {}}
    for variant, (snap, sep) in VARIANTS.items():
        advance = make_rollout_advance(spec, model_predictor(model.model), args.steps, SAVE_EVERY,
                                       snap_back=snap, phi_sb=model.config.graph.phi_sb,
                                       query=analytic_jar_query, pp_max_overlap=sep, jit=False)

        def trajectory(theta, window0, advance=advance):
            motion, jar_t = apply_parameters(names, theta, motion0, jar)
            window, t_eff = anchored_window(window0, jnp.asarray(packings.t0), motion0, motion, dt)
            state = RolloutState(window=window, step=jnp.zeros((), jnp.int32),
                                 energy=jnp.zeros((), jnp.float64))
            result = advance(model.params, model.norm_stats, state, motion, jar_t, t_eff)
            jar_frame = result.positions - result.offsets[:, None, :]
            return jar_frame, result.steps.energy_cum, result.steps.n_snapped

        @jax.jit
        def tangent(window0):
            theta = jnp.asarray([300.0], jnp.float64)
            primal, tan = jax.jvp(lambda th: trajectory(th, window0)[:2], (theta,),
                                  (jnp.ones_like(theta),))
            snapped = trajectory(theta, window0)[2]
            return primal, tan, snapped

        per_packing = []
        t0 = time.perf_counter()
        for k in range(len(packings)):
            window0 = jax.tree_util.tree_map(lambda a, k=k: a[k], packings.windows)
            (pos, energy), (dpos, denergy), snapped = jax.device_get(tangent(window0))
            pos_norm = np.sqrt(np.sum(np.asarray(dpos) ** 2, axis=(1, 2)))      # (P,)
            frame_energy = np.asarray(denergy)[SAVE_EVERY - 1::SAVE_EVERY]      # (P,)
            snaps = np.asarray(snapped).reshape(-1, SAVE_EVERY).sum(axis=1)      # (P,)
            per_packing.append({"dpos_norm": pos_norm.tolist(),
                                "denergy": frame_energy.tolist(),
                                "energy_J": float(np.asarray(energy)[-1]),
                                "snaps_per_frame": snaps.tolist(),
                                "finite": bool(np.all(np.isfinite(pos_norm)))})
            mid = len(pos_norm) // 2
            print(f"{variant} packing {k}: |dx/drpm| at {SAVE_EVERY * dt:g} / "
                  f"{(mid + 1) * SAVE_EVERY * dt:g} / {args.steps * dt:g} s = {pos_norm[0]:.3g} / "
                  f"{pos_norm[mid]:.3g} / {pos_norm[-1]:.3g} m/rpm, dE/drpm {frame_energy[-1]:.3g}"
                  " J/rpm", flush=True)
        results["variants"][variant] = {"packings": per_packing,
                                        "wall_s": time.perf_counter() - t0}
    summarize(results)
    OUT.mkdir(parents=True, exist_ok=True)
    with atomic_write(OUT / "jacobian_growth.json", "w") as fh:
        json.dump(results, fh, indent=1)
    plot(results)


def summarize(results: dict) -> None:
    """Fitted growth rate of log |dx/drpm| over the run, and the median per-frame growth
    factor in frames with and without a snap-back (per variant, over packings)."""
    dt_frame = results["dt"] * results["save_every"]
    for variant, data in results["variants"].items():
        rates, with_snap, without_snap = [], [], []
        for pk in data["packings"]:
            norm = np.asarray(pk["dpos_norm"])
            ok = np.isfinite(norm) & (norm > 0)
            t = dt_frame * (1 + np.arange(norm.size))
            if ok.sum() > 3:
                rates.append(float(np.polyfit(t[ok], np.log(norm[ok]), 1)[0]))
            growth = norm[1:] / norm[:-1]
            snaps = np.asarray(pk["snaps_per_frame"])[1:]
            good = np.isfinite(growth) & (norm[:-1] > 0)
            with_snap += growth[good & (snaps > 0)].tolist()
            without_snap += growth[good & (snaps == 0)].tolist()
        data["summary"] = {
            "growth_rate_per_s": rates,
            "median_frame_growth_with_snap": float(np.median(with_snap)) if with_snap else None,
            "median_frame_growth_without_snap": (float(np.median(without_snap))
                                                 if without_snap else None),
            "frames_with_snap": len(with_snap), "frames_without_snap": len(without_snap),
        }
        print(variant, json.dumps(data["summary"]), flush=True)


def plot(results: dict) -> None:
    import matplotlib  # deferred: plotting only

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    dt_frame = results["dt"] * results["save_every"]
    fig, ax = plt.subplots(figsize=(6, 4))
    colors = {"shipped": "tab:blue", "paper": "tab:orange", "free": "tab:green"}
    for variant, data in results["variants"].items():
        for i, pk in enumerate(data["packings"]):
            norm = np.asarray(pk["dpos_norm"])
            t = dt_frame * (1 + np.arange(norm.size))
            ax.semilogy(t, norm, color=colors[variant], alpha=0.7,
                        label=f"{variant} (median rate "
                              f"{np.median(data['summary']['growth_rate_per_s']):.0f} /s)"
                        if i == 0 else None)
    ax.set_xlabel("time since the packing's window [s]")
    ax.set_ylabel("|d (ball positions, jar frame) / d rpm| [m/rpm]")
    ax.set_title("Tangent growth of the surrogate rollout (standard case, 300 rpm)\n"
                 "shipped: snap-back + ball-ball separation; paper: snap-back; free: neither",
                 fontsize=8)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(OUT / "jacobian_growth.png", dpi=110)


if __name__ == "__main__":
    main()
