"""Benchmark: sampling the jar's SDF grid (analytic and from the mesh) and querying it.

Records (printed as a Markdown section, optionally written as JSON with --out):
- time to sample the default jar at 0.5 mm from the analytic SDF and from its mesh (exact
  branch-and-bound, first call including jit compilation, warm call, cache hit), the post jar;
- trimesh's chunked ``signed_distance`` on a subset of the same nodes, extrapolated (baseline);
- query cost of the jitted ``query_sdf_grid`` (24 balls per call, and 1M points), compile
  time separately;
- interpolation error tables (``sgn_jax.geometry.accuracy.grid_error_report``) at 0.5 and
  0.25 mm for both jars.

All analytic grids here are the single grid of the combined ``jar_sdf`` (``per_patch=False``),
the one comparable with mesh grids; ``benchmarks/bench_sdf_grid_patches.py`` measures the
patch-stacked grids that ``sdf_grid_from_jar`` builds by default.

Usage: python benchmarks/bench_sdf_grid.py [--out results.json] [--quick]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time

import jax
import jax.numpy as jnp
import numpy as np

import sgn_jax  # noqa: F401  (enables x64)
from sgn_jax.geometry import (
    JarParams,
    grid_node_coordinates,
    jar_mesh,
    query_sdf_grid,
    sdf_grid_from_jar,
)
from sgn_jax.geometry.accuracy import grid_error_report
from sgn_jax.pipelines.configure import sdf_grid_from_mesh
from sgn_jax.records.io_utils import machine_info, write_json

DEFAULT = JarParams()
POST = JarParams(post_radius=0.006, has_post=True)


def timed(fn, *args, **kwargs):
    start = time.perf_counter()
    out = fn(*args, **kwargs)
    jax.block_until_ready(getattr(out, "values", out))
    return out, time.perf_counter() - start


def bench_sampling(spacing: float, trimesh_points: int) -> dict:
    import trimesh

    res: dict = {}
    _, res["analytic_first_s"] = timed(sdf_grid_from_jar, DEFAULT, spacing, per_patch=False)
    grid, res["analytic_warm_s"] = timed(sdf_grid_from_jar, DEFAULT, spacing, per_patch=False)
    res["grid_shape"] = list(grid.shape)
    res["grid_nodes"] = int(np.prod(grid.shape))

    mesh = jar_mesh(DEFAULT)
    res["mesh_faces"] = len(mesh.faces)
    with tempfile.TemporaryDirectory() as cache:
        _, res["mesh_first_s"] = timed(sdf_grid_from_mesh, mesh, spacing, cache_dir=cache)
    with tempfile.TemporaryDirectory() as cache:
        mesh_grid, res["mesh_warm_s"] = timed(sdf_grid_from_mesh, mesh, spacing, cache_dir=cache)
        _, res["mesh_cache_hit_s"] = timed(sdf_grid_from_mesh, mesh, spacing, cache_dir=cache)
    post_mesh = jar_mesh(POST)
    res["post_mesh_faces"] = len(post_mesh.faces)
    with tempfile.TemporaryDirectory() as cache:
        _, res["post_mesh_warm_s"] = timed(sdf_grid_from_mesh, post_mesh, spacing, cache_dir=cache)
    res["mesh_vs_analytic_max_um"] = float(
        np.abs(np.asarray(mesh_grid.values, np.float64) - np.asarray(grid.values, np.float64)).max()
        * 1e6
    )

    # Baseline: trimesh's signed distance in chunks of 2000 points on random grid nodes.
    nodes = grid_node_coordinates(grid).reshape(-1, 3)
    subset = nodes[np.random.default_rng(0).choice(len(nodes), trimesh_points, replace=False)]
    start = time.perf_counter()
    for i in range(0, len(subset), 2000):
        trimesh.proximity.signed_distance(mesh, subset[i : i + 2000])
    elapsed = time.perf_counter() - start
    res["trimesh_points"] = trimesh_points
    res["trimesh_points_per_s"] = trimesh_points / elapsed
    res["trimesh_full_grid_extrapolated_s"] = len(nodes) / res["trimesh_points_per_s"]
    return res


def bench_queries(spacing: float) -> dict:
    res: dict = {}
    grid = sdf_grid_from_jar(DEFAULT, spacing, per_patch=False)
    query = jax.jit(query_sdf_grid)
    rng = np.random.default_rng(1)
    offset = jnp.zeros(3, jnp.float32)
    for n, key in [(24, "24_balls"), (1_000_000, "1M_points")]:
        pts = jnp.asarray(rng.uniform([-0.03, 0.005, -0.015], [0.03, 0.04, 0.015], (n, 3)), jnp.float32)
        start = time.perf_counter()
        compiled = query.lower(grid, pts, offset).compile()
        res[f"compile_{key}_s"] = time.perf_counter() - start
        jax.block_until_ready(compiled(grid, pts, offset))
        repeats = 2000 if n == 24 else 5
        start = time.perf_counter()
        for _ in range(repeats):
            out = compiled(grid, pts, offset)
        jax.block_until_ready(out)
        per_call = (time.perf_counter() - start) / repeats
        res[f"per_call_{key}_us"] = per_call * 1e6
        res[f"points_per_s_{key}"] = n / per_call
    return res


def bench_accuracy(spacings: list[float], n_points: int) -> dict:
    res: dict = {}
    for name, params in [("default", DEFAULT), ("post", POST)]:
        for spacing in spacings:
            # float32, as the surrogate uses it
            grid = sdf_grid_from_jar(params, spacing, per_patch=False)
            res[f"{name}_h{spacing * 1e3:g}mm"] = grid_error_report(params, grid, n_points, seed=0)
    return res


def markdown(results: dict) -> str:
    m, s, q, a = results["machine"], results["sampling"], results["queries"], results["accuracy"]
    lines = [
        "## SDF grid sampling and queries (`benchmarks/bench_sdf_grid.py`)",
        "",
        f"Machine: {m['platform']}, {m['cpu_count']} CPUs, load average at start "
        f"{m['load_average_start']:.1f} (shared machine: timings are noisy); jax {m['jax']}; "
        f"commit {m['commit']}; {m['date']}.",
        "",
        f"Default jar, h = {s['spacing_mm']} mm, grid {s['grid_shape']} = {s['grid_nodes']:,} "
        f"nodes, mesh {s['mesh_faces']} triangles (post jar {s['post_mesh_faces']}):",
        "",
        "| what | time |",
        "|---|---|",
        f"| analytic `sdf_grid_from_jar`, first call (incl. compile) | {s['analytic_first_s']:.2f} s |",
        f"| analytic `sdf_grid_from_jar`, warm | {s['analytic_warm_s']:.2f} s |",
        f"| mesh `sdf_grid_from_mesh`, first call (incl. jit compile) | {s['mesh_first_s']:.2f} s |",
        f"| mesh `sdf_grid_from_mesh`, warm (no cache) | {s['mesh_warm_s']:.2f} s |",
        f"| mesh `sdf_grid_from_mesh`, cache hit | {s['mesh_cache_hit_s']:.3f} s |",
        f"| post jar mesh, warm (no cache) | {s['post_mesh_warm_s']:.2f} s |",
        f"| trimesh `signed_distance`, chunks of 2000 ({s['trimesh_points']:,} nodes, "
        f"{s['trimesh_points_per_s']:,.0f} points/s), extrapolated to the grid | "
        f"{s['trimesh_full_grid_extrapolated_s']:.0f} s |",
        "",
        f"Mesh grid vs analytic grid: max difference {s['mesh_vs_analytic_max_um']:.2f} um "
        "(the 256-gon's sagitta is 1.51 um).",
        "",
        f"Jitted `query_sdf_grid` (float32, h = {s['spacing_mm']} mm): 24 balls "
        f"{q['per_call_24_balls_us']:.1f} us/call (compile {q['compile_24_balls_s']:.2f} s); "
        f"1M points {q['points_per_s_1M_points'] / 1e6:.1f} M points/s "
        f"(compile {q['compile_1M_points_s']:.2f} s).",
        "",
        "Interpolation error (float32 grid) at random cavity points vs the exact distance, "
        "max / rms in um (n points); 'crease' = cells that straddle a medial surface "
        "(two walls equidistant), 'band' = exact phi > -6 mm:",
        "",
        "| jar, h | all | smooth planar | smooth curved | crease | band | band, smooth |",
        "|---|---|---|---|---|---|---|",
    ]
    for key, rep in a.items():
        cells = [f"{rep[c]['max_um']:.2f} / {rep[c]['rms_um']:.2f} ({rep[c]['n']})"
                 for c in ("all", "smooth_planar", "smooth_curved", "crease", "band", "band_smooth")]
        lines.append(f"| {key.replace('_h', ', h = ')} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", help="write the results as JSON here")
    parser.add_argument("--quick", action="store_true", help="fewer points (smoke test)")
    args = parser.parse_args()

    results = {
        "machine": machine_info(),
    }
    spacing = 5e-4
    results["sampling"] = {"spacing_mm": spacing * 1e3,
                           **bench_sampling(spacing, 2000 if args.quick else 20_000)}
    results["queries"] = bench_queries(spacing)
    results["accuracy"] = bench_accuracy([5e-4] if args.quick else [5e-4, 2.5e-4],
                                         2000 if args.quick else 20_000)
    results["machine"]["load_average_end"] = os.getloadavg()[0]
    if args.out:
        write_json(args.out, results)
    print(markdown(results))


if __name__ == "__main__":
    main()
