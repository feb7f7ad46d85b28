"""The DEM's collision ledger (sgn_jax.dem.collisions): known-answer impacts, events adding up to
the energy ledger kind by kind, the same events whatever the pair list, overflow, the record."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from test_dem_contact import _ode_impact  # the contact law's head-on ODE, the tests' reference

import sgn_jax  # noqa: F401  (enables x64)
from sgn_jax.config import builtin_config_path, load_config, replace_section
from sgn_jax.dem import (
    DEMSpec,
    hertz_contact_time,
    init_state,
    make_params,
    plane_wall_fn,
    plane_walls,
)
from sgn_jax.dem import collisions as coll
from sgn_jax.dem.engine import DISSIPATION_KINDS, DEMError, make_advance
from sgn_jax.motion import CircleMotion
from sgn_jax.pipelines import dem_run as driver
from sgn_jax.records.trajectory import load_trajectory

RADIUS = 0.005
DT_DEM = 9.5e-7
STEEL = dict(young=2.05e9, poisson=0.235, friction=0.3, rolling_friction=0.045)


def _params(restitution, walls, gravity=(0.0, 0.0, 0.0), motion=None):
    motion = motion or CircleMotion(rpm=0.0, amplitude=0.0)
    return make_params(RADIUS, 7700.0, restitution=restitution, gravity=gravity,
                       geometry=walls, motion=motion, **STEEL)


def _events(state):
    ints, floats = coll.buffer_rows(state.collisions)
    return ints, floats


@pytest.mark.parametrize("partner", ["ball", "wall"])
def test_a_head_on_impact_is_one_event_with_the_analytic_speed_and_energy(partner):
    restitution, speed = 0.5, 1.0
    walls = plane_walls([[0.0, -1.0, 0.0]], [[0.0, -1.0, 0.0]])  # a floor far below
    params = _params(restitution, walls)
    if partner == "ball":  # relative speed `speed`, touching after one step
        pos = [[-RADIUS - 1e-7, 0, 0], [RADIUS + 1e-7, 0, 0]]
        vel = [[speed / 2, 0, 0], [-speed / 2, 0, 0]]
        law = params.pp
    else:  # one ball falling onto a floor at y = 0 (no gravity: constant speed)
        walls = plane_walls([[0.0, 0.0, 0.0]], [[0.0, -1.0, 0.0]])
        params = _params(restitution, walls)
        pos = [[0.0, RADIUS + 1e-7, 0.0]]
        vel = [[0.0, -speed, 0.0]]
        law = params.pw
    spec = DEMSpec(n_balls=len(pos), n_patches=1, dt_dem=DT_DEM, collision_capacity=8)
    state = init_state(spec, params, np.array(pos), np.array(vel))
    t_c = float(hertz_contact_time(law, speed))
    state = make_advance(spec, plane_wall_fn)(params, state, int(3 * t_c / DT_DEM))

    ints, floats = _events(state)
    assert int(state.collisions.buffer.count) == 1 and ints.shape == (1, coll.N_INTS)
    assert ints[0, coll.WALL] == (partner == "wall")
    assert floats[0, coll.IMPACT_NORMAL] == pytest.approx(speed, rel=1e-9)
    assert floats[0, coll.IMPACT_TANGENTIAL_SQ] == pytest.approx(0.0, abs=1e-20)
    # All the energy lost is the normal damping's: 1/2 m* v^2 (1 - e^2), e to 0.003 (the
    # accuracy of the DEM's restitution, tests/test_dem_contact.py).
    energy = floats[0, coll.ENERGY0:]
    expected = 0.5 * law.mass_eff * speed**2 * (1 - restitution**2)
    assert energy[0] == pytest.approx(expected, rel=2 * 2 * restitution * 0.003 / (1 - 0.25))
    assert np.all(np.abs(energy[1:]) < 1e-12 * energy[0])
    led = state.ledger.diss_pw if partner == "wall" else state.ledger.diss_pp
    np.testing.assert_allclose(energy, np.asarray(led), rtol=1e-12, atol=1e-30)
    # The event lasts as long as the contact law's impact (an accurate ODE solution), to a
    # step or two; its deepest overlap and force are below the undamped Hertz peaks.
    duration = (ints[0, coll.END_STEP] - ints[0, coll.START_STEP]) * DT_DEM
    assert duration == pytest.approx(_ode_impact(law, speed)[0], abs=2.5 * DT_DEM)
    undamped_overlap = (15 * law.mass_eff * speed**2
                        / (16 * law.young_eff * np.sqrt(law.radius_eff))) ** 0.4
    assert 0.7 * undamped_overlap < floats[0, coll.MAX_OVERLAP] < undamped_overlap
    assert floats[0, coll.PEAK_FORCE] > 0


def _box_run(pair_mode, capacity=4096, steps=40_000):
    """Ten balls thrown around a shaken open box (floor and four sides) under gravity."""
    half = 0.02
    walls = plane_walls([[0, 0, 0], [-half, 0, 0], [half, 0, 0], [0, 0, -half], [0, 0, half]],
                        [[0, -1, 0], [-1, 0, 0], [1, 0, 0], [0, 0, -1], [0, 0, 1]])
    params = _params(0.6, walls, gravity=(0.0, -9.81, 0.0),
                     motion=CircleMotion(rpm=600.0, amplitude=0.004))
    rng = np.random.default_rng(0)
    grid = np.array([[x, y, z] for x in (-0.011, 0.0, 0.011) for y in (0.006, 0.018)
                     for z in (-0.011, 0.011)])[:10]
    spec = DEMSpec(n_balls=10, n_patches=5, dt_dem=DT_DEM, pair_mode=pair_mode,
                   neighbour_capacity=6, neighbour_skin=0.0005, collision_capacity=capacity)
    state = init_state(spec, params, grid, rng.normal(0, 0.5, size=(10, 3)))
    return spec, params, make_advance(spec, plane_wall_fn)(params, state, steps)


def _closed_and_open(state):
    ints, floats = _events(state)
    open_ints, open_floats = coll.open_rows(state.collisions, state.pairs.i, state.pairs.j,
                                            int(state.step))
    return np.concatenate([ints, open_ints]), np.concatenate([floats, open_floats])


@pytest.mark.slow
def test_events_add_up_to_the_energy_ledger_kind_by_kind():
    spec, params, state = _box_run("neighbour")
    assert not bool(state.pairs.overflow) and int(state.pairs.rebuilds) > 10
    ints, floats = _closed_and_open(state)
    wall = ints[:, coll.WALL].astype(bool)
    assert np.sum(wall) > 5 and np.sum(~wall) > 5
    energy = floats[:, coll.ENERGY0:]
    total = float(np.sum(state.ledger.diss_pp) + np.sum(state.ledger.diss_pw))
    for mask, ledger in ((~wall, state.ledger.diss_pp), (wall, state.ledger.diss_pw)):
        for k, kind in enumerate(DISSIPATION_KINDS):
            assert np.sum(energy[mask, k]) == pytest.approx(float(ledger[k]), abs=1e-12 * total), kind
    # Every ball-ball event names a real pair i < j; every event lasts at least one step.
    assert np.all(ints[~wall, coll.BALL] < ints[~wall, coll.PARTNER])
    assert np.all(ints[:, coll.END_STEP] > ints[:, coll.START_STEP])
    assert np.all(floats[:, coll.PEAK_FORCE] > 0) and np.all(floats[:, coll.MAX_OVERLAP] > 0)


@pytest.mark.slow
def test_the_events_do_not_depend_on_the_pair_list():
    """The Verlet list moves pairs between slots at every rebuild; the events must not see it."""
    def table(mode):
        _, _, state = _box_run(mode, steps=20_000)
        ints, floats = _closed_and_open(state)
        order = np.lexsort((ints[:, coll.PARTNER], ints[:, coll.BALL], ints[:, coll.WALL],
                            ints[:, coll.START_STEP]))
        return ints[order], floats[order]

    ints_n, floats_n = table("neighbour")
    ints_p, floats_p = table("pairs")
    np.testing.assert_array_equal(ints_n, ints_p)
    np.testing.assert_allclose(floats_n, floats_p, rtol=1e-9, atol=1e-18)


@pytest.mark.slow
def test_an_overflowing_buffer_keeps_counting():
    spec, params, state = _box_run("neighbour", capacity=2, steps=20_000)
    count = int(state.collisions.buffer.count)
    assert count > 2
    ints, _ = coll.buffer_rows(state.collisions)
    assert ints.shape[0] == 2  # what was stored; the host sees count > capacity and stops


def test_nxn_pairs_refuse_the_ledger():
    with pytest.raises(DEMError, match="collision ledger"):
        DEMSpec(n_balls=3, n_patches=1, dt_dem=DT_DEM, pair_mode="nxn", collision_capacity=8)
    with pytest.raises(DEMError, match="collision_capacity"):
        DEMSpec(n_balls=3, n_patches=1, dt_dem=DT_DEM, collision_capacity=-1)


@pytest.fixture(scope="module")
def tiny_cfg():
    """Six balls dropped into the jar, 60 ms of settling (they land and bounce), chunks of 50
    samples."""
    cfg = load_config(builtin_config_path("emax_300rpm"))
    cfg = replace_section(cfg, "balls", count=6)
    return replace_section(cfg, "dem", settle_time=0.06, chunk_samples=50, duration=0.02)


@pytest.mark.slow
def test_the_record_carries_the_collision_table(tiny_cfg, tmp_path):
    out = tmp_path / "traj.npz"
    result = driver.run_dem(tiny_cfg, out_path=out, seed=2, progress=False)
    trajectory = load_trajectory(out)
    data = np.load(out)
    n = data["collision_ball"].shape[0]
    assert n > 0
    for name in driver.COLLISION_ARRAYS:
        assert data[name].shape[0] == n, name
    assert data["collision_energy"].shape == (n, 5)
    closure = result.summary["collisions"]
    assert closure["events"] == n and closure["worst_rel"] < 1e-9
    # Contacts open at t = 0 are flagged as begun before the record, the ones open at the end
    # as open; the others lie inside it.
    flags = data["collision_flags"]
    start, end = data["collision_start_s"], data["collision_start_s"] + data["collision_duration_s"]
    before = (flags & coll.FLAG_BEGAN_BEFORE) > 0
    assert np.all(start[before] < 0) and np.all(start[~before] >= 0)
    assert np.all(end <= trajectory.arrays["t"][-1] + 1e-12)
    assert np.all(data["collision_mass_eff"][data["collision_wall"]]
                  == pytest.approx(result.arrays["collision_mass_eff"].max()))
    assert trajectory.meta["extra_arrays"][-1] == "collision_flags"


@pytest.mark.slow
def test_an_overflowing_chunk_stops_the_run(tiny_cfg):
    # Seed 2 closes two contacts in the first chunk of 5 ms.
    cfg = replace_section(tiny_cfg, "dem", collision_capacity=1)
    with pytest.raises(DEMError, match="collision_capacity"):
        driver.run_dem(cfg, seed=2, progress=False)


# The slow tier (`pytest -m slow`; the default run's time): one more DEM run with the ledger off.
@pytest.mark.slow
def test_collisions_off_leaves_the_record_without_a_table(tiny_cfg):
    cfg = replace_section(tiny_cfg, "dem", collisions=False, settle_time=0.002)
    result = driver.run_dem(cfg, duration=0.001, seed=2, progress=False)
    assert "collision_ball" not in result.arrays and result.summary["collisions"] is None
    assert dataclasses.replace(driver.setup_from_config(cfg).spec).collision_capacity == 0
