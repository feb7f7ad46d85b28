"""The contact surrogate's collision ledger (sgn_jax.surrogate.collisions), recorded in the rollout.

- the events' energies add up to the model's own dissipation ledger (diss_pp + diss_pw of the
  rollout's steps), per pair kind, and a rollout in two calls gives the same events as one;
- a head-on impact of two balls is one event with the approach speed of the inputs;
- more events than the capacity raise, naming it;
- permuting the balls permutes the events;
- ``run_rollout(..., collisions=True)`` writes the table into a prediction that reads back.
"""

import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_contact import random_params  # random output layers: every impulse nonzero

from sgn_jax.motion import CircleMotion
from sgn_jax.surrogate.collisions import CollisionCapacityError
from sgn_jax.surrogate.contact import ContactNet, ContactPhysics
from sgn_jax.surrogate.graph import GraphSpec, Window, build_graph, with_spins
from sgn_jax.surrogate.rollout import make_rollout, make_rollout_advance

R, DT, W = 0.005, 1e-4, 3
GRAPH_SPEC = GraphSpec(n_particles=5, window=W, ball_radius=R, dt=DT, pp_skin=1.5e-3,
                 phi_pw=-0.0052, pp_pair_capacity=10)
MOTION = CircleMotion(rpm=300.0, amplitude=0.017)


def floor_query(height=0.0):
    """A flat floor y = height (+ the jar offset's y), the cavity above it."""
    def query(sdf, points, offset):
        del sdf
        return -(points[:, 1] - offset[1] - height), jnp.broadcast_to(
            jnp.array([0.0, -1.0, 0.0]), points.shape)
    return query


def cluster_window(rng, order=None):
    """5 balls: a touching cluster above the floor and one ball on it, moving (with spins)."""
    centres = np.array([[0.0, 0.0102, 0.0], [0.0099, 0.0102, 0.0], [0.0, 0.0102, 0.0099],
                        [0.005, 0.0190, 0.005], [0.03, 0.00499, 0.0]])
    vel = rng.normal(0.0, 0.3, (1, 5, 3)) + rng.normal(0.0, 0.02, (W + 1, 5, 3))
    pos = centres[None] + np.cumsum(vel * DT, axis=0) - (vel * DT).sum(0)[None]
    order = np.arange(5) if order is None else np.asarray(order)
    return with_spins(Window(positions=jnp.asarray(pos[:, order]), offsets=jnp.zeros((W, 3)),
                             offset_velocities=jnp.zeros((W, 3)),
                             frequency_hz=jnp.asarray(5.0)))


def random_net(window, spin=False, seed=4):
    """A contact model whose output layers are random: every impulse nonzero and arbitrary."""
    phys = ContactPhysics(ball_radius=R, dt=DT, window=W, history=3, gate_margin=2e-4,
                          rolling_friction=0.045)
    net = ContactNet(physics=phys, hidden=32, mlp_layers=3, spin=spin)
    graph, _ = build_graph(window, None, GRAPH_SPEC, floor_query())
    return net, random_params(net, graph, seed)


@pytest.fixture(scope="module")
def cluster_run():
    """40 steps of the cluster in one call: (net, params, window, rollout, result)."""
    window = cluster_window(np.random.default_rng(5))
    net, params = random_net(window)
    rollout = make_rollout(GRAPH_SPEC, net, 40, 10, query=floor_query(), snap_back=False,
                           collisions=True, collision_capacity=64)
    result = jax.device_get(rollout(params, None, window, MOTION, None, 0.0))
    return net, params, window, rollout, result


def test_event_energies_add_up_to_the_models_own_ledger(cluster_run):
    *_, result = cluster_run
    events = result.collision_arrays()
    energy, wall = events["collision_energy"], events["collision_wall"]
    assert energy.shape == (len(wall), 5) and len(wall) >= 4
    assert wall.any() and (~wall).any()
    assert np.all(energy[:, 2:] == 0.0)
    diss_pp, diss_pw = np.asarray(result.steps.diss_pp), np.asarray(result.steps.diss_pw)
    scale = np.abs(diss_pp).sum() + np.abs(diss_pw).sum()
    # with what below-floor steps left pending at the end (reported apart, small)
    pending = result.collision_pending().sum()
    assert abs(pending) <= 0.01 * scale
    assert energy.sum() + pending == pytest.approx(diss_pp.sum() + diss_pw.sum(),
                                                   abs=1e-6 * scale)
    assert energy[~wall].sum() == pytest.approx(diss_pp.sum(), abs=0.01 * scale)
    assert energy[wall].sum() == pytest.approx(diss_pw.sum(), abs=0.01 * scale)
    # both parts carry energy; durations are whole steps; m* of a pair and of a wall
    assert np.abs(energy[:, 0]).sum() > 0 and np.abs(energy[:, 1]).sum() > 0
    steps = events["collision_duration_s"] / DT
    np.testing.assert_allclose(steps, np.round(steps), atol=1e-9)
    assert np.all(steps >= 1)
    m = ContactPhysics().ball_mass
    np.testing.assert_allclose(events["collision_mass_eff"], np.where(wall, m, m / 2),
                               rtol=1e-6)
    assert np.all(events["collision_partner"][wall] == 0)
    assert np.all(events["collision_partner"][~wall] > events["collision_ball"][~wall])
    # the cluster starts in contact: its first events began before the rollout (bit 0)
    assert np.any(events["collision_flags"] & 1)


