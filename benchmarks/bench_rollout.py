"""Benchmark: SGN rollout speed (ms per step), vmapped batches, DEM comparison, gradient memory.

Measures, on this machine, compile time apart:

- ms per surrogate step of one rollout for each ``--hidden`` (default 256 and 128; the model of
  paper Table 3 otherwise: 4-layer MLPs, 1 interaction layer, window 7, 24 balls, standard edge
  capacity), and per batch step of ``--batch`` vmapped rollouts (different motions);
- the DEM (``sgn_jax.dem``) for ``--dem-seconds`` of motion of the standard case, and the
  surrogate's wall time for the same physical time (speed-up = DEM / SGN);
- peak RSS and compiled temporary memory of ``jax.grad`` of the cumulative energy through
  differentiated rollouts of ``--memory-steps`` steps (each in a fresh subprocess), with
  ``jax.checkpoint`` chunks and, for comparison, the compiled memory without them.

The network is randomly initialised (speed does not depend on the weights: static shapes); the
initial window comes from the DEM run (or a lattice of balls with --skip-dem).

    taskset -c 0 python benchmarks/bench_rollout.py --markdown   # one core
    python benchmarks/bench_rollout.py --markdown                # both cores

Prints one JSON document; with --markdown also the tables, to replace those of
docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

import sgn_jax  # noqa: F401  (enables x64 before any array is made)

ROOT = Path(__file__).resolve().parent.parent


def _standard_config(settle_time: float = 0.05):
    from sgn_jax.config import builtin_config_path, load_config, replace_section

    cfg = load_config(builtin_config_path("emax_300rpm"))
    return replace_section(cfg, "dem", settle_time=settle_time)


def _hand_stats(window: int):
    """Normalisation scales of the standard case (m/s, m, Hz, m/s^2, J)."""
    from sgn_jax.surrogate.normalization import Moments, NormStats

    def m(mean, std):
        return Moments(mean=np.asarray(mean, np.float64), std=np.asarray(std, np.float64))

    return NormStats(
        particle=m(np.zeros(7 * window), [0.5, 0.5, 0.5, 0.01, 1.0, 1.0, 1.0] * window),
        wall=m([0, 0, 0, 0, 0, 0, 5.0] * window, [0.017, 0.017, 0.017, 0.5, 0.5, 0.5, 1.0] * window),
        pp_edge=m(np.zeros(3), [0.01] * 3), pw_edge=m(np.zeros(3), [0.005] * 3),
        accel=m(np.zeros(3), [30.0] * 3), dissipation=m([5e-6], [1e-5]))


def lattice_window(cfg, spec):
    """24 balls on a lattice in the jar (at rest), as a Window ending at t = 0.1 s."""
    from sgn_jax.motion import offset
    from sgn_jax.pipelines.configure import motion_from_config
    from sgn_jax.surrogate.graph import Window

    t0 = 0.1
    xs = np.linspace(-0.03, 0.03, 6)
    centres = np.array([[x, 0.006 + 0.011 * j, z] for j in range(2) for z in (-0.006, 0.006)
                        for x in xs])[: spec.n_particles]
    pos = centres + np.asarray(offset(motion_from_config(cfg.motion), t0))
    w = spec.window
    window = Window(positions=np.broadcast_to(pos, (w + 1,) + pos.shape).copy(),
                    offsets=np.zeros((w, 3)), offset_velocities=np.zeros((w, 3)),
                    frequency_hz=np.float64(0.0))
    return window, t0


def _setup(hidden: int, window0, t0: float, cfg):
    import jax

    from sgn_jax.pipelines.configure import (
        graph_spec_from_config,
        motion_from_config,
        sdf_grid_from_config,
    )
    from sgn_jax.surrogate.graph import build_graph
    from sgn_jax.surrogate.model import count_params, init_params
    from sgn_jax.surrogate.normalization import normalize_graph
    from sgn_jax.surrogate.rollout import jar_state_window
    from sgn_jax.surrogate.sgn import SGN

    spec = graph_spec_from_config(cfg)
    sdf = sdf_grid_from_config(cfg)
    motion = motion_from_config(cfg.motion)
    stats = _hand_stats(spec.window)
    model = SGN(hidden=hidden, mlp_layers=cfg.model.mlp_layers,
                interaction_layers=cfg.model.interaction_layers)

    def init(window):
        graph, _ = build_graph(jar_state_window(window, motion, t0, spec.dt), sdf, spec)
        return init_params(model, normalize_graph(graph, stats), 0)

    params = jax.device_get(jax.jit(init)(window0))
    return dict(spec=spec, sdf=sdf, motion=motion, stats=stats, model=model, params=params,
                n_params=count_params(params))


def _time(fn, repeats: int) -> list[float]:
    import jax

    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t)
    return times


def bench_single(hidden: int, steps: int, repeats: int, window0, t0: float, cfg) -> dict:
    from sgn_jax.surrogate.rollout import make_rollout

    s = _setup(hidden, window0, t0, cfg)
    rollout = make_rollout(s["spec"], s["model"], steps, 10)
    args = (s["params"], s["stats"], window0, s["motion"], s["sdf"], t0)
    first = _time(lambda: rollout(*args), 1)[0]  # compiles
    times = _time(lambda: rollout(*args), repeats)
    compile_s = first - min(times)
    res = rollout(*args)
    gflop = model_gflop_per_step(s, window0, t0)
    return {"kind": "single", "hidden": hidden, "n_params": s["n_params"], "steps": steps,
            "compile_s": compile_s, "ms_per_step": 1e3 * min(times) / steps,
            "model_gflop_per_step": gflop, "gflop_per_s": gflop / (min(times) / steps),
            "ms_per_step_median": 1e3 * float(np.median(times)) / steps,
            "finite": bool(np.isfinite(np.asarray(res.positions)).all()),
            "edge_capacity": s["spec"].edge_capacity}


def model_gflop_per_step(s: dict, window0, t0: float) -> float:
    """XLA's flop count of one network evaluation (featurizer excluded) on the padded graph."""
    import jax

    from sgn_jax.surrogate.graph import build_graph
    from sgn_jax.surrogate.model import make_predict
    from sgn_jax.surrogate.rollout import jar_state_window

    graph, _ = jax.jit(lambda w: build_graph(jar_state_window(w, s["motion"], t0, s["spec"].dt),
                                             s["sdf"], s["spec"]))(window0)
    cost = jax.jit(make_predict(s["model"])).lower(s["params"], s["stats"], graph).compile()
    analysis = cost.cost_analysis()
    analysis = analysis[0] if isinstance(analysis, list) else analysis
    return float(analysis.get("flops", float("nan"))) / 1e9


