#!/usr/bin/env bash
# contact_k2 (session 7): the shipped contact_s1c continued with the envelope's four circle
# corners among its training records (docs/contact.md, runs table). One core, ~16 min.
# Data first (~35 min on two cores; the same records as contact_s1c's, sha256 aside, plus the
# corners):
#   python experiments/generate_data.py --ensembles experiments/contact/s1c_training_runs.toml --split train --out data/envelope --jobs 2
#   python experiments/generate_data.py --ensembles experiments/contact/s1c_kicks.toml --split train --out data/kicks --jobs 2
#   python experiments/generate_data.py --ensembles experiments/envelope/corners.toml --split train --out data/corners --jobs 2
# data/envelope must hold only those 55 runs (train_*.npz is globbed): s1c was trained on 55 of
# the envelope's 84 training runs (the packings that existed then), as its PROVENANCE.json lists.
set -euo pipefail
cd "$(dirname "$0")/../.."
T=experiments/contact/train_contact.py
C="--config experiments/contact/contact_dt2.toml --relative-floor 3e-4 --spin --overlap-limit 5e-5 --overlap-law-factor 1.5 --overlap-sweeps 3 --friction-sweeps 6 --checkpoint-every 100"
A1='data/kicks/kick_still_*_seed3[012]0[0-3].npz'
A2='data/corners/corner_*.npz'
python $T $C --also "$A1" --also "$A2" --out runs/contact_k1 --steps 600 --minutes 25 --unroll 24 --pushforward --init sgn_jax/data/models/contact --lr 1e-4 --lr-final 1e-5 --resume
python $T $C --also "$A1" --also "$A2" --out runs/contact_k2 --steps 300 --minutes 12 --unroll 12 --pushforward --init runs/contact_k1/checkpoints/best --lr 5e-5 --lr-final 1e-5 --resume
