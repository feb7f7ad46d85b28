#!/usr/bin/env bash
# More DEM packings of the six held-out charges and surrogates' evaluations on them, on a machine
# of many CPU cores without network (a lent device machine), inside a wall-time budget.
#
#   bash experiments/charges/device_heldout.sh MODEL [MODEL ...]
#
# MODEL: a training run folder or a checkpoint folder, or NAME=PATH (at most 5 models); a model
# that is not committed travels as a carried ignored path (e.g. runs/contact_charge/fourth_touch).
# Missing Python packages travel as wheels in .whl/ (ignored; carried), installed into $SITE.
# Settings from the environment (defaults):
#   SEEDS="104 105 106 107"  NAMES="" (all six)  DURATION=2.5 (s of DEM per record)
#   BUDGET=470 (s from this script's start to the end of the packing)  JOBS=0 (one per core)
#   TRIM_WINDOW=16 TRIM_DT=2e-4 (the trimmed records hold TRIM_WINDOW + 2 samples at TRIM_DT)
#   WORK=/tmp/device_heldout  OUT (the results; the device tool sets it)  PYTHON=python3
#   SITE=/tmp/site (where the wheels go)  CORES="" (e.g. 0-15; default: every core allowed)
#
# The call of the device tool (`run`, timeout_s 540, carry [".whl",
# "runs/contact_charge/fourth_touch"]; carry a run folder itself, not a symbolic link to it):
#   bash experiments/charges/device_heldout.sh touch=runs/contact_charge/fourth_touch
#
# What comes back ($OUT; experiments/charges/device_heldout.py says more): eval_<model>.json
# (evaluate.py's JSON over every charge: runs keyed <charge>_seed_<K>, summaries; a later model
# is evaluated here on the trimmed records with `evaluate.py --dem-reference eval_<model>.json`),
# records_trimmed.tar.gz (NAME/seed_K.npz, the first window of each new record),
# logs.tar.gz (every job's log, the per-charge evaluations, the bars, the job table) and
# device_heldout.log. Each stage is time-bounded: DEM jobs that cannot end by
# BUDGET - 80 s are skipped or killed, evaluations are killed at BUDGET - 20 s.
set -uo pipefail
export DH_T0=$(date +%s.%N)
PYTHON=${PYTHON:-python3}
OUT=${OUT:-runs/device_heldout}
WORK=${WORK:-/tmp/device_heldout}
SITE=${SITE:-/tmp/site}
mkdir -p "$OUT" "$WORK"
if compgen -G ".whl/*.whl" > /dev/null; then
    "$PYTHON" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
        --target "$SITE" .whl/*.whl || exit 3
    export PYTHONPATH=$SITE:$PWD${PYTHONPATH:+:$PYTHONPATH}
else
    export PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH}
fi
# One thread per process: every job runs pinned to its own core.
export JAX_PLATFORMS=cpu PYTHONUNBUFFERED=1 SGN_JAX_CACHE_DIR=$WORK/cache \
    XLA_FLAGS="--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1" \
    OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1 TF_CPP_MIN_LOG_LEVEL=2
{
    echo "host $(hostname 2>/dev/null) cores $(nproc) $(grep -m1 'model name' /proc/cpuinfo)"
    "$PYTHON" -c "import jax, numpy, sgn_jax.api; print('python', __import__('sys').version.split()[0], 'jax', jax.__version__, 'numpy', numpy.__version__, jax.devices())" 2>&1
} | tee -a "$OUT/device_heldout.log"
MODELS=()
for m in "$@"; do MODELS+=("$m"); done
[ ${#MODELS[@]} -gt 0 ] || { echo "usage: $0 MODEL [MODEL ...]"; exit 2; }
# shellcheck disable=SC2086
exec "$PYTHON" experiments/charges/device_heldout.py --models "${MODELS[@]}" \
    --seeds ${SEEDS:-104 105 106 107} ${NAMES:+--names $NAMES} --duration "${DURATION:-2.5}" \
    --budget "${BUDGET:-470}" --jobs "${JOBS:-0}" ${CORES:+--cores $CORES} \
    --trim-window "${TRIM_WINDOW:-16}" --trim-dt "${TRIM_DT:-2e-4}" --work "$WORK" --out "$OUT"
