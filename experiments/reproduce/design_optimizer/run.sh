#!/bin/bash
# The motion optimiser checked by the DEM (docs/results.md, "A motion optimised on the surrogate,
# checked by the DEM"): Adam over the circle's (rpm, amplitude) in the envelope to reach 0.3 W
# with the smallest peak jar acceleration, on the contact model's design-study gradients; then
# the DEM at the optimum (8 packings never trained on) and the report. Resumable.
set -euo pipefail
cd "$(dirname "$0")/../../.."
O="python experiments/reproduce/design_optimizer/optimize_motion.py --out runs/design/optimize_contact"
$O optimize --checkpoint contact
$O dem
$O report
