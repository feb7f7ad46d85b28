"""Tests of sgn_jax.analysis.metrics (docs/conventions.md sections 6 and 7) and the `sgn-jax
evaluate` CLI, on synthetic data with known answers: a perfect prediction, a 1 mm shift, dissipation
scaled by 1.1, offset starts, references that cover only part of the rollout, and small
ensembles."""

import json
import math
import warnings

import numpy as np
import pytest

from sgn_jax import cli, pairs
from sgn_jax.analysis import metrics
from sgn_jax.analysis.metrics import (
    AGITATED_SPEED_M_S,
    CoverageWarning,
    MetricsError,
    align,
    classify_state,
    compare,
    default_threshold,
    ensemble_summary,
    evaluate,
    jar_frame_speed,
    kinetic_energy_fd,
    mse_plateau,
    pairs_within,
    pearson_r,
    position_mse,
    pp_contact_counts,
    relative_error,
)
from sgn_jax.config import builtin_config_path, load_config, replace_section
from sgn_jax.records.prediction import (
    PredictionError,
    load_prediction,
    prediction_from_trajectory,
    save_prediction,
)
from sgn_jax.records.trajectory import build_meta, load_trajectory, save_trajectory

N_BALLS, N_SAMPLES, DT = 4, 301, 1e-4
RADIUS = 0.005
# Jar-frame ball centres: balls 0-1 are 11 mm apart (1 mm gap: inside the 1.5 mm edge skin),
# balls 2-3 12 mm apart (2 mm gap: outside); every other pair is farther. The balls translate
# rigidly, so exactly one pair is within the skin at every sample.
BASE = np.array([[-0.0155, 0.005, 0.0], [-0.0045, 0.005, 0.0],
                 [0.006, 0.005, 0.010], [0.018, 0.005, 0.010]])
DISS = [f"diss_{w}_{k}" for w in ("pp", "pw") for k in ("normal", "tangential", "slip", "rolling")]


def make_reference(path, n_samples=N_SAMPLES):
    """A valid docs/conventions.md section 4 trajectory: balls moving rigidly with the circular jar
    motion plus a vertical bounce; DEM contact (0, 1) listed at even samples only; smooth
    dissipation."""
    t = np.arange(n_samples) * DT
    omega = 2 * np.pi * 5.0
    offset = np.stack([0.017 * np.sin(omega * t), 0 * t, 0.017 * np.cos(omega * t)], axis=1)
    bounce = np.stack([0 * t, 0.002 * np.sin(2 * np.pi * 40 * t), 0 * t], axis=1)
    pos = BASE[None] + (offset + bounce)[:, None, :]
    vel = np.gradient(pos, DT, axis=0)
    pp_pairs = np.full((n_samples, 2, 2), -1, dtype=np.int32)
    pp_pairs[::2, 0] = [0, 1]
    arrays = {
        "t": t, "pos": pos, "vel": vel, "omega": np.zeros_like(pos),
        "offset": offset, "offset_vel": np.gradient(offset, DT, axis=0),
        "ke_trans": 0.5 * 4e-3 * np.sum(vel**2, axis=(1, 2)), "ke_rot": 0 * t,
        "pe_grav": 4e-3 * 9.81 * pos[..., 1].sum(axis=1), "e_elastic": 0 * t,
        "work_wall": 0 * t, "pp_pairs": pp_pairs,
        "pw_contact": np.ones((n_samples, N_BALLS), dtype=bool),
    }
    for i, name in enumerate(DISS):
        values = 1e-5 * (1 + i) * (1.5 + np.sin(2 * np.pi * 30 * t + i))
        values[0] = 0.0
        arrays[name] = values
    cfg = replace_section(load_config(builtin_config_path("emax_300rpm")), "balls", count=N_BALLS)
    save_trajectory(path, arrays, build_meta(cfg, seed=3))
    return load_trajectory(path)


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    return make_reference(tmp_path_factory.mktemp("ref") / "ref.npz")


