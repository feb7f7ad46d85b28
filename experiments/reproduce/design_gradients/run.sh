#!/bin/bash
# Design gradients against the DEM (docs/results.md, "Design gradients against the DEM"): the
# contact model's difference estimator with 24 packings at three design points x three
# parameters, and the paper-setting SGN's motion rows with 8 packings and both estimators, each
# beside the DEM's ensemble central differences. The DEM's side is read from this folder's
# expected/dem24.jsonl and expected/dem8.jsonl; DEM=run runs it anew (456 + 168 DEM runs).
# Resumable: a finished point is skipped. MODEL (default contact) and OUT choose the contact
# model and its folder (MODEL=contact_rebound OUT=runs/design_rebound: docs/collisions.md);
# SGN_ROWS=skip leaves out the paper-setting SGN's rows.
set -euo pipefail
cd "$(dirname "$0")/../../.."
HERE=experiments/reproduce/design_gradients
V="python $HERE/verify_gradients.py"
MODEL=${MODEL:-contact}
OUT=${OUT:-runs/design_contact}
SGN_ROWS=${SGN_ROWS:-run}
SGN=runs/design_emax_300rpm

mkdir -p $OUT/dem
if [ "${DEM:-committed}" = run ]; then
    $V --out $OUT dem --workers 2 --packings 24
else
    cp $HERE/expected/dem24.jsonl $OUT/dem/worker0.jsonl
fi

# The contact model, 24 packings (seeds 20-43), separation off, the difference estimator. Each
# group of parameters is one study: with a jar parameter among its names the DEM makes the
# packings in every jar the study evaluates (the default start), otherwise they are the base
# jar's packings. The groups, then merged into $OUT/surrogate.json:
S="surrogate --checkpoint $MODEL --separation off --estimators difference --packings 24"
$V --out $OUT/standard_motion $S --points standard --params motion.rpm,motion.amplitude
$V --out $OUT/standard_jar $S --points standard --params jar.straight_length
$V --out $OUT/edge_rpm $S --points edge --params motion.rpm
$V --out $OUT/edge_amplitude_jar $S --points edge --params motion.amplitude,jar.straight_length
$V --out $OUT/motion1_jar $S --points motion1 --params jar.straight_length
$V --out $OUT/motion1_motion $S --points motion1 --params motion.base_frequency_hz,motion.scale
$V --out $OUT merge $OUT/standard_motion $OUT/standard_jar $OUT/edge_rpm \
    $OUT/edge_amplitude_jar $OUT/motion1_jar $OUT/motion1_motion
$V --out $OUT report

[ "$SGN_ROWS" = skip ] && exit 0
# The SGN's DEM side (8 packings), only when its rows run.
mkdir -p $SGN/dem
if [ "${DEM:-committed}" = run ]; then
    $V --out $SGN dem --workers 2
else
    cp $HERE/expected/dem8.jsonl $SGN/dem/worker0.jsonl
fi
# The paper-setting SGN, 8 packings (seeds 20-27), its shipped rollout (separation on), both
# estimators (the difference estimator and the truncated-horizon autodiff one, 100 steps).
$V --out $SGN surrogate --checkpoint emax_300rpm --separation on \
    --params motion.rpm,motion.amplitude,motion.base_frequency_hz,motion.scale
$V --out $SGN report
