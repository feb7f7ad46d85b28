"""The charge-conditioned contact model (kind "contact_charge"): the physics built into it,
for balls of several sizes, masses and materials.

On an untrained network with random output layers (every impulse nonzero and arbitrary):
rotation and permutation equivariance with two ball sizes, momentum and angular momentum of
ball-ball impulses between unequal balls, the inputs of the same impact of a 6 mm and a 15 mm
ball, finite outputs for a padded mixture, and the graph's edges by each ball's own radius.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sgn_jax.dem.charge import BallClass, Charge, Material
from sgn_jax.dem.contact import head_on_peak_overlap, make_contact_law
from sgn_jax.surrogate.contact_charge import (
    GAP_COARSE,
    ChargePhysics,
    ContactChargeNet,
    ball_charge,
)
from sgn_jax.surrogate.graph import GraphSpec, Window, build_graph
from sgn_jax.surrogate.model import model_factory

DT, W = 1e-4, 3
STEEL = Material("steel", young=2.05e9, poisson=0.235, restitution=0.3, friction=0.3,
                 rolling_friction=0.045)
ZIRCONIA = Material("zirconia", young=1.6e9, poisson=0.3, restitution=0.5, friction=0.2,
                    rolling_friction=0.02)
# 3 steel balls of 10 mm and 2 zirconia balls of 6 mm (balls 3 and 4) in a steel jar
MIX = Charge(classes=(BallClass(3, 0.005, 7700.0, STEEL), BallClass(2, 0.003, 6000.0, ZIRCONIA)),
             wall=STEEL)
PHYS = ChargePhysics(dt=DT, window=W, history=3, gate_margin=2e-4, overlap_limit=5e-5,
                     overlap_law_factor=1.5, overlap_sweeps=2, friction_sweeps=3)


def spec(n):
    return GraphSpec(n_particles=n, window=W, ball_radius=0.005, dt=DT, pp_skin=1.5e-3,
                     phi_pw=-0.006, pp_pair_capacity=12)


def floor_query(up, height=0.0):
    """A flat floor ``height`` below the jar offset with unit normal ``up`` (into the cavity)."""
    up = jnp.asarray(up, jnp.float64)

    def query(sdf, points, offset):
        del sdf
        h = jnp.sum((points - offset) * up, axis=-1) + height
        return -h, jnp.broadcast_to(-up, points.shape)

    return query


# centres: two 10 mm balls on the floor overlapping, a 10 mm ball on them, a 6 mm ball against
# ball 0 and one against ball 1 (each pair 0.1 mm into contact)
CENTRES = np.array([[0.0, 0.0050, 0.0], [0.0099, 0.0050, 0.0], [0.00495, 0.01347, 0.0],
                    [0.0, 0.0050, 0.0079], [0.0099, 0.0050, -0.0079]])


def scene(rng, rotation=None, n_total=5, lift=0.0):
    """The mixture, moving (velocities ~0.3 m/s, spins ~50 rad/s), padded to ``n_total``."""
    n = len(CENTRES)
    vel = rng.normal(0.0, 0.3, (1, n, 3)) + rng.normal(0.0, 0.02, (W + 1, n, 3))
    pos = CENTRES[None] + np.array([0.0, lift, 0.0]) + np.cumsum(vel * DT, axis=0) \
        - (vel * DT).sum(0)[None]
    spins = rng.normal(0.0, 50.0, (n, 3))
    if n_total > n:   # absent balls parked far from everything, at rest
        far = np.array([0.5, 0.5, 0.5]) + 0.05 * np.arange(n_total - n)[:, None]
        pos = np.concatenate([pos, np.broadcast_to(far, (W + 1, n_total - n, 3))], axis=1)
        spins = np.concatenate([spins, np.zeros((n_total - n, 3))])
    offsets = np.cumsum(rng.normal(0.0, 0.1, (W, 3)) * DT, axis=0) * np.array([1, 0, 1])
    offset_vel = rng.normal(0.0, 0.2, (W, 3)) * np.array([1, 0, 1])
    rot = np.eye(3) if rotation is None else np.asarray(rotation)
    return Window(positions=jnp.asarray(pos @ rot.T), offsets=jnp.asarray(offsets @ rot.T),
                  offset_velocities=jnp.asarray(offset_vel @ rot.T),
                  frequency_hz=jnp.asarray(5.0), spins=jnp.asarray(spins @ rot.T),
                  charge=ball_charge(MIX, n_balls=n_total, classes=3))


def random_params(net, graph, seed=0, jit=False):
    init = jax.jit(net.init) if jit else net.init   # jit: one program instead of eager ops
    params = init(jax.random.PRNGKey(seed), graph)["params"]
    key = jax.random.PRNGKey(seed + 1)

    def perturb(path, leaf):
        nonlocal key
        key, sub = jax.random.split(key)
        if path[-1].key == "kernel" and leaf.shape[-1] == 2:
            return 0.5 * jax.random.normal(sub, leaf.shape, leaf.dtype)
        return leaf

    return jax.tree_util.tree_map_with_path(perturb, params)


def net_with(gravity=(0.0, -9.81, 0.0), spin=True, **physics):
    phys = dataclasses.replace(PHYS, gravity=tuple(float(g) for g in gravity), **physics)
    return ContactChargeNet(physics=phys, hidden=32, mlp_layers=3, spin=spin)


def terms_of(window, up=(0.0, 1.0, 0.0), gravity=(0.0, -9.81, 0.0), params=None, spin=True,
             floor_height=0.0, **physics):
    n = window.positions.shape[1]
    graph, _ = build_graph(window, None, spec(n), floor_query(up, floor_height))
    net = net_with(gravity, spin, **physics)
    params = random_params(net, graph) if params is None else params
    return net.apply({"params": params}, graph, method=ContactChargeNet.step_terms), params, graph


def test_the_kind_is_registered_and_builds_from_the_whole_config():
    from sgn_jax.api import load_config, replace_section

    cfg = replace_section(load_config("emax_300rpm"), "model", kind="contact_charge", hidden=16,
                          mlp_layers=3)
    model = model_factory("contact_charge").build_model(cfg)
    assert isinstance(model, ContactChargeNet) and model.physics.dt == cfg.dem.dt


@pytest.mark.slow
def test_edges_follow_each_balls_own_radius():
    """A 6 mm ball 1 mm from a 10 mm ball is joined (gap < skin 1.5 mm), at 2 mm it is not;
    the wall edge of a 6 mm ball starts 1 mm beyond its own contact (pw_skin), not the
    10 mm ball's; an absent ball has none."""
    tiny = Charge(classes=(BallClass(1, 0.005, 7700.0, STEEL), BallClass(2, 0.003, 7700.0, STEEL)),
                  wall=STEEL)

    def graph_of(gap_pp, gap_wall):
        x = np.array([[0.0, 0.02, 0.0], [0.008 + gap_pp, 0.02, 0.0], [0.03, 0.003 + gap_wall, 0.0]])
        pos = np.broadcast_to(x, (W + 1, 3, 3))
        charge = ball_charge(tiny)
        window = Window(positions=jnp.asarray(pos), offsets=jnp.zeros((W, 3)),
                        offset_velocities=jnp.zeros((W, 3)), frequency_hz=jnp.asarray(0.0),
                        charge=charge)
        return build_graph(window, None, spec(3), floor_query((0.0, 1.0, 0.0)))

    _, counts = graph_of(1.0e-3, 0.9e-3)
    assert int(counts.n_pp) == 2 and int(counts.n_pw) == 2     # ball 2 on the floor
    _, counts = graph_of(2.0e-3, 1.1e-3)
    assert int(counts.n_pp) == 0 and int(counts.n_pw) == 0
    graph, counts = build_graph(scene(np.random.default_rng(0), n_total=7), None, spec(7),
                                floor_query((0.0, 1.0, 0.0)))
    used = np.concatenate([np.asarray(graph.senders), np.asarray(graph.receivers)])
    assert not np.isin([5, 6], used).any()
    assert np.asarray(graph.nodes["present"]).tolist() == [True] * 5 + [False] * 4


