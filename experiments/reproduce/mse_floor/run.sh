#!/bin/bash
# The DEM's own MSE_t floor (docs/results.md, "The MSE_t plateau: the DEM's own floor"): the
# MSE_t plateau between unrelated DEM packings of the same case, and between two DEM runs of the
# same packing (standard case, seed 4) that differ only in the integration step.
# Needs the standard case's and Motion 1's held-out records (the paper protocol's data:
# python experiments/tools/generate_data.py --split eval --cases standard,motion1 --jobs 2).
set -euo pipefail
cd "$(dirname "$0")/../../.."
M="python experiments/reproduce/mse_floor/mse_baseline.py"
python experiments/tools/generate_data.py --split eval --cases standard,motion1 --out data --jobs 2
$M --case standard --out runs/mse_baseline_standard.json
$M --case motion1 --out runs/mse_baseline_motion1.json
# the same packing at half the DEM step (5 s of motion): the chaos floor of any surrogate
sgn-jax dem --config experiments/configs/emax_300rpm.toml --seed 4 --duration 5 \
    --dt-dem 4.716981132075472e-07 --out data/chaos/standard_seed4_halfdt.npz --no-progress
$M --files data/standard_seed4.npz data/chaos/standard_seed4_halfdt.npz --out runs/mse_chaos.json
