"""DEM driver and CLI: dataset writing, checkpoints and resume, dt_dem override, errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

import sgn_jax  # noqa: F401
from sgn_jax.cli import main
from sgn_jax.config import builtin_config_path, load_config, replace_section, save_config
from sgn_jax.dem.engine import DEMError
from sgn_jax.pipelines import dem_run as driver
from sgn_jax.records.trajectory import load_trajectory

DURATION = 0.003  # s of motion: 30 samples


@pytest.fixture(scope="module")
def tiny_cfg():
    """Six balls, 2 ms of settling, chunks of 10 samples (one compile per run)."""
    cfg = load_config(builtin_config_path("emax_300rpm"))
    cfg = replace_section(cfg, "balls", count=6)
    return replace_section(cfg, "dem", settle_time=0.002, chunk_samples=10, duration=DURATION)


@pytest.mark.slow
def test_run_dem_writes_a_valid_dataset(tiny_cfg, tmp_path):
    out = tmp_path / "traj.npz"
    result = driver.run_dem(tiny_cfg, out_path=out, seed=3, progress=False)
    load_trajectory(out)  # validates names, shapes, dtypes, finiteness
    n_samples = round(DURATION / 1e-4) + 1
    data = np.load(out)
    assert data["pos"].shape == (n_samples, 6, 3)
    np.testing.assert_allclose(data["t"], np.arange(n_samples) * 1e-4)
    assert data["diss_pp_normal"][0] == 0 and data["work_wall"][0] == 0
    meta = json.loads(str(data["meta"]))
    assert meta["seed"] == 3 and meta["substeps"] == 106
    assert meta["dt_dem"] == pytest.approx(1e-4 / 106)
    assert not driver.partial_dir(out).exists()
    s = result.summary
    assert s["balls_outside"] == 0 and s["max_phi_m"] < 0
    assert s["dem_steps"] == (20 + n_samples - 1) * 106
    # The ledger closes: the balls are still falling, and the residual is the integrator's
    # O(m g v dt) error, far below the energy that changed hands.
    total_energy_change = abs(data["pe_grav"][-1] - data["pe_grav"][0])
    assert total_energy_change > 1e-6
    assert abs(s["ledger_residual_J"]) < 1e-3 * total_energy_change


@pytest.mark.slow
def test_interrupted_run_resumes_from_its_last_chunk(tiny_cfg, tmp_path, monkeypatch):
    reference = driver.run_dem(tiny_cfg, out_path=tmp_path / "ref.npz", seed=1, progress=False)

    out = tmp_path / "resumed.npz"
    real_save = driver._save_npz
    calls = {"n": 0}

    def failing_save(path, arrays):
        calls["n"] += 1
        if calls["n"] == 5:  # settle chunk + state, first motion chunk + state, then stop
            raise KeyboardInterrupt
        real_save(path, arrays)

    monkeypatch.setattr(driver, "_save_npz", failing_save)
    with pytest.raises(KeyboardInterrupt):
        driver.run_dem(tiny_cfg, out_path=out, seed=1, progress=False)
    assert (driver.partial_dir(out) / "state.npz").is_file()
    assert not out.exists()
    monkeypatch.setattr(driver, "_save_npz", real_save)

    resumed = driver.run_dem(tiny_cfg, out_path=out, seed=1, progress=False)
    # Only the remaining chunks were simulated: no settling, no first chunk.
    assert resumed.summary["dem_steps"] == (30 - 10) * 106
    for name in ("pos", "vel", "omega", "diss_pw_normal", "e_elastic", "pp_pairs"):
        np.testing.assert_array_equal(resumed.arrays[name], reference.arrays[name])
    assert not driver.partial_dir(out).exists()

    # A checkpoint of another seed is not reused.
    with pytest.raises(KeyboardInterrupt):
        monkeypatch.setattr(driver, "_save_npz", failing_save)
        calls["n"] = 0
        driver.run_dem(tiny_cfg, out_path=out.with_name("other.npz"), seed=1, progress=False)
    monkeypatch.setattr(driver, "_save_npz", real_save)
    other = driver.run_dem(tiny_cfg, out_path=out.with_name("other.npz"), seed=2, progress=False)
    assert other.summary["dem_steps"] == (20 + 30) * 106


# The slow tier (`pytest -m slow`; the default run's time): two more DEM runs (dt override, float32).
@pytest.mark.slow
def test_dt_dem_override_and_float32(tiny_cfg):
    result = driver.run_dem(tiny_cfg, duration=0.001, dt_dem=4.75e-7, progress=False)
    assert result.meta["substeps"] == 211  # smallest k with 1e-4 / k <= 4.75e-7
    assert result.meta["dt_dem"] == pytest.approx(1e-4 / 211)
    single = driver.run_dem(tiny_cfg, duration=0.001, dtype="float32", progress=False)
    assert single.arrays["pos"].dtype == np.float64  # stored in float64 whatever the DEM ran in
    assert single.summary["dtype"] == "float32"
    np.testing.assert_allclose(single.arrays["pos"], result.arrays["pos"], atol=1e-5)


@pytest.mark.slow
def test_pp_capacity_overflow_is_an_error(tiny_cfg):
    cfg = replace_section(tiny_cfg, "dem", pp_capacity=1, settle_time=0.0)
    cfg = replace_section(cfg, "balls", count=40)
    # Forty balls dropped into the jar touch each other within 0.05 s.
    with pytest.raises(DEMError, match="pp_capacity"):
        driver.run_dem(cfg, duration=0.05, progress=False)


def test_cli_dem_prints_a_json_summary(tiny_cfg, tmp_path, capsys):
    config_path = tmp_path / "tiny.toml"
    save_config(tiny_cfg, config_path)
    out = tmp_path / "cli.npz"
    code = main(["dem", "--config", str(config_path), "--duration", "0.001", "--out", str(out),
                 "--seed", "4", "--no-progress"])
    assert code == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    for key in ("wall_time_s", "steps_per_s", "dissipation_J", "ledger_residual_J",
                "balls_outside", "compile_time_s"):
        assert key in summary
    assert summary["seed"] == 4 and out.is_file()
    # A bad output name is the user's error: one line, exit code 2.
    code = main(["dem", "--config", str(config_path), "--duration", "0.001",
                 "--out", str(tmp_path / "x.txt"), "--no-progress"])
    assert code == 2
    assert ".npz" in capsys.readouterr().err
