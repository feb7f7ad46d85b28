"""A charge in the config: [[balls.mix]], [[materials]], [[interactions]] (docs/charge.md);
the checks before any work, the step from the charge, and a short DEM run of a mixture."""

from __future__ import annotations

import numpy as np
import pytest

from sgn_jax.analysis.collisions import collision_statistics, load_events
from sgn_jax.config import (
    ConfigError,
    config_from_dict,
    config_to_dict,
    load_config,
    replace_section,
)
from sgn_jax.config import builtin_config_path as builtin
from sgn_jax.pipelines import dem_run as driver
from sgn_jax.pipelines.charge_sweep import (
    ball_fill,
    charge_point,
    charge_sweep,
    plot_charge_sweep,
)
from sgn_jax.pipelines.configure import (
    charge_from_config,
    check_surrogate_charge,
    params_from_config,
)
from sgn_jax.pipelines.validation import (
    CONTACT_STEPS_AT_1MS,
    charge_dt_dem_max,
    check_dem_config,
    contact_kinds,
)

ZIRCONIA = {"name": "zirconia", "young": 1.6e9, "poisson": 0.3, "restitution": 0.5,
            "friction": 0.2, "rolling_friction": 0.02}


def _mixed(**balls_changes) -> dict:
    data = config_to_dict(load_config(builtin("emax_300rpm")))
    data["balls"] = {"count": 8, "radius": 0.005, "density": 7700.0,
                     "mix": [{"count": 12, "radius": 0.003, "density": 6000.0,
                              "material": "zirconia"}], **balls_changes}
    data["materials"] = [dict(ZIRCONIA)]
    data["interactions"] = [{"materials": ["steel", "zirconia"], "restitution": 0.4,
                             "friction": 0.25, "rolling_friction": 0.03}]
    return data


def test_a_mixed_charge_from_the_config():
    cfg = config_from_dict(_mixed())
    assert cfg.balls.n_balls == 20 and not cfg.balls.single_class
    charge = charge_from_config(cfg)
    assert [c.material.name for c in charge.classes] == ["steel", "zirconia"]
    assert charge.pair_rule(charge.classes[0].material, charge.classes[1].material).friction \
        == pytest.approx(0.25)
    params = params_from_config(cfg)
    assert params.polydisperse and np.shape(params.radius) == (20,)
    assert np.shape(params.pp.mass_eff) == (2, 2)
    _, kinds = contact_kinds(cfg)
    assert sorted(kinds) == ["ball-ball 0-0", "ball-ball 0-1", "ball-ball 1-1",
                             "ball-wall 0", "ball-wall 1"]
    # The surrogates know one class of the jar's material: a clear error, not a wrong answer.
    with pytest.raises(ConfigError, match=r"balls\.mix"):
        check_surrogate_charge(cfg)
    one_zirconia = config_from_dict({**_mixed(), "balls": {"count": 20, "radius": 0.004,
                                                           "density": 6000.0,
                                                           "material": "zirconia"}})
    with pytest.raises(ConfigError, match="jar's material"):
        check_surrogate_charge(one_zirconia)


@pytest.mark.parametrize("change,match", [
    (lambda d: d["balls"]["mix"][0].update(material="unobtainium"), "unobtainium"),
    (lambda d: d["materials"].append(dict(ZIRCONIA)), "unique"),
    (lambda d: d["interactions"][0].update(materials=["steel", "glass"]), "glass"),
    (lambda d: d["interactions"].append(d["interactions"][0]), "two"),
    (lambda d: d["balls"]["mix"][0].update(count=0), "count"),
    (lambda d: d["materials"][0].update(restitution=0.0), "restitution"),
])
def test_bad_charges_are_refused_naming_the_value(change, match):
    data = _mixed()
    change(data)
    with pytest.raises(ConfigError, match=match):
        config_from_dict(data)


def test_checks_before_work_fill_and_grid_resolution():
    full = config_from_dict(_mixed(count=100))  # 100 x 10 mm + 12 x 6 mm balls: 43 % of 125 ml
    with pytest.raises(ConfigError, match="fill"):
        check_dem_config(full)
    tiny = _mixed()
    tiny["balls"]["mix"][0]["radius"] = 0.001   # 2 mm balls, 0.5 mm SDF spacing
    with pytest.raises(ConfigError, match="spacing"):
        check_dem_config(config_from_dict(tiny))