@pytest.mark.slow
def test_rotating_a_two_size_scene_rotates_the_accelerations():
    rng = np.random.default_rng(1)
    a = np.linalg.qr(np.random.default_rng(7).normal(size=(3, 3)))[0]
    rot = a * np.sign(np.linalg.det(a))
    window, _ = scene(rng), None
    terms, params, graph = terms_of(window)
    assert float(jnp.sum(terms["gate"])) >= 6            # pairs of both sizes and the floor act
    rng = np.random.default_rng(1)
    window_r = scene(rng, rotation=rot)
    terms_r, _, _ = terms_of(window_r, up=rot @ np.array([0.0, 1.0, 0.0]),
                             gravity=rot @ np.array([0.0, -9.81, 0.0]), params=params)
    for key, tol in (("dv", 1e-3), ("dw", 1e-3)):
        base = np.asarray(terms[key])[:5]
        scale = np.max(np.abs(base))
        assert scale > 0
        np.testing.assert_allclose(np.asarray(terms_r[key])[:5], base @ rot.T,
                                   atol=tol * scale)


def test_ball_ball_impulses_of_unequal_balls_keep_momentum_and_angular_momentum():
    """No gravity, the floor far away: the impulses are ball-ball only, between balls of 10 and
    6 mm, steel and zirconia (masses 4.0 g and 0.68 g): sum m dv = 0 and, about the origin,
    sum (x m dv + I dw) = 0 (each ball's own arm: the same contact point)."""
    rng = np.random.default_rng(2)
    window = scene(rng, lift=0.0)
    terms, _, graph = terms_of(window, gravity=(0.0, 0.0, 0.0), floor_height=1.0)
    acting_pw = np.asarray(terms["gate"]) * np.asarray(graph.edges["pw"])[0::2]
    assert acting_pw.sum() == 0 and float(jnp.sum(terms["gate"])) >= 4
    mass, radius = MIX.masses, MIX.radii
    dv, dw = np.asarray(terms["dv"])[:5], np.asarray(terms["dw"])[:5]
    impulse = mass[:, None] * dv
    scale = np.max(np.abs(impulse))
    assert scale > 1e-6
    np.testing.assert_allclose(impulse.sum(0), 0.0, atol=1e-5 * scale)
    x = np.asarray(window.positions[-1])
    inertia = 0.4 * mass * radius ** 2
    angular = np.cross(x, impulse) + inertia[:, None] * dw
    l_scale = np.max(np.abs(np.cross(x, impulse)))
    np.testing.assert_allclose(angular.sum(0), 0.0, atol=1e-4 * l_scale)


