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
set -euo pipefail
cd "$(dirname "$0")/../../.."
JOBS=${JOBS:-2}
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

EC="python experiments/tools/evaluate_contact.py --model contact --out runs/contact_eval"
ON="--rollout pp_separation=true"
$EC --name heldout --ensembles experiments/envelope/ensembles.toml --cases $HELDOUT \
    --data $ENVELOPE $(ref heldout)
$EC --name unseen --ensembles experiments/envelope/unseen.toml \
    --cases motion1,motion2,post_motion1 --data $UNSEEN $(ref unseen)
$EC --name standard --ensembles experiments/envelope/unseen.toml --cases standard \
    --data $UNSEEN $(ref standard)
$EC --name fresh --ensembles experiments/contact/fresh.toml --data $FRESH $(ref fresh)
$EC --name heldout_sepon --ensembles experiments/envelope/ensembles.toml --cases $HELDOUT \
    --data $ENVELOPE $ON $(ref heldout_sepon)
$EC --name unseen_sepon --ensembles experiments/envelope/unseen.toml \
    --cases motion1,motion2,post_motion1 --data $UNSEEN $ON $(ref unseen_sepon)

python experiments/tools/evaluate_contact.py --bars runs/contact_eval/{heldout,unseen,standard,fresh,heldout_sepon,unseen_sepon}.json