def make_prediction(tmp_path, reference, name="pred.npz", start=50, n_steps=200, save_every=10,
                    shift=0.0, energy_scale=1.0, **overrides):
    arrays, meta = prediction_from_trajectory(reference, start, n_steps, save_every=save_every)
    arrays["pos"] = arrays["pos"] + np.array([shift, 0.0, 0.0])
    arrays["dE"] = arrays["dE"] * energy_scale
    arrays["energy_cum"] = np.cumsum(arrays["dE"])
    arrays.update(overrides)
    path = tmp_path / name
    save_prediction(path, arrays, meta)
    return load_prediction(path)


# ---------------------------------------------------------------------------------------------
# Known answers


def test_perfect_prediction_gives_zero_error(tmp_path, reference):
    pred = make_prediction(tmp_path, reference)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # full coverage: no warning expected
        comparison = compare(pred, reference)
    s = comparison.summary
    assert s["overlap"]["complete"] and s["overlap"]["n_steps_compared"] == 200
    assert np.all(comparison.mse == 0.0)
    assert s["position"]["mse_plateau_m2"] == 0.0
    assert s["energy"]["baseline"] == "rollout start"
    assert s["energy"]["relative_error_final"] == pytest.approx(0.0, abs=1e-13)
    assert np.nanmax(comparison.energy_rel_error) < 1e-12
    assert s["energy"]["pearson_r"] == pytest.approx(1.0, abs=1e-12)
    expected_energy = reference.dissipation()[51:251].sum()
    assert s["energy"]["E_ref_final_J"] == pytest.approx(expected_energy, rel=1e-12)
    assert s["offset_max_abs_diff_m"] == 0.0
    assert s["spec_checks"] == {"no_balls_outside": True, "no_edge_overflow": True,
                                "reference_covers_prediction": True}
    regime = s["regime"]
    # one pair within the skin at every sample, for both the surrogate's edges and the DEM
    assert regime["pp_contacts_pred_mean"] == 1.0
    assert regime["pp_pairs_within_skin_ref_mean"] == 1.0
    assert regime["pp_pairs_within_skin_pred_frames_mean"] == 1.0
    # DEM contact list: (0, 1) at even samples; compared samples 51..250 hold 100 even ones
    assert regime["pp_contacts_ref_dem_mean"] == pytest.approx(0.5)
    assert regime["power_pred_W"] == pytest.approx(expected_energy / (200 * DT), rel=1e-12)
    assert regime["power_ref_W"] == pytest.approx(regime["power_pred_W"], rel=1e-12)
    assert regime["ke_fd_pred_mean_J"] == pytest.approx(regime["ke_fd_ref_mean_J"], rel=1e-12)
    assert regime["ke_fd_interval_s"] == pytest.approx(10 * DT)
    assert regime["state_pred"] == regime["state_ref"] == "agitated"  # 0.25 pairs per ball
    json.dumps(s, allow_nan=False)  # JSON-able, no NaN


def test_constant_1mm_shift_gives_mse_1e_6(tmp_path, reference):
    pred = make_prediction(tmp_path, reference, shift=1e-3)
    comparison = compare(pred, reference)
    np.testing.assert_allclose(comparison.mse, 1e-6, rtol=1e-9)
    assert comparison.summary["position"]["mse_plateau_m2"] == pytest.approx(1e-6, rel=1e-9)
    # energy untouched by the shift
    assert comparison.summary["energy"]["relative_error_final"] == pytest.approx(0.0, abs=1e-13)


def test_energy_scaled_by_1_1_gives_10_percent(tmp_path, reference):
    pred = make_prediction(tmp_path, reference, energy_scale=1.1)
    comparison = compare(pred, reference)
    s = comparison.summary
    assert s["energy"]["relative_error_final"] == pytest.approx(0.1, rel=1e-10)
    rel = comparison.energy_rel_error
    np.testing.assert_allclose(rel[np.isfinite(rel)], 0.1, rtol=1e-10)
    assert np.isfinite(rel).sum() == 200
    assert s["energy"]["relative_error_median_last_half"] == pytest.approx(0.1, rel=1e-10)
    # Pearson r is blind to a uniform scale (paper section 3)
    assert s["energy"]["pearson_r"] == pytest.approx(1.0, abs=1e-12)
    assert s["regime"]["power_pred_W"] == pytest.approx(1.1 * s["regime"]["power_ref_W"])