def test_permuting_the_balls_of_a_mixture_permutes_the_accelerations():
    """Without the overlap sweeps: a sweep divides each correction by the number of violated
    contacts of its balls, and a contact that the previous sweep brought exactly to its limit
    counts as violated or not by rounding, which the order of the balls changes (the contact
    kind's sweeps alike: a jump of ~1 % here)."""
    rng = np.random.default_rng(3)
    window = scene(rng)
    terms, params, _ = terms_of(window, overlap_sweeps=0)
    perm = np.array([3, 0, 4, 2, 1])
    charge = window.charge
    permuted = window.replace(
        positions=window.positions[:, perm], spins=window.spins[perm],
        charge=charge.replace(radius=charge.radius[perm], mass=charge.mass[perm],
                              ball_class=charge.ball_class[perm], present=charge.present[perm]))
    terms_p, _, _ = terms_of(permuted, params=params, overlap_sweeps=0)
    for key in ("dv", "dw"):
        base = np.asarray(terms[key])[:5]
        np.testing.assert_allclose(np.asarray(terms_p[key])[:5], base[perm],
                                   atol=1e-4 * np.max(np.abs(base)))


@pytest.mark.parametrize("spin", [False, True])
@pytest.mark.slow
def test_untrained_and_random_params_give_finite_outputs_for_a_padded_mixture(spin):
    """A mixture padded with 2 absent balls: finite outputs with the initial and with random
    parameters; the absent balls do not move; the present ones get what they get unpadded."""
    rng = np.random.default_rng(4)
    padded = scene(rng, n_total=7)
    rng = np.random.default_rng(4)
    plain = scene(rng, n_total=5)
    graph, _ = build_graph(padded, None, spec(7), floor_query((0.0, 1.0, 0.0)))
    net = net_with(spin=spin)
    init = net.init(jax.random.PRNGKey(0), graph)["params"]
    for params in (init, random_params(net, graph)):
        terms = net.apply({"params": params}, graph, method=ContactChargeNet.step_terms)
        for value in terms.values():
            assert np.all(np.isfinite(np.asarray(value)))
        assert np.all(np.asarray(terms["dv"])[5:] == 0.0)
        terms_5, _, _ = terms_of(plain, params=params, spin=spin)
        np.testing.assert_allclose(np.asarray(terms["dv"])[:5], np.asarray(terms_5["dv"])[:5],
                                   rtol=1e-5, atol=1e-9)
        accel, d_e = net.apply({"params": params}, graph)
        assert np.all(np.isfinite(np.asarray(accel))) and np.isfinite(np.asarray(d_e)).all()


@pytest.mark.slow
def test_the_same_impact_of_a_6mm_and_a_15mm_ball_is_the_same_input():
    """A steel ball of 6 mm and one of 15 mm, both at 1 m/s onto the floor, each at the deepest
    overlap of that impact by the DEM's own law (27 and 68 um): the model's gap input is the
    same for both, -peak / (2 L) = -0.5 (L from the charge in the graph, the law's peak from the
    DEM's host integration), and every input is finite and inside its range, unclipped where it
    is linear. The contact kind's fixed 5 um scale saturates on both."""
    rows = {}
    for diameter in (0.006, 0.015):
        r = diameter / 2
        single = Charge(classes=(BallClass(1, r, 7700.0, STEEL),), wall=STEEL)
        law = make_contact_law(STEEL.young, STEEL.poisson, STEEL.restitution, STEEL.friction,
                               STEEL.rolling_friction, r, single.classes[0].mass)
        peak = head_on_peak_overlap(law)
        y_now = r - peak
        vel = np.zeros((W + 1, 1, 3))
        vel[:, 0, 1] = -1.0
        pos = np.array([0.0, y_now, 0.0]) + np.cumsum(vel * DT, axis=0) - (vel * DT).sum(0)[None]
        window = Window(positions=jnp.asarray(pos), offsets=jnp.zeros((W, 3)),
                        offset_velocities=jnp.zeros((W, 3)), frequency_hz=jnp.asarray(0.0),
                        spins=jnp.zeros((1, 3)), charge=ball_charge(single))
        graph, _ = build_graph(window, None, spec(1), floor_query((0.0, 1.0, 0.0)))
        net = net_with()
        params = net.init(jax.random.PRNGKey(0), graph)["params"]
        geo = net.apply({"params": params}, graph, method=ContactChargeNet._edge_geometry)
        row = int(np.flatnonzero(np.asarray(geo["is_pw"]))[0])
        rows[diameter] = (np.asarray(geo["inputs"])[row], float(geo["scale_l"][row]), peak)
    for inputs, scale_l, peak in rows.values():
        assert np.all(np.isfinite(inputs)) and np.all(np.abs(inputs) <= 5.0)
        assert scale_l == pytest.approx(peak, rel=1e-4)      # L is the law's own peak at 1 m/s
        newest = inputs[8:12]                                # gap, fine gap, u, fine u
        assert newest[0] == pytest.approx(-1.0 / GAP_COARSE, abs=1e-3)
        assert -1.0 < inputs[0] < 3.0 and -5.0 < newest[2] < 0.0   # linear columns unclipped
    (a, _, peak_a), (b, _, peak_b) = rows[0.006], rows[0.015]
    assert peak_b / peak_a == pytest.approx(2.5, rel=0.02)   # the law's overlap scales with r
    np.testing.assert_allclose(a[8:10], b[8:10], atol=1e-4)  # the same state, both gap inputs


# --------------------------------------------------------------------------------------------
# The rollout of any charge: per-ball wall snap-back and separation, and the host driver


