"""Sphere on an incline: rolling without slip and sliding, with tilted gravity.

The plane is the floor y = 0; gravity is tilted by theta in the x-y plane, so "down the slope"
is +x. A ball starting at rest at its static overlap must reach

- a = (5/7) g (sin theta - mu_r cos theta), rolling without slip (mu = 0.3, theta = 20 deg,
  mu_r = 0 and 0.045);
- a = g (sin theta - mu cos theta), sliding (mu = 0.1, theta = 30 deg, mu_r = 0),

within 1 %. The three cases run as one vmap over materials and gravity.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

import sgn_jax  # noqa: F401
from sgn_jax.dem import DEMSpec, init_state, make_dem_step, make_params, plane_wall_fn, plane_walls
from sgn_jax.motion import CircleMotion

RADIUS = 0.005
G = 9.81
DT_DEM = 9.5e-7
N_STEPS = 40_000  # 0.038 s
CASES = (  # (friction, rolling friction, theta deg, expected acceleration)
    (0.3, 0.0, 20.0, 5 / 7 * G * np.sin(np.deg2rad(20.0))),
    (0.3, 0.045, 20.0, 5 / 7 * G * (np.sin(np.deg2rad(20.0)) - 0.045 * np.cos(np.deg2rad(20.0)))),
    (0.1, 0.0, 30.0, G * (np.sin(np.deg2rad(30.0)) - 0.1 * np.cos(np.deg2rad(30.0)))),
)


def _params(friction, rolling, theta_deg):
    th = np.deg2rad(theta_deg)
    return make_params(
        RADIUS, 7700.0, young=2.05e9, poisson=0.235, restitution=0.3, friction=friction,
        rolling_friction=rolling, gravity=(G * np.sin(th), -G * np.cos(th), 0.0),
        geometry=plane_walls([[0.0, 0.0, 0.0]], [[0.0, -1.0, 0.0]]),
        motion=CircleMotion(rpm=0.0, amplitude=0.0),
    )


def test_incline_rolling_and_sliding():
    all_params = [_params(mu, mur, th) for mu, mur, th, _ in CASES]
    batched = jax.tree.map(lambda *x: jnp.stack([jnp.asarray(v) for v in x]), *all_params)
    spec = DEMSpec(n_balls=1, n_patches=1, dt_dem=DT_DEM)
    step = make_dem_step(spec, plane_wall_fn)

    def run(params):
        normal_force = -params.mass * params.gravity[1]
        law = params.pw
        overlap = (normal_force / (4 / 3 * law.young_eff * jnp.sqrt(law.radius_eff))) ** (2 / 3)
        pos = jnp.stack([0.0 * overlap, RADIUS - overlap, 0.0 * overlap])[None]
        state = init_state(spec, params, pos)

        def body(s, _):
            s = step(params, s)
            return s, (s.vel[0, 0], s.omega[0, 2], s.pos[0, 1])

        return jax.lax.scan(body, state, None, length=N_STEPS)[1]

    vx, wz, y = (np.asarray(a) for a in jax.jit(jax.vmap(run))(batched))
    t = (np.arange(N_STEPS) + 1) * DT_DEM
    late = t > 0.01
    for k, (_mu, _mur, _th, expected) in enumerate(CASES):
        accel = np.polyfit(t[late], vx[k, late], 1)[0]
        assert abs(accel / expected - 1) < 0.01, (CASES[k], accel, expected)
        slip = vx[k, -1] + wz[k, -1] * RADIUS  # contact-point velocity along x
        if k < 2:  # rolls without slip
            assert abs(slip) < 1e-3 * vx[k, -1], (k, slip, vx[k, -1])
        else:  # slides: friction mu N spins it up at 2.5 mu g cos(theta) / R
            mu, th = CASES[k][0], np.deg2rad(CASES[k][2])
            spin_accel = 2.5 * mu * G * np.cos(th)
            expected_slip = (expected - spin_accel) * t[-1]
            assert abs(slip / expected_slip - 1) < 0.01, (slip, expected_slip)
        assert np.all(y[k] < RADIUS) and np.all(y[k] > RADIUS - 1e-5)  # stays on the plane