def test_small_functions_known_answers():
    a = np.array([1.0, 2.0, 4.0, 8.0])
    assert pearson_r(a, 3 * a + 2) == pytest.approx(1.0)
    assert pearson_r(a, -a) == pytest.approx(-1.0)
    b = np.array([2.0, 1.0, 5.0, 3.0])
    assert pearson_r(a, b) == pytest.approx(np.corrcoef(a, b)[0, 1], rel=1e-12)
    assert math.isnan(pearson_r(a, np.ones(4)))
    assert math.isnan(pearson_r(a[:1], b[:1]))
    rel = relative_error(np.array([1.0, 2.0, 3.0]), np.array([0.0, 1.0, 4.0]))
    assert math.isnan(rel[0]) and rel[1] == 1.0 and rel[2] == 0.25
    assert mse_plateau(np.array([9.0, 9.0, 1.0, 2.0, 3.0])) == 2.0
    assert math.isnan(mse_plateau(np.array([])))
    ref = np.zeros((2, 3, 3))
    pred = ref.copy()
    pred[1, 0] = [3.0, 0.0, 4.0]  # |d|^2 = 25 for one of 3 balls
    np.testing.assert_allclose(position_mse(pred, ref), [0.0, 25.0 / 3.0])
    with pytest.raises(MetricsError, match="same shape"):
        position_mse(pred, ref[:, :2])
    pairs = np.array([[[0, 1], [2, 3], [-1, -1]], [[-1, -1], [-1, -1], [-1, -1]]])
    np.testing.assert_array_equal(pp_contact_counts(pairs), [2, 0])


def test_pairs_within_across_chunks(monkeypatch):
    pos = np.broadcast_to(BASE, (7, 4, 3)).copy()
    pos[3:, 3] = pos[3:, 2] + [0.0114, 0.0, 0.0]  # 0.4 mm gap: now within the skin too
    monkeypatch.setattr(pairs, "_PAIR_CHUNK", 2)  # pairs_within lives in sgn_jax.pairs
    np.testing.assert_array_equal(pairs_within(pos, 2 * RADIUS + 1.5e-3), [1, 1, 1, 2, 2, 2, 2])
    np.testing.assert_array_equal(pairs_within(pos, 0.0105), 0)


def test_kinetic_energy_fd_uniform_velocity():
    t = np.array([0.0, 0.1, 0.3])
    v = np.array([1.0, -2.0, 2.0])  # |v|^2 = 9
    pos = t[:, None, None] * v[None, None, :] * np.ones((1, 5, 1))
    t_mid, ke = kinetic_energy_fd(t, pos, ball_mass=2.0)
    np.testing.assert_allclose(t_mid, [0.05, 0.2])
    np.testing.assert_allclose(ke, 0.5 * 2.0 * 5 * 9.0)


def test_jar_frame_speed_known_answer():
    t = np.array([0.0, 0.1, 0.3])
    offset = np.stack([np.sin(t), np.zeros(3), t**2], axis=1)  # any jar motion
    v = np.array([0.0, 3.0, 4.0])  # |v| = 5 m/s relative to the jar
    rel = t[:, None, None] * v * np.ones((1, 4, 1))
    pos = rel + offset[:, None, :]
    np.testing.assert_allclose(jar_frame_speed(t, pos, offset), [5.0, 5.0])
    # balls carried with the jar: zero speed in its frame, whatever the lab speed
    carried = np.ones((3, 4, 3)) * 0.01 + offset[:, None, :]
    np.testing.assert_allclose(jar_frame_speed(t, carried, offset), [0.0, 0.0], atol=1e-12)
    assert jar_frame_speed(t[:1], pos[:1], offset[:1]).shape == (0,)


