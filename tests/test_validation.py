"""Checks at the boundary (sgn_jax.pipelines.validation) and a DEM run that refuses to lie
(DEMRunError)."""

from __future__ import annotations

import warnings
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sgn_jax.cli import main
from sgn_jax.config import ConfigError, builtin_config_path, load_config, replace_section
from sgn_jax.errors import EnvelopeWarning, SGNJaxError
from sgn_jax.pipelines import dem_run as driver
from sgn_jax.pipelines.validation import (
    charge_dt_dem_max,
    check_dem_config,
    check_duration,
    envelope_notes,
    max_resolved_impact_speed,
    model_envelope,
    motion_peaks,
)


@pytest.fixture(scope="module")
def std():
    return load_config(builtin_config_path("emax_300rpm"))


def test_every_package_error_has_one_base():
    from sgn_jax.dem.engine import DEMError
    from sgn_jax.design import DesignError
    from sgn_jax.records.checkpoint import CheckpointError
    from sgn_jax.records.trajectory import DatasetError
    from sgn_jax.surrogate.rollout import RolloutError

    for cls in (ConfigError, CheckpointError, DatasetError, DEMError, DesignError, RolloutError,
                driver.DEMRunError):
        assert issubclass(cls, SGNJaxError), cls


def test_durations_are_checked(std):
    assert check_duration(1.5, dt=1e-4) == 1.5
    for bad in (0, -1, float("nan"), float("inf")):
        with pytest.raises(ConfigError, match="> 0"):
            check_duration(bad)
    with pytest.raises(ConfigError, match="shorter than one sample"):
        check_duration(1e-5, dt=1e-4)
    with pytest.raises(SGNJaxError, match="duration = 0"):
        driver.run_dem(std, duration=0.0, progress=False)


def test_standard_case_passes_and_its_peaks_are_the_circle(std):
    assert check_dem_config(std) == []
    peaks = motion_peaks(std.motion)
    omega = 2 * np.pi * 300 / 60
    assert peaks.speed == pytest.approx(0.017 * omega, rel=1e-6)
    assert peaks.acceleration == pytest.approx(0.017 * omega**2, rel=1e-6)


@pytest.mark.parametrize("section,key,value,match", [
    ("motion", "rpm", 1e7, "rpm <= 27"),
    ("balls", "count", 500, "count <= 90"),
])
def test_impossible_configs_are_refused_with_the_allowed_range(std, section, key, value, match):
    cfg = replace_section(std, section, **{key: value})
    with pytest.raises(ConfigError, match=match):
        check_dem_config(cfg)


def test_a_negative_rpm_is_a_config_error(std):
    with pytest.raises(ConfigError, match="rpm must be a finite number > 0, got -300"):
        replace_section(std, "motion", rpm=-300.0)


def test_fast_but_possible_motion_warns(std):
    cfg = replace_section(std, "motion", rpm=2400.0)
    with pytest.warns(EnvelopeWarning, match="validated range"):
        notes = check_dem_config(cfg)
    assert len(notes) == 1


def test_the_resolution_limit_follows_the_dem_step(std):
    coarse = replace_section(std, "dem", dt_dem_max=1e-5)
    v_fine, _ = max_resolved_impact_speed(std)
    v_coarse, rule = max_resolved_impact_speed(coarse)
    assert v_coarse < v_fine and "DEM steps" in rule


@pytest.mark.parametrize("args,needle", [
    (["--duration", "0"], "duration = 0.0 s"),
    (["--duration", "-1"], "duration = -1.0 s"),
])
def test_cli_dem_refuses_bad_durations(tmp_path, capsys, args, needle):
    code = main(["dem", "--config", str(builtin_config_path("emax_300rpm")), *args,
                 "--out", str(tmp_path / "x.npz")])
    assert code == 2
    assert needle in capsys.readouterr().err


def test_cli_jar_refuses_a_negative_rpm(tmp_path, capsys):
    text = builtin_config_path("emax_300rpm").read_text().replace("rpm = 300.0", "rpm = -300.0")
    path = tmp_path / "neg.toml"
    path.write_text(text)
    assert main(["jar", "--config", str(path), "--out", str(tmp_path / "j.stl")]) == 2
    assert "rpm must be a finite number > 0, got -300" in capsys.readouterr().err


# --------------------------------------------------------------------------------------------
# The DEM stops on invalid states


def _samples(n_samples=4, n_balls=3):
    pos = np.zeros((n_samples, n_balls, 3))
    pos[:, :, 1] = 0.01                      # on the jar's axis, 10 mm above the floor
    pos[:, :, 0] = [-0.012, 0.0, 0.012][:n_balls]
    return {"pos": pos, "vel": np.zeros_like(pos), "offset": np.zeros((n_samples, 3)),
            "offset_vel": np.zeros((n_samples, 3))}


