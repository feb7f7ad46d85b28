"""Benchmark: the surrogate against our DEM on the same physical work, in one run.

One command, ratios side by side on the same machine, compile time apart:

- **single rollout, one core**: seconds of wall time per simulated second, DEM vs each
  ``--models`` surrogate (one rollout, pair-capacity tiers on, SDF-grid walls);
- **batches**: B = ``--batches`` rollouts vmapped over packings, on one and on two cores,
  against the DEM vmapped over the same packings; wall time per rollout per simulated second;
- **ensemble**: ``--ensemble`` packings x ``--ensemble-seconds`` on two cores: the surrogate
  vmapped over the packings against the fastest DEM ensemble, measured both ways: vmapped in one
  process, and one pinned process per core running its share of the packings one after another.

Every measurement runs in a fresh subprocess pinned with ``taskset`` (JAX's thread settings do
not limit its threads; ``taskset`` does), so "one core" is one
core. The packings are 8 real settled DEM packings of the standard case (seeds 4-11), tiled to
the batch size (a vmapped step costs the same for any packing: static shapes, no tiers under
vmap). The surrogate's accuracy is not measured here: the models' held-out errors are in
docs/results.md and docs/benchmarks.md states them beside the ratios.

    python benchmarks/bench_ratio.py                      # prints JSON
    python benchmarks/bench_ratio.py --markdown           # and the table for docs/benchmarks.md

Writes benchmarks/results/bench_ratio.json.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

import sgn_jax  # noqa: F401  (enables x64 before any array is made)

ROOT = Path(__file__).resolve().parent.parent
PACKING_SEEDS = tuple(range(4, 12))
CONFIG = "emax_300rpm"


# ---------------------------------------------------------------------------------------------
# Workers (each runs in its own pinned subprocess and prints one JSON line)


def _config():
    from sgn_jax.api import load_config

    return load_config(CONFIG)


def _settled_states(cfg, n: int):
    """``n`` settled DEM states (8 real packings tiled), stacked on a leading axis."""
    import jax

    from sgn_jax.api import DEMEnsemble

    ens = DEMEnsemble()
    states = [ens.settled(cfg, s) for s in PACKING_SEEDS]
    tiled = [states[i % len(states)] for i in range(n)]
    return jax.tree_util.tree_map(lambda *a: np.stack(a), *tiled)


def worker_dem(batch: int, seconds: float, sequential: bool) -> dict:
    """The DEM of ``batch`` packings for ``seconds`` of motion: vmapped in one program, or (with
    ``sequential``) one packing after another in this process."""
    import jax

    from sgn_jax.dem.engine import make_sampler
    from sgn_jax.pipelines.dem_run import setup_from_config

    cfg = _config()
    setup = setup_from_config(cfg)
    n_samples = max(1, round(seconds / cfg.dem.dt))
    run = make_sampler(setup.spec, setup.jar.wall_fn, setup.substeps, setup.pp_capacity)
    states = _settled_states(cfg, batch)
    if sequential:
        one = jax.jit(lambda s: run(setup.params, s, n_samples)[0])
        first = jax.tree_util.tree_map(lambda a: a[0], states)
        t = time.perf_counter()
        jax.block_until_ready(one(first))
        compile_s = time.perf_counter() - t
        t = time.perf_counter()
        for k in range(batch):
            jax.block_until_ready(one(jax.tree_util.tree_map(lambda a, k=k: a[k], states)))
        wall = time.perf_counter() - t
    else:
        many = jax.jit(jax.vmap(lambda s: run(setup.params, s, n_samples)[0]))
        t = time.perf_counter()
        jax.block_until_ready(many(states))
        first_call = time.perf_counter() - t
        t = time.perf_counter()
        jax.block_until_ready(many(states))
        wall = time.perf_counter() - t
        compile_s = max(first_call - wall, 0.0)
    return {"wall_s": wall, "compile_s": compile_s, "batch": batch, "seconds": n_samples * cfg.dem.dt,
            "substeps": int(setup.substeps)}


def _surrogate(model: str):
    from sgn_jax.api import load_surrogate

    return load_surrogate(model)


def worker_sgn(model: str, batch: int, seconds: float, tiers: bool, devices: int = 1,
               batching: str = "vmap") -> dict:
    """``batch`` surrogate rollouts of ``seconds`` (vmapped over packings, or with ``batching``
    "map" one after another in the model's single-rollout form, ``experiment_tools.over_packings``;
    ``batch`` 1 is one plain rollout, with pair-capacity tiers when ``tiers``). ``devices`` >
    1: the batch is sharded over that many devices (``api.shard_packings``; on a CPU host
    devices, which the driver makes with ``XLA_FLAGS=--xla_force_host_platform_device_count``;
    with "map" each device maps over its share)."""
    import jax
    import jax.numpy as jnp

    from sgn_jax.api import make_rollout
    from sgn_jax.experiment_tools import model_predictor, over_packings
    from sgn_jax.motion import offset, velocity
    from sgn_jax.pipelines.configure import (
        graph_spec_from_config,
        motion_from_config,
        sdf_grid_from_config,
    )
    from sgn_jax.surrogate.graph import windows_from_arrays
    from sgn_jax.surrogate.model import count_params
    from sgn_jax.surrogate.rollout import single_rollout_model

    cfg = _config()
    surrogate = _surrogate(model)
    spec = graph_spec_from_config(surrogate.config, n_particles=cfg.balls.count)
    motion = motion_from_config(cfg.motion)
    sdf = sdf_grid_from_config(cfg)
    dt = float(spec.dt)   # the model's own step (a fast tier may step 2e-4 s)
    n_steps = max(10, round(seconds / dt) // 10 * 10)
    # Windows: each packing at rest in the jar at t0, history = the jar's motion (the DEM state
    # gives the positions; the speed of a vmapped or tiered step does not depend on them).
    states = jax.device_get(_settled_states(cfg, batch))
    w = spec.window
    t0 = w * dt
    times = t0 + dt * np.arange(-w, 1)
    offs, vels = np.asarray(offset(motion, jnp.asarray(times))), np.asarray(
        velocity(motion, jnp.asarray(times)))
    windows = []
    for k in range(batch):
        pos = np.asarray(states.pos[k]) - np.asarray(states.offset[k]) + offs[:, None, :]
        windows.append(windows_from_arrays(pos, offs, vels, float(cfg.motion.rpm) / 60.0,
                                           np.array([w]), w))
    windows = jax.tree_util.tree_map(lambda *a: np.concatenate(a), *windows)
    caps = spec.pp_pair_capacity
    tier_caps = tuple(sorted({c for c in (caps // 4, caps // 2) if 0 < c < caps}))
    module = surrogate.model
    if batch == 1 or batching == "map":
        # one rollout at a time: the kind's single-rollout form and tiers rule (as run_rollout)
        module, kind_tiers = single_rollout_model(module)
        tiers = tiers and kind_tiers
    rollout = make_rollout(spec, model_predictor(module), n_steps, 10,
                           pp_capacity_tiers=tier_caps if (tiers and batch == 1) else (),
                           jit=False)
    args = (surrogate.params, surrogate.norm_stats)
    if batch == 1:
        fn = jax.jit(lambda win: rollout(*args, win, motion, sdf, t0))
        inputs = jax.tree_util.tree_map(lambda a: a[0], windows)
    else:
        run_batch = over_packings(lambda win, shared: rollout(*shared, win, motion, sdf, t0),
                                  batching, shard=devices > 1)
        fn = lambda win: run_batch(win, args)  # noqa: E731
        inputs = windows
        if devices > 1:
            from sgn_jax.api import shard_packings

            if len(jax.devices()) != devices:
                raise SystemExit(f"worker_sgn: {len(jax.devices())} devices, asked for {devices}")
            inputs = shard_packings(windows)
    t = time.perf_counter()
    res = jax.block_until_ready(fn(inputs))
    first_call = time.perf_counter() - t
    t = time.perf_counter()
    res = jax.block_until_ready(fn(inputs))
    wall = time.perf_counter() - t
    outside = int(np.sum(np.asarray(res.steps.n_outside)))
    return {"wall_s": wall, "compile_s": max(first_call - wall, 0.0), "batch": batch,
            "seconds": n_steps * dt, "steps": n_steps, "tiers": list(tier_caps) if tiers and
            batch == 1 else [], "n_params": int(count_params(surrogate.params)),
            "hidden": int(surrogate.config.model.hidden),
            "mlp_layers": int(surrogate.config.model.mlp_layers), "ball_steps_outside": outside,
            "devices": int(devices), "dt": dt, "batching": batching if batch > 1 else "single",
            "energy_J": np.asarray(res.steps.energy_cum)[..., -1].ravel().tolist()}


WORKERS = {"dem": worker_dem, "sgn": worker_sgn}


# ---------------------------------------------------------------------------------------------
# Driver


def _spawn(cores: str, kind: str, **kwargs) -> subprocess.Popen:
    cmd = ["taskset", "-c", cores, sys.executable, __file__, "--worker", kind,
           "--worker-args", json.dumps(kwargs)]
    env = dict(os.environ)
    if kwargs.get("devices", 1) > 1:
        env["XLA_FLAGS"] = (env.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count="
                            f"{kwargs['devices']}").strip()
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True, cwd=ROOT, env=env)


def _collect(proc: subprocess.Popen, what: str) -> dict:
    out, _ = proc.communicate()
    if proc.returncode != 0:
        raise SystemExit(f"bench_ratio: worker {what} failed (exit {proc.returncode})")
    return json.loads(out.strip().splitlines()[-1])


def run(cores: str, kind: str, **kwargs) -> dict:
    """One worker on ``cores``; its JSON result with the per-rollout cost added."""
    what = f"{kind} {kwargs} on cores {cores}"
    print(f"bench_ratio: {what} ...", file=sys.stderr, flush=True)
    res = _collect(_spawn(cores, kind, **kwargs), what)
    res["cores"] = cores
    res["s_per_rollout_second"] = res["wall_s"] / (res["batch"] * res["seconds"])
    return res


def dem_processes(n_packings: int, seconds: float, measured: int | None = None) -> dict:
    """The DEM ensemble as one pinned process per core, each running its share in sequence.

    ``measured`` < ``n_packings``: run only that many packings (split over the cores) and scale
    the wall time by ``n_packings / measured``; one process runs its packings one after another
    with one compiled program, so its time is linear in their number (recorded as
    ``measured_packings`` and ``scale``)."""
    cores = sorted(os.sched_getaffinity(0))[:2]
    run_n = n_packings if measured is None else max(len(cores), min(measured, n_packings))
    share = [run_n // len(cores) + (i < run_n % len(cores)) for i in range(len(cores))]
    print(f"bench_ratio: DEM ensemble as {len(cores)} processes {share} ...", file=sys.stderr,
          flush=True)
    procs = [_spawn(str(c), "dem", batch=k, seconds=seconds, sequential=True)
             for c, k in zip(cores, share, strict=True)]
    results = [_collect(p, "dem process") for p in procs]
    scale = n_packings / run_n
    return {"wall_s": scale * max(r["wall_s"] for r in results),
            "compile_s": max(r["compile_s"] for r in results), "processes": results,
            "batch": n_packings, "measured_packings": run_n, "scale": scale,
            "seconds": results[0]["seconds"], "cores": ",".join(map(str, cores))}


def bench(args) -> dict:
    out: dict = {"single": {}, "batches": [], "ensemble": {}}
    dem1 = run("0", "dem", batch=1, seconds=args.seconds, sequential=True)
    out["single"]["dem"] = dem1
    for model in args.models:
        sgn = run("0", "sgn", model=model, batch=1, seconds=args.seconds, tiers=True)
        sgn["ratio_vs_dem"] = dem1["s_per_rollout_second"] / sgn["s_per_rollout_second"]
        out["single"][model] = sgn
    for cores in ("0", "0,1"):
        for b in args.batches:
            dem = run(cores, "dem", batch=b, seconds=args.batch_seconds, sequential=False)
            row = {"cores": cores, "batch": b, "dem": dem}
            for model in args.models:
                sgn = run(cores, "sgn", model=model, batch=b, seconds=args.batch_seconds,
                          tiers=False)
                sgn["ratio_vs_dem"] = dem["s_per_rollout_second"] / sgn["s_per_rollout_second"]
                row[model] = sgn
            out["batches"].append(row)
    if args.ensemble:
        n, secs = args.ensemble, args.ensemble_seconds
        ens = {"packings": n, "seconds": secs}
        ens["dem_processes"] = dem_processes(n, secs, args.dem_ensemble_packings)
        # The vmapped DEM of the whole ensemble would take as long as the processes or longer
        # (vmap barely raises its throughput on a CPU: docs/benchmarks.md, "DEM throughput");
        # it is extrapolated from the largest measured batch on two cores instead of run.
        rows = [r for r in out["batches"] if r["cores"] == "0,1"]
        if rows:
            row = max(rows, key=lambda r: r["batch"])
            ens["dem_vmapped_extrapolated"] = {
                "wall_s": row["dem"]["s_per_rollout_second"] * n * secs,
                "from_batch": row["batch"]}
        fastest = min([ens["dem_processes"]["wall_s"]]
                      + [ens["dem_vmapped_extrapolated"]["wall_s"]] * bool(rows))
        ens["fastest_dem_s"] = fastest
        for model in args.ensemble_models or args.models:
            sgn = run("0,1", "sgn", model=model, batch=n, seconds=secs, tiers=False)
            sgn["ratio_vs_fastest_dem"] = fastest / sgn["wall_s"]
            ens[model] = sgn
            # the same ensemble sharded over two host devices (one per core): the same
            # powers to float tolerance, and the time of the device strategy
            sharded = run("0,1", "sgn", model=model, batch=n, seconds=secs, tiers=False,
                          devices=2)
            sharded["ratio_vs_fastest_dem"] = fastest / sharded["wall_s"]
            a, b = np.asarray(sgn["energy_J"]), np.asarray(sharded["energy_J"])
            sharded["max_rel_energy_diff_vs_unsharded"] = float(np.max(np.abs(a - b) / np.abs(a)))
            ens[model + " (2 devices)"] = sharded
            # one packing after another on each device (batching "map": the model's
            # single-rollout form, experiment_tools.over_packings), one device per core
            mapped = run("0,1", "sgn", model=model, batch=n, seconds=secs, tiers=False,
                         devices=2, batching="map")
            mapped["ratio_vs_fastest_dem"] = fastest / mapped["wall_s"]
            ens[model + " (map, 2 devices)"] = mapped
        out["ensemble"] = ens
    return out


def markdown(res: dict, machine: dict, args) -> str:
    s = res["single"]
    lines = [f"\n## Surrogate vs DEM, same work, one run (`benchmarks/bench_ratio.py`, "
             f"commit {machine['commit']})\n",
             f"Machine: {machine['processor']}, {machine['cpu_count']} cores, jax "
             f"{machine['jax']}, load {machine['load_average']} at the end. Wall time per "
             "simulated second of one rollout (compile apart); ratio = DEM / surrogate.\n",
             "| work | DEM s/s | " + " | ".join(f"`{m}` s/s (ratio)" for m in args.models)
             + " |", "|---|---|" + "---|" * len(args.models)]
    cells = [f"{s[m]['s_per_rollout_second']:.3f} ({s[m]['ratio_vs_dem']:.1f}x)"
             for m in args.models]
    lines.append(f"| single rollout, one core | {s['dem']['s_per_rollout_second']:.2f} | "
                 + " | ".join(cells) + " |")
    for row in res["batches"]:
        cores = "one core" if row["cores"] == "0" else "two cores"
        cells = [f"{row[m]['s_per_rollout_second']:.3f} ({row[m]['ratio_vs_dem']:.1f}x)"
                 for m in args.models]
        lines.append(f"| batch {row['batch']} vmapped, {cores} | "
                     f"{row['dem']['s_per_rollout_second']:.2f} | " + " | ".join(cells) + " |")
    if res["ensemble"]:
        e = res["ensemble"]
        lines += ["", f"Ensemble of {e['packings']} packings x {e['seconds']} s on two cores "
                  f"(wall s): DEM as two pinned processes {e['dem_processes']['wall_s']:.1f}"
                  + (f" (measured on {e['dem_processes']['measured_packings']} packings, "
                     f"scaled x{e['dem_processes']['scale']:g})"
                     if e["dem_processes"].get("scale", 1) != 1 else "") + ", "
                  f"DEM vmapped {e['dem_vmapped_extrapolated']['wall_s']:.1f} (extrapolated "
                  f"from the batch-{e['dem_vmapped_extrapolated']['from_batch']} row); "
                  + "; ".join(f"`{m}` vmapped {e[m]['wall_s']:.2f} "
                              f"({e[m]['ratio_vs_fastest_dem']:.1f}x the fastest DEM), sharded "
                              f"over 2 host devices {e[m + ' (2 devices)']['wall_s']:.2f} "
                              f"({e[m + ' (2 devices)']['ratio_vs_fastest_dem']:.1f}x; energies "
                              "within "
                              f"{e[m + ' (2 devices)']['max_rel_energy_diff_vs_unsharded']:.1e}"
                              " of the unsharded run), mapped one packing after another on each "
                              f"of 2 host devices {e[m + ' (map, 2 devices)']['wall_s']:.2f} "
                              f"({e[m + ' (map, 2 devices)']['ratio_vs_fastest_dem']:.1f}x)"
                              for m in (args.ensemble_models or args.models)) + "."]
    comp = "; ".join(f"`{m}` {s[m]['compile_s']:.1f} s" for m in args.models)
    lines += ["", f"Compile time (single rollout): DEM {s['dem']['compile_s']:.1f} s; {comp}.",
              "Models: " + "; ".join(f"`{m}` hidden {s[m]['hidden']}, {s[m]['mlp_layers']}-layer "
                                     f"MLPs, {s[m]['n_params']} parameters" for m in args.models)
              + ". Command: `python benchmarks/bench_ratio.py " + " ".join(sys.argv[1:]) + "`."]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--models", nargs="+", default=["emax_300rpm", "envelope"],
                   help="shipped model names or checkpoint paths")
    p.add_argument("--seconds", type=float, default=0.2, help="simulated s, single rollouts")
    p.add_argument("--batches", type=int, nargs="*", default=[1, 8, 32, 128])
    p.add_argument("--batch-seconds", type=float, default=0.02, help="simulated s per batch")
    p.add_argument("--ensemble", type=int, default=32, help="packings (0: skip)")
    p.add_argument("--ensemble-seconds", type=float, default=2.0)
    p.add_argument("--ensemble-models", nargs="*", default=None,
                   help="models of the ensemble row (default: --models)")
    p.add_argument("--dem-ensemble-packings", type=int, default=None,
                   help="run this many of the ensemble's DEM packings and scale (default: all)")
    p.add_argument("--out", default="benchmarks/results/bench_ratio.json")
    p.add_argument("--markdown", action="store_true",
                   help="also print the results as a markdown section, to replace the table of "
                        "docs/benchmarks.md")
    p.add_argument("--worker", choices=sorted(WORKERS), help=argparse.SUPPRESS)
    p.add_argument("--worker-args", default="{}", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.worker:
        print(json.dumps(WORKERS[args.worker](**json.loads(args.worker_args))))
        return 0
    from sgn_jax.experiment_tools import machine_info, write_json

    t = time.perf_counter()
    res = bench(args)
    machine = machine_info()
    doc = {"machine": machine, "args": vars(args), "results": res,
           "total_s": time.perf_counter() - t}
    write_json(ROOT / args.out, doc)
    print(json.dumps(doc, indent=1, default=float))
    if args.markdown:
        print(markdown(res, machine, args))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