def bench_in_loop(hidden: int, steps: int, repeats: int, traj, start: int, cfg,
                  tiers: tuple[int, ...]) -> dict:
    """ms per step on realistic states: the network runs every step on the graph of the current
    window (so its cost is paid), but the balls follow the DEM (its accelerations are used, the
    network's output is added times 1e-30), so the contact counts are the DEM's. With
    ``tiers`` the network runs on the smallest ball-pair capacity that holds the pairs."""
    import jax
    import jax.numpy as jnp

    from sgn_jax.pipelines.rollout_run import initial_window
    from sgn_jax.surrogate.graph import dissipation_per_interval, targets_from_arrays
    from sgn_jax.surrogate.rollout import ReplayTable, make_rollout, model_predictor

    window0, t0 = initial_window(traj, start, cfg.graph.window), float(traj.t[start])
    s = _setup(hidden, window0, t0, cfg)
    accel, de = targets_from_arrays(traj.pos, dissipation_per_interval(traj),
                                    start + np.arange(steps), s["spec"].dt)
    table = ReplayTable(accel=jnp.asarray(accel), dE=jnp.asarray(de))
    network = model_predictor(s["model"])

    def predictor(params, stats, graph, step):
        a, d = network(params[0], stats, graph, step)
        n = s["spec"].n_particles
        return (params[1].accel[step] + 1e-30 * a[:n].astype(jnp.float64),
                params[1].dE[step] + 1e-30 * d.astype(jnp.float64))

    rollout = make_rollout(s["spec"], predictor, steps, 10, snap_back=False,
                           pp_capacity_tiers=tiers)
    args = ((s["params"], table), s["stats"], window0, s["motion"], s["sdf"], t0)
    first = _time(lambda: rollout(*args), 1)[0]
    times = _time(lambda: rollout(*args), repeats)
    res = jax.device_get(rollout(*args))
    pairs = res.steps.n_pp_edges / 2
    return {"kind": "in_loop", "hidden": hidden, "steps": steps, "tiers": list(tiers),
            "compile_s": first - min(times), "ms_per_step": 1e3 * min(times) / steps,
            "mean_pairs": float(pairs.mean()), "max_pairs": int(pairs.max()),
            "mean_pw_edges": float(res.steps.n_pw_edges.mean()),
            "pair_capacity": s["spec"].pp_pair_capacity}


