#!/bin/bash
# The shipped contact model's recipe from scratch (docs/training.md, "Retraining the shipped
# model from scratch"): the 79 training records, the four stages of the built-in config
# contact_train, then the trained model on the 12 held-out motions of
# experiments/reproduce/contact_heldout (ball-ball separation off). Resumable: rerun it after a
# kill. JOBS=1 for one core.
set -euo pipefail
cd "$(dirname "$0")/../../.."
JOBS=${JOBS:-2}
GEN="python experiments/tools/generate_data.py --split train --jobs $JOBS"
$GEN --ensembles experiments/contact/training_runs.toml --out data/envelope
$GEN --ensembles experiments/contact/kicks.toml --out data/kicks
$GEN --ensembles experiments/envelope/corners.toml --out data/corners
sgn-jax train --config contact_train --data data --out runs/contact_train --resume
MODEL=runs/contact_train/corners/checkpoints/best OUT=runs/contact_train_eval SEPON=0 \
    JOBS=$JOBS bash experiments/reproduce/contact_heldout/run.sh