def test_the_snap_back_threshold_follows_each_balls_radius():
    from sgn_jax.surrogate.rollout import charge_snap_threshold, snap_back_shift

    radius = jnp.asarray([0.005, 0.003, 0.003])
    threshold = charge_snap_threshold(-0.0049, 0.005, radius)
    # a 5 mm ball keeps the config's -4.9 mm; a 3 mm ball is snapped from the same 0.1 mm depth
    np.testing.assert_allclose(threshold, [-0.0049, -0.0029, -0.0029], rtol=0, atol=1e-15)
    # ball 1 touches the wall 0.05 mm deep (phi = -2.95 mm): not snapped; ball 2 0.15 mm deep
    phi = jnp.asarray([-0.0049, -0.00295, -0.00285])
    normal = jnp.tile(jnp.asarray([[0.0, -1.0, 0.0]]), (3, 1))
    shift, snapped = snap_back_shift(phi, normal, threshold)
    assert snapped.tolist() == [True, False, True]
    np.testing.assert_allclose(shift[2], [0.0, 0.00005, 0.0], rtol=0, atol=1e-15)   # into the jar
    # with one threshold (a 5 mm ball's) every small ball touching the wall would be snapped
    assert bool(snap_back_shift(phi, normal, -0.0049)[1][1])


def test_separation_with_two_sizes_stops_at_the_sum_of_the_radii():
    from sgn_jax.surrogate.rollout import separate_pairs

    pos = jnp.asarray([[0.0, 0.0, 0.0], [0.0079, 0.0, 0.0]])   # 5 + 3 mm balls, 0.1 mm overlap
    shift, pairs = separate_pairs(pos, jnp.asarray([0.005, 0.003]), 0.0)
    assert int(pairs) == 1
    np.testing.assert_allclose(jnp.linalg.norm(pos[1] + shift[1] - pos[0] - shift[0]), 0.008,
                               rtol=1e-12)
    assert int(separate_pairs(pos, 0.003, 0.0)[1]) == 0   # 6 mm apart with one 3 mm radius


def test_contact_census_counts_each_pair_by_its_own_radii():
    from sgn_jax.analysis.metrics import contact_census
    from sgn_jax.geometry import JarParams

    jar = JarParams(radius=0.02, straight_length=0.035, height=0.047)
    # a 5 mm ball with two 3 mm balls: one 7.9 mm away (touching), one 9 mm away (not
    # touching: 5 + 3 = 8 mm; two 5 mm balls would, 10 mm)
    pos = np.asarray([[[0.0, 0.0, 0.0], [0.0079, 0.0, 0.0], [0.0, 0.0, 0.009]]] * 3)
    census = contact_census(pos, np.zeros((3, 3)), jar, np.asarray([0.005, 0.003, 0.003]))
    assert census["pp_touching_mean"] == 1.0
    np.testing.assert_allclose(census["deepest_pp_overlap_m"], 1e-4, rtol=1e-9)
    np.testing.assert_allclose(census["deepest_pp_overlap_rel"], 1e-4 / 0.003, rtol=1e-9)
    # one radius for all (the 5 mm) sees a second touching pair and a deeper overlap
    one = contact_census(pos, np.zeros((3, 3)), jar, 0.005)
    assert one["pp_touching_mean"] == 2.0


def test_wall_contact_lifetimes_count_each_run_of_frames_by_each_balls_own_radius():
    from sgn_jax.analysis.metrics import wall_contact_lifetimes
    from sgn_jax.geometry import JarParams

    jar = JarParams(radius=0.02, straight_length=0.035, height=0.047)
    # (the jar's floor is y = 0) ball 0 (5 mm) 4.9 mm above the floor in frames 1-3 and 6
    # (two runs: 3 frames and 1), else 10 mm; ball 1 (3 mm) always 4 mm above it (never
    # touching; a 5 mm ball there would)
    frames = 8
    pos = np.zeros((frames, 2, 3))
    pos[:, 0] = [0.0, 0.010, 0.0]
    pos[[1, 2, 3, 6], 0] = [0.0, 0.0049, 0.0]
    pos[:, 1] = [0.008, 0.004, 0.0]
    out = wall_contact_lifetimes(pos, np.zeros((frames, 3)), jar, np.asarray([0.005, 0.003]),
                                 longest=3)
    assert out["pw_contacts"] == 2
    assert out["pw_contact_frames_hist"] == [1, 0, 1]
    assert out["pw_contact_frames_mean"] == 2.0
    np.testing.assert_allclose(out["pw_fraction_per_ball"], [4 / frames, 0.0])
    np.testing.assert_allclose(out["pw_touching_mean"], 4 / frames)
    one = wall_contact_lifetimes(pos, np.zeros((frames, 3)), jar, 0.005, longest=3)
    assert one["pw_contact_frames_hist"] == [1, 0, 2]   # ball 1 touches in all 8 frames too


