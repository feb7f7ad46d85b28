"""Ensembles sharded over devices (sgn_jax.api.shard_packings) give the unsharded numbers.

The check runs in a fresh process with two host CPU devices
(``XLA_FLAGS=--xla_force_host_platform_device_count=2``: the flag must be set before JAX
starts), so that the rest of the suite keeps one device: tests/two_device_checks.py, whose
``ensemble`` check the default run makes once per session together with
tests/test_train_sharded.py's (conftest.py's ``two_device_results``).

What "the same" means, measured: a sharded ensemble of two packings (one per device) is
bit-identical to rolling each packing out alone. The one-device vmapped batch of two differs
from both at float32 rounding (batched matmuls round differently), which the chaotic rollout
amplifies by about e^7 per 10 ms: after 100 steps positions differ by ~1e-6 m, energies by
~2e-4 relative, and the 0.01-s ensemble power by ~4e-3 relative; those are the tolerances below.
"""

from __future__ import annotations

import pytest
from two_device_checks import run_in_two_device_process


def _check_ensemble(out: dict) -> None:
    assert len(out["devices"]) == 2                      # one packing on each device
    assert out["max_pos_diff_alone"] == 0.0              # each device runs its packing alone
    assert out["max_pos_diff"] < 1e-5                     # vs the batched run: float32 rounding
    assert out["energy_sharded"] == pytest.approx(out["energy_plain"], rel=2e-3)
    assert "multiple of 2" in out["odd"]


def test_sharded_ensemble_equals_unsharded_on_two_host_devices(two_device_results):
    """The default run: the sharded ensemble rollout (the design study's sharding, the same
    ``shard_packings`` placement under a gradient, is checked in the slow tier below)."""
    _check_ensemble(two_device_results["ensemble"])


@pytest.mark.slow
def test_sharded_ensemble_and_design_study_equal_unsharded_on_two_host_devices():
    out = run_in_two_device_process(["ensemble_study"])["ensemble_study"]
    _check_ensemble(out)
    assert out["power"][1] == pytest.approx(out["power"][0], rel=2e-2)
    assert out["grad"][1] == pytest.approx(out["grad"][0], rel=5e-2)