def test_deepest_pair_overlap_known_answer():
    from sgn_jax.analysis.metrics import deepest_pair_overlap

    pos = np.zeros((3, 3, 3))
    pos[:, 2] = [0.1, 0.0, 0.0]  # a third ball far away
    pos[0, 1] = [0.0095, 0.0, 0.0]  # 9.5 mm apart: 0.5 mm overlap for R = 5 mm
    pos[1, 1] = [0.0, 0.012, 0.0]  # 12 mm apart: a 2 mm gap
    pos[2, 1] = [0.0, 0.0, 0.0]  # coincident: overlap 2 R
    np.testing.assert_allclose(deepest_pair_overlap(pos, RADIUS), [5e-4, -2e-3, 1e-2],
                               atol=1e-15)
    # the deepest pair wins, whichever pair it is
    pos[0, 2] = [0.0095 + 0.009, 0.0, 0.0]  # 1 mm overlap with ball 1
    assert deepest_pair_overlap(pos[:1], RADIUS)[0] == pytest.approx(1e-3, abs=1e-15)
    assert np.isnan(deepest_pair_overlap(pos[:, :1], RADIUS)).all()
    with pytest.raises(MetricsError, match=r"\(T, N, 3\)"):
        deepest_pair_overlap(pos[0], RADIUS)


GOOD_MOTION = {"jar_speed_dem_m_s": 0.27, "jar_speed_sgn_m_s": 0.30, "snapped_ball_steps": 10,
               "ball_steps": 240_000, "overlap_dem_m": 62e-6, "overlap_sgn_m": 80e-6,
               "mse_plateau_m2": 6e-4}


def test_motion_checks_pass_within_the_dem_range():
    from sgn_jax.analysis.metrics import motion_checks, motion_warning_lines, motion_warnings

    checks = motion_checks(**GOOD_MOTION)
    assert [c["name"] for c in checks] == ["jar_speed", "snapped", "overlap", "mse_plateau"]
    assert all(c["ok"] is True for c in checks)
    assert motion_warnings(checks) == [] and motion_warning_lines([]) == []
    by_name = {c["name"]: c for c in checks}
    assert by_name["jar_speed"]["dem"] == 0.27 and by_name["jar_speed"]["sgn"] == 0.30
    assert by_name["overlap"]["dem"] == pytest.approx(62.0) and by_name["overlap"]["unit"] == "um"
    assert by_name["mse_plateau"]["dem"] == metrics.MSE_FLOOR_SAME_PACKING_M2
    assert by_name["mse_plateau"]["ratio_to_unrelated"] == pytest.approx(6e-4 / 8.2e-4)
    json.dumps(checks, allow_nan=False)
    # exactly at the limits is still in range (the MSE limit is "at or above": out)
    edge = dict(GOOD_MOTION, jar_speed_sgn_m_s=0.27 * 1.2, snapped_ball_steps=2_400,
                overlap_sgn_m=0.5e-3)
    assert motion_warnings(motion_checks(**edge)) == []
    # missing values: not judged, no warning
    missing = motion_checks(jar_speed_dem_m_s=None, jar_speed_sgn_m_s=0.5,
                            snapped_ball_steps=None, ball_steps=None, overlap_dem_m=None,
                            overlap_sgn_m=float("nan"), mse_plateau_m2=None)
    assert [c["ok"] for c in missing] == [None] * 4 and motion_warnings(missing) == []


