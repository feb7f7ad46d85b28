"""Ensembles sharded over devices (sgn_jax.api.shard_packings) give the unsharded numbers, and
data-parallel training (sgn_jax.surrogate.train.DataParallel) gives the one-device update.

The checks run in a fresh process with two host CPU devices
(``XLA_FLAGS=--xla_force_host_platform_device_count=2``: the flag must be set before JAX
starts), so that the rest of the suite keeps one device: tests/two_device_checks.py, whose
``ensemble`` and ``step`` checks the default run makes once per session in one process
(conftest.py's ``two_device_results``). Both sets of tests are in this one file: with
``--dist loadfile`` they run in one xdist worker, so the other worker never waits for the
two-device process (it waited 15-18 s for it when they were two files).

What "the same" means for ensembles, measured: a sharded ensemble of two packings (one per device) is
bit-identical to rolling each packing out alone (the default run checks this). The one-device
vmapped batch of two (checked in the slow tier) differs from both at float32 rounding (batched matmuls round differently), which the chaotic rollout
amplifies by about e^7 per 10 ms: after 100 steps positions differ by ~1e-6 m, energies by
~2e-4 relative, and the 0.01-s ensemble power by ~4e-3 relative; those are the tolerances below.
"""

from __future__ import annotations

import pytest
from two_device_checks import run_in_two_device_process


def _check_ensemble(out: dict) -> None:
    assert len(out["devices"]) == 2                      # one packing on each device
    assert out["max_pos_diff_alone"] == 0.0              # each device runs its packing alone
    assert out["energy_sharded"] == out["energy_alone"]
    assert min(out["energy_alone"]) > 0                   # the balls did collide
    assert "multiple of 2" in out["odd"]


@pytest.mark.slow
def test_sharded_ensemble_equals_unsharded_on_two_host_devices(two_device_results):
    """The default run: the sharded ensemble rollout (the design study's sharding, the same
    ``shard_packings`` placement under a gradient, is checked in the slow tier below)."""
    _check_ensemble(two_device_results["ensemble"])


@pytest.mark.slow
def test_sharded_ensemble_and_design_study_equal_unsharded_on_two_host_devices():
    out = run_in_two_device_process(["ensemble_study"])["ensemble_study"]
    _check_ensemble(out)
    assert out["max_pos_diff"] < 1e-5     # vs the one-device batch: float32 rounding
    # each device maps over its packings (batching="map", jax.shard_map): float32 rounding
    assert out["max_pos_diff_mapped"] < 1e-5
    assert out["power"][1] == pytest.approx(out["power"][0], rel=2e-2)
    assert abs(out["grad"][0]) > 0
    assert out["grad"][1] == pytest.approx(out["grad"][0], rel=5e-2)


# --------------------------------------------------------------------------------------------
# Data-parallel training
#
# What "the same" means, measured (hidden 16, 5 steps at lr 1e-3, 2 x 4 graphs per step, no
# noise): the sharded step sums the two devices' gradients, the one-device step sums over one
# batch of the same 8 samples, so they differ only in float32 summation order. With plain SGD
# the parameters differ by 2.9e-11 after 5 steps, exactly as much as the one-device step on the
# same samples in reverse order. Adam divides each gradient component by its own running RMS, so
# a component that is nearly zero by cancellation (rounding noise ~1e-9 against eps = 1e-8)
# turns its rounding into a visible update: the parameters differ by 1.6e-6 (one device on the
# reversed samples: 1.7e-6). Tolerances: 1e-9 with SGD, 1e-5 with Adam (1 % of one step's lr).
# SGD is the sharp check (Adam is blind to a gradient's scale): a gradient counted once per
# device instead of once moved the SGD parameters by 2.8e-4.


@pytest.fixture(scope="module")
def result(two_device_results):
    return two_device_results["step"]


@pytest.mark.slow
def test_the_sharded_step_gives_the_one_device_update_on_the_same_samples(result):
    assert all(group == [4, 4] for group in result["plan"][:5])    # 8 samples a step
    for name, tol in (("sgd", 1e-9), ("adam", 1e-5)):
        r = result[name]
        assert r["replicated"] and r["devices"] == 2 and r["step"] == 5
        assert r["moved"] > 1e-4                  # the steps did move the parameters
        assert r["sharded"] < tol, (name, r)
        assert r["sums_rel"] < 1e-5, (name, r)    # the loss sums, summed over the devices
        assert r["eval"][1] == pytest.approx(r["eval"][0], rel=1e-5)


# Slow tier: a second two-device process that trains through the whole loop. Its
# twin in the default run is the step check above (the loop calls that same sharded step and
# packer) and test_more_devices_than_there_are_is_a_clear_error (the loop's device check).
@pytest.mark.slow
def test_the_training_loop_runs_data_parallel():
    run = run_in_two_device_process(["loop"])["loop"]
    assert run["devices"] == 2 and run["config_devices"] == 2
    assert run["max_graphs"] == 3                 # batch_size 6 over 2 devices
    assert len(run["losses"]) == 2
    assert all(v is not None and v == v and v < 1e3 for row in run["losses"] for v in row)


def test_more_devices_than_there_are_is_a_clear_error(tmp_path):
    from sgn_jax.config import builtin_config_path, load_config, replace_section
    from sgn_jax.pipelines.train_run import train
    from sgn_jax.surrogate.train import TrainingError

    cfg = load_config(builtin_config_path("emax_300rpm"))
    cfg = replace_section(cfg, "train", batch_size=4)
    with pytest.raises(TrainingError, match="xla_force_host_platform_device_count"):
        train(cfg, [], tmp_path / "x", devices=4, sdf=object(), progress=False,
              log=lambda m: None)