def test_a_rollout_in_chunks_records_the_events_of_one_call(cluster_run):
    """Ten calls of 4 steps, drained after each (as run_rollout does), give the events of one
    call of 40; a call that ends inside events flushes them with flags bit 1."""
    from sgn_jax.surrogate.collisions import concat_tables
    from sgn_jax.surrogate.rollout import init_state

    net, params, window, _, whole = cluster_run
    advance = make_rollout_advance(GRAPH_SPEC, net, 4, 2, query=floor_query(), snap_back=False,
                                   collisions=True, collision_capacity=64)
    state = init_state(window, MOTION, 0.0, DT, collision_capacity=64)
    tables = []
    for call in range(10):
        part = jax.device_get(advance(params, None, state, MOTION, None, 0.0))
        tables.append(part.collision_arrays(flush=call == 9))
        if call == 0:
            flushed = part.collision_arrays(flush=True)
            still_open = (flushed["collision_flags"] & 2) > 0
            assert still_open.any()
            np.testing.assert_allclose(flushed["collision_duration_s"][still_open],
                                       4 * DT - flushed["collision_start_s"][still_open])
        state = part.final.replace(collisions=part.final.collisions.replace(count=np.int32(0)))
    joined, expected = concat_tables(tables), whole.collision_arrays()
    assert joined.keys() == expected.keys()
    for key, value in expected.items():
        np.testing.assert_allclose(joined[key], value, rtol=1e-6, atol=1e-12, err_msg=key)


def test_overflow_raises_naming_the_capacity(cluster_run):
    net, params, window, _, result = cluster_run
    n_closed = len(result.collision_arrays(flush=False)["collision_ball"])
    assert n_closed >= 2
    rollout = make_rollout(GRAPH_SPEC, net, 40, 10, query=floor_query(), snap_back=False,
                           collisions=True, collision_capacity=1)
    small = jax.device_get(rollout(params, None, window, MOTION, None, 0.0))
    with pytest.raises(CollisionCapacityError, match=r"collision_capacity = 1\b.*raise it"):
        small.collision_arrays()
    with pytest.raises(CollisionCapacityError, match="integer >= 1"):
        make_rollout(GRAPH_SPEC, net, 10, 10, collisions=True, collision_capacity=0)


def test_permuted_balls_give_the_permuted_events(cluster_run):
    _, params, _, rollout, result = cluster_run
    order = np.array([3, 0, 4, 1, 2])   # new ball k is old ball order[k]
    window = cluster_window(np.random.default_rng(5), order)
    permuted = jax.device_get(rollout(params, None, window, MOTION, None, 0.0)).collision_arrays()

    def keyed(events, old_of_new):
        rows = {}
        for k in range(len(events["collision_ball"])):
            wall = bool(events["collision_wall"][k])
            a = int(old_of_new[events["collision_ball"][k]])
            b = -1 if wall else int(old_of_new[events["collision_partner"][k]])
            key = (min(a, b) if not wall else a, max(a, b), round(events["collision_start_s"][k]
                                                                  / DT))
            rows[key] = np.concatenate([[events["collision_duration_s"][k],
                                         events["collision_impact_normal"][k],
                                         events["collision_peak_force"][k]],
                                        events["collision_energy"][k, :2]])
        return rows

    a, b = keyed(result.collision_arrays(), np.arange(5)), keyed(permuted, order)
    assert a.keys() == b.keys()
    for key in a:
        np.testing.assert_allclose(b[key], a[key], rtol=1e-4, atol=1e-9, err_msg=str(key))


