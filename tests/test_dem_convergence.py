"""Time-step convergence of the standard case (slow: ~20 M DEM steps).

The mean dissipation power over 1 s of motion at dt_dem = 9.5e-7 s (k = 106) and at half of it
(k = 212) must agree within the spread of 4 seeds. The single runs are chaotic (and the charge
is multistable, docs/conventions.md section 7), so only the ensemble statistics can be compared.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

import sgn_jax  # noqa: F401
from sgn_jax.config import builtin_config_path, load_config
from sgn_jax.pipelines.dem_run import run_dem

SEEDS = (0, 1, 2, 3)


@pytest.mark.slow
def test_dissipation_power_converges_in_dt_dem():
    cfg = load_config(builtin_config_path("emax_300rpm"))
    power = {}
    contacts = {}
    for dt_dem in (9.5e-7, 4.75e-7):
        runs = [run_dem(cfg, duration=1.0, seed=s, dt_dem=dt_dem, progress=False).summary
                for s in SEEDS]
        power[dt_dem] = np.array([r["mean_dissipation_power_W"] for r in runs])
        contacts[dt_dem] = np.array([r["mean_pp_contacts"] for r in runs])
        for r in runs:
            assert r["balls_outside"] == 0
            assert abs(r["ledger_residual_rel"]) < 0.01
    coarse, fine = power[9.5e-7], power[4.75e-7]
    spread = max(coarse.std(ddof=1), fine.std(ddof=1))
    print(json.dumps({"seeds": SEEDS, "power_W_dt_9.5e-7": coarse.tolist(),
                      "power_W_dt_4.75e-7": fine.tolist(),
                      "mean_pp_contacts_dt_9.5e-7": contacts[9.5e-7].tolist(),
                      "mean_pp_contacts_dt_4.75e-7": contacts[4.75e-7].tolist(),
                      "mean_difference_W": float(coarse.mean() - fine.mean()),
                      "spread_W": float(spread)}))
    assert abs(coarse.mean() - fine.mean()) <= spread