@pytest.mark.slow   # ~25 s: the walls' SDF grid and a rollout compile
def test_run_rollout_rolls_a_mixture_out_with_the_records_own_charge():
    """``sgn_jax.api.run_rollout`` of the charge-reading kind from a record of a two-size
    charge: the window carries the record's charge (its radii and masses in the prediction's
    meta), the rollout is finite, and a config of another ball count is a clear error."""
    from types import SimpleNamespace

    from sgn_jax.api import load_config, replace_section, run_rollout
    from sgn_jax.config import config_from_dict, config_to_dict
    from sgn_jax.pipelines.configure import charge_from_config, graph_spec_from_config
    from sgn_jax.pipelines.contact_train_run import identity_stats
    from sgn_jax.records.checkpoint import TrainedModel
    from sgn_jax.surrogate.rollout import RolloutError

    base = replace_section(load_config("emax_300rpm"), "model", kind="contact_charge",
                           hidden=16, mlp_layers=3)
    model_cfg = replace_section(base, "rollout", chunk_steps=20, checkpoint_steps=20)
    dt = float(model_cfg.dem.dt)
    data = config_to_dict(model_cfg)
    data["balls"] = {"count": 4, "radius": 0.005, "density": 7700.0,
                     "mix": [{"count": 6, "radius": 0.003, "density": 6000.0}]}
    case_cfg = config_from_dict(data)
    charge = charge_from_config(case_cfg)
    # the balls at rest on a lattice in the lower jar, clear of each other and of the wall
    lattice = [(x, y, z) for y in (0.008, 0.020) for x in (-0.012, 0.0, 0.012)
               for z in (-0.006, 0.006)][:10]
    pos = np.broadcast_to(np.asarray(lattice), (12, 10, 3)).copy()
    traj = SimpleNamespace(pos=pos, offset=np.zeros((12, 3)), offset_vel=np.zeros((12, 3)),
                           t=dt * np.arange(12),
                           meta={"dt": dt, "config": config_to_dict(case_cfg)})
    net = model_factory("contact_charge").build_model(model_cfg)
    w = int(model_cfg.graph.window)
    window = Window(positions=jnp.asarray(pos[:w + 1]), offsets=jnp.zeros((w, 3)),
                    offset_velocities=jnp.zeros((w, 3)), frequency_hz=jnp.asarray(5.0),
                    spins=jnp.zeros((10, 3)), charge=ball_charge(charge))
    graph, _ = build_graph(window, None, graph_spec_from_config(model_cfg, 10),
                           floor_query((0.0, 1.0, 0.0), 0.02))
    params = model_factory("contact_charge").init_params(net, graph, 0)
    trained = TrainedModel(model=net, params=params,
                           norm_stats=identity_stats(int(model_cfg.graph.window)),
                           config=model_cfg, meta={})
    out = run_rollout(trained, traj, None, 20 * dt, progress=False, save_every=10)
    assert out["steps"] == 20 and np.isfinite(out["arrays"]["pos"]).all()
    np.testing.assert_allclose(out["meta"]["ball_radii"], charge.radii, rtol=0)
    np.testing.assert_allclose(out["meta"]["ball_masses"], charge.masses, rtol=1e-12)
    assert out["outside_ball_steps"] == 0

    other = replace_section(case_cfg, "balls", count=5)   # 11 balls against a record of 10
    with pytest.raises(RolloutError, match="the charge has 11 balls .* the initial record has 10"):
        run_rollout(trained, traj, None, 20 * dt, None, other, progress=False, save_every=10)


def test_the_touch_term_counts_contacts_the_model_and_the_dem_disagree_on():
    from sgn_jax.surrogate.contact_charge_train import touch_mismatch

    radius = jnp.asarray([0.005, 0.003, 0.003])
    present = jnp.asarray([1.0, 1.0, 0.0])
    far = jnp.full((3,), -0.02)          # every ball far from the wall
    # the DEM's 5 + 3 mm pair rests 1 um into contact; the third ball is absent
    x_dem = jnp.asarray([[0.0, 0.0, 0.0], [0.008 - 1e-6, 0.0, 0.0], [0.0, 0.0, 0.0085]])
    assert float(touch_mismatch(x_dem, x_dem, radius, present, far, far)) == 0.0
    # the model's pair 20 um apart: one contact of two balls missed
    x_apart = x_dem.at[1, 0].add(2.1e-5)
    missed = float(touch_mismatch(x_apart, x_dem, radius, present, far, far))
    assert 0.15 < missed < 0.25           # (sigmoid(0.5) - ~0)^2 / 2 balls
    # the absent ball's overlap with ball 0 (0.5 mm) counts for nothing
    x_absent = x_dem.at[2, 2].set(0.0075)
    assert float(touch_mismatch(x_absent, x_dem, radius, present, far, far)) == 0.0
    # a ball the model leaves on the wall that the DEM's left
    wall_m = far.at[0].set(-0.005 + 1e-6)
    assert float(touch_mismatch(x_dem, x_dem, radius, present, wall_m, far)) > 0.15


def test_the_law_rebound_time_of_a_pair_depends_on_its_restitution_alone():
    """The pair table's ``rebound_time`` (the law's head-on contact time times the speed over
    its peak overlap, :func:`head_on_contact_time`) is the same for every size and mass of a
    material pair (the law is self-similar), grows as the restitution falls (longer damped
    contacts), and tends to Hertz's elastic 2.94 as e -> 1 (its time, 2.87 (m*^2 / (R* Y*^2
    v))^(1/5), within 1 %)."""
    from sgn_jax.dem.contact import head_on_contact_time, hertz_contact_time
    from sgn_jax.surrogate.contact_charge import PAIR_COLUMNS, pair_table

    column = PAIR_COLUMNS.index("rebound_time")
    table = pair_table(MIX)[..., column]             # steel-steel, steel-zirconia, walls
    for a, b in ((0, 0), (0, 2), (1, 2)):            # class 1: zirconia, class 2: the wall
        assert np.isfinite(table[a, b]) and table[a, b] > 2.94
    law_a = make_contact_law(2.05e9, 0.235, 0.3, 0.3, 0.0, 0.005, 0.004)
    law_b = make_contact_law(2.05e9, 0.235, 0.3, 0.3, 0.0, 0.0015, 2e-4, radius_2=0.007,
                             mass_2=0.01)
    ratio_a = head_on_contact_time(law_a) / head_on_peak_overlap(law_a)
    assert ratio_a == pytest.approx(table[0, 2], rel=1e-6)   # steel ball, steel wall
    assert head_on_contact_time(law_b) / head_on_peak_overlap(law_b) == pytest.approx(ratio_a,
                                                                                    rel=2e-3)
    bouncy = make_contact_law(2.05e9, 0.235, 0.74, 0.3, 0.0, 0.005, 0.004)
    assert head_on_contact_time(bouncy) / head_on_peak_overlap(bouncy) < ratio_a
    elastic = make_contact_law(2.05e9, 0.235, 0.999, 0.3, 0.0, 0.005, 0.004)
    assert head_on_contact_time(elastic, 0.5) == pytest.approx(hertz_contact_time(elastic, 0.5),
                                                               rel=0.01)


