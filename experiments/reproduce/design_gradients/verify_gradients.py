"""Check the surrogate's design gradients against DEM ensemble central differences.

At each design point (the standard case, a circle near the envelope's fast edge, Motion 1) and
for three parameters (the motion's frequency, its amplitude, the jar's straight length), the
DEM runs the same 8 packings at theta - h, theta and theta + h; the central difference of the
ensemble-mean power, with its standard error, is set beside the surrogate's estimated gradient
(sgn_jax.api.design_study) and the surrogate's own ensemble central difference.

    V=experiments/reproduce/design_gradients/verify_gradients.py
    python $V dem --workers 2            # the DEM's side, resumable (8 packings: 168 runs)
    python $V surrogate                  # the surrogate's gradients (both estimators)
    python $V surrogate-paired           # jar parameters from the DEM's own side packings
    python $V report                     # the table and one plot per point and parameter

``--out DIR`` (before the command) puts everything in DIR instead of runs/design, e.g. one
model's check beside another's (copy the DEM lines, e.g. expected/dem24.jsonl of this folder, to
DIR/dem/worker0.jsonl to reuse them); ``surrogate --checkpoint contact --separation off
--estimators difference --packings 24`` checks the contact model with 24 packings and the
difference estimator only; ``dem --packings 24`` runs the DEM's side with 24 packings (seeds
20-43); ``--points edge --params motion.rpm`` (either command) one row.

**Where the packings start.** A study of a jar-shape parameter lets the DEM make each packing
in every jar it evaluates (``--start auto``, the API's default: ``dem`` when a jar parameter is
among the names), as the DEM's own side runs do; with a multistable charge the start can decide
the state of a 1.5-s run. ``surrogate-paired`` runs the surrogate from the very packings the
DEM's side runs start from (the same seeds settled in each side's jar) and reports that central
difference beside the other. The bar is max(25 %, 2 DEM standard errors).

Outputs go to runs/design/ (DEM lines in dem/worker*.jsonl, appended and fsynced per run so a
killed job resumes; surrogate.json; report.md; one plot per point and parameter).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

import sgn_jax.api as sj
import sgn_jax.experiment_tools as tools
from sgn_jax.experiment_tools import append_jsonl, read_jsonl

OUT = Path("runs/design")
SEEDS = tuple(range(20, 28))  # never used for training (standard-case training used 0-3)
DURATION, BURN_IN = 1.5, 0.5  # s of motion; power averaged over (BURN_IN, DURATION]

POINTS: dict[str, dict] = {
    "standard": {"config": "emax_300rpm", "set": {},
                 "steps": {"motion.rpm": 50.0, "motion.amplitude": 0.003,
                           "jar.straight_length": 0.005}},
    "edge": {"config": "emax_300rpm", "set": {"motion.rpm": 450.0, "motion.amplitude": 0.018},
             "steps": {"motion.rpm": 50.0, "motion.amplitude": 0.002,
                       "jar.straight_length": 0.005}},
    "motion1": {"config": "motion1", "set": {},
                "steps": {"motion.base_frequency_hz": 0.8, "motion.scale": 0.08,
                          "jar.straight_length": 0.005}},
}
# Priority order of the DEM work: the standard rpm difference is the headline check.
ORDER = [("standard", "motion.rpm"), ("standard", None), ("standard", "motion.amplitude"),
         ("standard", "jar.straight_length"), ("edge", "motion.rpm"), ("edge", None),
         ("motion1", "motion.base_frequency_hz"), ("motion1", None),
         ("edge", "motion.amplitude"), ("motion1", "motion.scale"),
         ("edge", "jar.straight_length"), ("motion1", "jar.straight_length")]


def point_config(name: str):
    """The config of a design point (its base config with the point's settings)."""
    point = POINTS[name]
    cfg = sj.load_config(point["config"])
    if point["set"]:
        cfg = sj.design_config(cfg, list(point["set"]), list(point["set"].values()))
    return cfg


def variant_config(point: str, param: str | None, side: int):
    cfg = point_config(point)
    if param is None or side == 0:
        return cfg
    study_names = [param]
    base = sj.parameter_values_of(cfg, study_names)[0]
    return sj.design_config(cfg, study_names, [base + side * POINTS[point]["steps"][param]])


def dem_jobs(packings: int = len(SEEDS), rows: Sequence[str] | None = None
             ) -> list[tuple[str, str | None, int, int]]:
    """The DEM runs: for each (point, parameter) of :data:`ORDER` (or of ``rows``,
    ``"point:parameter"``), both sides on seeds 20 .. 20 + packings - 1."""
    jobs = []
    order = ORDER if rows is None else [tuple(r.split(":")) for r in rows]
    for point, param in order:
        for seed in range(SEEDS[0], SEEDS[0] + packings):
            if param is None:
                jobs.append((point, None, 0, seed))
            else:
                jobs.extend([(point, param, -1, seed), (point, param, 1, seed)])
    return jobs


def job_key(job) -> str:
    point, param, side, seed = job
    return f"{point}|{param}|{side}|{seed}"


def done_keys() -> set[str]:
    """Keys of the DEM runs already logged (a line cut by a kill is redone)."""
    return {r["key"] for path in (OUT / "dem").glob("worker*.jsonl") for r in read_jsonl(path)
            if "key" in r}


def cmd_dem_worker(index: int, of: int, packings: int = len(SEEDS),
                   rows: Sequence[str] | None = None) -> None:
    jobs = [j for i, j in enumerate(dem_jobs(packings, rows)) if i % of == index]
    done = done_keys()
    todo = [j for j in jobs if job_key(j) not in done]
    ensemble = sj.DEMEnsemble()
    path = OUT / "dem" / f"worker{index}.jsonl"
    t_start = time.perf_counter()
    for n, job in enumerate(todo, 1):
        point, param, side, seed = job
        cfg = variant_config(point, param, side)
        t0 = time.perf_counter()
        result = ensemble.power(cfg, seed, DURATION, BURN_IN)
        result.update(key=job_key(job), point=point, param=param, side=side,
                      wall_s=time.perf_counter() - t0)
        append_jsonl(path, result)
        rate = (time.perf_counter() - t_start) / n
        print(f"[worker {index}] {n}/{len(todo)} {job_key(job)}: {result['power_W']:.4f} W, "
              f"{result['wall_s']:.1f} s; ETA {rate * (len(todo) - n) / 60:.1f} min", flush=True)


def cmd_dem(workers: int, packings: int = len(SEEDS), rows: Sequence[str] | None = None
            ) -> None:
    procs = []
    for i in range(workers):
        cmd = [sys.executable, __file__, "--out", str(OUT), "dem-worker", "--index", str(i),
               "--of", str(workers), "--packings", str(packings)]
        if rows is not None:
            cmd += ["--rows", ",".join(rows)]
        if workers > 1 and os.path.exists("/usr/bin/taskset"):
            cmd = ["taskset", "-c", str(i % os.cpu_count()), *cmd]
        procs.append(subprocess.Popen(cmd))
    codes = [p.wait() for p in procs]
    if any(codes):
        sys.exit(f"a DEM worker failed: exit codes {codes}")


def load_dem() -> dict[tuple, list[float]]:
    table: dict[tuple, dict[int, float]] = {}
    for path in sorted((OUT / "dem").glob("worker*.jsonl")):
        for r in read_jsonl(path):
            side = int(r["side"])
            key = (r["point"], None if side == 0 else r["param"], side)
            table.setdefault(key, {})[int(r["seed"])] = float(r["power_W"])
    return {k: [v[s] for s in sorted(v)] for k, v in table.items()}


def cmd_surrogate(checkpoint: str | None, horizon: int, segments: int,
                  separation: bool | None = None, start: str = "auto",
                  estimators: str = "both", packings: int = len(SEEDS),
                  points: Sequence[str] | None = None,
                  params: Sequence[str] | None = None) -> None:
    model = sj.load_surrogate(checkpoint)
    results = {}
    path = OUT / "surrogate.json"
    if path.exists():
        results = json.loads(path.read_text())
    for point in POINTS if points is None else points:
        if point in results:
            continue
        cfg = sj.at_surrogate_step(point_config(point), model)   # a 2e-4 s model at its step
        names = [n for n in POINTS[point]["steps"] if params is None or n in params]
        if not names:
            continue
        t0 = time.perf_counter()
        # The study's start as a user's: with a jar parameter among the names ("auto") the DEM
        # makes the seeds' packings in every jar the study evaluates.
        point_start = tools.resolve_start(start, names)
        # The DEM's seeds, or more of them (20, 21, ...): the surrogate's packings are cheap,
        # and its estimate's standard error shrinks with them (the DEM's ensemble stays 8).
        seeds = tuple(range(SEEDS[0], SEEDS[0] + packings))
        packings_ = (sj.make_packings(cfg, seeds) if point_start == "packing"
                     else sj.seed_packings(cfg, seeds))
        t_pack = time.perf_counter() - t0
        # "estimate": the truncated-horizon autodiff estimator; "surrogate_fd": the default
        # difference estimator at the DEM's steps (the same packings on both sides).
        difference_only = estimators == "difference"
        study = sj.design_study(model, cfg, names, packings_, duration=DURATION,
                                burn_in=BURN_IN, horizon=horizon, n_segments=segments,
                                estimator="difference" if difference_only else "horizon",
                                separation=separation, start=point_start,
                                steps={n: POINTS[point]["steps"][n] for n in names})
        t0 = time.perf_counter()
        est = study.estimate()
        t_est = time.perf_counter() - t0
        fd = {}
        for i, name in enumerate(names):
            h = POINTS[point]["steps"][name]
            sides = {}
            if difference_only:     # the study's own estimate: its side powers (+h rows first)
                rows = np.asarray(est["side_powers_W"])
                sides = {1: rows[i].tolist(), -1: rows[len(names) + i].tolist()}
            for side in (-1, 1):
                if side in sides:
                    continue
                theta = study.theta0.copy()
                theta[i] += side * h
                sides[side] = study.powers(theta).tolist()
            diff = (np.asarray(sides[1]) - np.asarray(sides[-1])) / (2 * h)
            fd[name] = {"h": h, "minus_W": sides[-1], "plus_W": sides[1],
                        "gradient": float(diff.mean()),
                        "gradient_se": float(diff.std(ddof=1) / np.sqrt(diff.size))}
        if difference_only:   # no horizon estimate in this run (the report shows "-")
            est = {k: v for k, v in est.items() if not k.startswith("gradient")}
        results[point] = {"theta0": study.theta0.tolist(), "names": names, "estimate": est,
                          "surrogate_fd": fd, "packings_s": t_pack, "estimate_s": t_est,
                          "horizon": horizon, "segments": segments,
                          "checkpoint": checkpoint, "separation": separation,
                          "start": point_start, "seeds": list(seeds)}
        OUT.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(results, indent=1))
        print(json.dumps({point: {"gradient": est.get("gradient"),
                                  "fd": {n: v["gradient"] for n, v in fd.items()}}}), flush=True)