def test_motion_warnings_fire_one_per_problem():
    """The user's report: 0.50 vs 0.27 m/s, 118,702 of 240,000 ball-steps snapped, balls
    sinking into each other, MSE plateau 1.25e-3 m^2, with the energy within 1 %."""
    from sgn_jax.analysis.metrics import (
        ENERGY_TRUST_WARNING,
        motion_checks,
        motion_warning_lines,
        motion_warnings,
    )

    bad = motion_checks(jar_speed_dem_m_s=0.27, jar_speed_sgn_m_s=0.50,
                        snapped_ball_steps=118_702, ball_steps=240_000, overlap_dem_m=62e-6,
                        overlap_sgn_m=9.99e-3, mse_plateau_m2=1.25e-3)
    assert [c["ok"] for c in bad] == [False] * 4
    messages = motion_warnings(bad)
    assert len(messages) == 4
    assert "0.500 m/s" in messages[0] and "0.270 m/s" in messages[0] and "+85 %" in messages[0]
    assert "118,702 of 240,000 ball-steps (49.5 %)" in messages[1]
    assert "9,990 um" in messages[2] and "62 um" in messages[2]
    assert "1.52x" in messages[3] and "no information beyond the jar's size" in messages[3]
    lines = motion_warning_lines(messages)
    assert len(lines) == 5 and all(line.startswith("WARNING: ") for line in lines)
    assert lines[-1] == f"WARNING: {ENERGY_TRUST_WARNING}"
    assert "energy agreement alone should not be trusted" in lines[-1]
    # each check fires alone; too slow counts like too fast; MSE at the level itself fires
    for change, name in ((dict(jar_speed_sgn_m_s=0.20), "jar_speed"),
                         (dict(snapped_ball_steps=2_401), "snapped"),
                         (dict(overlap_sgn_m=0.51e-3), "overlap"),
                         (dict(mse_plateau_m2=metrics.MSE_FLOOR_UNRELATED_M2), "mse_plateau")):
        checks = motion_checks(**dict(GOOD_MOTION, **change))
        assert [c["name"] for c in checks if c["ok"] is False] == [name]
        assert len(motion_warnings(checks)) == 1


def test_compare_reports_motion_checks(tmp_path, reference):
    pred = make_prediction(tmp_path, reference)
    motion = compare(pred, reference).summary["motion"]
    assert [c["ok"] for c in motion["checks"]] == [True] * 4 and motion["warnings"] == []
    by_name = {c["name"]: c for c in motion["checks"]}
    # no pair of the synthetic charge touches (closest gap 1 mm): deepest overlap 0 for both
    assert by_name["overlap"]["dem"] == 0.0 and by_name["overlap"]["sgn"] == 0.0
    assert by_name["jar_speed"]["sgn"] == pytest.approx(by_name["jar_speed"]["dem"], rel=1e-12)
    assert by_name["snapped"]["ball_steps"] == 200 * N_BALLS

    # balls 0 and 1 of the surrogate on top of each other, every ball snapped every step
    arrays, _ = prediction_from_trajectory(reference, 50, 200, save_every=10)
    pos = arrays["pos"].copy()
    pos[:, 1] = pos[:, 0] + np.array([0.001, 0.0, 0.0])  # 1 mm apart: 9 mm overlap
    bad = make_prediction(tmp_path, reference, name="bad.npz", pos=pos,
                          n_snapped=np.full(200, N_BALLS))
    summary = compare(bad, reference).summary
    failed = [c["name"] for c in summary["motion"]["checks"] if c["ok"] is False]
    assert failed == ["snapped", "overlap"]
    assert {c["name"]: c for c in summary["motion"]["checks"]}["overlap"]["sgn"] == \
        pytest.approx(9000.0)
    assert metrics.headline(summary)["motion_warnings"] == summary["motion"]["warnings"]
    assert len(summary["motion"]["warnings"]) == 2


def test_speed_rule_reads_positions_not_energy(tmp_path, reference):
    """The default state rule gives the same state for predictions that differ in energy only,
    and the same jar-frame speed for the prediction and its perfect reference."""
    preds = [make_prediction(tmp_path, reference, name=f"s{i}.npz", energy_scale=s)
             for i, s in enumerate([1.0, 3.0])]
    summaries = [evaluate(p, reference) for p in preds]
    for summary in summaries:
        regime = summary["regime"]
        assert regime["state_rule"] == "speed"
        assert regime["jar_speed_pred_mean_m_s"] == pytest.approx(
            regime["jar_speed_ref_mean_m_s"], rel=1e-9)
    assert summaries[0]["regime"]["state_pred"] == summaries[1]["regime"]["state_pred"]
    ens = ensemble_summary(summaries)
    assert ens["states"]["classify_by"] == "speed"
    assert ens["states"]["agreement"] == 1.0
    speed = summaries[0]["regime"]["jar_speed_ref_mean_m_s"]
    low = ensemble_summary(summaries, threshold=0.5 * speed)
    high = ensemble_summary(summaries, threshold=2.0 * speed)
    assert low["states"]["ref"]["agitated"]["count"] == 2
    assert high["states"]["ref"]["bed"]["count"] == 2


