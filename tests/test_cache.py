"""The user cache (sgn_jax.records.cache): settled packings reused across runs, switched off by
env."""

from __future__ import annotations

import numpy as np
import pytest

from sgn_jax.config import builtin_config_path, load_config, replace_section
from sgn_jax.pipelines import dem_run as driver
from sgn_jax.records import cache


@pytest.fixture
def tiny_cfg():
    cfg = load_config(builtin_config_path("emax_300rpm"))
    cfg = replace_section(cfg, "balls", count=6)
    return replace_section(cfg, "dem", settle_time=0.003, chunk_samples=10)


@pytest.fixture
def cache_dir(tmp_path, monkeypatch):
    monkeypatch.delenv(cache.ENV_OFF, raising=False)
    monkeypatch.setenv(cache.ENV_DIR, str(tmp_path / "cache"))
    return tmp_path / "cache"


def test_cache_root_and_switch(monkeypatch, tmp_path):
    monkeypatch.setenv(cache.ENV_DIR, str(tmp_path / "x"))
    monkeypatch.setenv(cache.ENV_OFF, "1")
    assert cache.cache_root() == tmp_path / "x"
    assert not cache.cache_enabled() and cache.settled_dir() is None
    assert cache.enable_compilation_cache() is None
    monkeypatch.setenv(cache.ENV_OFF, "0")
    assert cache.cache_enabled() and cache.settled_dir() == tmp_path / "x" / "settled"


# The slow tier (`pytest -m slow`; the default run's time): two DEM runs through the settled-packing cache.
@pytest.mark.slow
def test_second_run_reuses_the_settled_packing_bit_for_bit(tiny_cfg, cache_dir):
    first = driver.run_dem(tiny_cfg, duration=0.002, seed=5, progress=False)
    assert not first.summary["settle_cached"]
    assert len(list((cache_dir / "settled").glob("*.npz"))) == 1
    second = driver.run_dem(tiny_cfg, duration=0.002, seed=5, progress=False)
    assert second.summary["settle_cached"] and second.summary["settle_wall_s"] == 0
    np.testing.assert_array_equal(first.arrays["pos"], second.arrays["pos"])
    np.testing.assert_array_equal(first.arrays["diss_pp_normal"], second.arrays["diss_pp_normal"])
    # Another seed settles anew. Another rpm rests the jar at the same place: it reuses the
    # packing and equals a fresh run of that rpm bit for bit. Another phase rests the jar
    # elsewhere: settled anew (a translated packing would differ in the last bits).
    other_seed = driver.run_dem(tiny_cfg, duration=0.001, seed=6, progress=False)
    assert not other_seed.summary["settle_cached"]
    faster = replace_section(tiny_cfg, "motion", rpm=400.0)
    third = driver.run_dem(faster, duration=0.002, seed=5, progress=False)
    assert third.summary["settle_cached"]
    fresh = driver.run_dem(faster, duration=0.002, seed=5, progress=False, settle_cache=False)
    np.testing.assert_array_equal(third.arrays["pos"], fresh.arrays["pos"])
    turned = replace_section(tiny_cfg, "motion", phase=0.5)
    assert not driver.run_dem(turned, duration=0.001, seed=5,
                              progress=False).summary["settle_cached"]


@pytest.mark.slow
def test_a_damaged_entry_is_settled_again(tiny_cfg, cache_dir):
    driver.run_dem(tiny_cfg, duration=0.001, seed=7, progress=False)
    (entry,) = (cache_dir / "settled").glob("*.npz")
    entry.write_bytes(b"not an npz")
    again = driver.run_dem(tiny_cfg, duration=0.001, seed=7, progress=False)
    assert not again.summary["settle_cached"]
    assert driver.run_dem(tiny_cfg, duration=0.001, seed=7,
                          progress=False).summary["settle_cached"]


def test_no_cache_writes_nothing(tiny_cfg, cache_dir, monkeypatch):
    monkeypatch.setenv(cache.ENV_OFF, "1")
    result = driver.run_dem(tiny_cfg, duration=0.001, seed=8, progress=False)
    assert not result.summary["settle_cached"]
    assert not cache_dir.exists()
