#!/bin/bash
# The contact model on motions and packings it never trained on (docs/results.md, "The contact
# model on held-out motions"): the 6 held-out envelope motions, Motion 1, Motion 2 and the post
# jar (2 s), the standard case (10 s) and two fresh motions, 8 packings each; with the ball-ball
# separation off (its own setting) and, for the held-out and unseen sets, on. Then the bars.
#
# By default the DEM's side comes from this folder's expected/*.json (a DEM run's statistics do
# not depend on the model) and the rollouts start from the first 2 ms of each DEM run, which
# equal the full runs' first samples bit for bit. DEM=full runs the whole DEM records instead
# (~1.5 h of both cores) and computes the DEM's side from them. Resumable. JOBS=1 for one core.
# MODEL=DIR evaluates another model (a training run's checkpoint, docs/training.md) into
# OUT=DIR (default runs/contact_eval); SEPON=0 leaves out the runs with the separation on;
# PARALLEL=1 runs the evaluations side by side (a machine with many cores).
set -euo pipefail
cd "$(dirname "$0")/../../.."
JOBS=${JOBS:-2}
MODEL=${MODEL:-contact}
OUT=${OUT:-runs/contact_eval}
SEPON=${SEPON:-1}
PARALLEL=${PARALLEL:-0}
HERE=experiments/reproduce/contact_heldout
HELDOUT=heldout_c00,heldout_c01,heldout_c02,heldout_h00,heldout_h01,heldout_h02
GEN="python experiments/tools/generate_data.py --split eval --jobs $JOBS"

if [ "${DEM:-prefix}" = full ]; then
    $GEN --ensembles experiments/envelope/ensembles.toml --cases $HELDOUT --out data/envelope
    $GEN --ensembles experiments/envelope/unseen.toml --out data/unseen
    $GEN --ensembles experiments/contact/fresh.toml --out data/fresh
    ENVELOPE=data/envelope UNSEEN=data/unseen FRESH=data/fresh
    ref() { :; }
else
    for E in experiments/envelope/ensembles.toml experiments/envelope/unseen.toml \
             experiments/contact/fresh.toml; do
        $GEN --ensembles "$E" --prefix 0.002 --out data/prefix
    done
    ENVELOPE=data/prefix UNSEEN=data/prefix FRESH=data/prefix
    ref() { echo "--dem-reference $HERE/expected/$1.json"; }
fi

EC="python experiments/tools/evaluate_contact.py --model $MODEL --out $OUT"
ON="--rollout pp_separation=true"
run() { if [ "$PARALLEL" = 1 ]; then "$@" & else "$@"; fi; }
run $EC --name heldout --ensembles experiments/envelope/ensembles.toml --cases $HELDOUT \
    --data $ENVELOPE $(ref heldout)
run $EC --name unseen --ensembles experiments/envelope/unseen.toml \
    --cases motion1,motion2,post_motion1 --data $UNSEEN $(ref unseen)
run $EC --name standard --ensembles experiments/envelope/unseen.toml --cases standard \
    --data $UNSEEN $(ref standard)
run $EC --name fresh --ensembles experiments/contact/fresh.toml --data $FRESH $(ref fresh)
NAMES="heldout unseen standard fresh"
if [ "$SEPON" = 1 ]; then
    run $EC --name heldout_sepon --ensembles experiments/envelope/ensembles.toml \
        --cases $HELDOUT --data $ENVELOPE $ON $(ref heldout_sepon)
    run $EC --name unseen_sepon --ensembles experiments/envelope/unseen.toml \
        --cases motion1,motion2,post_motion1 --data $UNSEEN $ON $(ref unseen_sepon)
    NAMES="$NAMES heldout_sepon unseen_sepon"
fi
[ "$PARALLEL" = 1 ] && for job in $(jobs -p); do wait "$job"; done

python experiments/tools/evaluate_contact.py --bars $(for n in $NAMES; do echo "$OUT/$n.json"; done)
