"""A new contact law added in one file (tests/extensions/linear_spring_dashpot.py), run through
the DEM and the surrogate rollout with nothing else changed (docs/dem.md, "Adding a contact law").

(a) Head-on impacts (ball-ball and ball-wall, no gravity) at several speeds: the restitution is
    the analytic exp(-pi zeta / sqrt(1 - zeta^2)) of a linear spring-dashpot, the contact lasts
    pi / omega_d at every speed (a Hertz contact would get shorter as v^(-1/5)), and the energy
    ledger, with the law's own elastic energy, closes at every step.
(b) The standard jar case, selected by ``[dem] contact_law = "linear_spring_dashpot"``, through
    the DEM driver (settling, motion, run checks, dataset file) and then the rollout driven by
    the replay predictor, which reproduces the DEM positions to float64 rounding.
"""

from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import sgn_jax  # noqa: F401  (x64)
from sgn_jax.config import ConfigError, replace_section
from sgn_jax.dem import (
    DEMError,
    DEMSpec,
    contact_law,
    contact_law_names,
    init_state,
    ledger_balance,
    make_dem_step,
    make_params,
    plane_wall_fn,
    plane_walls,
)
from sgn_jax.motion import CircleMotion
from sgn_jax.surrogate.graph import dissipation_per_interval, targets_from_arrays
from sgn_jax.surrogate.rollout import ReplayTable, make_rollout, replay_predictor

RADIUS = 0.005
DT_DEM = 2.5e-7  # 550-650 steps per contact
SPEEDS = (0.1, 0.5, 1.0, 2.0, 5.0)
STEEL = dict(young=2.05e9, poisson=0.235, friction=0.3, rolling_friction=0.045)
RESTITUTION = 0.3
N_STEPS = 1000


def _load_extension():
    """Import the extension by path (tests/ is not a package), once per process."""
    name = "sgn_jax_tests_ext_linear_spring_dashpot"
    if name not in sys.modules:
        path = Path(__file__).parent / "extensions" / "linear_spring_dashpot.py"
        spec = importlib.util.spec_from_file_location(name, path)
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
    return sys.modules[name]


EXT = _load_extension()
LAW = EXT.LINEAR_SPRING_DASHPOT


def test_the_law_is_registered_and_selectable_by_name():
    assert contact_law("linear_spring_dashpot") is LAW
    assert {"hertz_mindlin", "linear_spring_dashpot"} <= set(contact_law_names())
    spec = DEMSpec(n_balls=1, n_patches=1, dt_dem=DT_DEM, contact_law="linear_spring_dashpot")
    assert spec.contact_law is LAW
    assert DEMSpec(n_balls=1, n_patches=1, dt_dem=DT_DEM).contact_law.name == "hertz_mindlin"
    with pytest.raises(DEMError, match="unknown contact law 'no_such_law'; registered: "):
        DEMSpec(n_balls=1, n_patches=1, dt_dem=DT_DEM, contact_law="no_such_law")