def test_classify_state():
    assert classify_state(1.0, 0.75, "contacts") == "bed"
    assert classify_state(0.5, 0.75, "contacts") == "agitated"
    # the default rule is the jar-frame ball speed (m/s): agitated when >= threshold
    assert classify_state(0.27, AGITATED_SPEED_M_S) == "agitated"
    assert classify_state(0.12, AGITATED_SPEED_M_S) == "bed"
    assert default_threshold("speed") == AGITATED_SPEED_M_S
    assert default_threshold("contacts") == 0.75
    with pytest.raises(MetricsError, match="explicit threshold"):
        default_threshold("power")
    assert classify_state(0.3, 0.2, "power") == "agitated"
    assert classify_state(0.1, 0.2, "power") == "bed"
    assert classify_state(math.nan, 0.75) == "unknown"
    assert classify_state(math.nan, 0.75, "contacts") == "unknown"
    with pytest.raises(MetricsError, match="classify_by"):
        classify_state(1.0, 0.75, "kinetic")


# ---------------------------------------------------------------------------------------------
# Alignment


def test_alignment_with_offset_start(tmp_path, reference):
    pred = make_prediction(tmp_path, reference, start=37, n_steps=120, save_every=7)
    al = align(pred, reference)
    np.testing.assert_array_equal(al.step_index, np.arange(120))
    np.testing.assert_array_equal(al.step_ref_index, 38 + np.arange(120))
    np.testing.assert_array_equal(al.frame_ref_index, 37 + 7 * np.arange(al.frame_index.size))
    assert al.frame_index.size == 120 // 7 + 1
    assert al.start_ref_index == 37 and al.overlap["complete"]
    assert evaluate(pred, reference)["position"]["mse_max_m2"] == 0.0


def test_reference_starting_late_rebases_energy(tmp_path, reference):
    pred = make_prediction(tmp_path, reference, start=50, n_steps=200)
    late = reference.slice(100, None)  # t from t[100]; the rollout started at t[50]
    with pytest.warns(CoverageWarning, match="covers only part"):
        comparison = compare(pred, late)
    s = comparison.summary
    assert not s["overlap"]["complete"] and not s["overlap"]["reference_covers_start"]
    assert s["overlap"]["n_steps_compared"] == 151  # steps ending at samples 100..250
    assert s["overlap"]["t_first_s"] == pytest.approx(100 * DT)
    assert s["energy"]["baseline"].startswith("first compared step")
    assert s["energy"]["E_ref_final_J"] == pytest.approx(reference.dissipation()[101:251].sum(),
                                                         rel=1e-12)
    assert s["energy"]["relative_error_final"] == pytest.approx(0.0, abs=1e-12)
    assert np.isnan(comparison.energy_ref[:49]).all()
    assert not s["spec_checks"]["reference_covers_prediction"]


def test_reference_ending_early_compares_overlap(tmp_path, reference):
    pred = make_prediction(tmp_path, reference, start=50, n_steps=200, energy_scale=1.1)
    short = reference.slice(0, 150)
    with pytest.warns(CoverageWarning, match=r"comparing 99/200 steps"):
        comparison = compare(pred, short)
    s = comparison.summary
    assert s["overlap"]["t_last_s"] == pytest.approx(149 * DT)
    assert s["energy"]["baseline"] == "rollout start"
    assert s["energy"]["relative_error_final"] == pytest.approx(0.1, rel=1e-10)
    assert np.isnan(comparison.energy_ref[99:]).all()
    assert s["position"]["n_frames"] == 10  # frames at samples 50, 60, ..., 140
    assert s["energy"]["E_pred_full_J"] == pytest.approx(1.1 * reference.dissipation()[51:251].sum())