def test_the_exact_law_rebound_at_the_wall_caps_the_charge_kinds_resting_balls():
    """``law_rebound_exact = "wall"`` in the charge kind (``ChargePhysics.rebound_exact``): the
    mixture at rest, balls 0 and 1 pressed 1 um into the floor, ball 2 on them. Their floor
    contacts (closed over the window, nothing coming in) get a ceiling of about gravity over
    one step, each with its own restitution; the ball-ball contacts get none; without the
    rule no ceiling at all. The config key reaches the physics; the rule without the law
    rebound, and an unknown value, are refused."""
    from sgn_jax.config import builtin_config_path, load_config, replace_section
    from sgn_jax.surrogate.contact import ContactModelError
    from sgn_jax.surrogate.contact_charge import physics_from_config

    pos = np.broadcast_to(CENTRES - np.array([0.0, 1e-6, 0.0]), (W + 1, 5, 3))
    window = Window(positions=jnp.asarray(pos), offsets=jnp.zeros((W, 3)),
                    offset_velocities=jnp.zeros((W, 3)), frequency_hz=jnp.asarray(5.0),
                    spins=jnp.zeros((5, 3)), charge=ball_charge(MIX, n_balls=5, classes=3))
    graph, _ = build_graph(window, None, spec(5), floor_query((0.0, 1.0, 0.0)))

    def geometry(exact):
        net = net_with(law_rebound=True, rebound_exact=exact)
        params = net.init(jax.random.PRNGKey(0), graph)["params"]
        return net.apply({"params": params}, graph, method=ContactChargeNet._edge_geometry)

    geo = geometry("wall")
    acting = np.asarray(geo["gate"]) > 0
    wall = acting & np.asarray(geo["is_pw"])
    pair = acting & np.asarray(geo["is_pp"])
    ceiling = np.asarray(geo["ceiling"])
    assert wall.sum() == 2 and pair.sum() >= 2
    assert np.all(ceiling[wall] <= 9.81 * DT + 1e-6)
    assert np.all(np.isinf(ceiling[pair]))
    assert "ceiling" not in geometry("off")

    cfg = load_config(builtin_config_path("contact_charge_train"))
    cfg = replace_section(cfg, "model", law_rebound=True, overlap_law_factor=1.5,
                          law_rebound_exact="wall")
    assert physics_from_config(cfg).rebound_exact == "wall"
    with pytest.raises(ContactModelError, match="rebound_exact"):
        dataclasses.replace(PHYS, rebound_exact="wall")
    with pytest.raises(ContactModelError, match="rebound_exact"):
        dataclasses.replace(PHYS, law_rebound=True, rebound_exact="walls")


@pytest.mark.slow
def test_a_rollout_step_on_the_rows_that_may_act_gives_what_the_whole_graph_gives():
    """The single-rollout step on the rows that may act (``compact_per_ball``,
    ``ContactNet.rollout_terms``) with the charge kind's own gate margin, L / L_REF per
    contact (``_reach_and_margin``): its candidates hold every acting row of a padded mixture,
    and the step on them gives the whole graph's accelerations, target and ledger (on the
    compacted graph and through the step's choice)."""
    from sgn_jax.surrogate.graph import compact_edge_pairs

    window = scene(np.random.default_rng(6), n_total=7)
    graph, _ = jax.jit(build_graph, static_argnums=(1, 2, 3))(
        window, None, spec(7), floor_query((0.0, 1.0, 0.0)))
    net = net_with(overlap_sweeps=1, friction_sweeps=1)
    params = random_params(net, graph, jit=True)

    def run(form, method, g=graph):   # jitted: one program each instead of eager op by op
        return jax.jit(lambda p, g: form.apply({"params": p}, g, method=method))(params, g)

    keep = np.asarray(run(net, ContactChargeNet._gate_candidates))
    geo = run(net, ContactChargeNet._edge_geometry)
    acting = np.asarray(geo["gate"]) > 0
    assert np.asarray(geo["is_pp"])[acting].sum() >= 3 and np.asarray(geo["is_pw"])[acting].any()
    assert np.all(keep[acting]) and keep.sum() < keep.size   # a superset, not every row
    whole = run(net, ContactChargeNet.rollout_terms)
    rows = int(keep.sum())
    form = net.clone(compact_per_ball=(rows - 0.5) / (2 * 7))   # a block of ceil(2 f N) rows
    outputs = [run(net, ContactChargeNet.rollout_terms, compact_edge_pairs(graph, keep, rows)),
               run(form, ContactChargeNet.rollout_terms)]
    for out in outputs:
        for got, want in zip(out, whole, strict=True):
            want = np.asarray(want)
            np.testing.assert_allclose(np.asarray(got), want, rtol=1e-5,
                                       atol=1e-6 * np.max(np.abs(want)))
    assert np.all(np.asarray(whole[0])[5:7] == 0.0)   # the absent balls stay