def test_the_step_resolves_the_shortest_contact_of_the_charge():
    standard = load_config(builtin("emax_300rpm"))
    assert charge_dt_dem_max(standard) > standard.dem.dt_dem_max   # unchanged
    assert driver.setup_from_config(standard).dt_dem == standard.dem.dt_dem
    cfg = config_from_dict(_mixed())
    setup = driver.setup_from_config(cfg)
    law, kinds = contact_kinds(cfg)
    shortest = min(float(law.contact_time(p, 1.0)) for p, _ in kinds.values())
    assert shortest / setup.dt_dem >= CONTACT_STEPS_AT_1MS
    assert setup.dt_dem < standard.dem.dt_dem_max


@pytest.mark.slow
def test_a_short_dem_run_of_a_mixture(tmp_path):
    data = _mixed()
    data["dem"].update(settle_time=0.03, chunk_samples=50)
    cfg = config_from_dict(data)
    run = driver.run_dem(cfg, duration=0.03, out_path=tmp_path / "mix.npz", progress=False)
    pos = run.arrays["pos"]
    assert pos.shape == (301, 20, 3) and np.all(np.isfinite(pos))
    assert run.meta["n_balls"] == 20
    np.testing.assert_allclose(run.meta["ball_radii"], [0.005] * 8 + [0.003] * 12)
    assert run.meta["ball_mass"] * 20 == pytest.approx(float(np.sum(run.meta["ball_masses"])))
    # The energy ledger closes (work in = change of energy + dissipation) and the collision
    # ledger's events add up to it.
    a = run.arrays
    energy = a["ke_trans"] + a["ke_rot"] + a["pe_grav"] + a["e_elastic"]
    diss = sum(np.sum(a[f"diss_{w}_{k}"]) for w in ("pp", "pw")
               for k in ("normal", "tangential", "slip", "rolling", "stiffness"))
    residual = (energy[-1] - energy[0]) + diss - (a["work_wall"][-1] - a["work_wall"][0])
    assert abs(residual) < 1e-3 * max(diss, 1e-9), (residual, diss)
    closure = run.summary["collisions"]
    assert closure["events"] > 0 and closure["worst_rel"] < 1e-3, closure
    # Statistics per pair of ball classes, adding up to the pair kinds.
    table = load_events(tmp_path / "mix.npz")
    assert table.class_kinds == ("ball-ball 0-0", "ball-ball 0-1", "ball-ball 1-1",
                                 "ball-wall 0", "ball-wall 1")
    stats = collision_statistics(table)
    for kind, parts in (("ball-ball", ("0-0", "0-1", "1-1")), ("ball-wall", ("0", "1"))):
        for name in ("power_W", "frequency_per_ball_hz"):
            total = sum(stats[f"{name}[{kind} {p}]"] for p in parts)
            assert total == pytest.approx(stats[f"{name}[{kind}]"], rel=1e-12)
    assert stats["power_W[ball-wall 1]"] > 0 and stats["power_W[ball-ball 0-1]"] > 0


def test_charge_points_hold_the_filling_or_the_count():
    std = load_config(builtin("emax_300rpm"))
    fill = ball_fill(std)
    small = charge_point(std, "diameter", 0.006)             # fixed filling: more balls
    assert small.balls.radius == 0.003
    assert abs(ball_fill(small) / fill - 1) < 0.02 and small.balls.count == 111  # 24 (5/3)^3
    same_count = charge_point(std, "diameter", 0.006, hold="count")
    assert same_count.balls.count == 24
    fuller = charge_point(std, "fill", 0.15)
    assert fuller.balls.radius == std.balls.radius and abs(ball_fill(fuller) - 0.15) < 0.005
    with pytest.raises(ConfigError, match="fill"):
        charge_point(std, "fill", 1.5)
    with pytest.raises(ConfigError, match="mix"):
        charge_point(config_from_dict(_mixed()), "fill", 0.1)


@pytest.mark.slow
def test_a_tiny_charge_sweep_against_its_own_dem_runs(tmp_path):
    cfg = replace_section(load_config(builtin("emax_300rpm")), "dem", settle_time=0.02)
    result = charge_sweep(cfg, "fill", [0.02], packings=2, duration=0.02, burn_in=0.01)
    assert [p["n_balls"] for p in result["points"]] == [5]
    for point in result["points"]:
        assert len(point["powers_W"]) == 2
        assert point["power_total_W"] >= point["power_W"] > 0
        assert point["specific_W_per_kg"] == pytest.approx(point["power_total_W"]
                                                           / point["mass_kg"])
    assert plot_charge_sweep(result, tmp_path / "sweep.png").exists()
    with pytest.raises(ConfigError, match="fill"):   # a point that cannot be placed
        charge_sweep(cfg, "fill", [0.5], packings=2, duration=0.02, burn_in=0.01)
