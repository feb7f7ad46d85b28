#!/bin/bash
# The motion-general SGN (`envelope`) and the paper-setting SGN (`emax_300rpm`) on the 6 held-out
# motions of the envelope design (8 held-out packings each, 1.5 s), and `envelope` on Motion 1,
# Motion 2, the post jar (2 s) and the standard case (10 s); each with the ball-ball separation
# off and on (docs/results.md, "The motion-general SGN on held-out motions"). Resumable.
# JOBS=1 for one core.
set -uo pipefail
cd "$(dirname "$0")/../../.."
JOBS=${JOBS:-2}
HERE=experiments/reproduce/envelope_heldout
HELDOUT=heldout_c00,heldout_c01,heldout_c02,heldout_h00,heldout_h01,heldout_h02
GEN="python experiments/tools/generate_data.py --split eval --jobs $JOBS"
$GEN --ensembles experiments/envelope/ensembles.toml --out data/envelope || exit 1
$GEN --ensembles experiments/envelope/unseen.toml --out data/unseen || exit 1

evaluate() {  # NAME MODEL SEPARATION ENSEMBLES CASES DATA
    python $HERE/evaluate_model.py --name "$1" --model "$2" --rollout "pp_separation=$3" \
        --ensembles "$4" --cases "$5" --data "$6" \
        || echo "run.sh: $1: some rollouts failed or went non-finite"
    python $HERE/report.py --experiment "runs/experiments/$1" --markdown \
        --out "runs/experiments/$1/report.json" | tee "runs/experiments/$1/report.md"
}
for SEP in off on; do
    [ $SEP = on ] && FLAG=true || FLAG=false
    for MODEL in envelope emax_300rpm; do
        evaluate ${MODEL}_sep$SEP $MODEL $FLAG experiments/envelope/ensembles.toml $HELDOUT data/envelope
    done
    evaluate envelope_unseen_sep$SEP envelope $FLAG experiments/envelope/unseen.toml \
        motion1,motion2,post_motion1 data/unseen
    evaluate envelope_standard_sep$SEP envelope $FLAG experiments/envelope/unseen.toml standard data/unseen
done
# one condensed row per model and rollout (mean and worst power error, Spearman, speeds, overlaps)
python $HERE/report.py --ablation --experiment runs/experiments/envelope_sepoff \
    --experiment runs/experiments/envelope_sepon --experiment runs/experiments/emax_300rpm_sepoff \
    --experiment runs/experiments/emax_300rpm_sepon