@pytest.mark.slow   # ~40 s: the shipped model's rollout compiles
def test_the_shipped_charge_model_lets_a_two_size_mixture_fall_in_the_moving_jar():
    """The shipped ``contact_charge`` (docs/contact_charge.md) on a mixture it never saw, 4
    steel balls of 10 mm and 6 zirconia-density balls of 6 mm started at rest on a lattice in
    the Emax jar at 300 rpm: 0.1 s of rollout is finite, no ball leaves the jar, the balls
    fall (their mean height drops by more than a ball radius) and the model's own ledger
    dissipates energy in ball-ball and ball-wall contacts."""
    from types import SimpleNamespace

    from sgn_jax.api import load_config, load_surrogate, run_rollout
    from sgn_jax.config import config_from_dict, config_to_dict
    from sgn_jax.motion import offset, velocity
    from sgn_jax.pipelines.configure import motion_from_config

    trained = load_surrogate("contact_charge")
    dt = float(trained.config.dem.dt)
    data = config_to_dict(load_config("emax_300rpm"))
    data["balls"] = {"count": 4, "radius": 0.005, "density": 7700.0,
                     "mix": [{"count": 6, "radius": 0.003, "density": 6000.0}]}
    data["dem"]["dt"] = dt
    case_cfg = config_from_dict(data)
    # a lattice in the jar's frame, carried with the jar (its offset at each sample time)
    lattice = [(x, y, z) for y in (0.012, 0.026) for x in (-0.012, 0.0, 0.012)
               for z in (-0.006, 0.006)][:10]
    motion = motion_from_config(case_cfg.motion)
    t = dt * np.arange(12)
    jar = np.asarray(offset(motion, t))
    traj = SimpleNamespace(pos=np.asarray(lattice)[None] + jar[:, None], offset=jar,
                           offset_vel=np.asarray(velocity(motion, t)), t=t,
                           meta={"dt": dt, "config": data})
    out = run_rollout(trained, traj, None, 0.1, None, case_cfg, progress=False, save_every=100)
    arrays = out["arrays"]
    assert out["steps"] == 1000 and np.isfinite(arrays["pos"]).all()
    assert out["outside_ball_steps"] == 0
    height = arrays["pos"][:, :, 1].mean(axis=1)   # y is up; the jar moves in x and z
    assert height[-1] < height[0] - 0.005
    assert np.sum(arrays["diss_pp_model"]) > 0 and np.sum(arrays["diss_pw_model"]) > 0


@pytest.mark.slow
def test_the_shipped_charge_model_rebounds_a_mixed_pair_at_its_materials_restitution():
    """The shipped ``contact_charge`` (its ``law_rebound_exact = "fresh"``, docs/contact.md,
    "One step", item 7) on a head-on impact of two free balls it never saw as a pair, a 10 mm
    steel ball and a 6 mm zirconia one (the pair's restitution by the charge's mixing rule),
    at 0.2 and 1 m/s, each at eight phases of the step: the balls part at e v, e the pair's
    own (float32), and the pair's momentum is kept."""
    from sgn_jax.api import load_surrogate, replace_section
    from sgn_jax.motion import CircleMotion
    from sgn_jax.pipelines.configure import graph_spec_from_config
    from sgn_jax.surrogate.rollout import make_rollout, model_predictor, single_rollout_model

    trained = load_surrogate("contact_charge")
    pair = Charge(classes=(BallClass(1, 0.005, 7700.0, STEEL), BallClass(1, 0.003, 6000.0,
                                                                         ZIRCONIA)),
                  wall=STEEL)
    e = pair.pair_rule(STEEL, ZIRCONIA).restitution
    masses = pair.masses
    # no wall patches: the floor below is one plane, far from both balls
    spec = graph_spec_from_config(replace_section(trained.config, "graph", wall_patches=0),
                                  n_particles=2)
    dt, w = spec.dt, spec.window
    model, _ = single_rollout_model(trained.model)

    def far_floor(sdf, points, offset):   # a floor 1 m below: no ball-wall contact
        del sdf, offset
        return -(points[..., 1] + 1.0), jnp.broadcast_to(jnp.array([0.0, -1.0, 0.0]),
                                                        points.shape)

    roll = make_rollout(spec, model_predictor(model), 40, 1, query=far_floor, snap_back=False)
    for v in (0.2, 1.0):
        for phase in np.linspace(0.0, 1.0, 8, endpoint=False):
            gap0 = (4.0 + phase) * v * dt            # touching 4-5 steps into the rollout
            x = np.array([[-0.005 - gap0 / 2, 0.0, 0.0], [0.003 + gap0 / 2, 0.0, 0.0]])
            vel = np.array([[v, 0.0, 0.0], [0.0, 0.0, 0.0]])   # the steel ball hits the other
            pos = x[None] + (np.arange(w + 1) - w)[:, None, None] * dt * vel[None]
            window = Window(positions=jnp.asarray(pos), offsets=jnp.zeros((w, 3)),
                            offset_velocities=jnp.zeros((w, 3)), frequency_hz=jnp.asarray(0.0),
                            spins=jnp.zeros((2, 3)), charge=ball_charge(pair))
            out = roll(trained.params, trained.norm_stats, window, CircleMotion(0.0, 0.0),
                       None, 0.0)
            p = np.asarray(out.positions, np.float64)
            end_vel = (p[-1] - p[-2]) / dt
            parting = end_vel[1, 0] - end_vel[0, 0]
            assert parting == pytest.approx(e * v, rel=2e-3), (v, phase)
            momentum = masses @ end_vel[:, 0]
            assert momentum == pytest.approx(masses[0] * v, rel=1e-4)


