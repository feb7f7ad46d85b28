"""Cold vs warm starts with the user cache (sgn_jax.records.cache): a short DEM run and a
design-study session, each run twice in fresh processes sharing one new cache directory.

    python benchmarks/bench_warm_start.py            # writes benchmarks/results/warm_start.json

Records wall times, the DEM's compile and settling times, and the design session's first-call
time (tracing + compile or cache load) beside a second call (run only), with the machine and
commit. docs/validation.md quotes the numbers.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from sgn_jax.records.io_utils import atomic_write, git_commit, machine_info

DESIGN_SESSION = r"""
import json, time
t0 = time.perf_counter()
import jax
import sgn_jax.api as sj
cfg = sj.load_config("emax_300rpm")
model = sj.load_surrogate()
packings = sj.make_packings(cfg, seeds=range(2))
t1 = time.perf_counter()
study = sj.design_study(model, cfg, ["motion.rpm"], packings, duration=0.06, burn_in=0.02,
                        horizon=10, n_segments=2)
vg = jax.jit(jax.value_and_grad(study.power))
t2 = time.perf_counter()
p, g = vg(study.theta0); jax.block_until_ready(g)
t3 = time.perf_counter()
p, g = vg(study.theta0); jax.block_until_ready(g)
t4 = time.perf_counter()
print(json.dumps({"setup_s": t1 - t0, "first_call_s": t3 - t2, "second_call_s": t4 - t3,
                  "power_W": float(p), "gradient_W_per_rpm": float(g[0])}))
"""


def _last_json(text: str) -> dict:
    for line in reversed(text.strip().splitlines()):
        try:
            return json.loads(line)
        except ValueError:
            continue
    raise RuntimeError(f"no JSON line in:\n{text[-2000:]}")


def main() -> None:
    results = {"machine": machine_info(), "commit": git_commit(), "runs": {}}
    with tempfile.TemporaryDirectory() as cache, tempfile.TemporaryDirectory() as out:
        env = {**os.environ, "SGN_JAX_CACHE_DIR": cache}
        env.pop("SGN_JAX_NO_CACHE", None)
        for label in ("cold", "warm"):
            t0 = time.perf_counter()
            proc = subprocess.run(
                [sys.executable, "-m", "sgn_jax.cli", "dem", "--config", "emax_300rpm",
                 "--duration", "0.05", "--out", str(Path(out) / f"{label}.npz"),
                 "--no-progress"], env=env, capture_output=True, text=True, check=True)
            summary = _last_json(proc.stdout)
            results["runs"][f"dem_{label}"] = {
                "wall_s": time.perf_counter() - t0,
                **{k: summary[k] for k in ("compile_time_s", "settle_wall_s", "settle_cached",
                                           "motion_wall_s")}}
            t0 = time.perf_counter()
            proc = subprocess.run([sys.executable, "-c", DESIGN_SESSION], env=env,
                                  capture_output=True, text=True, check=True)
            results["runs"][f"design_{label}"] = {"wall_s": time.perf_counter() - t0,
                                                  **_last_json(proc.stdout)}
            print(label, json.dumps(results["runs"]), flush=True)
    path = Path(__file__).parent / "results" / "warm_start.json"
    with atomic_write(path, "w") as fh:
        json.dump(results, fh, indent=1)
    print(json.dumps(results["runs"], indent=1))


if __name__ == "__main__":
    main()