def test_no_overlap_or_wrong_ball_count_is_refused(tmp_path, reference):
    pred = make_prediction(tmp_path, reference, start=50, n_steps=20)
    with pytest.raises(MetricsError, match="no prediction step has a reference sample"):
        align(pred, reference.slice(0, 40))
    other = make_reference(tmp_path / "three.npz")
    arrays = dict(other.arrays)
    arrays["pos"] = arrays["pos"][:, :3]
    for name in ("vel", "omega"):
        arrays[name] = arrays[name][:, :3]
    arrays["pw_contact"] = arrays["pw_contact"][:, :3]
    meta = dict(other.meta, n_balls=3)
    save_trajectory(tmp_path / "three.npz", arrays, meta)
    with pytest.raises(MetricsError, match="4 balls but the reference has 3"):
        align(pred, load_trajectory(tmp_path / "three.npz"))


def test_prediction_from_trajectory_checks_arguments(reference):
    with pytest.raises(PredictionError, match="start_index"):
        prediction_from_trajectory(reference, 290, 20)
    with pytest.raises(PredictionError, match="save_every"):
        prediction_from_trajectory(reference, 0, 20, save_every=0)


# ---------------------------------------------------------------------------------------------
# Ensembles


def test_ensemble_summary_known_spread(tmp_path, reference):
    scales = [1.0, 1.2, 0.9]
    preds = [make_prediction(tmp_path, reference, name=f"p{i}.npz", energy_scale=s)
             for i, s in enumerate(scales)]
    summaries = [evaluate(p, reference) for p in preds]
    power_ref = summaries[0]["regime"]["power_ref_W"]
    ens = ensemble_summary(summaries, classify_by="contacts")
    assert ens["n_runs"] == 3 and not ens["meets_spec_minimum"]
    expected = power_ref * np.array(scales)
    assert ens["power"]["pred_W"]["mean"] == pytest.approx(expected.mean(), rel=1e-12)
    assert ens["power"]["pred_W"]["std"] == pytest.approx(expected.std(ddof=1), rel=1e-10)
    assert ens["power"]["pred_W"]["min"] == pytest.approx(expected.min(), rel=1e-12)
    assert ens["power"]["ref_W"]["std"] == pytest.approx(0.0, abs=1e-12 * power_ref)
    assert ens["power"]["relative_error_of_means"] == pytest.approx(0.1 / 3, rel=1e-10)
    # 1 pair per 4 balls = 0.25 < 0.75: all agitated; a 0.2 threshold makes them all beds
    assert ens["states"]["pred"]["agitated"]["count"] == 3
    assert ens["states"]["ref"]["fraction_agitated"] == 1.0
    bed = ensemble_summary(summaries, classify_by="contacts", threshold=0.2)
    assert bed["states"]["pred"]["bed"]["count"] == 3 and bed["states"]["agreement"] == 1.0
    # by power: the 1.2x run is "agitated" above 1.1 x power_ref, the reference runs are not
    by_power = ensemble_summary(summaries, classify_by="power", threshold=1.1 * power_ref)
    assert [r["state_pred"] for r in by_power["runs"]] == ["bed", "agitated", "bed"]
    assert by_power["states"]["ref"]["bed"]["count"] == 3
    assert by_power["states"]["agreement"] == pytest.approx(2 / 3)
    assert ens["contacts"]["pred_mean"] == 1.0 and ens["contacts"]["ref_dem_mean"] == 0.5
    # the same from predictions and references directly
    direct = ensemble_summary(preds, [reference] * 3)
    assert direct["power"]["pred_W"] == ens["power"]["pred_W"]
    json.dumps(ens, allow_nan=False)


def test_ensemble_summary_refuses_bad_input(reference):
    with pytest.raises(MetricsError, match="at least one run"):
        ensemble_summary([])
    with pytest.raises(MetricsError, match="needs an explicit threshold"):
        ensemble_summary([{"regime": {}}], classify_by="power")
    with pytest.raises(MetricsError, match="not a summary"):
        ensemble_summary([{"energy": 1}])
    with pytest.raises(MetricsError, match="one reference per prediction"):
        ensemble_summary(["a.npz", "b.npz"], [reference])


# ---------------------------------------------------------------------------------------------
# CLI


