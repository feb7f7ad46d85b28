"""The surrogate's collision statistics against the DEM's on ensembles of packings.

For every case and evaluation seed of an ensembles file, the contact model rolls out from the
DEM record's first window over the record's interval with its collision ledger on (ball-ball
separation off, the model's own setting); the DEM's events over the same interval come from
the record's collision table. Per case, the ensemble mean and standard error of every statistic
of docs/collisions.md for both, and the bars:

- collision frequency (all contacts, per ball per second) within 15 %;
- mean stress energy per collision within 15 %;
- normal share of the dissipation within 5 percentage points;
- the dissipated-energy spectrum's power within 20 % in every decade that holds at least 5 %
  of the DEM's dissipated energy;
- the power above the threshold (default 1e-4 J of dissipated energy per collision) within 20 %.

    python experiments/tools/evaluate_collisions.py --ensembles experiments/envelope/ensembles.toml \\
        --cases heldout_c00,... --data data/envelope --out runs/collisions_eval --name heldout

Resumable (each run's surrogate events are kept in OUT/NAME_events/); writes OUT/NAME.json and
OUT/NAME.md, and with --figures the figures of `sgn-jax spectra` per case. Each decade's error
comes with its standard error over the packings (in parentheses, percent points).

``--dem-merge-gap S`` (a diagnostic, not the bars): the DEM's events are first merged at a
coarser time resolution, a pair's contacts parted by less than S seconds counted as one
(``EventTable.merge_recontacts``), to see which resolution the surrogate's events match.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import time
from pathlib import Path

import numpy as np

import sgn_jax.api as sj
import sgn_jax.experiment_tools as tools

BARS = {"frequency": 0.15, "stress_energy": 0.15, "normal_share_pp": 0.05, "decade": 0.20,
        "power_above": 0.20}


def _save_table(path: Path, table) -> None:
    fields = {f.name: getattr(table, f.name) for f in dataclasses.fields(table)}
    fields["path"] = "" if fields["path"] is None else str(fields["path"])
    if fields["ball_class"] is None:  # one ball class: nothing to store (np.load refuses objects)
        del fields["ball_class"]
    tmp = path.with_suffix(".tmp.npz")
    np.savez(tmp, **{k: np.asarray(v) for k, v in fields.items()})
    tmp.replace(path)


def _load_table(path: Path):
    # allow_pickle: a cache this script wrote with ball_class = None holds it as an object
    # array (one ball class), which np.load refuses otherwise
    with np.load(path, allow_pickle=True) as data:
        fields = {k: data[k] for k in data.files}
    ball_class = fields.pop("ball_class", None)
    if ball_class is not None and ball_class.dtype != object:
        fields["ball_class"] = ball_class
    for name in ("record_duration_s", "record_start_s", "total_mass_kg"):
        fields[name] = float(fields[name])
    fields["n_balls"] = int(fields["n_balls"])
    fields["source"] = str(fields["source"])
    fields["path"] = str(fields["path"]) or None
    return sj.EventTable(**fields)


def surrogate_table(model, cfg, traj, window: int, n_steps: int, key: str,
                    force_fraction: float | None = None):
    """The model's events over ``n_steps`` steps from sample ``window`` of ``traj`` (the
    ledger's force floor ``force_fraction``; None: the ledger's default)."""
    dt = float(cfg.dem.dt)
    extra = {} if force_fraction is None else {"collision_force_fraction": force_fraction}
    res = sj.run_rollout(model, traj, window, n_steps * dt, None, cfg, save_every=1,
                         progress=False, collisions=True, **extra)
    a = res["arrays"]
    if not np.all(np.isfinite(np.asarray(a["pos"]))):
        raise SystemExit(f"{key}: the rollout went non-finite")
    return tools.events_from_arrays(a, res["meta"], source="surrogate", path=key)


def relative(model: float, dem: float) -> float:
    return (model - dem) / dem if dem else float("nan")


def case_bars(dem, model, threshold: float) -> dict:
    """The bars of one case from the two ensembles (EnsembleStatistics)."""
    d, m = dem.mean, model.mean
    out = {
        "frequency": relative(m["frequency_per_ball_hz[all]"], d["frequency_per_ball_hz[all]"]),
        "stress_energy": relative(m["mean_stress_energy_J[all]"],
                                  d["mean_stress_energy_J[all]"]),
        "normal_share_pp": m["normal_share[all]"] - d["normal_share[all]"],
        "power_above": relative(m["power_above_W"], d["power_above_W"]),
        "power": relative(m["power_W[all]"], d["power_W[all]"]),
        "decades": [row for row in tools.decade_comparison(dem, model)
                    if row["power_relative_difference"] is not None],
    }
    misses = [name for name in ("frequency", "stress_energy", "normal_share_pp", "power_above")
              if not abs(out[name]) <= BARS[name]]
    misses += [f"decade {row['lo_J']:.0e}" for row in out["decades"]
               if not abs(row["power_relative_difference"]) <= BARS["decade"]]
    out["misses"] = misses
    out["threshold_J"] = threshold
    return out


def _fmt_se(mean: float, se: float, scale: float = 1.0, digits: int = 3) -> str:
    return f"{mean * scale:.{digits}g} ({se * scale:.2g})"


def _se_text(se: float | None) -> str:
    """`` (SE)`` in percent points, or nothing (a report written before decades had SEs)."""
    return "" if se is None or not math.isfinite(se) else f" ({100 * se:.0f})"


def markdown(rows: list[dict]) -> str:
    head = ("| case | collisions /ball/s DEM | model | error | mean stress energy (uJ) DEM | "
            "model | error | normal share DEM | model | diff (pp) | power above 1e-4 J (W) DEM "
            "| model | error | decades (power error (SE)) | misses |")
    lines = [head, "|" + "---|" * 16]
    for r in rows:
        d, m, b = r["dem"], r["model"], r["bars"]
        dec = ", ".join(f"{row['lo_J']:.0e}: {100 * row['power_relative_difference']:+.0f}"
                        + _se_text(row.get("power_relative_difference_se")) + " %"
                        for row in b["decades"])
        lines.append(
            f"| {r['case']} | {_fmt_se(*d['frequency'])} | {_fmt_se(*m['frequency'])} | "
            f"{100 * b['frequency']:+.1f} % | {_fmt_se(*d['stress_energy'], 1e6)} | "
            f"{_fmt_se(*m['stress_energy'], 1e6)} | {100 * b['stress_energy']:+.1f} % | "
            f"{_fmt_se(*d['normal_share'])} | {_fmt_se(*m['normal_share'])} | "
            f"{100 * b['normal_share_pp']:+.1f} | {_fmt_se(*d['power_above'])} | "
            f"{_fmt_se(*m['power_above'])} | {100 * b['power_above']:+.1f} % | {dec} | "
            f"{', '.join(b['misses']) or '-'} |")
    return "\n".join(lines)


def _pair(ens, name):
    return float(ens.mean[name]), float(ens.se[name])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", default="contact")
    ap.add_argument("--name", required=True)
    ap.add_argument("--ensembles", required=True)
    ap.add_argument("--data", required=True, help="folder of the DEM records (with collisions)")
    ap.add_argument("--cases", default=None)
    ap.add_argument("--threshold", type=float, default=1e-4,
                    help="J of dissipated energy per collision (default 1e-4)")
    ap.add_argument("--force-fraction", type=float, default=None,
                    help="the surrogate ledger's force floor as a fraction of m* g (default: "
                         "the ledger's, sgn_jax.surrogate.collisions.EVENT_FORCE_FRACTION)")
    ap.add_argument("--dem-merge-gap", type=float, default=0.0,
                    help="s; > 0: a diagnostic against the DEM's events seen at a coarser time "
                         "resolution, a pair's contacts parted less than this merged into one "
                         "(EventTable.merge_recontacts; the bars are then not the issue's)")
    ap.add_argument("--out", default="runs/collisions_eval")
    ap.add_argument("--figures", action="store_true", help="the figures of each case")
    args = ap.parse_args()

    tools.enable_compilation_cache()
    model = tools.load_trained_model(tools.resolve_checkpoint(args.model))
    out = Path(args.out)
    events_dir = out / f"{args.name}_events"
    events_dir.mkdir(parents=True, exist_ok=True)
    rows = []
    for case in tools.select_cases(tools.load_ensembles(args.ensembles), args.cases):
        cfg = sj.replace_section(sj.load_config(case.config_path), "rollout",
                                 pp_separation=False)
        dt = float(model.config.dem.dt)
        cfg = sj.replace_section(cfg, "dem", dt=dt)
        window = int(model.config.graph.window)
        dem_tables, model_tables, wall = [], [], 0.0
        for seed in [s for s in case.seeds if s not in case.train_seeds]:
            key = f"{case.name}_seed{seed}"
            path = Path(args.data) / f"{key}.npz"
            if not path.exists():
                print(f"missing {path}; skipped", flush=True)
                continue
            traj = sj.load_trajectory(path).at_step(dt)
            n_steps = len(traj.t) - 2 - window
            t0 = float(traj.t[window])
            dem_table = sj.load_events(path).window(t0, t0 + n_steps * dt)
            if args.dem_merge_gap > 0:
                dem_table = dem_table.merge_recontacts(args.dem_merge_gap)
            dem_tables.append(dem_table)
            cached = events_dir / f"{key}.npz"
            if cached.exists():
                table = _load_table(cached)
            else:
                start = time.perf_counter()
                table = surrogate_table(model, cfg, traj, window, n_steps, key,
                                        args.force_fraction)
                wall += time.perf_counter() - start
                _save_table(cached, table)
            model_tables.append(table)
            print(json.dumps({"run": key, "dem_events": int(np.sum(dem_tables[-1].new)),
                              "model_events": int(np.sum(table.new))}), flush=True)
        if not dem_tables:
            continue
        spectra = sj.collision_spectra(dem=dem_tables, surrogate=model_tables,
                                       threshold=args.threshold)
        dem, mod = spectra.dem, spectra.surrogate
        names = {"frequency": "frequency_per_ball_hz[all]",
                 "stress_energy": "mean_stress_energy_J[all]",
                 "normal_share": "normal_share[all]", "power_above": "power_above_W",
                 "power": "power_W[all]", "frequency_pp": "frequency_per_ball_hz[ball-ball]",
                 "frequency_pw": "frequency_per_ball_hz[ball-wall]"}
        row = {"case": case.name, "n": len(dem_tables),
               "dem": {k: _pair(dem, v) for k, v in names.items()},
               "model": {k: _pair(mod, v) for k, v in names.items()},
               "bars": case_bars(dem, mod, args.threshold), "rollout_wall_s": wall}
        rows.append(row)
        print(json.dumps({"case": case.name, "misses": row["bars"]["misses"]}), flush=True)
        if args.figures:
            spectra.plot(out / f"{args.name}_{case.name}")
    result = {"model": args.model, "threshold_J": args.threshold, "bars": BARS,
              "dem_merge_gap_s": args.dem_merge_gap, "cases": rows}
    (out / f"{args.name}.json").write_text(json.dumps(result, indent=1))
    table = markdown(rows)
    (out / f"{args.name}.md").write_text(table + "\n")
    print(table)


if __name__ == "__main__":
    main()