def bench_batch(hidden: int, batch: int, steps: int, repeats: int, window0, t0: float,
                cfg) -> dict:
    import jax
    import jax.numpy as jnp

    from sgn_jax.motion import CircleMotion
    from sgn_jax.surrogate.rollout import make_rollout

    s = _setup(hidden, window0, t0, cfg)
    rollout = make_rollout(s["spec"], s["model"], steps, 10, jit=False)
    rpm = jnp.linspace(270.0, 330.0, batch, dtype=jnp.float64)
    motions = CircleMotion(rpm=rpm, amplitude=jnp.full(batch, 0.017, jnp.float64),
                           phase=jnp.zeros(batch, jnp.float64))
    batched = jax.jit(jax.vmap(rollout, in_axes=(None, None, None, 0, None, None)))
    window0 = jax.tree_util.tree_map(lambda a: jnp.asarray(a, jnp.float64), window0)
    args = (s["params"], s["stats"], window0, motions, s["sdf"], jnp.asarray(t0, jnp.float64))
    t = time.perf_counter()
    compiled = batched.lower(*args).compile()
    compile_s = time.perf_counter() - t
    times = _time(lambda: compiled(*args), repeats)
    best = min(times)
    return {"kind": "batch", "hidden": hidden, "batch": batch, "steps": steps,
            "compile_s": compile_s, "ms_per_batch_step": 1e3 * best / steps,
            "ms_per_rollout_step": 1e3 * best / steps / batch}


def bench_dem(cfg, seconds: float) -> tuple[dict, object]:
    from sgn_jax.pipelines.dem_run import run_dem
    from sgn_jax.records.trajectory import Trajectory

    run = run_dem(cfg, duration=seconds, progress=False)
    s = run.summary
    traj = Trajectory(arrays=run.arrays, meta=dict(run.meta))
    return {"kind": "dem", "seconds_of_motion": s["duration_s"], "motion_wall_s": s["motion_wall_s"],
            "compile_s": s["compile_time_s"], "steps_per_s": s["steps_per_s"],
            "dem_steps_of_motion": int(round(s["duration_s"] / s["dt_dem"])),
            "dt_dem": s["dt_dem"], "pair_mode": s["pair_mode"]}, traj


# --------------------------------------------------------------------------------------------
# Memory of differentiated rollouts (run in a fresh process per size)


def differentiated_rollout_memory(n_steps: int, hidden: int = 16, checkpoint_steps: int = 100
                                  ) -> dict:
    """Peak RSS and compiled temporary memory of ``jax.grad`` (w.r.t. the network parameters) of
    the cumulative energy of an ``n_steps`` rollout (24 balls, standard jar and motion), with
    ``jax.checkpoint`` chunks of ``checkpoint_steps``; and the compiled temporary memory of the
    same gradient without chunks (not run). Call in a fresh process for a meaningful RSS."""
    import jax
    import jax.numpy as jnp

    from sgn_jax.pipelines.configure import graph_spec_from_config
    from sgn_jax.surrogate.rollout import make_rollout

    cfg = _standard_config()
    spec = graph_spec_from_config(cfg)
    window0, t0 = lattice_window(cfg, spec)
    s = _setup(hidden, window0, t0, cfg)

    def gradient(chunk: int):
        rollout = make_rollout(spec, s["model"], n_steps, 10, checkpoint_steps=chunk, jit=False)
        return jax.jit(jax.grad(lambda p: rollout(p, s["stats"], window0, s["motion"], s["sdf"],
                                                  t0).energy))

    t = time.perf_counter()
    compiled = gradient(checkpoint_steps).lower(s["params"]).compile()
    compile_s = time.perf_counter() - t
    t = time.perf_counter()
    grads = jax.block_until_ready(compiled(s["params"]))
    run_s = time.perf_counter() - t
    peak_rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    grad_norm = float(jnp.sqrt(sum(jnp.sum(g * g) for g in jax.tree_util.tree_leaves(grads))))
    temp = compiled.memory_analysis().temp_size_in_bytes
    unchunked = gradient(n_steps).lower(s["params"]).compile().memory_analysis()
    return {"steps": n_steps, "hidden": hidden, "checkpoint_steps": checkpoint_steps,
            "peak_rss_mb": peak_rss_mb, "temp_bytes": int(temp),
            "temp_bytes_unchunked": int(unchunked.temp_size_in_bytes), "compile_s": compile_s,
            "run_s": run_s, "grad_norm": grad_norm}