def test_cli_evaluate_end_to_end(tmp_path, reference, capsys):
    make_prediction(tmp_path, reference, name="pred.npz", shift=1e-3, energy_scale=1.1)
    out = tmp_path / "eval"
    code = cli.main(["evaluate", "--prediction", str(tmp_path / "pred.npz"),
                     "--reference", str(reference.path), "--out", str(out)])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    lines = captured.out.strip().splitlines()
    assert len(lines) == 1
    headline = json.loads(lines[0])
    assert headline["mse_plateau_m2"] == pytest.approx(1e-6, rel=1e-9)
    assert headline["energy_relative_error_final"] == pytest.approx(0.1, rel=1e-10)
    assert headline["balls_outside_total"] == 0 and headline["reference_covers_prediction"]
    saved = json.loads((out / "metrics.json").read_text())
    assert saved["energy"]["pearson_r"] == pytest.approx(1.0, abs=1e-12)
    for name in ("position_mse", "cumulative_energy", "trajectory_xz"):
        png = out / f"{name}.png"
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000


def test_cli_evaluate_prints_motion_warnings(tmp_path, reference, capsys):
    make_prediction(tmp_path, reference, name="good.npz")
    code = cli.main(["evaluate", "--prediction", str(tmp_path / "good.npz"), "--reference",
                     str(reference.path), "--out", str(tmp_path / "good")])
    captured = capsys.readouterr()
    assert code == 0 and "WARNING" not in captured.err
    assert json.loads(captured.out)["motion_warnings"] == []

    make_prediction(tmp_path, reference, name="snapped.npz", n_snapped=np.full(200, N_BALLS))
    code = cli.main(["evaluate", "--prediction", str(tmp_path / "snapped.npz"), "--reference",
                     str(reference.path), "--out", str(tmp_path / "snapped")])
    captured = capsys.readouterr()
    assert code == 0
    lines = [line for line in captured.err.splitlines() if "WARNING:" in line]
    assert len(lines) == 2
    assert "800 of 800 ball-steps (100.0 %) were snapped" in lines[0]
    assert "energy agreement alone should not be trusted" in lines[1]
    assert len(captured.out.strip().splitlines()) == 1  # stdout stays one JSON line
    assert len(json.loads(captured.out)["motion_warnings"]) == 1
    saved = json.loads((tmp_path / "snapped" / "metrics.json").read_text())
    assert saved["motion"]["warnings"] == json.loads(captured.out)["motion_warnings"]


def test_cli_evaluate_ensemble_and_errors(tmp_path, reference, capsys):
    for i, scale in enumerate([1.0, 1.2]):
        make_prediction(tmp_path, reference, name=f"p{i}.npz", energy_scale=scale)
    short = tmp_path / "short.npz"
    sliced = reference.slice(0, 150)
    save_trajectory(short, sliced.arrays, sliced.meta)
    out = tmp_path / "ens"
    code = cli.main(["evaluate", "--prediction", str(tmp_path / "p0.npz"),
                     str(tmp_path / "p1.npz"), "--reference", str(reference.path), str(short),
                     "--out", str(out)])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    assert "covers only part" in captured.err  # the short reference is reported
    headline = json.loads(captured.out)
    assert headline["n_runs"] == 2 and len(headline["runs"]) == 2
    assert (out / "run_00" / "metrics.json").exists() and (out / "run_01" / "cumulative_energy.png").exists()
    ensemble = json.loads((out / "ensemble.json").read_text())
    assert ensemble["runs"][1]["energy_relative_error_final"] == pytest.approx(0.2, rel=1e-10)
    assert (out / "ensemble.png").stat().st_size > 10_000

    code = cli.main(["evaluate", "--prediction", str(tmp_path / "p0.npz"), "--reference",
                     str(reference.path), str(short), "--out", str(out)])
    assert code == 2 and "one reference per prediction" in capsys.readouterr().err
    code = cli.main(["evaluate", "--prediction", str(reference.path), "--reference",
                     str(reference.path), "--out", str(out)])
    assert code == 2 and "is a DEM trajectory file" in capsys.readouterr().err
    code = cli.main(["evaluate", "--prediction", str(tmp_path / "p0.npz"), "--reference",
                     str(reference.path), "--out", str(out), "--classify-by", "power"])
    assert code == 2 and "needs --threshold" in capsys.readouterr().err