def head_on(speed, n_samples=12):
    """Two balls 0.1 mm apart along x closing at ``speed`` each (2 speed together), far above
    the floor, sampled at DT: positions (n_samples, 2, 3)."""
    t = (np.arange(n_samples) - (n_samples - 1)) * DT
    x0 = R + 5e-5 - speed * t          # ball 0 at -x0, ball 1 at +x0
    pos = np.zeros((n_samples, 2, 3))
    pos[:, 0, 0], pos[:, 1, 0] = -x0, x0
    pos[:, :, 1] = 0.05
    return pos


@pytest.mark.slow
def test_a_head_on_impact_is_one_event_with_the_approach_speed_of_its_inputs():
    """An untrained model (the same impulse, 0.21 m/s, on every acting contact): the pair acts
    from the step its gap can close until it has separated, one event."""
    spec = GraphSpec(n_particles=2, window=W, ball_radius=R, dt=DT, pp_skin=1.5e-3,
                     phi_pw=-0.0052, pp_pair_capacity=2)
    pos = head_on(0.4)[-(W + 1):]
    window = with_spins(Window(positions=jnp.asarray(pos), offsets=jnp.zeros((W, 3)),
                               offset_velocities=jnp.zeros((W, 3)),
                               frequency_hz=jnp.asarray(0.0)))
    phys = ContactPhysics(ball_radius=R, dt=DT, window=W, history=3, gravity=(0.0, 0.0, 0.0))
    net = ContactNet(physics=phys, hidden=16, mlp_layers=2)
    params = net.init(jax.random.PRNGKey(0), build_graph(window, None, spec, floor_query())[0])
    rollout = make_rollout(spec, net, 30, 10, query=floor_query(), snap_back=False,
                           collisions=True, collision_capacity=8)
    result = jax.device_get(rollout(params["params"], None, window,
                                    CircleMotion(rpm=0.0, amplitude=0.0), None, 0.0))
    events = result.collision_arrays()
    assert len(events["collision_ball"]) == 1
    assert (events["collision_ball"][0], events["collision_partner"][0]) == (0, 1)
    assert not events["collision_wall"][0] and events["collision_flags"][0] == 0
    assert events["collision_impact_normal"][0] == pytest.approx(0.8, rel=1e-5)
    assert events["collision_impact_tangential"][0] == pytest.approx(0.0, abs=1e-6)
    assert events["collision_mass_eff"][0] == pytest.approx(phys.ball_mass / 2, rel=1e-6)
    assert events["collision_start_s"][0] == pytest.approx(0.0, abs=1e-12)   # gap < u dt
    # du_n = 0.3 softplus(0) per step: 0.8 m/s of approach needs 4 steps to turn
    assert 4 <= round(events["collision_duration_s"][0] / DT) <= 8
    assert events["collision_peak_force"][0] == pytest.approx(
        phys.ball_mass / 2 * 0.3 * np.log(2.0) / DT, rel=1e-5)
    total = float(np.sum(result.steps.diss_pp))
    assert events["collision_energy"][0].sum() + result.collision_pending().sum() == \
        pytest.approx(total, rel=1e-5)
    # the energy is all in the normal part: a head-on impulse has no tangential part
    assert abs(events["collision_energy"][0, 1]) <= 1e-6 * abs(total)


@pytest.mark.slow
def test_run_rollout_writes_the_collision_table_into_the_prediction(tmp_path):
    """The shipped contact model on a head-on pair (the public path: run_rollout, as
    `sgn-jax rollout --collisions`); the prediction reads back with the table."""
    from sgn_jax.motion import offset, velocity
    from sgn_jax.pipelines.configure import motion_from_config
    from sgn_jax.pipelines.rollout_run import run_rollout
    from sgn_jax.records.prediction import load_prediction
    from sgn_jax.records.shipped_models import load_surrogate

    model = load_surrogate()
    dt = float(model.config.dem.dt)
    t = np.arange(12) * dt
    motion = motion_from_config(model.config.motion)
    jar, jar_velocity = np.asarray(offset(motion, t)), np.asarray(velocity(motion, t))
    # in the jar's frame: 23.5 mm above its floor on its axis (20 mm from every wall), each
    # ball at 0.5 m/s towards the other, 0.2 mm apart at the start
    x = R + 1e-4 + 0.5 * (t[-1] - t)
    pos = np.zeros((12, 2, 3))
    pos[:, 0, 0], pos[:, 1, 0], pos[:, :, 1] = -x, x, 0.0235
    traj = types.SimpleNamespace(pos=pos + jar[:, None], t=t, offset=jar,
                                 offset_vel=jar_velocity, meta={"dt": dt},
                                 omega=np.zeros((12, 2, 3)))
    out = tmp_path / "pred.npz"
    summary = run_rollout(model, traj, 11, 0.004, out, progress=False, collisions=True,
                          collision_capacity=16)
    pred = load_prediction(out)
    assert summary["collision_events"] == pred.collision_ball.size == 1
    assert (pred.collision_ball[0], pred.collision_partner[0]) == (0, 1)
    assert not pred.collision_wall[0] and pred.collision_flags[0] == 0
    # the contact begins when the 0.2 mm gap has closed at 1 m/s (the gated steps before,
    # below the force floor, are no contact yet)
    assert pred.collision_start_s[0] == pytest.approx(t[-1] + 2e-4, abs=dt + 1e-12)
    assert pred.collision_impact_normal[0] == pytest.approx(1.0, rel=1e-4)
    # a trained model dissipates, less than the impact's kinetic energy, mostly normal
    stress = 0.5 * pred.collision_mass_eff[0] * 1.0 ** 2
    assert 0 < pred.collision_energy[0].sum() < stress
    assert pred.collision_energy[0, 0] > 0.9 * pred.collision_energy[0].sum()
    total = pred.diss_pp_model.sum() + pred.diss_pw_model.sum()
    pending = sum(pred.meta["collisions"]["pending_J"])
    assert pred.collision_energy.sum() + pending == pytest.approx(total, rel=1e-5)
    assert pred.meta["collisions"]["capacity"] == 16


