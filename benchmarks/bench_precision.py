"""Benchmark: float32 against bfloat16 matmuls for the fast tier's MLP shapes.

The SGN's cost is its MLPs: a 4-layer MLP of width H applied to every edge slot (240 per graph
at the standard capacities) and node (25). This times that block, jitted, in float32 and with
bfloat16 inputs and weights (``preferred_element_type=float32``: bf16 products, f32
accumulation, what a bf16 surrogate would run), for each ``--hidden``, interleaved in one
process so that both see the same load, and records whether the CPU has native bf16
(``avx512_bf16`` / ``amx_bf16`` in /proc/cpuinfo).

    taskset -c 0 python benchmarks/bench_precision.py [--hidden 64 128] [--markdown]

Writes benchmarks/results/bench_precision.json; with --markdown prints the table that replaces
the one of docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

ROOT = Path(__file__).resolve().parent.parent


def cpu_bf16_flags() -> list[str]:
    """The CPU flags that give native bf16 arithmetic (empty: emulated)."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return []
    flags = next((line.split(":", 1)[1].split() for line in text.splitlines()
                  if line.startswith("flags")), [])
    return sorted(f for f in flags if "bf16" in f)


def mlp_block(hidden: int, dtype, rows: int, layers: int = 4, width_in: int = 0):
    """A jitted ``rows x width_in`` -> ``rows x 3`` ReLU MLP in ``dtype`` with f32 accumulation."""
    key = jax.random.PRNGKey(0)
    sizes = [width_in or 3 * hidden] + [hidden] * (layers - 1) + [3]
    keys = jax.random.split(key, len(sizes))
    weights = [(jax.random.normal(k, (a, b), jnp.float32) / np.sqrt(a)).astype(dtype)
               for k, a, b in zip(keys[:-1], sizes[:-1], sizes[1:], strict=True)]
    x = jax.random.normal(keys[-1], (rows, sizes[0]), jnp.float32).astype(dtype)

    @jax.jit
    def run(x, weights):
        h = x
        for i, w in enumerate(weights):
            h = jnp.matmul(h, w, preferred_element_type=jnp.float32)
            if i < len(weights) - 1:
                h = jax.nn.relu(h).astype(dtype)
        return h

    return run, x, weights


def time_call(fn, *args, repeats: int) -> float:
    """Best time (s) of ``repeats`` blocks of 200 calls, per call."""
    jax.block_until_ready(fn(*args))
    best = float("inf")
    for _ in range(repeats):
        t = time.perf_counter()
        for _ in range(200):
            out = fn(*args)
        jax.block_until_ready(out)
        best = min(best, (time.perf_counter() - t) / 200)
    return best


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--hidden", type=int, nargs="+", default=[64, 128])
    p.add_argument("--rows", type=int, default=265, help="edge + node slots per graph")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--out", default="benchmarks/results/bench_precision.json")
    p.add_argument("--markdown", action="store_true",
                   help="also print the table, to replace the one of docs/benchmarks.md")
    args = p.parse_args(argv)
    from sgn_jax.experiment_tools import machine_info, write_json

    rows = []
    for hidden in args.hidden:
        f32 = mlp_block(hidden, jnp.float32, args.rows)
        bf16 = mlp_block(hidden, jnp.bfloat16, args.rows)
        t32 = min(time_call(f32[0], *f32[1:], repeats=1) for _ in range(args.repeats))
        t16 = min(time_call(bf16[0], *bf16[1:], repeats=1) for _ in range(args.repeats))
        rows.append({"hidden": hidden, "rows": args.rows, "float32_us": t32 * 1e6,
                     "bfloat16_us": t16 * 1e6, "bf16_over_f32": t16 / t32})
    doc = {"machine": machine_info(), "cpu_bf16_flags": cpu_bf16_flags(), "rows": rows}
    write_json(ROOT / args.out, doc)
    print(json.dumps(doc, indent=1))
    if args.markdown:
        m = doc["machine"]
        lines = [f"\n## float32 vs bfloat16 MLP blocks (`benchmarks/bench_precision.py`, "
                 f"commit {m['commit']})\n",
                 f"{m['processor']}, {m['cpu_count']} cores, jax {m['jax']}; native bf16 "
                 f"flags: {', '.join(doc['cpu_bf16_flags']) or 'none (bf16 is emulated)'}. "
                 f"A 4-layer MLP over {args.rows} rows (a graph's edge and node slots), "
                 "best of the repeats, per call:\n",
                 "| hidden | float32 (us) | bfloat16 inputs, f32 accumulation (us) | bf16 / f32 |",
                 "|---|---|---|---|"]
        lines += [f"| {r['hidden']} | {r['float32_us']:.1f} | {r['bfloat16_us']:.1f} | "
                  f"{r['bf16_over_f32']:.2f} |" for r in rows]
        print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
