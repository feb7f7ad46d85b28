"""The collision statistics (sgn_jax.analysis.collisions), their ensemble reduction, the
spectra of DEM and surrogate records (sgn_jax.pipelines.spectra) and ``sgn-jax spectra``:
synthetic event tables with answers known by hand, and tiny records written by the real
record writers."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest

from sgn_jax.analysis import collisions as C
from sgn_jax.cli import main
from sgn_jax.config import builtin_config_path, config_to_dict, load_config, replace_section
from sgn_jax.pipelines.spectra import CollisionSpectra, collision_spectra
from sgn_jax.records.prediction import save_prediction
from sgn_jax.records.trajectory import build_meta, save_trajectory

N_BALLS = 4
BALL_MASS = 4.0e-3  # kg


def make_table(rows, *, duration=2.0, n_balls=N_BALLS, source="dem", start=0.0):
    """An event table from rows of (wall, start_s, impact_normal, mass_eff, energy (5,), flags)."""
    n = len(rows)
    wall = np.array([r[0] for r in rows], dtype=bool)
    return C.EventTable(
        ball=np.zeros(n, np.int32), partner=np.ones(n, np.int32), wall=wall,
        start_s=[r[1] for r in rows], duration_s=np.full(n, 1e-4),
        impact_normal=[r[2] for r in rows], impact_tangential=np.full(n, 0.1),
        max_overlap=np.full(n, 1e-6), peak_force=np.full(n, 10.0),
        mass_eff=[r[3] for r in rows], energy=np.array([r[4] for r in rows]).reshape(n, 5),
        flags=[r[5] for r in rows], record_duration_s=duration, record_start_s=start,
        n_balls=n_balls, total_mass_kg=n_balls * BALL_MASS, source=source)


def energy(normal, tangential=0.0, slip=0.0):
    return [normal, tangential, slip, 0.0, 0.0]


# Five events over 2 s with 4 balls: three ball-ball (one already touching at the start), two
# ball-wall.
ROWS = [
    (False, 0.0, 0.05, 2e-3, energy(1e-9), C.FLAG_BEGAN_BEFORE),   # resting contact
    (False, 0.5, 1.0, 2e-3, energy(8e-4, 2e-4), 0),                # hard impact: 1e-3 J
    (False, 1.0, 0.1, 2e-3, energy(5e-6, 0.0, 5e-6), 0),           # 1e-5 J
    (True, 1.2, 0.5, 4e-3, energy(1e-4), 0),                       # exactly 1e-4 J
    (True, 1.9, 0.2, 4e-3, energy(2e-5), C.FLAG_OPEN_AT_END),       # 2e-5 J
]


@pytest.fixture
def table():
    return make_table(ROWS)


# ---------------------------------------------------------------------------------------------
# One statistic each, answers by hand


def test_frequency_counts_new_events_per_ball_per_second(table):
    # new events: 2 ball-ball, 2 ball-wall; 4 balls, 2 s
    assert C.collision_frequency(table, "ball-ball") == pytest.approx(2 / (4 * 2.0))
    assert C.collision_frequency(table, "ball-wall") == pytest.approx(2 / (4 * 2.0))
    assert C.collision_frequency(table) == pytest.approx(4 / 8.0)
    with pytest.raises(ValueError, match="kind='wall'"):
        C.collision_frequency(table, "wall")


def test_power_specific_power_stress_energy_and_split(table):
    total = 1e-9 + 1e-3 + 1e-5 + 1e-4 + 2e-5
    assert C.dissipated_power(table) == pytest.approx(total / 2.0)
    assert C.dissipated_power(table, "ball-wall") == pytest.approx(1.2e-4 / 2.0)
    assert C.specific_power(table) == pytest.approx(total / 2.0 / (4 * BALL_MASS))
    # stress energy 0.5 m* v^2 of the new events only (the resting contact has no impact)
    stress = [0.5 * 2e-3 * 1.0, 0.5 * 2e-3 * 0.01, 0.5 * 4e-3 * 0.25, 0.5 * 4e-3 * 0.04]
    assert C.mean_stress_energy(table) == pytest.approx(np.mean(stress))
    assert C.mean_stress_energy(table, "ball-ball") == pytest.approx(np.mean(stress[:2]))
    split = C.dissipation_split(table)
    assert split["normal"] == pytest.approx((total - 2e-4 - 5e-6) / total)
    assert split["normal"] + split["tangential"] == pytest.approx(1.0)
    assert split["columns"]["slip"] == pytest.approx(5e-6 / total)
    empty = make_table([(False, 0.1, 0.1, 2e-3, energy(0.0), 0)])
    assert math.isnan(C.dissipation_split(empty)["normal"])
    assert math.isnan(C.mean_stress_energy(empty, "ball-wall"))
    receding = make_table([(False, 0.1, -0.3, 2e-3, energy(1e-6), 0)])
    assert C.mean_stress_energy(receding) == 0.0  # not approaching: no impact energy


def test_log_edges_are_decade_aligned_and_exact():
    edges = C.ENERGY_EDGES
    assert edges.size == 37 and edges[0] == 1e-10 and edges[-1] == 1e-1
    assert edges[24] == 1e-4 and edges[4] == 1e-9  # whole decades are the literals
    assert np.allclose(np.diff(np.log10(edges)), 0.25)
    with pytest.raises(ValueError, match="powers of ten"):
        C.log_edges(2e-10, 1e-1)


def test_spectrum_places_each_event_in_its_bin(table):
    spec = C.dissipation_spectrum(table)
    per_s = 1 / 2.0
    # 1e-9 J (bin 4), 1e-5 J (bin 20), 2e-5 J (bin 21: [1.78e-5, 3.16e-5)), 1e-4 J on an edge
    # (bin 24, [1e-4, 1.78e-4)), 1e-3 J (bin 28)
    expected_bins = {4: 1e-9, 20: 1e-5, 21: 2e-5, 24: 1e-4, 28: 1e-3}
    assert set(np.flatnonzero(spec.rate)) == set(expected_bins)
    for b, e in expected_bins.items():
        assert spec.rate[b] == pytest.approx(per_s)
        assert spec.power[b] == pytest.approx(e * per_s)
    assert spec.total_power == pytest.approx(C.dissipated_power(table))
    # outside the bins: nothing dropped
    odd = make_table([(False, 0.1, 0.1, 2e-3, energy(0.0), 0),
                      (False, 0.2, 0.1, 2e-3, energy(0.5), 0)])
    spec = C.dissipation_spectrum(odd)
    assert spec.rate.sum() == 0 and spec.rate_below == pytest.approx(0.5)
    assert spec.rate_above == pytest.approx(0.5) and spec.power_above == pytest.approx(0.25)
    # the stress spectrum bins the stress energy, leaves out the event that began before
    stress = C.stress_spectrum(table)
    assert stress.rate.sum() * 2.0 == pytest.approx(4)
    # the wall impact at 0.5 m/s: 0.5 * 4e-3 * 0.25 = 5e-4 J, bin 26 ([3.16e-4, 5.62e-4));
    # its power is what it dissipated (1e-4 J in 2 s)
    assert stress.rate[26] == pytest.approx(per_s)
    assert stress.power[26] == pytest.approx(1e-4 * per_s)


def test_power_above_threshold(table):
    assert C.power_above(table, 1e-4) == pytest.approx((1e-3 + 1e-4) / 2.0)  # 1e-4 counts
    assert C.power_above(table, 1.01e-4) == pytest.approx(1e-3 / 2.0)
    assert C.power_above(table, 1e-4, kind="ball-wall") == pytest.approx(1e-4 / 2.0)
    # by stress energy: 1e-3 J (ball-ball impact) and 5e-4 J (wall) are >= 1e-4 J
    assert C.power_above(table, 1e-4, by="stress") == pytest.approx((1e-3 + 1e-4) / 2.0)
    assert C.power_above(table, 6e-4, by="stress") == pytest.approx(1e-3 / 2.0)
    thresholds = np.array([0.0, 1e-4, 1e-3, 1.0])
    share = C.power_share_above(table, thresholds)
    total = C.dissipated_power(table) * 2.0
    assert share == pytest.approx([1.0, 1.1e-3 / total, 1e-3 / total, 0.0])
    curve = C.power_share_above(table)
    assert np.all(np.diff(curve) <= 1e-15) and curve[0] == pytest.approx(1.0)
    with pytest.raises(ValueError, match="by='impact'"):
        C.power_above(table, 1e-4, by="impact")


def test_impact_speed_distribution(table):
    dist = C.impact_speed_distribution(table)
    speeds = np.array([1.0, 0.1, 0.5, 0.2])
    assert dist.mean == pytest.approx(speeds.mean())
    assert dist.median == pytest.approx(np.median(speeds))
    assert dist.quantiles[0.9] == pytest.approx(np.quantile(speeds, 0.9))
    assert dist.rate.sum() == pytest.approx(4 / 2.0)
    assert dist.rate[np.searchsorted(C.SPEED_EDGES, 1.0, side="right") - 1] == pytest.approx(0.5)
    walls = C.impact_speed_distribution(table, "ball-wall", component="tangential")
    assert walls.mean == pytest.approx(0.1)


def test_window_keeps_events_that_begin_in_it(table):
    part = table.window(1.0, 2.0)
    assert part.n_events == 3 and part.record_duration_s == pytest.approx(1.0)
    assert C.collision_frequency(part) == pytest.approx(3 / 4.0)
    with pytest.raises(C.CollisionDataError, match="inside the record"):
        table.window(1.0, 3.0)


def test_ensemble_mean_and_standard_error():
    # three packings with 1, 2 and 6 ball-ball events in 1 s, 4 balls
    tables = [make_table([(False, 0.1 * i, 0.5, 2e-3, energy(1e-4), 0) for i in range(n)],
                         duration=1.0) for n in (1, 2, 6)]
    ens = C.ensemble_statistics(tables)
    freqs = np.array([1, 2, 6]) / 4.0
    assert ens.n_records == 3 and ens.n_events == (1, 2, 6)
    assert ens.mean["frequency_per_ball_hz[all]"] == pytest.approx(freqs.mean())
    assert ens.se["frequency_per_ball_hz[all]"] == pytest.approx(freqs.std(ddof=1) / np.sqrt(3))
    # per bin for the spectra
    rates = np.array([1, 2, 6], dtype=float)
    assert ens.mean["dissipation_rate_hz"][24] == pytest.approx(rates.mean())
    assert ens.se["dissipation_rate_hz"][24] == pytest.approx(rates.std(ddof=1) / np.sqrt(3))
    assert ens.se["dissipation_rate_hz"][0] == 0.0
    # no ball-wall events: the mean stress energy is NaN in each, so NaN in the ensemble
    assert math.isnan(ens.mean["mean_stress_energy_J[ball-wall]"])
    # one record: no scatter
    assert math.isnan(C.ensemble_statistics(tables[:1]).se["frequency_per_ball_hz[all]"])
    mean, se = C.mean_and_se([[1.0, np.nan], [3.0, 2.0], [np.nan, np.nan]])
    assert mean == pytest.approx([2.0, 2.0]) and se[0] == pytest.approx(1.0)
    assert math.isnan(se[1])
    with pytest.raises(C.CollisionDataError, match="separately"):
        C.ensemble_statistics([tables[0], make_table(ROWS, source="surrogate")])


def test_decade_comparison_and_the_result_object():
    dem = [make_table([(False, 0.1, 0.5, 2e-3, energy(3e-4), 0),
                       (False, 0.2, 0.1, 2e-3, energy(3e-7), 0)], duration=1.0)
           for _ in range(2)]
    surr = [make_table([(False, 0.1, 0.5, 2e-3, energy(3.3e-4), 0)], duration=1.0,
                       source="surrogate") for _ in range(3)]
    result = collision_spectra(dem=dem, surrogate=surr, threshold=1e-4)
    assert isinstance(result, CollisionSpectra)
    rows = {row["lo_J"]: row for row in result.decades()}
    assert rows[1e-4]["power_relative_difference"] == pytest.approx(0.1)
    assert rows[1e-7]["power_relative_difference"] is None  # under 5 % of the DEM's power
    # identical packings: no scatter, so the difference is known exactly
    assert rows[1e-4]["power_relative_difference_se"] == pytest.approx(0.0, abs=1e-12)
    assert rows[1e-7]["power_relative_difference_se"] is None
    text = result.table()
    assert "collisions per ball per s, all" in text and "surr vs DEM" in text
    out = result.to_json()
    json.dumps(out, allow_nan=False)  # NaN became null
    assert out["dem"]["n_records"] == 2 and out["surrogate"]["n_records"] == 3
    assert out["surrogate"]["mean"]["power_above_W"] == pytest.approx(3.3e-4)
    assert len(out["energy_edges_J"]) == 37


# ---------------------------------------------------------------------------------------------
# Records written by the real writers, the CLI


T_SAMPLES, DT = 11, 0.01  # a 0.1 s record


def _collision_arrays(seed: int, n_events: int = 6):
    rng = np.random.default_rng(seed)
    wall = np.arange(n_events) % 3 == 0
    return {
        "collision_ball": rng.integers(0, N_BALLS - 1, n_events).astype(np.int32),
        "collision_partner": np.full(n_events, N_BALLS - 1, np.int32),
        "collision_wall": wall,
        "collision_start_s": np.sort(rng.uniform(0, 0.1, n_events)),
        "collision_duration_s": np.full(n_events, 2e-4),
        "collision_impact_normal": rng.uniform(0.05, 1.0, n_events),
        "collision_impact_tangential": rng.uniform(0.0, 0.3, n_events),
        "collision_max_overlap": rng.uniform(1e-7, 1e-5, n_events),
        "collision_peak_force": rng.uniform(1.0, 50.0, n_events),
        "collision_mass_eff": np.where(wall, 4e-3, 2e-3),
        "collision_energy": np.abs(rng.normal(0, 1e-4, (n_events, 5))),
        "collision_flags": np.zeros(n_events, np.int8),
    }


def _config():
    return replace_section(load_config(builtin_config_path("emax_300rpm")), "balls",
                           count=N_BALLS)


def write_dem_record(path, seed=0, collisions=True):
    rng = np.random.default_rng(seed)
    T = T_SAMPLES
    arrays = {
        "t": np.arange(T) * DT,
        "pos": rng.normal(0, 0.01, (T, N_BALLS, 3)),
        "vel": np.zeros((T, N_BALLS, 3)), "omega": np.zeros((T, N_BALLS, 3)),
        "offset": np.zeros((T, 3)), "offset_vel": np.zeros((T, 3)),
        "ke_trans": np.zeros(T), "ke_rot": np.zeros(T), "pe_grav": np.zeros(T),
        "e_elastic": np.zeros(T), "work_wall": np.zeros(T),
        "pp_pairs": np.full((T, 2, 2), -1, np.int32),
        "pw_contact": np.zeros((T, N_BALLS), bool),
        **{f"diss_{w}_{k}": np.zeros(T) for w in ("pp", "pw")
           for k in ("normal", "tangential", "slip", "rolling")},
    }
    cfg = replace_section(_config(), "dem", dt=DT)
    if collisions:
        arrays.update(_collision_arrays(seed))
    save_trajectory(path, arrays, build_meta(cfg, seed=seed))
    return path


def write_surrogate_record(path, seed=0):
    rng = np.random.default_rng(seed)
    S, dt, t_start = 50, 2e-3, 0.0  # 0.1 s of rollout
    d_e = rng.uniform(0, 1e-4, S)
    arrays = {
        "t_step": t_start + dt * np.arange(1, S + 1), "dE": d_e, "energy_cum": np.cumsum(d_e),
        **{name: np.zeros(S, np.int64) for name in ("n_pp_edges", "n_pw_edges", "overflow",
                                                   "n_outside", "n_snapped")},
        "t_pos": t_start + dt * np.array([0, 25, 50]),
        "pos": rng.normal(0, 0.01, (3, N_BALLS, 3)), "offset": np.zeros((3, 3)),
        **_collision_arrays(seed + 100),
    }
    meta = {"dt": dt, "save_every": 25, "init_index": 6, "config": config_to_dict(_config())}
    save_prediction(path, arrays, meta)
    return path


def test_load_events_from_real_records(tmp_path):
    dem = C.load_events(write_dem_record(tmp_path / "dem.npz"))
    assert dem.source == "dem" and dem.n_events == 6 and dem.n_balls == N_BALLS
    assert dem.record_duration_s == pytest.approx(0.1)
    mass = 4 / 3 * math.pi * 0.005**3 * 7700.0
    assert dem.total_mass_kg == pytest.approx(N_BALLS * mass)
    surr = C.load_events(write_surrogate_record(tmp_path / "surr.npz"))
    assert surr.source == "surrogate" and surr.record_duration_s == pytest.approx(0.1)
    assert surr.total_mass_kg == pytest.approx(N_BALLS * mass)  # from the config's [balls]


def test_cli_spectra_on_dem_and_surrogate_records(tmp_path, capsys):
    for i in range(3):
        write_dem_record(tmp_path / f"dem_{i}.npz", seed=i)
        write_surrogate_record(tmp_path / f"surr_{i}.npz", seed=i)
    out = tmp_path / "figures"
    rc = main(["spectra", "--dem", str(tmp_path / "dem_*.npz"), "--surrogate",
               str(tmp_path / "surr_0.npz"), str(tmp_path / "surr_1.npz"),
               "--out", str(out), "--threshold", "1e-4"])
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    lines = captured.out.strip().splitlines()
    assert lines[0].startswith("statistic") and "mean stress energy, all" in captured.out
    line = json.loads(lines[-1])
    assert line["dem"]["n_records"] == 3 and line["surrogate"]["n_records"] == 2
    assert line["threshold_J"] == 1e-4 and "decades" in line
    assert line["dem"]["mean"]["frequency_per_ball_hz[all]"] == pytest.approx(6 / (4 * 0.1))
    for name, path in line["figures"].items():
        assert (out / f"{name}.png").is_file() and path.endswith(".png")
    # --json FILE, --window, one source, no plots
    rc = main(["spectra", "--surrogate", str(tmp_path / "surr_0.npz"), "--window", "0.0",
               "0.05", "--json", str(tmp_path / "s.json"), "--no-plots"])
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    saved = json.loads((tmp_path / "s.json").read_text())
    assert saved["window_s"] == [0.0, 0.05] and "dem" not in saved
    assert "{" not in captured.out  # the table only


def test_cli_spectra_refuses_bad_input(tmp_path, capsys):
    plain = write_dem_record(tmp_path / "plain.npz", collisions=False)
    assert main(["spectra", "--dem", str(plain), "--no-plots"]) == 2
    err = capsys.readouterr().err
    assert "holds no collision events" in err and "sgn-jax dem" in err and "collisions = true" in err
    dem = write_dem_record(tmp_path / "dem.npz")
    assert main(["spectra", "--surrogate", str(dem), "--no-plots"]) == 2
    assert "is a DEM trajectory, not a rollout prediction" in capsys.readouterr().err
    assert main(["spectra", "--dem", str(tmp_path / "missing_*.npz")]) == 2
    assert "matches no file" in capsys.readouterr().err
    assert main(["spectra", "--dem", str(dem), "--threshold", "0"]) == 2
    assert "--threshold must be an energy > 0 J" in capsys.readouterr().err
    assert main(["spectra"]) == 2
    assert "--dem FILE" in capsys.readouterr().err


def test_a_record_without_events_gives_zeros_and_nan(tmp_path):
    empty = make_table([])
    stats = C.collision_statistics(empty)
    assert stats["frequency_per_ball_hz[all]"] == 0.0 and stats["power_W[all]"] == 0.0
    assert math.isnan(stats["mean_stress_energy_J[all]"]) and math.isnan(stats["share_above"])
    assert math.isnan(stats["impact_speed_q90_m_s"]) and not stats["dissipation_rate_hz"].any()
    out = collision_spectra(dem=[empty, make_table(ROWS)]).to_json()
    json.dumps(out, allow_nan=False)
    assert out["dem"]["n_events"] == [0, 4]


def test_inconsistent_event_arrays_are_refused():
    arrays = {f"collision_{k}": np.zeros(3) for k in C.EVENT_FIELDS}
    arrays["collision_energy"] = np.zeros((3, 4))  # one dissipation kind short
    arrays.update(t=np.arange(5) * 0.01, pos=np.zeros((5, 2, 3)))
    with pytest.raises(C.CollisionDataError, match="'energy' has shape"):
        C.events_from_arrays(arrays, {"ball_mass": 4e-3}, source="dem")
    del arrays["collision_flags"]
    with pytest.raises(C.CollisionDataError, match="collision_flags"):
        C.events_from_arrays(arrays, {"ball_mass": 4e-3}, source="dem")


def test_a_decades_difference_carries_the_scatter_of_both_ensembles():
    """Per-decade SEs from the packings' own decade powers, propagated to the relative
    difference: DEM packings 2e-4 and 4e-4 J in one second (mean 3e-4, SE 1e-4), surrogate
    3e-4 and 3.6e-4 (mean 3.3e-4, SE 3e-5)."""
    dem = [make_table([(False, 0.1, 0.5, 2e-3, energy(e), 0)], duration=1.0)
           for e in (2e-4, 4e-4)]
    surr = [make_table([(False, 0.1, 0.5, 2e-3, energy(e), 0)], duration=1.0,
                       source="surrogate") for e in (3e-4, 3.6e-4)]
    row = {r["lo_J"]: r for r in collision_spectra(dem=dem, surrogate=surr).decades()}[1e-4]
    assert row["power_se_W"]["reference"] == pytest.approx(1e-4)
    assert row["power_se_W"]["other"] == pytest.approx(3e-5)
    assert row["power_relative_difference"] == pytest.approx(0.1)
    expected = 1.1 * math.hypot(3e-5 / 3.3e-4, 1e-4 / 3e-4)
    assert row["power_relative_difference_se"] == pytest.approx(expected)


def test_merging_recontacts_joins_a_pairs_contacts_closer_than_the_gap():
    """Pair (0, 1) touches at 0.1 s and 0.1002 s (parted 0.1 ms) and at 0.2 s; ball 0 meets
    the wall in between: at a 0.15 ms resolution the pair's first two contacts are one event
    (energies summed, the first one's impact, the last one's end), the rest stay apart."""
    rows = [(False, 0.1, 0.5, 2e-3, energy(3e-4), 0),
            (False, 0.1002, 0.2, 2e-3, energy(1e-4, 2e-5), 2),
            (False, 0.2, 0.3, 2e-3, energy(5e-5), 0),
            (True, 0.1001, 0.4, 4e-3, energy(2e-4), 1)]
    table = dataclasses.replace(make_table(rows), duration_s=np.full(4, 1e-4))
    merged = table.merge_recontacts(1.5e-4)
    assert merged.n_events == 3
    first = np.flatnonzero(~merged.wall & (merged.start_s < 0.15))[0]
    assert merged.duration_s[first] == pytest.approx(0.1003 - 0.1)
    assert merged.impact_normal[first] == pytest.approx(0.5)
    assert merged.energy[first] == pytest.approx(energy(4e-4, 2e-5))
    assert merged.flags[first] == C.FLAG_OPEN_AT_END          # the last part's
    assert merged.flags[merged.wall][0] == C.FLAG_BEGAN_BEFORE
    assert merged.dissipated.sum() == pytest.approx(table.dissipated.sum())
    # a gap shorter than the parting merges nothing; negative gaps are refused
    assert table.merge_recontacts(0.5e-4).n_events == 4
    with pytest.raises(ValueError, match="gap_s"):
        table.merge_recontacts(-1.0)
