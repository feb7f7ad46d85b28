"""api.rollout_sweep: M motions x K packings in one vmapped program, each rollout the one
api.rollout_ensemble gives for its config; configs that differ outside [motion] are refused."""

from __future__ import annotations

import jax
import numpy as np
import pytest

import sgn_jax.api as sj
from sgn_jax.config import replace_section

# XLA compilations in this process (jax.monitoring), to check that a second ensemble under
# another motion runs the program already compiled.
_COMPILES: list[float] = []


def _count_compiles(event: str, duration: float, **_) -> None:
    if event == "/jax/core/compile/backend_compile_duration":
        _COMPILES.append(duration)


jax.monitoring.register_event_duration_secs_listener(_count_compiles)


@pytest.fixture(scope="module")
def setting(contact_short_packings):
    # The default (contact) model at its 2e-4 s step, settle_time 0.02 s, seeds 0 and 1
    # (conftest.py): the file's other test uses the same fixture, so the file makes one.
    model, cfg, packings = contact_short_packings
    return cfg, model, packings


@pytest.mark.slow
def test_a_sweep_equals_one_ensemble_per_motion(setting):
    cfg, model, packings = setting
    cfgs = [replace_section(cfg, "motion", rpm=rpm) for rpm in (250.0, 350.0)]
    sweep = sj.rollout_sweep(model, cfgs, packings, duration=0.01)
    assert sweep.positions.shape[:2] == (2, 2)
    assert sweep.steps.energy_cum.shape[:2] == (2, 2)
    for m, c in enumerate(cfgs):
        compiled_before = len(_COMPILES)
        alone = sj.rollout_ensemble(model, c, packings, duration=0.01)
        if m:   # the motion's values are arguments of the first motion's compiled program
            assert len(_COMPILES) == compiled_before, _COMPILES[compiled_before:]
        # A batch of 4 rounds the float32 network differently from a batch of 2, and the
        # rollout amplifies it (tests/test_sharding.py measures the same: ~1e-6 m, 2e-4 J/J
        # after 100 steps); a wrong motion or packing would differ by millimetres.
        np.testing.assert_allclose(sweep.positions[m], alone.positions, rtol=0, atol=1e-5)
        np.testing.assert_allclose(sweep.steps.energy_cum[m], alone.steps.energy_cum,
                                   rtol=2e-3)
    # the two motions give different rollouts
    assert np.abs(sweep.positions[0] - sweep.positions[1]).max() > 1e-4


def test_a_sweep_varies_the_motion_only(setting):
    cfg, model, packings = setting
    other_jar = replace_section(cfg, "jar", straight_length=0.03)
    with pytest.raises(sj.DesignError, match=r"\[jar\]"):
        sj.rollout_sweep(model, [cfg, other_jar], packings, duration=0.01)
    with pytest.raises(sj.DesignError, match="at least one"):
        sj.rollout_sweep(model, [], packings, duration=0.01)


@pytest.mark.slow
def test_an_ensemble_mapped_one_packing_after_another_equals_the_vmapped_one(
        contact_short_packings):
    """``batching="map"``: the packings one after another (``lax.map``) in the model's
    single-rollout form (the contact kind's acting-rows MLPs): the vmapped ensemble's
    rollouts, to the float32 rounding a batch changes (as above)."""
    model, cfg, packings = contact_short_packings
    runs = {b: sj.rollout_ensemble(model, cfg, packings, duration=0.01, batching=b)
            for b in ("vmap", "map")}
    assert runs["map"].positions.shape == runs["vmap"].positions.shape
    np.testing.assert_allclose(runs["map"].positions, runs["vmap"].positions, rtol=0,
                               atol=1e-5)
    np.testing.assert_allclose(runs["map"].steps.energy_cum, runs["vmap"].steps.energy_cum,
                               rtol=2e-3)
    assert np.abs(runs["map"].positions[:, -1] - runs["map"].positions[:, 0]).max() > 1e-5
    with pytest.raises(sj.DesignError, match="batching"):
        sj.rollout_ensemble(model, cfg, packings, duration=0.01, batching="pmap")
