"""Numbers for the DEM validation table of docs/dem.md (its known-answer cases).

Prints markdown rows: normal impacts (restitution, contact duration vs an ODE solution of the
same law and vs Hertz for e = 1) and the incline cases. The assertions live in
tests/test_dem_contact.py and tests/test_dem_incline.py; this script only reports.

    python benchmarks/dem_validation.py
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from scipy.integrate import solve_ivp

import sgn_jax  # noqa: F401
from sgn_jax.dem import (
    DEMSpec,
    hertz_contact_time,
    init_state,
    make_dem_step,
    make_params,
    plane_wall_fn,
    plane_walls,
)
from sgn_jax.motion import CircleMotion
from sgn_jax.records.io_utils import git_commit

R = 0.005
DT = 9.5e-7
SPEEDS = (0.1, 0.5, 1.0, 2.0, 5.0)
STEEL = dict(young=2.05e9, poisson=0.235, friction=0.3, rolling_friction=0.045)
REST = CircleMotion(rpm=0.0, amplitude=0.0)


def ode(law, v):
    def rhs(_t, y):
        d = max(y[0], 0.0)
        gamma = law.damping_factor * np.sqrt(2 * law.young_eff * np.sqrt(law.radius_eff * d)
                                             * law.mass_eff)
        f = 4 / 3 * law.young_eff * np.sqrt(law.radius_eff) * d**1.5 + gamma * y[1]
        return [y[1], -f / law.mass_eff]

    def leave(_t, y):
        return y[0]

    leave.terminal, leave.direction = True, -1
    sol = solve_ivp(rhs, [0, 1], [0, v], method="DOP853", rtol=1e-12, atol=1e-16, events=leave,
                    first_step=1e-10)
    return sol.t_events[0][-1]


def impacts(kind, e):
    if kind == "wall":
        walls = plane_walls([[0, 0, 0]], [[0, -1, 0]])
        n = 1
    else:
        walls = plane_walls([[0, -1, 0]], [[0, -1, 0]])
        n = 2
    params = make_params(R, 7700.0, restitution=e, gravity=(0, 0, 0), geometry=walls,
                         motion=REST, **STEEL)
    spec = DEMSpec(n_balls=n, n_patches=1, dt_dem=DT)
    step = make_dem_step(spec, plane_wall_fn)

    def run(v):
        z = 0.0 * v
        if kind == "wall":
            pos, vel = jnp.array([[0.0, R, 0.0]]), jnp.stack([z, -v, z])[None]
        else:
            pos = jnp.array([[-R, 0.0, 0.0], [R, 0.0, 0.0]])
            vel = jnp.stack([jnp.stack([v / 2, z, z]), jnp.stack([-v / 2, z, z])])
        s0 = init_state(spec, params, pos, vel=vel)

        def body(s, _):
            ov = R - s.pos[0, 1] if kind == "wall" else 2 * R - (s.pos[1, 0] - s.pos[0, 0])
            return step(params, s), ov

        return jax.lax.scan(body, s0, None, length=700)

    final, ov = jax.jit(jax.vmap(run))(jnp.asarray(SPEEDS))
    ov = np.asarray(ov)
    if kind == "wall":
        out = np.asarray(final.vel[:, 0, 1])
    else:
        out = -np.asarray(final.vel[:, 0, 0] - final.vel[:, 1, 0])
    law = params.pw if kind == "wall" else params.pp
    rows = []
    for k, v in enumerate(SPEEDS):
        last = int(np.nonzero(ov[k] > 0)[0][-1])
        a, b = ov[k, last], ov[k, last + 1]
        duration = (last + a / (a - b)) * DT
        reference = ode(law, v) if e < 1 else hertz_contact_time(law, v)
        rows.append((kind, e, v, out[k] / v, duration, reference))
    return rows


def incline():
    """(mu, mu_r, theta, a measured, a expected) for the three incline cases."""
    g = 9.81
    cases = ((0.3, 0.0, 20.0, True), (0.3, 0.045, 20.0, True), (0.1, 0.0, 30.0, False))
    spec = DEMSpec(n_balls=1, n_patches=1, dt_dem=DT)
    step = make_dem_step(spec, plane_wall_fn)
    rows = []
    for mu, mur, theta, rolls in cases:
        th = np.deg2rad(theta)
        params = make_params(R, 7700.0, young=2.05e9, poisson=0.235, restitution=0.3,
                             friction=mu, rolling_friction=mur,
                             gravity=(g * np.sin(th), -g * np.cos(th), 0.0),
                             geometry=plane_walls([[0, 0, 0]], [[0, -1, 0]]), motion=REST)
        law = params.pw
        load = params.mass * g * np.cos(th)
        overlap = (load / (4 / 3 * law.young_eff * np.sqrt(law.radius_eff))) ** (2 / 3)
        s0 = init_state(spec, params, jnp.array([[0.0, R - overlap, 0.0]]))

        def body(s, _, p=params):
            s = step(p, s)
            return s, s.vel[0, 0]

        _, vx = jax.jit(lambda s, b=body: jax.lax.scan(b, s, None, length=40_000))(s0)
        t = (np.arange(40_000) + 1) * DT
        late = t > 0.01
        accel = np.polyfit(t[late], np.asarray(vx)[late], 1)[0]
        expected = (5 / 7 * g * (np.sin(th) - mur * np.cos(th)) if rolls
                    else g * (np.sin(th) - mu * np.cos(th)))
        rows.append((mu, mur, theta, "rolls" if rolls else "slides", accel, expected))
    return rows


def main() -> None:
    print(f"commit {git_commit()}, dt_dem = {DT:g} s\n")
    print("| contact | e (input) | v (m/s) | e measured | t_c DEM (us) | t_c reference (us) "
          "| rel. diff |")
    print("|---|---|---|---|---|---|---|")
    for kind in ("wall", "pair"):
        for e in (0.3, 1.0):
            for kind_, e_, v, e_meas, tc, ref in impacts(kind, e):
                ref_name = "ODE" if e_ < 1 else "Hertz"
                print(f"| {kind_} | {e_} | {v} | {e_meas:.4f} | {tc * 1e6:.2f} | "
                      f"{ref * 1e6:.2f} ({ref_name}) | {tc / ref - 1:+.2%} |")
    print("\n| mu | mu_r | theta (deg) | motion | a measured (m/s2) | a expected (m/s2) | rel. diff |")
    print("|---|---|---|---|---|---|---|")
    for mu, mur, theta, kind, accel, expected in incline():
        print(f"| {mu} | {mur} | {theta} | {kind} | {accel:.4f} | {expected:.4f} | "
              f"{accel / expected - 1:+.3%} |")


if __name__ == "__main__":
    main()