@pytest.mark.slow
def test_an_ensemble_records_each_packings_events(contact_short_packings):
    """rollout_ensemble(collisions=True) of the shipped model: each packing's events add up to
    its own ledger (the standard case: 24 balls in their settled bed)."""
    from sgn_jax.pipelines.studies import rollout_ensemble

    model, cfg, packings = contact_short_packings
    result = rollout_ensemble(model, cfg, packings, 0.01, batching="map", collisions=True,
                              collision_capacity=512)
    for k in range(2):
        events = result.collision_arrays(packing=k)
        ledger = float(np.sum(result.steps.diss_pp[k]) + np.sum(result.steps.diss_pw[k]))
        assert events["collision_ball"].size >= 3   # the bed: its contacts last
        pending = result.collision_pending(packing=k).sum()
        assert events["collision_energy"].sum() + pending == pytest.approx(ledger, rel=1e-5)
    with pytest.raises(Exception, match="packing=k"):
        result.collision_arrays()


def test_the_cli_refuses_a_capacity_below_one(tmp_path, capsys):
    from sgn_jax.cli import main

    code = main(["rollout", "--init", str(tmp_path / "none.npz"), "--duration", "0.01",
                 "--out", str(tmp_path / "p.npz"), "--collisions", "--collision-capacity", "0"])
    assert code == 2
    assert "--collision-capacity must be >= 1" in capsys.readouterr().err


@pytest.mark.slow
def test_a_design_study_gives_a_collision_statistic_and_its_gradient(contact_short_packings):
    """sj.design_study's collision statistics: events of the measurement interval only, the
    estimate the packings' mean, a finite central-difference gradient; a jar parameter and an
    unknown statistic refused."""
    import sgn_jax.api as sj
    from sgn_jax.analysis.collisions import collision_statistics
    from sgn_jax.design import DesignError

    model, cfg, packings = contact_short_packings
    study = sj.design_study(model, cfg, ["motion.rpm"], packings, duration=0.04, burn_in=0.02,
                            n_segments=2)
    tables = study.collision_tables()
    t0 = float(packings.t0)
    assert len(tables) == len(packings)
    for table in tables:
        assert table.record_duration_s == pytest.approx(0.02)
        assert np.all(table.start_s >= t0 + 0.02 - 1e-12) and np.all(table.start_s < t0 + 0.04)
    est = study.collision_estimate("frequency_per_ball_hz[all]", steps={"motion.rpm": 60.0})
    per_packing = [collision_statistics(t)["frequency_per_ball_hz[all]"] for t in tables]
    assert est["value"] == pytest.approx(np.mean(per_packing), rel=1e-9)
    assert est["value"] > 0 and np.isfinite(est["gradient"]["motion.rpm"]["value"])
    assert est["gradient"]["motion.rpm"]["step"] == 60.0
    with pytest.raises(DesignError, match="scalar collision statistic"):
        study.collision_estimate("dissipation_power_W")
    jar_study = sj.design_study(model, cfg, ["jar.radius"], packings, duration=0.04,
                                burn_in=0.02, n_segments=2, start="packing")
    with pytest.raises(DesignError, match="motion parameters"):
        jar_study.collision_tables()
