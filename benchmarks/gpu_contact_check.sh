#!/bin/bash
# Run on a lent GPU machine from the repo root (the device tool: carry .whl and .gpucache, see
# docs/benchmarks.md, "The shipped contact model and the DEM on one H200 GPU"): the wheels of the
# dependencies the image lacks, the settled packings cache; writes $OUT/gpu.log.
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl && export PYTHONPATH=/tmp/site:$PWD || exit 1
rm -rf sgn_jax/data/models/contact/2750   # a stale step of the old shipped model left on the machine
ls sgn_jax/data/models/contact
export SGN_JAX_CACHE_DIR=$PWD/.gpucache SGN_JAX_NO_CACHE=0 PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader
python3 -c "import jax; print(jax.__version__, jax.devices())"
for B in 1 32 256 1024; do
  timeout 90 python3 benchmarks/bench_ratio.py --worker sgn --worker-args "{\"model\": \"contact\", \"batch\": $B, \"seconds\": 0.1, \"tiers\": false}" 2>&1 | grep -v Warn | tail -1 | cut -c1-400 | tee -a $OUT/gpu.log
done
for a in '{"batch": 32, "seconds": 0.01, "sequential": false}' '{"batch": 256, "seconds": 0.005, "sequential": false}' '{"batch": 1, "seconds": 0.005, "sequential": true}'; do
  timeout 150 python3 benchmarks/bench_ratio.py --worker dem --worker-args "$a" 2>&1 | grep -v Warn | tail -1 | cut -c1-600 | tee -a $OUT/gpu.log
done
echo DONE | tee -a $OUT/gpu.log