def cmd_surrogate_paired(checkpoint: str | None, separation: bool | None = None) -> None:
    """The surrogate's central difference of every jar parameter from the DEM's own side
    packings (the seeds settled in each side's jar), into surrogate.json's
    ``surrogate_fd_paired``."""
    model = sj.load_surrogate(checkpoint)
    path = OUT / "surrogate.json"
    results = json.loads(path.read_text()) if path.exists() else {}
    for point, spec in POINTS.items():
        names = list(spec["steps"])
        paired = results.setdefault(point, {}).setdefault("surrogate_fd_paired", {})
        for name in [n for n in names if n.startswith("jar.") and n not in paired]:
            h = spec["steps"][name]
            sides = {}
            for side in (-1, 1):
                cfg = sj.at_surrogate_step(variant_config(point, name, side), model)
                packings = sj.make_packings(cfg, SEEDS)          # settled in this side's jar
                study = sj.design_study(model, cfg, names, packings, duration=DURATION,
                                        burn_in=BURN_IN, separation=separation,
                                        start="packing")
                sides[side] = study.powers(study.theta0).tolist()
            diff = (np.asarray(sides[1]) - np.asarray(sides[-1])) / (2 * h)
            paired[name] = {"h": h, "minus_W": sides[-1], "plus_W": sides[1],
                            "gradient": float(diff.mean()),
                            "gradient_se": float(diff.std(ddof=1) / np.sqrt(diff.size)),
                            "checkpoint": checkpoint, "separation": separation}
            OUT.mkdir(parents=True, exist_ok=True)
            tmp = path.with_suffix(".tmp")
            tmp.write_text(json.dumps(results, indent=1))
            tmp.replace(path)
            print(json.dumps({point: {name: paired[name]["gradient"]}}), flush=True)


