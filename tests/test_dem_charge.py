"""The DEM with a charge of several ball classes (sgn_jax.dem.charge, docs/charge.md).

Known answers: a head-on impact of two balls of different size, density and material has the
pair's restitution and the contact duration of an accurate ODE of the same law (Hertz's
t_c for e = 1); a loose mixture in free space keeps its momentum and angular momentum and its
energy ledger closes; rotating a two-size scene rotates its motion; a ball of each material
comes to rest on the floor at Hertz's static overlap.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import sgn_jax  # noqa: F401  (enables x64)
from sgn_jax.dem import (
    DEMSpec,
    contact_forces,
    hertz_contact_time,
    init_state,
    ledger_balance,
    make_advance,
    make_contact_law,
    make_dem_step,
    make_params,
    plane_wall_fn,
    plane_walls,
)
from sgn_jax.dem.cells import cell_grid_for
from sgn_jax.dem.charge import (
    BallClass,
    Charge,
    ChargeError,
    Material,
    PairRule,
    charge_params,
    contact_params,
    mixed_pair_rule,
    pair_params,
)
from sgn_jax.motion import CircleMotion
from tests.test_dem_contact import _crossings, _ode_impact

DT_DEM = 9.5e-7
SPEEDS = (0.1, 1.0, 5.0)
AT_REST = CircleMotion(rpm=0.0, amplitude=0.0)
STEEL = Material("steel", young=2.05e9, poisson=0.235, restitution=0.3, friction=0.3,
                 rolling_friction=0.045)
ZIRCONIA = Material("zirconia", young=1.6e9, poisson=0.3, restitution=0.5, friction=0.2,
                    rolling_friction=0.02)
GLASS = Material("glass", young=1.0e9, poisson=0.22, restitution=0.7, friction=0.4,
                 rolling_friction=0.01)
FAR_WALL = plane_walls([[0.0, -1.0, 0.0]], [[0.0, -1.0, 0.0]])  # never touched


def _two_class_charge(restitution: float) -> Charge:
    big = BallClass(1, 0.005, 7700.0, STEEL)
    small = BallClass(1, 0.003, 6000.0, ZIRCONIA)
    rule = PairRule(restitution=restitution, friction=0.3, rolling_friction=0.02)
    return Charge(classes=(big, small), wall=STEEL, pair_rules=((("zirconia", "steel"), rule),))


def _head_on(restitution: float, n_steps: int = 700):
    """A 5 mm steel ball and a 3 mm zirconia ball touching, approaching along x at each speed
    (split so the total momentum is zero)."""
    charge = _two_class_charge(restitution)
    params = charge_params(charge, (0.0, 0.0, 0.0), FAR_WALL, AT_REST)
    spec = DEMSpec(n_balls=2, n_patches=1, dt_dem=DT_DEM, pair_mode="pairs")
    step = make_dem_step(spec, plane_wall_fn)
    m1, m2 = charge.masses
    r1, r2 = charge.radii

    def run(params, speed):
        pos = jnp.array([[-r1, 0.0, 0.0], [r2, 0.0, 0.0]])
        zero = 0.0 * speed
        vel = jnp.stack([jnp.stack([speed * m2 / (m1 + m2), zero, zero]),
                         jnp.stack([-speed * m1 / (m1 + m2), zero, zero])])
        state = init_state(spec, params, pos, vel=vel)

        def body(s, _):
            return step(params, s), r1 + r2 - (s.pos[1, 0] - s.pos[0, 0])

        return jax.lax.scan(body, state, None, length=n_steps)

    final, overlap = jax.jit(jax.vmap(run, in_axes=(None, 0)))(params, jnp.asarray(SPEEDS))
    out_speed = np.asarray(final.vel[:, 0, 0] - final.vel[:, 1, 0])
    return pair_params(params.pp, 0, 1), np.asarray(overlap), out_speed, final, (m1, m2)


def test_mixed_pair_restitution_and_duration_match_the_law():
    law, overlap, out_speed, final, (m1, m2) = _head_on(0.3)
    # The pair's own parameters: R* and m* of the two sizes, the two materials' Y*.
    assert law.radius_eff == pytest.approx(0.005 * 0.003 / 0.008)
    assert law.mass_eff == pytest.approx(m1 * m2 / (m1 + m2))
    y_eff = 1.0 / ((1 - 0.235**2) / 2.05e9 + (1 - 0.3**2) / 1.6e9)
    assert law.young_eff == pytest.approx(y_eff)
    for k, speed in enumerate(SPEEDS):
        assert out_speed[k] < 0
        assert abs(abs(out_speed[k]) / speed - 0.3) <= 0.003, (speed, out_speed[k])
        t_ode, e_ode = _ode_impact(law, speed)
        assert abs(e_ode - 0.3) < 1e-6
        assert abs(_crossings(overlap[k], DT_DEM) / t_ode - 1) < 0.01
    # Momentum (zero) is kept and the lost kinetic energy is in the normal damping.
    momentum = m1 * np.asarray(final.vel[:, 0, 0]) + m2 * np.asarray(final.vel[:, 1, 0])
    assert np.all(np.abs(momentum) < 1e-12 * np.asarray(SPEEDS) * m1)
    lost = 0.5 * law.mass_eff * (np.asarray(SPEEDS) ** 2 - out_speed**2)
    np.testing.assert_allclose(np.asarray(final.ledger.diss_pp[:, 0]), lost, rtol=1e-3)


def test_mixed_pair_elastic_duration_is_hertz():
    law, overlap, out_speed, _, _ = _head_on(1.0)
    for k, speed in enumerate(SPEEDS):
        assert abs(abs(out_speed[k]) / speed - 1.0) < 1e-3
        t_hertz = hertz_contact_time(law, speed)
        assert abs(_crossings(overlap[k], DT_DEM) / t_hertz - 1) < 0.01, (speed, t_hertz)


def _cloud(seed: int, n_big: int = 5, n_small: int = 7) -> tuple[Charge, np.ndarray,
                                                                 np.ndarray, np.ndarray]:
    """A loose cloud of two sizes in free space with random velocities and spins."""
    charge = Charge(classes=(BallClass(n_big, 0.005, 7700.0, STEEL),
                             BallClass(n_small, 0.003, 3000.0, GLASS)), wall=STEEL)
    rng = np.random.default_rng(seed)
    radii = charge.radii
    pos: list[np.ndarray] = []
    while len(pos) < charge.n_balls:  # non-overlapping, within a 3 cm box
        x = rng.uniform(-0.015, 0.015, 3)
        r = radii[len(pos)]
        if all(np.linalg.norm(x - p) > r + radii[k] + 1e-4 for k, p in enumerate(pos)):
            pos.append(x)
    pos_arr = np.asarray(pos)
    vel = -0.8 * pos_arr / 0.015 + rng.normal(0.0, 0.1, pos_arr.shape)  # converging
    omega = rng.normal(0.0, 50.0, pos_arr.shape)
    return charge, pos_arr, vel, omega


def _momenta(charge: Charge, state) -> tuple[np.ndarray, np.ndarray]:
    m = charge.masses[:, None]
    inertia = 0.4 * charge.masses * charge.radii**2
    pos, vel, omega = (np.asarray(a) for a in (state.pos, state.vel, state.omega))
    linear = np.sum(m * vel, axis=0)
    angular = np.sum(np.cross(pos, m * vel), axis=0) + np.sum(inertia[:, None] * omega, axis=0)
    return linear, angular


@pytest.mark.parametrize("pair_mode", ["neighbour", "nxn"])
@pytest.mark.slow
def test_mixture_keeps_momentum_and_closes_its_ledger(pair_mode):
    charge, pos, vel, omega = _cloud(1)
    params = charge_params(charge, (0.0, 0.0, 0.0), FAR_WALL, AT_REST)
    spec = DEMSpec(n_balls=charge.n_balls, n_patches=1, dt_dem=DT_DEM, pair_mode=pair_mode,
                   neighbour_skin=0.002)
    state = init_state(spec, params, pos, vel=vel, omega=omega)
    advance = make_advance(spec, plane_wall_fn)
    balance0 = float(ledger_balance(spec, plane_wall_fn, params, state))
    p0, l0 = _momenta(charge, state)
    final = advance(params, state, 20000)  # 19 ms: the cloud collapses and collides
    p1, l1 = _momenta(charge, final)
    diss = float(np.sum(final.ledger.diss_pp))
    assert diss > 1e-3 * 0.5 * float(np.sum(charge.masses * np.sum(vel**2, axis=1)))
    scale_p = float(np.sum(charge.masses * np.linalg.norm(vel, axis=1)))
    np.testing.assert_allclose(p1, p0, atol=1e-9 * scale_p)
    np.testing.assert_allclose(l1, l0, atol=1e-9 * scale_p * 0.015)
    residual = float(ledger_balance(spec, plane_wall_fn, params, final)) - balance0
    assert abs(residual) < 1e-3 * diss, (residual, diss)


def test_two_size_scene_is_rotation_equivariant():
    charge, pos, vel, omega = _cloud(2)
    rotation = np.linalg.qr(np.random.default_rng(3).normal(size=(3, 3)))[0]
    if np.linalg.det(rotation) < 0:
        rotation[:, 0] *= -1
    params = charge_params(charge, (0.0, 0.0, 0.0), FAR_WALL, AT_REST)
    spec = DEMSpec(n_balls=charge.n_balls, n_patches=1, dt_dem=DT_DEM, pair_mode="pairs")
    advance = make_advance(spec, plane_wall_fn)
    a = advance(params, init_state(spec, params, pos, vel=vel, omega=omega), 8000)
    b = advance(params, init_state(spec, params, pos @ rotation.T, vel=vel @ rotation.T,
                                   omega=omega @ rotation.T), 8000)
    assert float(np.sum(a.ledger.diss_pp)) > 0  # there were contacts
    np.testing.assert_allclose(np.asarray(b.pos), np.asarray(a.pos) @ rotation.T, atol=1e-10)
    np.testing.assert_allclose(np.asarray(b.vel), np.asarray(a.vel) @ rotation.T, atol=1e-8)
    np.testing.assert_allclose(np.asarray(b.omega), np.asarray(a.omega) @ rotation.T,
                               atol=1e-5)


@pytest.mark.parametrize("material,density", [(STEEL, 7700.0), (ZIRCONIA, 6000.0),
                                              (GLASS, 2600.0)])
def test_a_ball_of_each_material_comes_to_rest_on_the_floor(material, density):
    radius = 0.004
    floor = plane_walls([[0.0, 0.0, 0.0]], [[0.0, -1.0, 0.0]])
    charge = Charge(classes=(BallClass(1, radius, density, material),), wall=STEEL)
    params = charge_params(charge, (0.0, -9.81, 0.0), floor, AT_REST)
    spec = DEMSpec(n_balls=1, n_patches=1, dt_dem=DT_DEM)
    state = init_state(spec, params, np.array([[0.0, radius + 0.002, 0.0]]),
                       vel=np.array([[0.05, 0.0, 0.0]]))
    final = make_advance(spec, plane_wall_fn)(params, state, 300000)  # 0.29 s
    law = params.pw
    # Hertz's static overlap: m g = 4/3 Y* sqrt(R*) d^1.5
    d_static = (charge.masses[0] * 9.81 / (4.0 / 3.0 * law.young_eff
                                           * math.sqrt(law.radius_eff))) ** (2.0 / 3.0)
    overlap = radius - float(final.pos[0, 1])
    assert abs(overlap / d_static - 1) < 0.02, (overlap, d_static)
    assert float(np.linalg.norm(final.vel[0])) < 1e-3
    # The wall contact mixes the two materials: Y* of both, the mean of their restitution.
    assert law.young_eff == pytest.approx(1.0 / ((1 - material.poisson**2) / material.young
                                                 + (1 - 0.235**2) / 2.05e9))
    expected = mixed_pair_rule(material, STEEL)
    assert expected.restitution == pytest.approx(0.5 * (material.restitution + 0.3))


def test_one_class_of_the_jars_material_gives_the_classic_parameters():
    charge = Charge(classes=(BallClass(24, 0.005, 7700.0, STEEL),), wall=STEEL)
    params = charge_params(charge, (0.0, -9.81, 0.0), FAR_WALL, AT_REST)
    classic = make_params(0.005, 7700.0, young=2.05e9, poisson=0.235, restitution=0.3,
                          friction=0.3, rolling_friction=0.045, gravity=(0.0, -9.81, 0.0),
                          geometry=FAR_WALL, motion=AT_REST)
    assert not params.polydisperse
    for a, b in zip(jax.tree_util.tree_leaves(params), jax.tree_util.tree_leaves(classic),
                    strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_pair_tables_and_rules():
    charge = _two_class_charge(0.4)
    pp, pw = contact_params(charge)
    assert np.shape(pp.radius_eff) == (2, 2) and np.shape(pw.radius_eff) == (2,)
    np.testing.assert_allclose(pp.radius_eff, np.asarray(pp.radius_eff).T)
    # The explicit rule for (zirconia, steel); zirconia with itself: its own values.
    assert pair_params(pp, 0, 1).friction == pytest.approx(0.3)
    assert pair_params(pp, 1, 1).friction == pytest.approx(ZIRCONIA.friction)
    assert pw.radius_eff[1] == pytest.approx(0.003)
    with pytest.raises(ChargeError, match="unobtainium"):
        Charge(classes=charge.classes, wall=STEEL,
               pair_rules=((("unobtainium", "steel"), PairRule(0.5, 0.3, 0.0)),))
    with pytest.raises(ChargeError, match="restitution"):
        Material("bad", 2e9, 0.3, restitution=1.5, friction=0.3, rolling_friction=0.0)


@pytest.mark.slow
def test_cell_list_rebuilds_give_the_same_run_as_all_pairs():
    charge, pos, vel, omega = _cloud(4)
    params = charge_params(charge, (0.0, 0.0, 0.0), FAR_WALL, AT_REST)
    base = DEMSpec(n_balls=charge.n_balls, n_patches=1, dt_dem=DT_DEM, neighbour_skin=2e-4)
    grid = cell_grid_for([-0.02] * 3, [0.02] * 3, 2 * 0.005 + 2e-4, 0.003, charge.n_balls)
    runs = []
    for spec in (base, dataclasses.replace(base, cell_grid=grid, cell_lower=(-0.02,) * 3)):
        state = init_state(spec, params, pos, vel=vel, omega=omega)
        runs.append(make_advance(spec, plane_wall_fn)(params, state, 6000))
    a, b = runs
    assert int(a.pairs.rebuilds) > 10 and not bool(b.pairs.overflow)
    np.testing.assert_array_equal(np.asarray(a.pos), np.asarray(b.pos))
    np.testing.assert_array_equal(np.asarray(a.pairs.i), np.asarray(b.pairs.i))


def test_cdt_rolling_law_uses_the_elastic_force_r_star_and_no_twist():
    law = make_contact_law(2.05e9, 0.235, 0.3, 0.3, 0.045, radius_1=0.005, mass_1=4e-3,
                           radius_2=0.005, mass_2=4e-3)
    overlap = jnp.array([1e-5, 1e-5])
    normal = jnp.array([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    arm = 0.005 - 0.5 * overlap
    v_rel = jnp.array([[0.1, 0.0, 0.0], [0.1, 0.0, 0.0]])        # approaching: damping > 0
    omega = jnp.array([[0.0, 0.0, 3.0], [5.0, 0.0, 0.0]])        # rolling; pure twist about n
    history = jnp.zeros((2, 3))
    edem = contact_forces(law, overlap, normal, arm, v_rel, omega, history, DT_DEM)
    cdt = contact_forces(law, overlap, normal, arm, v_rel, omega, history, DT_DEM,
                         rolling="cdt")
    np.testing.assert_allclose(np.linalg.norm(edem.torque_rolling[0]),
                               0.045 * abs(float(edem.normal_total[0])) * float(arm[0]))
    np.testing.assert_allclose(np.linalg.norm(cdt.torque_rolling[0]),
                               0.045 * float(cdt.normal_spring[0]) * law.radius_eff)
    assert float(np.linalg.norm(edem.torque_rolling[1])) > 0   # EDEM type A resists twist
    assert float(np.linalg.norm(cdt.torque_rolling[1])) == 0.0
    with pytest.raises(ValueError, match="rolling"):
        contact_forces(law, overlap, normal, arm, v_rel, omega, history, DT_DEM, rolling="x")
