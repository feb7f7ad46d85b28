"""Known-answer tests of the Hertz-Mindlin contact law (MercuryDPM style).

Normal impacts ball-wall and ball-ball at 0.1-5 m/s with dt_dem = 9.5e-7 s, no gravity:
restitution 0.300 +- 0.003, contact duration within 1 % of an accurate ODE solution of the same
force law, and for e = 1 within 1 % of Hertz's t_c = 2.87 (m*^2 / (R* Y*^2 v))^(1/5).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import sgn_jax  # noqa: F401  (enables x64)
from sgn_jax.dem import (
    DEMSpec,
    contact_forces,
    hertz_contact_time,
    init_state,
    make_dem_step,
    make_params,
    plane_wall_fn,
    plane_walls,
)
from sgn_jax.motion import CircleMotion

RADIUS = 0.005
DT_DEM = 9.5e-7
SPEEDS = (0.1, 0.5, 1.0, 2.0, 5.0)
STEEL = dict(young=2.05e9, poisson=0.235, friction=0.3, rolling_friction=0.045)
AT_REST = CircleMotion(rpm=0.0, amplitude=0.0)


def _params(restitution: float, walls):
    return make_params(RADIUS, 7700.0, restitution=restitution, gravity=(0.0, 0.0, 0.0),
                       geometry=walls, motion=AT_REST, **STEEL)


def _ode_impact(law, speed: float) -> tuple[float, float]:
    """(contact duration, restitution) of m* d'' = -(F_s(d) + gamma_n(d) d'), d(0)=0, d'(0)=v."""
    def rhs(_t, y):
        d, v = y
        dp = max(d, 0.0)
        s_n = 2 * law.young_eff * np.sqrt(law.radius_eff * dp)
        gamma = law.damping_factor * np.sqrt(s_n * law.mass_eff)
        f = 4.0 / 3.0 * law.young_eff * np.sqrt(law.radius_eff) * dp**1.5 + gamma * v
        return [v, -f / law.mass_eff]

    def leave(_t, y):
        return y[0]

    leave.terminal, leave.direction = True, -1
    sol = solve_ivp(rhs, [0.0, 1.0], [0.0, speed], method="DOP853", rtol=1e-12, atol=1e-16,
                    events=leave, first_step=1e-10)
    return float(sol.t_events[0][-1]), float(-sol.y_events[0][-1][1] / speed)


def _crossings(overlap: np.ndarray, dt: float) -> float:
    """Contact duration from overlaps sampled every dt, starting at overlap 0 (linear interp.)."""
    inside = overlap > 0
    last = int(np.nonzero(inside)[0][-1])
    assert last + 1 < len(overlap), "the run ended before the contact did"
    a, b = overlap[last], overlap[last + 1]
    return (last + a / (a - b)) * dt


# One compiled simulator per contact type, the parameters (restitution) and speeds its
# arguments: the restitution and the elastic tests run the same program.
_SIMULATORS = {}


def _simulator(kind, make_run):
    if kind not in _SIMULATORS:
        _SIMULATORS[kind] = jax.jit(jax.vmap(make_run(), in_axes=(None, 0)))
    return _SIMULATORS[kind]


def _simulate_wall(restitution: float, n_steps: int):
    """Ball starting at wall contact (overlap 0) moving into a floor plane at each speed."""
    walls = plane_walls([[0.0, 0.0, 0.0]], [[0.0, -1.0, 0.0]])
    params = _params(restitution, walls)

    def make_run():
        spec = DEMSpec(n_balls=1, n_patches=1, dt_dem=DT_DEM)
        step = make_dem_step(spec, plane_wall_fn)

        def run(params, speed):
            state = init_state(spec, params, jnp.array([[0.0, RADIUS, 0.0]]),
                               vel=jnp.stack([jnp.zeros(()), -speed, jnp.zeros(())])[None])

            def body(s, _):
                return step(params, s), RADIUS - s.pos[0, 1]

            final, overlap = jax.lax.scan(body, state, None, length=n_steps)
            return final, overlap

        return run

    final, overlap = _simulator(("wall", n_steps), make_run)(params, jnp.asarray(SPEEDS))
    out_speed = -np.asarray(final.vel[:, 0, 1])  # approach speed, < 0 after a bounce
    return params.pw, np.asarray(overlap), out_speed, final, params


def _simulate_pair(restitution: float, n_steps: int):
    """Two balls touching (overlap 0), approaching head-on along x at relative speed v."""
    walls = plane_walls([[0.0, -1.0, 0.0]], [[0.0, -1.0, 0.0]])  # far away, never touched
    params = _params(restitution, walls)

    def make_run():
        spec = DEMSpec(n_balls=2, n_patches=1, dt_dem=DT_DEM)
        step = make_dem_step(spec, plane_wall_fn)

        def run(params, speed):
            pos = jnp.array([[-RADIUS, 0.0, 0.0], [RADIUS, 0.0, 0.0]])
            half = 0.5 * speed
            vel = jnp.stack([jnp.stack([half, 0.0 * half, 0.0 * half]),
                             jnp.stack([-half, 0.0 * half, 0.0 * half])])
            state = init_state(spec, params, pos, vel=vel)

            def body(s, _):
                return step(params, s), 2 * RADIUS - (s.pos[1, 0] - s.pos[0, 0])

            return jax.lax.scan(body, state, None, length=n_steps)

        return run

    final, overlap = _simulator(("pair", n_steps), make_run)(params, jnp.asarray(SPEEDS))
    out_speed = np.asarray(final.vel[:, 0, 0] - final.vel[:, 1, 0])  # approach speed
    return params.pp, np.asarray(overlap), out_speed, final, params


@pytest.mark.parametrize("simulate", [_simulate_wall, _simulate_pair], ids=["wall", "pair"])
@pytest.mark.slow
def test_restitution_and_duration_match_ode(simulate):
    law, overlap, out_speed, final, params = simulate(0.3, 700)
    for k, speed in enumerate(SPEEDS):
        restitution = abs(out_speed[k]) / speed
        assert out_speed[k] < 0  # it bounced back
        assert abs(restitution - 0.3) <= 0.003, (speed, restitution)
        t_ode, e_ode = _ode_impact(law, speed)
        assert abs(e_ode - 0.3) < 1e-6  # the force law itself gives e = 0.3 exactly
        duration = _crossings(overlap[k], DT_DEM)
        assert abs(duration / t_ode - 1) < 0.01, (speed, duration, t_ode)
    # Ledger: all the kinetic energy lost went into normal damping (no tangential motion).
    mass_eff = law.mass_eff
    lost = 0.5 * mass_eff * (np.asarray(SPEEDS) ** 2 - out_speed**2)
    diss = np.asarray(final.ledger.diss_pw[:, 0] + final.ledger.diss_pp[:, 0])
    np.testing.assert_allclose(diss, lost, rtol=1e-3)
    others = np.asarray(final.ledger.diss_pw[:, 1:]) + np.asarray(final.ledger.diss_pp[:, 1:])
    assert np.all(np.abs(others) < 1e-12)


@pytest.mark.parametrize("simulate", [_simulate_wall, _simulate_pair], ids=["wall", "pair"])
def test_elastic_duration_matches_hertz(simulate):
    # 700 steps as in the test above (one program for both; the contacts end by step 600, and
    # the balls then fly apart without gravity)
    law, overlap, out_speed, _, _ = simulate(1.0, 700)
    for k, speed in enumerate(SPEEDS):
        assert abs(abs(out_speed[k]) / speed - 1.0) < 1e-3
        duration = _crossings(overlap[k], DT_DEM)
        t_hertz = hertz_contact_time(law, speed)
        assert abs(duration / t_hertz - 1) < 0.01, (speed, duration, t_hertz)


def test_coulomb_limit_and_history_rules():
    """Sliding contacts carry exactly mu |F_n|; open contacts drop their history."""
    params = _params(0.3, plane_walls([[0.0, 0.0, 0.0]], [[0.0, -1.0, 0.0]]))
    law = params.pw
    normal = jnp.array([[0.0, -1.0, 0.0]] * 3)
    overlap = jnp.array([1e-6, 1e-6, -1e-7])
    arm = RADIUS - overlap / 2
    # contact 0 slides fast (Coulomb), contact 1 creeps (sticks), contact 2 is open.
    v_rel = jnp.array([[2.0, 0.0, 0.0], [1e-6, 0.0, 0.0], [1.0, 0.0, 0.0]])
    history = jnp.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [1e-7, 0.0, 0.0]])
    out = contact_forces(law, overlap, normal, arm, v_rel, jnp.zeros((3, 3)), history, DT_DEM)
    ft = np.linalg.norm(np.asarray(out.tangential), axis=1)
    fn = np.abs(np.asarray(out.normal_total))
    assert ft[0] == pytest.approx(law.friction * fn[0], rel=1e-12)
    assert ft[1] < law.friction * fn[1]
    assert bool(out.sliding[0]) and not bool(out.sliding[1])
    assert np.all(np.asarray(out.history)[2] == 0.0) and ft[2] == 0.0 and fn[2] == 0.0
    # The tangential force opposes the sliding direction and yields a torque about z.
    assert float(out.tangential[0, 0]) < 0
    assert float(out.torque_tangential[0, 2]) != 0.0


def test_history_rotation_keeps_length():
    """A history left out of the tangent plane is rotated into it with its length kept."""
    params = _params(1.0, plane_walls([[0.0, 0.0, 0.0]], [[0.0, -1.0, 0.0]]))
    tilt = np.deg2rad(10.0)
    normal = jnp.array([[np.sin(tilt), -np.cos(tilt), 0.0]])
    history = jnp.array([[1e-7, 0.0, 0.0]])
    out = contact_forces(params.pw, jnp.array([1e-6]), normal, jnp.array([RADIUS]),
                         jnp.zeros((1, 3)), jnp.zeros((1, 3)), history, DT_DEM)
    new = np.asarray(out.history)[0]
    assert np.linalg.norm(new) == pytest.approx(1e-7, rel=1e-9)
    assert abs(np.dot(new, np.asarray(normal)[0])) < 1e-20