def _impact(kind: str):
    """Head-on impacts at SPEEDS (vmapped): per step the overlap and the ledger balance."""
    if kind == "wall":
        walls = plane_walls([[0.0, 0.0, 0.0]], [[0.0, -1.0, 0.0]])
        pos = jnp.array([[0.0, RADIUS, 0.0]])
        n = 1
    else:
        walls = plane_walls([[0.0, -1.0, 0.0]], [[0.0, -1.0, 0.0]])  # never touched
        pos = jnp.array([[-RADIUS, 0.0, 0.0], [RADIUS, 0.0, 0.0]])
        n = 2
    params = make_params(RADIUS, 7700.0, restitution=RESTITUTION, gravity=(0.0, 0.0, 0.0),
                         geometry=walls, motion=CircleMotion(rpm=0.0, amplitude=0.0),
                         contact_law=LAW, **STEEL)
    spec = DEMSpec(n_balls=n, n_patches=1, dt_dem=DT_DEM, contact_law=LAW)
    step = make_dem_step(spec, plane_wall_fn)

    def approach(s):  # approach speed (> 0 closing)
        return -s.vel[0, 1] if kind == "wall" else s.vel[0, 0] - s.vel[1, 0]

    def overlap(s):
        return RADIUS - s.pos[0, 1] if kind == "wall" else 2 * RADIUS - (s.pos[1, 0] - s.pos[0, 0])

    def run(speed):
        if kind == "wall":
            vel = jnp.zeros((1, 3)).at[0, 1].set(-speed)
        else:
            vel = jnp.zeros((2, 3)).at[0, 0].set(0.5 * speed).at[1, 0].set(-0.5 * speed)
        state = init_state(spec, params, pos, vel=vel)

        def body(s, _):
            s = step(params, s)
            return s, (overlap(s), ledger_balance(spec, plane_wall_fn, params, s))

        final, (ov, balance) = jax.lax.scan(body, state, None, length=N_STEPS)
        return approach(final), ov, balance, final.ledger

    out, ov, balance, ledger = jax.device_get(jax.jit(jax.vmap(run))(jnp.asarray(SPEEDS)))
    law_params = params.pw if kind == "wall" else params.pp
    return law_params, out, ov, balance, ledger


@pytest.mark.parametrize("kind", ["wall", "pair"])
def test_linear_impact_matches_the_analytic_restitution_duration_and_ledger(kind):
    p, out_speed, overlap, balance, ledger = _impact(kind)
    zeta = p.zeta
    assert zeta == pytest.approx(EXT.damping_ratio(RESTITUTION), rel=1e-12)
    e_analytic = math.exp(-math.pi * zeta / math.sqrt(1 - zeta**2))
    assert e_analytic == pytest.approx(RESTITUTION, rel=1e-12)
    omega_d = math.sqrt(p.stiffness_n / p.mass_eff) * math.sqrt(1 - zeta**2)
    t_analytic = math.pi / omega_d
    assert t_analytic / DT_DEM > 100  # resolved

    speeds = np.asarray(SPEEDS)
    restitution = -out_speed / speeds  # out_speed < 0: separating
    # The damping acts with the velocity at the start of the step: an O(zeta omega dt) error,
    # here 1e-4 (wall) and 2e-3 (pair) relative.
    np.testing.assert_allclose(restitution, e_analytic, rtol=3e-3)
    # Linear: the whole impact scales with the speed, so e is the same at every speed.
    np.testing.assert_allclose(restitution, restitution[0], rtol=1e-9)
    # Duration: the steps with overlap > 0, the closing crossing interpolated (the impact starts
    # at overlap 0 at t = 0).
    for k in range(len(SPEEDS)):
        inside = np.nonzero(overlap[k] > 0)[0]
        last = int(inside[-1])
        assert last + 1 < N_STEPS and np.all(np.diff(inside) == 1)  # one contact, then free
        a, b = overlap[k, last], overlap[k, last + 1]
        duration = (last + 1 + a / (a - b)) * DT_DEM
        assert duration == pytest.approx(t_analytic, rel=5e-3), (SPEEDS[k], duration)
        # The peak overlap scales linearly with the speed (Hertz: as v^0.8).
        assert overlap[k].max() / speeds[k] == pytest.approx(
            overlap[0].max() / speeds[0], rel=1e-3)

    # Ledger with the law's elastic energy 1/2 k_n d^2: KE + E_el + dissipation - initial is
    # the integration error of the spring alone: in mid-contact the bounded O(omega dt)
    # oscillation of symplectic Euler (omega dt ~ 0.006 here), after the impact a residual far
    # below the 91 % of the kinetic energy that was dissipated. A law whose energy is not the
    # integral of its force (e.g. Hertz energy with linear forces: 40 % off at the peak
    # overlap) fails both.
    ke0 = 0.5 * p.mass_eff * speeds**2
    drift = np.abs(balance - balance[:, :1])
    assert np.all(drift.max(axis=1) < 2e-3 * ke0), drift.max(axis=1) / ke0
    assert np.all(drift[:, -1] < 1e-4 * ke0), drift[:, -1] / ke0
    diss = ledger.diss_pw[:, 0] + ledger.diss_pp[:, 0]
    np.testing.assert_allclose(diss, 0.5 * p.mass_eff * (speeds**2 - out_speed**2), rtol=1e-4)
    others = np.concatenate([ledger.diss_pw[:, 1:], ledger.diss_pp[:, 1:]], axis=1)
    assert np.all(np.abs(others) < 1e-12 * ke0[:, None])