@pytest.fixture(scope="module")
def setup3(std):
    cfg = replace_section(std, "balls", count=3)
    setup = driver.setup_from_config(cfg)
    jar = setup.jar
    sdf = jax.jit(jax.vmap(jax.vmap(lambda x: jar.sdf_fn(jar.geometry, x))))
    return setup, sdf


def test_check_samples_names_sample_ball_and_cause(setup3):
    setup, sdf = setup3
    assert driver.check_samples(setup, _samples(), sdf) is None
    s = _samples()
    s["pos"][2, 1] = [0.0, 0.06, 0.0]        # above the lid (height 47 mm)
    assert driver.check_samples(setup, s, sdf)[:3] == (2, 1, "outside")
    s = _samples()
    s["vel"][1, 2, 0] = np.nan
    assert driver.check_samples(setup, s, sdf)[:3] == (1, 2, "non-finite")
    s = _samples()
    s["vel"][3, 0, 0] = 1e6                  # t_c(1e6 m/s) is a few DEM steps
    index, ball, cause, detail = driver.check_samples(setup, s, sdf)
    assert (index, ball, cause) == (3, 0, "unresolved-contact")
    assert "need >= 20" in detail
    s["vel"][3, 0, 0] = 5.0                  # a fast but resolved impact
    assert driver.check_samples(setup, s, sdf) is None


@pytest.mark.slow
def test_a_run_with_an_unresolved_contact_stops_with_the_time_and_keeps_the_valid_part(
        std, tmp_path):
    cfg = replace_section(std, "balls", count=4)
    # A DEM step of 25 us resolves Hertz contacts only below about 0.02 m/s. As a config's
    # bound it is lowered to the charge's step; chosen on purpose (dt_dem=) it is refused;
    # with the check switched off the run starts and must stop by itself as soon as the
    # falling balls exceed that speed (while settling).
    cfg = replace_section(cfg, "dem", dt_dem_max=2.5e-5, settle_time=0.01, chunk_samples=20)
    assert driver.setup_from_config(cfg).dt_dem <= charge_dt_dem_max(cfg)
    with pytest.raises(ConfigError):
        driver.run_dem(cfg, duration=0.2, dt_dem=2.5e-5, progress=False)   # before any work
    out = tmp_path / "run.npz"
    with pytest.raises(driver.DEMRunError) as info:
        driver.run_dem(cfg, duration=0.2, dt_dem=2.5e-5, out_path=out, progress=False,
                       check=False)
    err = info.value
    assert err.cause == "unresolved-contact"
    assert f"ball {err.ball}" in str(err) and "need >= 20" in str(err)
    assert not out.exists()
    if err.valid is not None:
        t = err.valid.arrays["t"]
        assert t[-1] < err.time_s + 1e-12
        assert np.all(np.isfinite(err.valid.arrays["pos"]))


def test_envelope_of_a_single_motion_model(std):
    env = model_envelope(std)
    assert envelope_notes(std, env) == []
    fast = replace_section(std, "motion", rpm=400.0)
    notes = envelope_notes(fast, env)
    assert any("rpm = 400" in n for n in notes)
    motion1 = load_config(builtin_config_path("motion1"))
    assert any("harmonic" in n for n in envelope_notes(motion1, env))
    stated = model_envelope(std, {"envelope": {"circle_rpm": [150, 500],
                                               "circle_amplitude": [0.01, 0.02],
                                               "harmonic_base_hz": [3, 8],
                                               "harmonic_max_axis_amplitude": 0.026}})
    assert envelope_notes(fast, stated) == []
    assert envelope_notes(motion1, stated) == []
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert envelope_notes(replace_section(std, "motion", rpm=600.0), stated)
    # A model trained over the shipped envelope states it whole: its per-harmonic limits hold
    # too (a 24 mm first harmonic is within the 26 mm sum but above the 20 mm limit).
    from sgn_jax.records.envelope import load_envelope

    full = model_envelope(std, {"envelope": load_envelope().to_meta()})
    assert full.motion == load_envelope()
    assert envelope_notes(motion1, full) == [] and envelope_notes(fast, full) == []
    wide = replace_section(std, "motion", kind="harmonic", base_frequency_hz=5.0,
                           x_sin=(0.024, 0.0))
    assert envelope_notes(wide, stated) == []
    assert any("first-harmonic amplitude" in n for n in envelope_notes(wide, full))


def test_sdf_is_negative_inside_for_the_fixture(setup3):
    setup, sdf = setup3
    phi = np.asarray(sdf(jnp.asarray(_samples()["pos"])))
    assert np.all(phi < -0.005)


