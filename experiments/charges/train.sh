#!/bin/bash
# The charge-conditioned contact model's training recipe (docs/contact_charge.md, "Training"),
# stage by stage on one core; each stage warm-starts from the one before and resumes after a
# kill (rerun this script: a finished stage is skipped). Needs the charge design's DEM records
# (experiments/charges/make_data.py --split train) and the standard charge's training motions
# (data/envelope/train_*.npz, docs/training.md).
#   OUT=runs/contact_charge CORE=1 bash experiments/charges/train.sh
set -euo pipefail
cd "$(dirname "$0")/../.."
OUT=${OUT:-runs/contact_charge}
CORE=${CORE:-0}
DRIVER="taskset -c $CORE python -m sgn_jax.pipelines.contact_charge_train_run --data data/charges"
TRAIN="$DRIVER --config sgn_jax/configs/contact_charge_train.toml"
CHARGES=$(ls data/charges/*/seed_*.npz | tr '\n' ' ')
stage() {   # stage NAME ARGS...: skip a finished stage, resume an interrupted one
    local name=$1; shift
    if [ -f "$OUT/$name/summary.json" ]; then echo "stage $name done"; return; fi
    local resume=""
    [ -d "$OUT/$name/checkpoints/latest" ] && resume="--resume"
    ${TRAINER:-$TRAIN} --out "$OUT/$name" $resume "$@"
}
# 1. one-step-ahead behaviour on the charges: short unrolls, a high learning rate (~23 min)
stage unroll6 --steps 4000 --batch-size 8 --unroll 6
# 2. long unrolls fed with the model's own predictions, the charges (twice) and the standard
#    charge's training motions (~14 min)
stage unroll24 --records $CHARGES data/envelope/train_*.npz \
    --init-from "$OUT/unroll6/checkpoints/latest" --unroll 24 --pushforward \
    --lr-init 3e-4 --lr-final 1e-5 --steps 900 --batch-size 8 --checkpoint-every 100
# 3. the contact-state term: the model's balls touch where the DEM's do (~15 min)
stage touch --records $CHARGES data/envelope/train_*.npz \
    --init-from "$OUT/unroll24/checkpoints/latest" --unroll 24 --pushforward --touch-weight 30 \
    --lr-init 2e-4 --lr-final 1e-5 --steps 900 --batch-size 8 --checkpoint-every 100
# 4. the law rebound on (experiments/charges/rebound_train.toml), the same settings (~15 min)
TRAINER="$DRIVER --config experiments/charges/rebound_train.toml" \
stage rebound --records $CHARGES data/envelope/train_*.npz \
    --init-from "$OUT/touch/checkpoints/latest" --unroll 24 --pushforward --touch-weight 30 \
    --lr-init 2e-4 --lr-final 1e-5 --steps 900 --batch-size 8 --checkpoint-every 100
# 5. the shipped model (contact_charge): the same at half the step, 1e-4 s
#    (experiments/charges/rebound_fine_train.toml, 600 steps, ~11 min)
TRAINER="$DRIVER --config experiments/charges/rebound_fine_train.toml" \
stage fine --records $CHARGES data/envelope/train_*.npz \
    --init-from "$OUT/rebound/checkpoints/latest" --unroll 24 --pushforward --touch-weight 30 \
    --lr-init 2e-4 --lr-final 1e-5 --steps 600 --batch-size 8 --checkpoint-every 100
# 6. the shipped settings, the same weights rolled out with every fresh impact passive, the
#    rebound in the overlap sweeps for free balls and the friction sweeps on the walls only
#    (docs/contact_charge.md, "Training on charges of different ball counts")
if [ ! -d "$OUT/shipped" ]; then
    python -c "import sys, sgn_jax.experiment_tools as xt; xt.derive_contact_model(
        sys.argv[1], sys.argv[2], law_rebound_exact='fresh', rebound_sweeps='free',
        friction_sweep_contacts='wall')" "$OUT/fine/checkpoints/latest" "$OUT/shipped"
fi
echo "the shipped model: $OUT/shipped (experiments/tools/ship_model.py --run $OUT/shipped ...)"