def test_an_unknown_law_in_a_config_names_the_key():
    from sgn_jax.config import builtin_config_path, load_config
    from sgn_jax.pipelines.configure import params_from_config

    cfg = replace_section(load_config(builtin_config_path("emax_300rpm")), "dem",
                          contact_law="no_such_law")
    with pytest.raises(ConfigError, match=r"\[dem\] contact_law: unknown contact law "
                                          r"'no_such_law'; registered: .*linear_spring_dashpot"):
        params_from_config(cfg)


START = 7  # the first sample with a full window (W = 7)
REPLAY_STEPS = 30


@pytest.fixture(scope="module")
def linear_dem(tmp_path_factory):
    """The standard case with the linear law: 0.05 s settling, 0.004 s of motion (41 samples),
    through the DEM driver and the dataset file."""
    from sgn_jax.config import builtin_config_path, load_config
    from sgn_jax.pipelines.configure import (
        graph_spec_from_config,
        motion_from_config,
        sdf_grid_from_config,
    )
    from sgn_jax.pipelines.dem_run import run_dem
    from sgn_jax.records.trajectory import load_trajectory, save_trajectory

    cfg = load_config(builtin_config_path("emax_300rpm"))
    cfg = replace_section(cfg, "dem", settle_time=0.05, contact_law="linear_spring_dashpot")
    run = run_dem(cfg, duration=0.004, progress=False)
    path = tmp_path_factory.mktemp("dem") / "dem.npz"
    save_trajectory(path, run.arrays, run.meta)
    traj = load_trajectory(path)
    spec = graph_spec_from_config(traj.config)
    return traj, spec, sdf_grid_from_config(traj.config), motion_from_config(traj.config.motion)


@pytest.mark.slow
def test_linear_law_runs_in_the_jar_and_the_replay_rollout_reproduces_it(linear_dem):
    traj, spec, grid, motion = linear_dem
    from sgn_jax.pipelines.rollout_run import initial_window

    assert traj.config.dem.contact_law == "linear_spring_dashpot"
    assert len(traj.pos) >= START + REPLAY_STEPS + 1
    window = slice(START, START + REPLAY_STEPS + 1)
    # Balls touch the wall and each other over the replayed window (so the law matters).
    assert traj.arrays["pw_contact"][window].sum() > 0
    assert traj.arrays["n_pp_contacts"][window].sum() > 0
    assert traj.arrays["e_elastic"][window].max() > 0
    # The DEM's ledger closes with the law's elastic energy (a Hertz energy with linear forces
    # would not): the residual is tiny against the energy dissipated.
    dissipated = traj.cumulative_dissipation("all", "all")[-1]
    assert dissipated > 0
    assert np.abs(traj.energy_balance()).max() < 1e-3 * dissipated

    ends = START + np.arange(REPLAY_STEPS)
    accel, de = targets_from_arrays(traj.pos, dissipation_per_interval(traj), ends, spec.dt)
    table = ReplayTable(accel=jnp.asarray(accel), dE=jnp.asarray(de))
    rollout = make_rollout(spec, replay_predictor(), REPLAY_STEPS, 1, snap_back=False)
    res = jax.device_get(rollout(table, None, initial_window(traj, START, spec.window), motion,
                                 grid, traj.t[START]))
    assert np.abs(res.positions - traj.pos[window]).max() < 1e-12
    np.testing.assert_array_equal(res.steps.energy_cum, np.cumsum(de))
    assert res.steps.energy_cum[-1] > 0  # the linear law's dissipation is what was replayed
    assert res.steps.n_outside.sum() == 0 and res.steps.overflow.sum() == 0