def memory_in_subprocess(n_steps: int, hidden: int) -> dict:
    here = str(Path(__file__).resolve().parent)
    code = (f"import json, sys; sys.path.insert(0, {here!r}); from bench_rollout import "
            f"differentiated_rollout_memory as f; print(json.dumps(f({n_steps}, hidden={hidden})))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


# --------------------------------------------------------------------------------------------


def machine() -> dict:
    from sgn_jax.records.io_utils import machine_info

    return machine_info()


def markdown(report: dict) -> str:
    m = report["machine"]
    cores = m["cores_used"]
    lines = [
        f"\n## Rollout ({'one core, taskset -c 0' if cores == 1 else f'{cores} cores'}; "
        f"benchmarks/bench_rollout.py, commit {m['commit']})\n",
        f"{m['platform']}, {m['cpu_count']} CPUs ({cores} used), jax {m['jax']} "
        f"({m['backend']}), load average at start {m['load_average']} (other jobs were running: "
        "the numbers are upper bounds). Random SGN weights, 24 balls, window 7, edge capacity "
        f"{report['single'][0]['edge_capacity'] if report['single'] else '?'} directed edges per "
        "graph, float32 network, float64 positions; compile time apart; best of the repeats.\n",
        "| model | rollouts | steps | compile (s) | ms per step | ms per rollout-step |",
        "|---|---|---|---|---|---|",
    ]
    for r in report["single"]:
        lines.append(f"| hidden {r['hidden']} ({r['n_params']:,} params, "
                     f"{r['model_gflop_per_step']:.3f} GFLOP/step, {r['gflop_per_s']:.0f} GFLOP/s) "
                     f"| 1 | {r['steps']} | {r['compile_s']:.1f} | {r['ms_per_step']:.3f} | "
                     f"{r['ms_per_step']:.3f} |")
    for r in report["batch"]:
        lines.append(f"| hidden {r['hidden']} | {r['batch']} (vmap) | {r['steps']} | "
                     f"{r['compile_s']:.1f} | {r['ms_per_batch_step']:.3f} | "
                     f"{r['ms_per_rollout_step']:.3f} |")
    if report.get("in_loop"):
        lines.append("")
        lines.append("Realistic states (the network runs every step, the balls follow the DEM "
                     "replay, so the edge counts are the DEM's; mean "
                     f"{report['in_loop'][0]['mean_pairs']:.1f} ball pairs within the skin, max "
                     f"{report['in_loop'][0]['max_pairs']}, capacity "
                     f"{report['in_loop'][0]['pair_capacity']}; "
                     f"{report['in_loop'][0]['mean_pw_edges']:.1f} directed ball-wall edges):\n")
        lines.append("| model | pair-capacity tiers | compile (s) | ms per step |")
        lines.append("|---|---|---|---|")
        for r in report["in_loop"]:
            tiers = ", ".join(map(str, r["tiers"])) or "none (full capacity)"
            lines.append(f"| hidden {r['hidden']} | {tiers} | {r['compile_s']:.1f} | "
                         f"{r['ms_per_step']:.3f} |")
    dem = report.get("dem")
    if dem:
        lines.append("")
        lines.append(f"DEM (sgn_jax.dem, standard case, dt_dem = {dem['dt_dem']:.4g} s, "
                     f"{dem['pair_mode']}): {dem['seconds_of_motion']:g} s of motion in "
                     f"{dem['motion_wall_s']:.1f} s ({dem['steps_per_s']:,.0f} DEM steps/s; "
                     f"compile {dem['compile_s']:.1f} s apart).\n")
        lines.append("| surrogate | wall time per simulated second (s) | speed-up vs DEM |")
        lines.append("|---|---|---|")
        per_second = dem["motion_wall_s"] / dem["seconds_of_motion"]
        for r in report["single"]:
            sgn = r["ms_per_step"] * 1e-3 * 1e4
            lines.append(f"| hidden {r['hidden']}, 1 rollout | {sgn:.2f} | {per_second / sgn:.1f}x |")
        for r in report.get("in_loop", []):
            if r["tiers"]:
                sgn = r["ms_per_step"] * 1e-3 * 1e4
                lines.append(f"| hidden {r['hidden']}, 1 rollout, pair tiers {r['tiers']} "
                             f"(realistic states) | {sgn:.2f} | {per_second / sgn:.1f}x |")
        for r in report["batch"]:
            sgn = r["ms_per_rollout_step"] * 1e-3 * 1e4
            lines.append(f"| hidden {r['hidden']}, per rollout in a vmapped batch of {r['batch']} "
                         f"| {sgn:.2f} | {per_second / sgn:.1f}x |")
    if report.get("memory"):
        lines.append("")
        lines.append("Memory of jax.grad of the cumulative energy through a rollout (fresh "
                     "process per row; checkpoint chunks of 100 steps):\n")
        lines.append("| steps | hidden | peak RSS (MB) | compiled temp (MB) | compiled temp "
                     "without checkpointing (MB) | grad run (s) |")
        lines.append("|---|---|---|---|---|---|")
        for r in report["memory"]:
            lines.append(f"| {r['steps']} | {r['hidden']} | {r['peak_rss_mb']:.0f} | "
                         f"{r['temp_bytes'] / 1e6:.1f} | {r['temp_bytes_unchunked'] / 1e6:.1f} | "
                         f"{r['run_s']:.1f} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hidden", type=int, nargs="+", default=[256, 128])
    parser.add_argument("--steps", type=int, default=1000, help="steps per single rollout")
    parser.add_argument("--batch", type=int, nargs="*", default=[8, 64])
    parser.add_argument("--batch-steps", type=int, default=100, help="steps per batched rollout")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--dem-seconds", type=float, default=1.0)
    parser.add_argument("--skip-dem", action="store_true")
    parser.add_argument("--memory-steps", type=int, nargs="*", default=[1000, 10000])
    parser.add_argument("--memory-hidden", type=int, default=64)
    parser.add_argument("--markdown", action="store_true",
                        help="also print the results as markdown, to replace the tables of "
                             "docs/benchmarks.md")
    args = parser.parse_args()

    from sgn_jax.pipelines.configure import graph_spec_from_config
    from sgn_jax.pipelines.rollout_run import initial_window

    report: dict = {"machine": machine(), "single": [], "batch": [], "memory": []}
    cfg = _standard_config()
    spec = graph_spec_from_config(cfg)
    if args.skip_dem:
        window0, t0 = lattice_window(cfg, spec)
    else:
        report["dem"], traj = bench_dem(cfg, args.dem_seconds)
        start = len(traj.t) // 2
        window0, t0 = initial_window(traj, start, spec.window), float(traj.t[start])
        print(json.dumps(report["dem"]), file=sys.stderr)
    report["in_loop"] = []
    for hidden in args.hidden:
        report["single"].append(bench_single(hidden, args.steps, args.repeats, window0, t0, cfg))
        print(json.dumps(report["single"][-1]), file=sys.stderr)
        if not args.skip_dem:
            cap = spec.pp_pair_capacity
            for tiers in ((), (cap // 4, cap // 2)):
                report["in_loop"].append(bench_in_loop(hidden, args.steps, args.repeats, traj,
                                                       start, cfg, tiers))
                print(json.dumps(report["in_loop"][-1]), file=sys.stderr)
        for batch in args.batch:
            report["batch"].append(bench_batch(hidden, batch, args.batch_steps,
                                               max(1, args.repeats - 1), window0, t0, cfg))
            print(json.dumps(report["batch"][-1]), file=sys.stderr)
    for steps in args.memory_steps:
        report["memory"].append(memory_in_subprocess(steps, args.memory_hidden))
        print(json.dumps(report["memory"][-1]), file=sys.stderr)
    print(json.dumps(report, indent=1))
    if args.markdown:
        print(markdown(report))


if __name__ == "__main__":
    main()