def test_friction_sweeps_on_the_walls_only_leave_each_ball_ball_stick_to_the_network():
    """``friction_sweep_contacts = "wall"``: the sweeps change the ball-wall contacts'
    tangential impulses and leave every ball-ball contact's at the network's (what the model
    gives without sweeps), where ``"all"`` changes both kinds."""
    window = scene(np.random.default_rng(3))
    off, params, graph = terms_of(window, friction_sweeps=0)
    walls, _, _ = terms_of(window, params=params, friction_sweeps=3,
                           friction_sweep_contacts="wall")
    every, _, _ = terms_of(window, params=params, friction_sweeps=3)
    net = net_with()
    geo = net.apply({"params": params}, graph, method=ContactChargeNet._edge_geometry)
    acting = np.asarray(geo["gate"]) > 0
    pp, pw = acting & np.asarray(geo["is_pp"]), acting & np.asarray(geo["is_pw"])
    assert pp.sum() >= 3 and pw.sum() >= 2
    du_off, du_walls, du_every = (np.asarray(t["du_t"]) for t in (off, walls, every))
    np.testing.assert_allclose(du_walls[pp], du_off[pp], rtol=1e-6, atol=1e-12)
    assert np.max(np.abs(du_walls[pw] - du_off[pw])) > 1e-3 * np.max(np.abs(du_off[pw]))
    assert np.max(np.abs(du_every[pp] - du_off[pp])) > 1e-3 * np.max(np.abs(du_off[pp]))
    with pytest.raises(Exception, match="friction_sweep_contacts"):
        net_with(friction_sweep_contacts="pp")


def test_rebound_sweeps_keep_an_impact_at_its_rebound_with_the_struck_balls_other_contact():
    """``rebound_sweeps``: a 10 mm steel ball strikes a 6 mm zirconia ball that rests against
    another 10 mm ball (a chain, in free space). Past the impact's contact time the step alone
    ends the impact at e v only for the pair by itself; the resting contact behind then
    pushes the struck ball back and the pair parts slower. With the sweeps ("all") the pair
    parts at e v with both contacts acting; with "free" the struck ball, held by its resting
    contact, is left to the step; without an impact the sweeps change nothing."""
    from sgn_jax.surrogate.contact import ContactModelError

    # materials of the DEM's stiffness, so that the impact is over within the window
    steel = dataclasses.replace(STEEL, young=2.1e11)
    zirconia = dataclasses.replace(ZIRCONIA, young=2.1e11)
    chain = Charge(classes=(BallClass(2, 0.005, 7700.0, steel),
                            BallClass(1, 0.003, 6000.0, zirconia)), wall=steel)
    e = chain.pair_rule(steel, zirconia).restitution
    v = 0.2
    pos = np.zeros((W + 1, 3, 3))
    # ball 2 (zirconia) at the origin; ball 0 (steel) strikes it at v, its gap +10 um at the
    # oldest slot of the window and closing 20 um per step (the impact began 2.5 steps before
    # the end of this one, past its contact time); ball 1 (steel) rests 0.5 um into ball 2
    pos[:, 0, 0] = -0.008 - 30e-6 + v * DT * np.arange(W + 1)
    pos[:, 1, 0] = 0.008 - 0.5e-6
    radii = np.array([0.005, 0.005, 0.003])

    def window_of(positions):
        return Window(positions=jnp.asarray(positions), offsets=jnp.zeros((W, 3)),
                      offset_velocities=jnp.zeros((W, 3)), frequency_hz=jnp.asarray(0.0),
                      spins=jnp.zeros((3, 3)), charge=ball_charge(chain, radii=radii))

    # the floor 1 m below (no wall); a limit deep enough that the rebound alone sets the step
    physics = dict(gravity=(0.0, 0.0, 0.0), law_rebound=True, rebound_exact="fresh",
                   overlap_limit=3e-4, overlap_sweeps=4, floor_height=1.0)
    alone, params, _ = terms_of(window_of(pos), **physics)
    swept, _, _ = terms_of(window_of(pos), params=params, rebound_sweeps="all", **physics)
    vel = (pos[-1] - pos[-2]) / DT

    def parting(terms):
        end = vel + np.asarray(terms["dv"])[:3]
        return end[2, 0] - end[0, 0]

    assert parting(alone) < 0.97 * e * v              # pushed back by the resting contact
    assert parting(swept) == pytest.approx(e * v, rel=2e-3)
    # "free": the struck ball is held by its resting contact, so the impact is left to the step
    held, _, _ = terms_of(window_of(pos), params=params, rebound_sweeps="free", **physics)
    np.testing.assert_array_equal(np.asarray(held["dv"]), np.asarray(alone["dv"]))
    # the resting contact alone (ball 0 far away): the sweeps have nothing to add
    apart = pos.copy()
    apart[:, 0, 0] -= 0.01
    quiet, _, _ = terms_of(window_of(apart), params=params, **physics)
    quiet_swept, _, _ = terms_of(window_of(apart), params=params, rebound_sweeps="all",
                                 **physics)
    np.testing.assert_array_equal(np.asarray(quiet["dv"]), np.asarray(quiet_swept["dv"]))
    with pytest.raises(ContactModelError, match="rebound_sweeps"):
        dataclasses.replace(PHYS, rebound_sweeps="all")       # without the law rebound
    with pytest.raises(ContactModelError, match="rebound_sweeps"):
        dataclasses.replace(PHYS, law_rebound=True, rebound_sweeps="walls")
    from sgn_jax.api import load_config, replace_section
    from sgn_jax.config import ConfigError
    from sgn_jax.surrogate.contact_charge import physics_from_config

    cfg = replace_section(load_config("emax_300rpm"), "model", kind="contact_charge", spin=True,
                          overlap_limit=5e-5, overlap_law_factor=1.5, law_rebound=True,
                          overlap_sweeps=3, rebound_sweeps="free")
    assert physics_from_config(cfg).rebound_sweeps == "free"
    with pytest.raises(ConfigError, match="rebound_sweeps"):
        replace_section(cfg, "model", overlap_sweeps=0)
    with pytest.raises(ConfigError, match="rebound_sweeps"):
        replace_section(cfg, "model", rebound_sweeps="pp")