BAR = 0.25   # within max(25 %, 2 DEM standard errors)


def _verdict(g: float | None, g_dem: float, se_dem: float) -> tuple[bool | None, bool | None]:
    """(same sign as the DEM, within max(25 %, 2 DEM standard errors)) of a gradient."""
    if g is None:
        return None, None
    return (bool(np.sign(g) == np.sign(g_dem)),
            bool(abs(g - g_dem) <= max(BAR * abs(g_dem), 2 * se_dem)))


def cmd_merge(parts: Sequence[Path]) -> None:
    """Merge the surrogate.json of several ``surrogate`` runs (each of some parameters of a
    point, e.g. with another start) into OUT/surrogate.json: per point the union of their
    difference estimates, and under ``runs`` which run gave which parameters."""
    merged: dict = {}
    for part in parts:
        for point, res in json.loads((part / "surrogate.json").read_text()).items():
            into = merged.setdefault(point, {"theta0": [], "names": [],
                                             "estimate": {}, "surrogate_fd": {}, "runs": []})
            if not into["estimate"]:   # the first run's (its centre power; no horizon estimate)
                into["estimate"] = {k: v for k, v in res.get("estimate", {}).items()
                                    if not k.startswith("gradient")}
            # theta0 stays aligned with names: each parameter's centre from the run that gave it
            for name, x0 in zip(res.get("names", []), res.get("theta0") or [], strict=True):
                if name not in into["names"]:
                    into["names"].append(name)
                    into["theta0"].append(x0)
            into["surrogate_fd"].update(res.get("surrogate_fd", {}))
            into["runs"].append({"file": str(part / "surrogate.json"),
                                 **{k: res.get(k) for k in ("names", "start", "seeds",
                                                            "checkpoint", "separation")}})
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "surrogate.json").write_text(json.dumps(merged, indent=1))