def test_a_charge_the_model_was_not_trained_on_is_named(std):
    env = model_envelope(std, {"envelope": {"circle_rpm": [150, 500],
                                            "circle_amplitude": [0.01, 0.02]}})
    assert envelope_notes(std, env) == []
    small = replace_section(std, "balls", count=60, radius=0.003)
    notes = envelope_notes(small, env)
    assert any("[balls] radius (m) = 0.003" in n for n in notes), notes
    assert any("[balls] count = 60" in n for n in notes), notes
    light = replace_section(std, "material", restitution=0.7)
    assert any("[material] restitution = 0.7" in n for n in envelope_notes(light, env))
    anything = model_envelope(std, {"envelope": {"circle_rpm": [150, 500],
                                                 "circle_amplitude": [0.01, 0.02],
                                                 "any_charge": True}})
    assert envelope_notes(small, anything) == []


def _charge_model(std):
    """A contact_charge model config and the meta of a checkpoint that states the recipe's
    envelope (the shipped motion envelope and the shipped charge envelope), built by hand."""
    from sgn_jax.records.charge_envelope import charge_model_envelope, load_charge_envelope
    from sgn_jax.records.envelope import load_envelope

    meta = {"envelope": charge_model_envelope(load_envelope(), load_charge_envelope())}
    return replace_section(std, "model", kind="contact_charge"), meta


def test_a_charge_model_warns_naming_a_charge_parameter_outside_its_envelope(std):
    from sgn_jax.pipelines.validation import warn_outside_envelope
    from sgn_jax.records.charge_envelope import load_charge_envelope
    from sgn_jax.records.envelope import load_envelope

    model_cfg, meta = _charge_model(std)
    small = replace_section(std, "balls", count=373, radius=0.002)  # 4 mm balls, 10 % of the jar
    expected = "ball class 0 diameter (m) = 0.004 is outside the charge envelope [0.006, 0.015]"
    with pytest.warns(EnvelopeWarning) as caught:
        notes = warn_outside_envelope(small, model_cfg, meta)
    assert notes[:-1] == [expected], notes          # the last note names the envelope's source
    assert str(caught[0].message) == f"outside the surrogate's envelope: {expected}"
    # a checkpoint trained before the charge model stated its envelope covers the recipe's
    derived = model_envelope(model_cfg, {})
    assert derived.charges == load_charge_envelope() and derived.motion == load_envelope()
    assert envelope_notes(small, derived)[0] == expected


def test_a_charge_model_covers_its_charges_on_the_motion_envelope_and_its_circles(std):
    from sgn_jax.geometry import jar_volume
    from sgn_jax.pipelines.configure import jar_params_from_config
    from sgn_jax.records.charge_envelope import (
        ball_volume,
        charge_model_envelope,
        load_charge_envelope,
    )

    model_cfg, meta = _charge_model(std)
    env = model_envelope(model_cfg, meta)
    volume = float(jar_volume(jar_params_from_config(std.jar)))
    count = round(0.10 * volume / ball_volume(0.008))          # 8 mm balls, 10 % of the jar
    eight = replace_section(std, "balls", count=count, radius=0.004)
    at = lambda cfg, rpm: replace_section(cfg, "motion", rpm=rpm)  # noqa: E731
    motion1 = load_config(builtin_config_path("motion1"))
    assert envelope_notes(at(eight, 400.0), env) == []
    assert envelope_notes(at(eight, 574.0), env) == []        # a charge circle, past 500 rpm
    assert envelope_notes(motion1, env) == []                   # the motion envelope
    fast = envelope_notes(at(eight, 650.0), env)                # outside both: both ranges
    assert any("rpm = 650" in n and "[150, 500]" in n for n in fast), fast
    assert any("rpm = 650" in n and "charge envelope's circles [200, 600]" in n for n in fast)
    circles = model_envelope(model_cfg, {"envelope": charge_model_envelope(
        None, load_charge_envelope())})                         # trained on the circles only
    assert envelope_notes(at(eight, 574.0), circles) == []
    assert envelope_notes(motion1, circles)[0].startswith("[motion] kind = 'harmonic': the "
                                                          "charge envelope's motions are circles")
    # the contact kind over the motion envelope: no charge circles, its one training charge
    from sgn_jax.records.envelope import load_envelope

    contact = model_envelope(std, {"envelope": load_envelope().to_meta()})
    assert contact.charges is None
    assert any("rpm = 574" in n for n in envelope_notes(at(std, 574.0), contact))
    assert any("differs from the model's charge" in n for n in envelope_notes(eight, contact))


def test_a_charge_training_states_the_circles_and_the_motion_envelope_it_saw(std):
    from sgn_jax.pipelines.contact_charge_train_run import stated_envelope
    from sgn_jax.records.envelope import load_envelope

    model_cfg, _ = _charge_model(std)
    heldout = load_config(Path(__file__).parents[1] / "experiments" / "charges" / "configs"
                          / "heldout_05.toml")                       # 574 rpm, 17 mm
    circles = stated_envelope(model_cfg, [heldout])
    assert set(circles) == {"charge"} and circles["charge"]["rpm"] == [200.0, 600.0]
    both = stated_envelope(model_cfg, [heldout, load_config(builtin_config_path("motion1"))])
    assert both == {**load_envelope().to_meta(), "charge": circles["charge"]}