def cmd_report() -> None:
    import matplotlib  # deferred: plotting only

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    dem = load_dem()
    surr = json.loads((OUT / "surrogate.json").read_text()) if (OUT / "surrogate.json").exists() \
        else {}
    rows = ["| point | parameter | h | DEM P(-h) W | DEM P(+h) W | DEM central diff (SE) | "
            "surrogate, difference estimator (SE) | sign | within max(25 %, 2 SE) | "
            "surrogate from the DEM's side packings (SE) | within | "
            "surrogate, horizon estimator (SE) | sign | within |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    out = {}
    for point, spec in POINTS.items():
        for name, h in spec["steps"].items():
            minus, plus = dem.get((point, name, -1)), dem.get((point, name, 1))
            if not minus or not plus or len(minus) != len(plus):
                continue
            diff = (np.asarray(plus) - np.asarray(minus)) / (2 * h)
            g_dem, se_dem = sj.ensemble_mean(diff)
            s = surr.get(point, {})
            g_s = s.get("estimate", {}).get("gradient", {}).get(name)
            se_s = s.get("estimate", {}).get("gradient_se", {}).get(name)
            fd = s.get("surrogate_fd", {}).get(name, {})
            g_fd = fd.get("gradient")
            sign, within = _verdict(g_fd, g_dem, se_dem)
            sign_h, within_h = _verdict(g_s, g_dem, se_dem)
            fd_p = s.get("surrogate_fd_paired", {}).get(name, {})
            g_p = fd_p.get("gradient")
            within_p = _verdict(g_p, g_dem, se_dem)[1]
            out[f"{point}|{name}"] = dict(dem=g_dem, dem_se=se_dem, n=len(diff),
                                          surrogate_difference=g_fd,
                                          surrogate_difference_se=fd.get("gradient_se"),
                                          sign=sign, within=within, surrogate_horizon=g_s,
                                          surrogate_horizon_se=se_s, sign_horizon=sign_h,
                                          within_horizon=within_h, surrogate_paired=g_p,
                                          surrogate_paired_se=fd_p.get("gradient_se"),
                                          within_paired=within_p)
            f = lambda v: "-" if v is None else f"{v:.4g}"  # noqa: E731
            rows.append(f"| {point} | {name} | {h:g} | {np.mean(minus):.4f} | {np.mean(plus):.4f}"
                        f" | {g_dem:.4g} ({se_dem:.2g}) | {f(g_fd)} ({f(fd.get('gradient_se'))})"
                        f" | {sign} | {within} | {f(g_p)} ({f(fd_p.get('gradient_se'))})"
                        f" | {'-' if within_p is None else within_p}"
                        f" | {f(g_s)} ({f(se_s)}) | {sign_h} | {within_h} |")
            fig, ax = plt.subplots(figsize=(5, 3.6))
            centre = dem.get((point, None, 0))
            # (a surrogate run of some of the point's parameters: the others' rows are the DEM's)
            x0 = s["theta0"][s["names"].index(name)] if name in s.get("names", ()) else None
            if x0 is None:
                x0 = sj.parameter_values_of(point_config(point), [name])[0]
            xs = [x0 - h, x0 + h]
            ys = [np.mean(minus), np.mean(plus)]
            es = [np.std(minus, ddof=1) / np.sqrt(len(minus)),
                  np.std(plus, ddof=1) / np.sqrt(len(plus))]
            if centre:
                xs.insert(1, x0)
                ys.insert(1, np.mean(centre))
                es.insert(1, np.std(centre, ddof=1) / np.sqrt(len(centre)))
            ax.errorbar(xs, ys, yerr=es, fmt="o-", color="k", capsize=3,
                        label="DEM ensemble mean (+-SE)")
            if s and name in s.get("names", ()):
                p0 = s["estimate"]["power_W"]
                sx = [x0 - h, x0, x0 + h]
                sy = [np.mean(fd["minus_W"]), p0, np.mean(fd["plus_W"])] if fd else None
                if sy:
                    ax.plot(sx, sy, "s--", color="tab:blue", label="surrogate ensemble mean")
                if g_fd is not None:
                    ax.plot([x0 - h, x0 + h], [p0 - g_fd * h, p0 + g_fd * h], "-",
                            color="tab:red", label="surrogate gradient (difference estimator)")
            ax.set_xlabel(f"{name} [{sj.parameter_unit(name)}]")
            ax.set_ylabel("mean dissipation power [W]")
            ax.set_title(f"{point}: power vs {name}\n({len(minus)} DEM packings, power over {BURN_IN}-"
                         f"{DURATION} s)", fontsize=9)
            ax.legend(fontsize=7)
            fig.tight_layout()
            fig.savefig(OUT / f"{point}_{name.replace('.', '_')}.png", dpi=110)
            plt.close(fig)
    (OUT / "report.md").write_text("\n".join(rows) + "\n")
    (OUT / "report.json").write_text(json.dumps(out, indent=1))
    print("\n".join(rows))


def main() -> None:
    global OUT
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=OUT, help="output folder (default runs/design)")
    sub = p.add_subparsers(dest="cmd", required=True)
    d = sub.add_parser("dem")
    d.add_argument("--workers", type=int, default=2)
    w = sub.add_parser("dem-worker")
    w.add_argument("--index", type=int, required=True)
    w.add_argument("--of", type=int, required=True)
    for q in (d, w):
        q.add_argument("--packings", type=int, default=len(SEEDS),
                       help=f"seeds {SEEDS[0]}.. per side (default {len(SEEDS)})")
        q.add_argument("--rows", default=None,
                       help="comma-separated point:parameter rows (default: all, in order)")
    s = sub.add_parser("surrogate")
    s.add_argument("--checkpoint", default=None)
    s.add_argument("--horizon", type=int, default=100)
    s.add_argument("--segments", type=int, default=8)
    s.add_argument("--separation", choices=("config", "on", "off"), default="config",
                   help="the ball-ball separation (default: the point's config)")
    s.add_argument("--points", default=None,
                   help=f"comma-separated design points (default all: {', '.join(POINTS)})")
    s.add_argument("--params", default=None,
                   help="comma-separated parameters (default: each point's three); a point "
                   "without any of them is skipped")
    s.add_argument("--packings", type=int, default=len(SEEDS),
                   help=f"the surrogate's packings, seeds {SEEDS[0]}.. (default {len(SEEDS)}: "
                   "the DEM's)")
    s.add_argument("--estimators", choices=("both", "difference"), default="both",
                   help="both (default): the horizon estimator's estimate and the difference "
                   "estimator's sides as separate evaluations; difference: one difference "
                   "estimate of the study (its sides), no horizon estimator")
    s.add_argument("--start", choices=("auto", "packing", "dem", "settle"), default="auto",
                   help="the study's start (sgn_jax.api.design_study; default auto: the DEM "
                   "makes the packings in every evaluated jar where a jar parameter is studied)")
    sp = sub.add_parser("surrogate-paired")
    sp.add_argument("--checkpoint", default=None)
    sp.add_argument("--separation", choices=("config", "on", "off"), default="config")
    mg = sub.add_parser("merge", help="merge the surrogate.json of other --out folders")
    mg.add_argument("parts", nargs="+", type=Path)
    sub.add_parser("report")
    args = p.parse_args()
    OUT = args.out
    rows = None if getattr(args, "rows", None) is None else args.rows.split(",")
    if args.cmd == "dem":
        cmd_dem(args.workers, args.packings, rows)
    elif args.cmd == "dem-worker":
        cmd_dem_worker(args.index, args.of, args.packings, rows)
    elif args.cmd == "surrogate":
        known = {n for spec in POINTS.values() for n in spec["steps"]}
        unknown = sorted(set(args.params.split(",")) - known) if args.params else []
        if unknown:
            p.error(f"--params {unknown}: not a parameter of the check (one of {sorted(known)})")
        cmd_surrogate(args.checkpoint, args.horizon, args.segments,
                      {"config": None, "on": True, "off": False}[args.separation], args.start,
                      args.estimators, args.packings,
                      None if args.points is None else args.points.split(","),
                      None if args.params is None else args.params.split(","))
    elif args.cmd == "surrogate-paired":
        cmd_surrogate_paired(args.checkpoint,
                             {"config": None, "on": True, "off": False}[args.separation])
    elif args.cmd == "merge":
        cmd_merge(args.parts)
    else:
        cmd_report()


if __name__ == "__main__":
    main()
