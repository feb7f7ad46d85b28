"""The contact-impulse surrogate (model kind "contact"): the physics built into it.

Checked on an untrained network with random output layers (so that every impulse is nonzero
and arbitrary): these properties hold by construction, whatever the parameters.
- total ball-ball momentum is conserved to rounding (equal and opposite impulses);
- a rotated scene (positions, velocities, the wall and gravity) gives rotated accelerations;
- permuting the balls permutes the accelerations;
- normal impulses are repulsive only, tangential ones inside the Coulomb cone;
- the model's own energy ledger closes over a rollout: jar work + gravity's work - change of
  kinetic energy = the dissipation it reports, per step and summed (and with the potential
  energy from the positions, up to the integrator's telescoping term).
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sgn_jax.surrogate.contact import (
    ContactNet,
    ContactPhysics,
    InputScales,
    _scaled_inputs,
    edge_geometry,
)
from sgn_jax.surrogate.graph import GraphSpec, Window, build_graph
from sgn_jax.surrogate.model import model_factory

R, DT, W = 0.005, 1e-4, 3
PHYS = ContactPhysics(ball_radius=R, dt=DT, window=W, history=3, gate_margin=2e-4)
GRAPH_SPEC = GraphSpec(n_particles=5, window=W, ball_radius=R, dt=DT, pp_skin=1.5e-3,
                 phi_pw=-0.0052, pp_pair_capacity=10)


def floor_query(up):
    """A flat floor through the jar offset with unit normal ``up`` (into the cavity)."""
    up = jnp.asarray(up, jnp.float64)

    def query(sdf, points, offset):
        del sdf
        height = jnp.sum((points - offset) * up, axis=-1)
        return -height, jnp.broadcast_to(-up, points.shape)

    return query


def scene(rng, rotation=None):
    """5 balls: a touching cluster above the floor, one ball touching the floor, moving."""
    centres = np.array([[0.0, 0.0102, 0.0], [0.0099, 0.0102, 0.0], [0.0, 0.0102, 0.0099],
                        [0.005, 0.0190, 0.005], [0.03, 0.00499, 0.0]])
    vel = rng.normal(0.0, 0.3, (W + 1, 5, 3)) * 0.0 + rng.normal(0.0, 0.3, (1, 5, 3))
    vel = vel + rng.normal(0.0, 0.02, vel.shape)
    pos = centres[None] + np.cumsum(vel * DT, axis=0) - (vel * DT).sum(0)[None]
    offsets = np.cumsum(rng.normal(0.0, 0.1, (W, 3)) * DT, axis=0) * np.array([1, 0, 1])
    offset_vel = rng.normal(0.0, 0.2, (W, 3)) * np.array([1, 0, 1])
    rot = np.eye(3) if rotation is None else np.asarray(rotation)
    return Window(positions=jnp.asarray(pos @ rot.T), offsets=jnp.asarray(offsets @ rot.T),
                  offset_velocities=jnp.asarray(offset_vel @ rot.T),
                  frequency_hz=jnp.asarray(5.0)), rot


def random_params(net, graph, seed=0, jit=False):
    init = jax.jit(net.init) if jit else net.init   # jit: one program instead of eager ops
    params = init(jax.random.PRNGKey(seed), graph)["params"]
    key = jax.random.PRNGKey(seed + 1)

    def perturb(path, leaf):
        nonlocal key
        key, sub = jax.random.split(key)
        if len(path) == 3 and path[-1].key == "kernel" and leaf.shape[-1] == 2:
            return 0.5 * jax.random.normal(sub, leaf.shape, leaf.dtype)
        return leaf

    return jax.tree_util.tree_map_with_path(perturb, params)


def net_with(gravity, spin=False):
    phys = ContactPhysics(**{**PHYS.__dict__, "gravity": tuple(float(g) for g in gravity),
                             "rolling_friction": 0.045})
    return ContactNet(physics=phys, hidden=32, mlp_layers=3, spin=spin)


def terms_of(window, up=(0.0, 1.0, 0.0), gravity=(0.0, -9.81, 0.0), params=None, spin=False,
             friction_sweeps=0):
    graph, _ = build_graph(window, None, GRAPH_SPEC, floor_query(up))
    net = net_with(gravity, spin)
    if friction_sweeps:
        net = net.clone(physics=dataclasses.replace(net.physics, friction_sweeps=friction_sweeps))
    params = random_params(net, graph) if params is None else params
    return net.apply({"params": params}, graph, method=ContactNet.step_terms), params, graph


def test_contact_kind_is_registered_and_builds_from_the_whole_config():
    from sgn_jax.api import load_config, replace_section

    cfg = replace_section(load_config("emax_300rpm"), "model", kind="contact", hidden=16,
                          mlp_layers=3)
    model = model_factory("contact").build_model(cfg)
    assert isinstance(model, ContactNet)
    assert model.physics.ball_radius == cfg.balls.radius and model.physics.dt == cfg.dem.dt
    assert model.physics.ball_mass == pytest.approx(4.0317e-3, rel=1e-4)


@pytest.mark.parametrize("line", ['velocity_encoding = "differences"', "interaction_layers = 1",
                                  "interaction_layers = 2"])
def test_a_contact_config_that_sets_a_key_of_the_sgn_is_refused(tmp_path, line):
    """``[model] kind = "contact"`` reads neither ``velocity_encoding`` nor
    ``interaction_layers``: a TOML that sets one (even to its default) is refused, naming it."""
    from sgn_jax.config import ConfigError, builtin_config_path, load_config

    text = builtin_config_path("emax_300rpm").read_text()
    model = text[text.index("[model]"):text.index("[", text.index("[model]") + 1)]
    path = tmp_path / "contact.toml"
    path.write_text(text.replace(model, f'[model]\nkind = "contact"\nhidden = 16\n{line}\n\n'))
    key = line.split()[0]
    with pytest.raises(ConfigError, match=rf"\['{key}'\] are not read by model kind 'contact'"
                                          r".*remove them"):
        load_config(path)
    path.write_text(text.replace(model, '[model]\nkind = "contact"\nhidden = 16\n\n'))
    assert load_config(path).model.hidden == 16


def test_a_contact_config_is_written_and_read_back_without_the_sgn_keys():
    """The writer leaves the keys the contact kind does not read out; a saved record's config
    that lists them (every key of [model]) reads back with them dropped; a contact model with
    more than one interaction layer does not exist."""
    from sgn_jax.config import (
        ConfigError,
        config_from_dict,
        config_to_dict,
        replace_section,
        resolve_config,
        saved_config_from_dict,
    )

    sgn = resolve_config("emax_300rpm")
    contact = replace_section(sgn, "model", kind="contact", hidden=16)
    written = config_to_dict(contact)
    assert "velocity_encoding" not in written["model"] and "interaction_layers" not in written[
        "model"]
    assert config_from_dict(written).model.hidden == 16
    assert {"velocity_encoding", "interaction_layers"} <= set(config_to_dict(sgn)["model"])
    saved = {**written, "model": {**written["model"], "velocity_encoding": "differences",
                                  "interaction_layers": 1}}
    with pytest.raises(ConfigError, match="velocity_encoding"):
        config_from_dict(saved)
    assert saved_config_from_dict(saved).model == config_from_dict(written).model
    with pytest.raises(ConfigError, match="interaction_layers = 2.*kind 'contact'"):
        replace_section(contact, "model", interaction_layers=2)


# The slow tier: a speed-up's equality (the graphs without the node-wall queries give the same
# step); every contact-model test of the default run builds its graphs without them.
@pytest.mark.slow
def test_its_graphs_skip_the_node_wall_columns_it_never_reads():
    """Kind "contact" reads only the nodes' velocities (its walls are its ball-wall edges), so
    its config's graphs leave the W nearest-wall queries out (``GraphSpec.node_walls``): the
    same step as from a graph with them; the SGN's graphs keep them."""
    import dataclasses

    from sgn_jax.api import load_config, replace_section
    from sgn_jax.pipelines.configure import graph_spec_from_config

    cfg = load_config("emax_300rpm")
    assert graph_spec_from_config(cfg).node_walls
    assert not graph_spec_from_config(replace_section(cfg, "model", kind="contact")).node_walls
    window, _ = scene(np.random.default_rng(3))
    graphs = {walls: build_graph(window, None, dataclasses.replace(GRAPH_SPEC, node_walls=walls),
                                 floor_query((0.0, 1.0, 0.0)))[0] for walls in (True, False)}
    phi_columns = np.arange(3, 7 * W, 7)
    assert np.abs(np.asarray(graphs[True].nodes["features"])[:5, phi_columns]).max() > 1e-3
    # (without wall patches the ball-wall edges are built from the newest slot's query)
    assert not np.asarray(graphs[False].nodes["features"])[:5, phi_columns[:-1]].any()
    np.testing.assert_array_equal(graphs[True].edges["features"],
                                  graphs[False].edges["features"])
    net = net_with((0.0, -9.81, 0.0))
    params = random_params(net, graphs[True])
    dv = [net.apply({"params": params}, graphs[w], method=ContactNet.step_terms)["dv"]
          for w in (True, False)]
    assert np.abs(np.asarray(dv[0])).max() > 0
    np.testing.assert_array_equal(dv[0], dv[1])


@pytest.mark.slow
def test_ball_ball_momentum_is_conserved_to_rounding():
    window, _ = scene(np.random.default_rng(0))
    terms, _, graph = terms_of(window)
    geo = edge_geometry(graph, PHYS)
    assert float(jnp.sum(geo["gate"] * geo["is_pp"])) >= 4  # two touching pairs act
    # The floor ball (index 4) alone touches a wall: the other balls' momentum change is
    # gravity's only, and the ball-ball impulses sum to zero.
    dv = np.asarray(terms["dv"][:4], np.float64) - np.array([0, -9.81 * DT, 0])
    impulses = dv * PHYS.ball_mass
    scale = np.abs(impulses).max()
    assert scale > 1e-6
    np.testing.assert_allclose(impulses.sum(axis=0), 0.0, atol=1e-6 * scale)


@pytest.mark.slow
def test_gradients_are_finite_for_balls_at_rest():
    """Balls at rest in a still jar have a relative tangential velocity of exactly 0: the
    derivative of |v_t| must stay finite there (it was infinite, which made the design study's
    horizon gradients and the training loss on still-jar data NaN)."""
    window, _ = scene(np.random.default_rng(0))
    still = window.replace(positions=jnp.broadcast_to(window.positions[-1], window.positions.shape),
                           offsets=jnp.zeros_like(window.offsets),
                           offset_velocities=jnp.zeros_like(window.offset_velocities))
    _, params, _ = terms_of(still)
    net = net_with((0.0, -9.81, 0.0))

    def energy(shift):
        moved = still.replace(positions=still.positions + shift)
        graph, _ = build_graph(moved, None, GRAPH_SPEC, floor_query((0.0, 1.0, 0.0)))
        terms = net.apply({"params": params}, graph, method=ContactNet.step_terms)
        return jnp.sum(terms["dv"] ** 2) + terms["diss_pw"][0]

    # jitted: one program instead of ~250 eager compiles of the backward pass's ops
    grad = np.asarray(jax.jit(jax.grad(energy))(jnp.zeros_like(still.positions)))
    assert np.all(np.isfinite(grad))
    assert float(np.abs(grad).max()) > 0


def rotation_matrix(rng):
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def test_rotated_scene_gives_rotated_accelerations():
    rng = np.random.default_rng(1)
    window, _ = scene(np.random.default_rng(2))
    terms, params, _ = terms_of(window)
    rot = rotation_matrix(rng)
    window_r, _ = scene(np.random.default_rng(2), rot)
    up_r = rot @ np.array([0.0, 1.0, 0.0])
    g_r = rot @ np.array([0.0, -9.81, 0.0])
    terms_r, _, _ = terms_of(window_r, up=up_r, gravity=g_r, params=params)
    dv, dv_r = np.asarray(terms["dv"][:5]), np.asarray(terms_r["dv"][:5])
    np.testing.assert_allclose(dv_r, dv @ rot.T, atol=1e-5 * np.abs(dv).max())
    for name in ("diss_pp", "diss_pw", "work_wall"):
        np.testing.assert_allclose(terms_r[name][0], terms[name][0], rtol=1e-4, atol=1e-12)


def test_permuted_balls_give_permuted_accelerations():
    window, _ = scene(np.random.default_rng(3))
    terms, params, _ = terms_of(window)
    perm = np.array([3, 0, 4, 1, 2])
    window_p = window.replace(positions=window.positions[:, perm])
    terms_p, _, _ = terms_of(window_p, params=params)
    np.testing.assert_allclose(np.asarray(terms_p["dv"][:5]), np.asarray(terms["dv"][:5])[perm],
                               rtol=1e-5, atol=1e-9)
    np.testing.assert_allclose(terms_p["diss_pp"][0], terms["diss_pp"][0], rtol=1e-5)


@pytest.mark.parametrize("seed", range(4))
def test_normal_impulses_repel_and_tangential_ones_stay_in_the_cone(seed):
    window, _ = scene(np.random.default_rng(10 + seed))
    terms, _, _ = terms_of(window)
    du_n, du_t = np.asarray(terms["du_n"]), np.asarray(terms["du_t"])
    assert (du_n >= 0).all() and du_n.max() > 0
    assert (np.abs(du_t) <= PHYS.friction * du_n + 1e-12).all()
    # Out of reach (gated off): no impulse at all.
    gate = np.asarray(terms["gate"])
    assert (du_n[gate == 0] == 0).all()


def test_energy_ledger_closes_over_a_rollout():
    """Jar work + gravity's work - change of kinetic energy = the model's dissipation, every
    step (to float32 rounding) and over 200 steps of a moving jar."""
    from sgn_jax.surrogate.graph import slide_window

    rng = np.random.default_rng(5)
    window, _ = scene(rng)
    query = floor_query((0.0, 1.0, 0.0))
    graph, _ = build_graph(window, None, GRAPH_SPEC, query)
    net = net_with((0.0, -9.81, 0.0))
    params = random_params(net, graph, seed=4)
    g = np.array([0.0, -9.81, 0.0])
    m = PHYS.ball_mass

    @jax.jit
    def step(window):
        graph, _ = build_graph(window, None, GRAPH_SPEC, query)
        terms = net.apply({"params": params}, graph, method=ContactNet.step_terms)
        return terms

    ledger_rows, t = [], 0.0
    for _s in range(200):
        terms = step(window)
        pos = np.asarray(window.positions, np.float64)
        v_now = (pos[-1] - pos[-2]) / DT
        dv = np.asarray(terms["dv"][:5], np.float64)
        v_next = v_now + dv
        x_next = pos[-1] + v_next * DT
        d_ke = 0.5 * m * np.sum(v_next ** 2 - v_now ** 2)
        w_grav = m * np.sum((0.5 * (v_now + v_next)) @ g) * DT
        d_pe = -m * np.sum((x_next - pos[-1]) @ g)
        ledger_rows.append((float(terms["work_wall"][0]), w_grav, d_ke, d_pe,
                            float(terms["diss_pp"][0]) + float(terms["diss_pw"][0])))
        t += DT
        jar_v = np.array([0.3 * np.cos(40 * t), 0.0, 0.3 * np.sin(40 * t)])
        jar_x = np.asarray(window.offsets[-1]) + jar_v * DT
        window = slide_window(window, jnp.asarray(x_next), jnp.asarray(jar_x), jnp.asarray(jar_v))
    w_wall, w_grav, d_ke, d_pe, diss = (np.array(c) for c in zip(*ledger_rows, strict=False))
    assert np.isfinite(diss).all() and np.abs(diss).sum() > 0 and np.abs(w_wall).sum() > 0
    # Per step: float32 impulses and midpoint velocities; relative to the step's energy flow.
    flow = np.abs(w_wall) + np.abs(d_ke) + np.abs(w_grav)
    np.testing.assert_array_less(np.abs(w_wall + w_grav - d_ke - diss), 1e-4 * flow + 1e-12)
    total = w_wall.sum() + w_grav.sum() - d_ke.sum()
    assert diss.sum() == pytest.approx(total, rel=1e-4)
    # With the potential energy of the positions: the difference telescopes to
    # m g . (v_end - v_start) dt / 2 per ball, tiny against the dissipation here.
    total_pe = w_wall.sum() - d_ke.sum() - d_pe.sum()
    assert abs(total_pe - total) <= 5.0 * m * 9.81 * DT * 5 + 1e-3 * abs(total)


def test_wall_patches_give_a_corner_ball_one_edge_per_wall():
    """With GraphSpec.wall_patches a ball in the corner of floor and side wall has two
    ball-wall edges (floor normal -y, side normal +x), as the DEM has two contacts; the nearest
    wall graph has one."""
    from sgn_jax.geometry import JarParams
    from sgn_jax.scene import analytic_jar_query

    jar = JarParams(radius=0.02, straight_length=0.035, height=0.047, post_radius=0.0,
                    has_post=False)
    n = 2
    corner = np.array([0.0175 + 0.02 - 0.00499, 0.00499, 0.0])   # touches floor and side
    centre = np.array([0.0, 0.02, 0.0])                          # touches nothing
    pos = np.broadcast_to(np.stack([corner, centre]), (W + 1, n, 3))
    window = Window(positions=jnp.asarray(pos), offsets=jnp.zeros((W, 3)),
                    offset_velocities=jnp.zeros((W, 3)), frequency_hz=jnp.asarray(5.0))
    counts = {}
    # jitted: two programs instead of ~250 eager compiles of the jar query's ops
    jar_graph = jax.jit(build_graph, static_argnums=(1, 2, 3))
    for patches in (0, 4):
        spec = GraphSpec(n_particles=n, window=W, ball_radius=R, dt=DT, pp_pair_capacity=1,
                         wall_patches=patches)
        graph, c = jar_graph(window, jar, spec, analytic_jar_query)
        counts[patches] = int(c.n_pw) // 2
        if patches:
            geo = jax.jit(edge_geometry, static_argnums=1)(graph, PHYS)
            normals = np.asarray(geo["normal"])[np.asarray(geo["is_pw"])]
            assert sorted(np.round(normals @ np.array([1.0, 0.0, 0.0]))) == [0.0, 1.0]
            assert sorted(np.round(normals @ np.array([0.0, -1.0, 0.0]))) == [0.0, 1.0]
            assert (np.asarray(geo["gate"])[np.asarray(geo["is_pw"])] == 1).all()
    assert counts == {0: 1, 4: 2}


# patches = 4 in the slow tier: the same rows split
# with the wall-patch edges of a jar with four patches; patches = 0 runs by default.
@pytest.mark.parametrize("patches", [0, pytest.param(4, marks=pytest.mark.slow)])
def test_each_kind_on_its_own_rows_gives_what_both_on_every_row_give(patches):
    """``ContactPhysics.wall_patches`` known (from the config, as the graphs') and the model's
    single-rollout form (``rows_by_kind``): each MLP runs only on its own kind's rows, half the
    work; the impulses are those of running both MLPs on every row (``wall_patches=None``), on
    a scene with ball-ball and ball-wall contacts. So are those of each MLP on its kind's
    acting rows only (``acting_per_ball``), in a block that holds them and in one too small
    for them (the step falls back to the rows by kind)."""
    import dataclasses

    from sgn_jax.geometry import JarParams
    from sgn_jax.scene import analytic_jar_query

    jar = JarParams(radius=0.02, straight_length=0.035, height=0.047, post_radius=0.0,
                    has_post=False)
    rng = np.random.default_rng(7)
    # a small heap on the floor near the side wall, moving: both contact kinds act
    # (more ball-ball and ball-wall rows than N: the ball-wall rows do not start at row 0)
    centres = np.array([[0.025, 0.00499, 0.0], [0.025, 0.0149, 0.0], [0.0151, 0.00499, 0.0],
                        [0.0200, 0.0120, 0.0070], [0.0340, 0.00499, 0.0]])
    vel = rng.normal(0.0, 0.2, (1, 5, 3)) + rng.normal(0.0, 0.02, (W + 1, 5, 3))
    pos = centres[None] + np.cumsum(vel * DT, axis=0) - (vel * DT).sum(0)[None]
    window = Window(positions=jnp.asarray(pos), offsets=jnp.zeros((W, 3)),
                    offset_velocities=jnp.asarray(rng.normal(0.0, 0.1, (W, 3))),
                    frequency_hz=jnp.asarray(5.0))
    spec = dataclasses.replace(GRAPH_SPEC, wall_patches=patches)
    graph, _ = build_graph(window, jar, spec, analytic_jar_query)
    forms = {"rows by kind": {"acting_per_ball": 0.0}, "acting": {},
             "acting, block too small": {"acting_per_ball": 0.2}}   # a block of 1 row

    def step_terms(known, **form):
        net = ContactNet(physics=dataclasses.replace(PHYS, wall_patches=known), hidden=32,
                         mlp_layers=3)
        params = random_params(net, graph, seed=11)
        # rows by kind where the patches are known
        single = net.for_single_rollout().clone(**form)
        return single.apply({"params": params}, graph, method=ContactNet.step_terms)

    both = step_terms(None, acting_per_ball=0.0)
    for change in forms.values():
        own = step_terms(patches, **change)
        gate = np.asarray(both["gate"]) > 0
        geo = edge_geometry(graph, PHYS, primary_only=True)
        assert np.asarray(geo["is_pp"])[gate].any() and np.asarray(geo["is_pw"])[gate].any()
        # more acting contacts of a kind than the block of 1 row: the fallback runs
        assert max(np.sum(np.asarray(geo[k])[gate]) for k in ("is_pp", "is_pw")) > 1
        if patches == 0:
            assert int(np.sum(geo["is_pp"])) + int(np.sum(geo["is_pw"])) > 5
        np.testing.assert_allclose(np.asarray(own["du_n"]), np.asarray(both["du_n"]),
                                   rtol=1e-5, atol=1e-9)
        np.testing.assert_allclose(np.asarray(own["dv"]), np.asarray(both["dv"]),
                                   rtol=1e-5, atol=1e-9)


@pytest.mark.slow   # the charge kind's twin (tests/test_contact_charge.py) runs by default
def test_a_rollout_step_on_the_rows_that_may_act_gives_what_the_whole_graph_gives():
    """``compact_per_ball`` (the single-rollout form, ``ContactNet.rollout_terms``): the step
    on the graph of the edge pairs that may act (``_gate_candidates``, a superset of the gate,
    ``compact_edge_pairs``) gives the whole graph's accelerations, target and ledger, on the
    compacted graph and through the step's choice in a block that holds the candidates;
    with an overlap and a friction sweep, spin and both contact kinds acting."""
    from sgn_jax.surrogate.graph import compact_edge_pairs, with_spins

    rng = np.random.default_rng(3)
    centres = np.array([[0.0, 0.00499, 0.0], [0.0099, 0.00499, 0.0], [0.00495, 0.01347, 0.0],
                        [0.03, 0.00499, 0.0], [0.02, 0.03, 0.0]])
    vel = rng.normal(0.0, 0.3, (1, 5, 3)) + rng.normal(0.0, 0.02, (W + 1, 5, 3))
    pos = centres[None] + np.cumsum(vel * DT, axis=0) - (vel * DT).sum(0)[None]
    window = with_spins(Window(positions=jnp.asarray(pos), offsets=jnp.zeros((W, 3)),
                               offset_velocities=jnp.asarray(rng.normal(0.0, 0.1, (W, 3))),
                               frequency_hz=jnp.asarray(5.0)))
    window = window.replace(spins=jnp.asarray(rng.normal(0.0, 50.0, (5, 3))))
    graph, _ = jax.jit(build_graph, static_argnums=(1, 2, 3))(
        window, None, GRAPH_SPEC, floor_query((0.0, 1.0, 0.0)))
    phys = dataclasses.replace(PHYS, overlap_limit=5e-5, overlap_sweeps=1, friction_sweeps=1)
    net = ContactNet(physics=phys, hidden=16, mlp_layers=2, spin=True)
    params = random_params(net, graph, seed=5, jit=True)

    def run(form, method, g=graph):   # jitted: one program each instead of eager op by op
        return jax.jit(lambda p, g: form.apply({"params": p}, g, method=method))(params, g)

    keep = np.asarray(run(net, ContactNet._gate_candidates))
    geo = run(net, ContactNet._edge_geometry)
    acting = np.asarray(geo["gate"]) > 0
    assert np.asarray(geo["is_pp"])[acting].any() and np.asarray(geo["is_pw"])[acting].any()
    assert np.all(keep[acting]) and keep.sum() < keep.size   # a superset, not every row
    whole = run(net, ContactNet.rollout_terms)
    rows = int(keep.sum())
    compacted = compact_edge_pairs(graph, jnp.asarray(keep), rows)
    assert compacted.senders.shape == (2 * rows,)
    form = net.clone(compact_per_ball=(rows - 0.5) / (2 * 5))   # a block of ceil(2 f N) rows
    outputs = [run(net, ContactNet.rollout_terms, compacted),
               run(form, ContactNet.rollout_terms)]
    # accelerations, target, ledger: each within 1e-5 of its own largest value
    scales = [np.max(np.abs(np.asarray(w))) for w in whole]
    for out in outputs:
        errors = [np.max(np.abs(np.asarray(g) - np.asarray(w))) / scale
                  for g, w, scale in zip(out, whole, scales, strict=True)]
        assert max(errors) < 1e-5, errors
    assert scales[0] > 1.0   # the contacts act


# --------------------------------------------------------------------------------------------
# Spin as state (``ContactNet(spin=True)``, ``[model] spin = true``)


def spinning_scene(seed, rotation=None):
    window, rot = scene(np.random.default_rng(seed), rotation)
    spins = np.random.default_rng(seed + 100).normal(0.0, 60.0, (5, 3))   # rad/s, R w ~ 0.3 m/s
    return window.replace(spins=jnp.asarray(spins @ rot.T)), rot


@pytest.mark.parametrize("friction_sweeps", [0, 3])
def test_spin_conserves_the_pairs_linear_and_angular_momentum(friction_sweeps):
    """The tangential impulse acts at the contact point (the midpoint of a pair) and turns
    both balls, rolling friction is an internal torque: the ball-ball contacts change neither
    the total momentum nor the total angular momentum (about any point) of the balls; nor do
    the friction sweeps' impulses and torques."""
    window, _ = spinning_scene(0)
    terms, _, _ = terms_of(window, spin=True, friction_sweeps=friction_sweeps)
    m, inertia = PHYS.ball_mass, 0.4 * PHYS.ball_mass * R ** 2
    g_dv = np.array([0.0, -9.81 * DT, 0.0])
    # balls 0-3 touch one another, not a wall (ball 4 alone is on the floor)
    dp = m * (np.asarray(terms["dv"][:4], np.float64) - g_dv)
    dl_spin = inertia * np.asarray(terms["dw"][:4], np.float64)
    x = np.asarray(window.positions[-1, :4], np.float64)
    assert np.abs(dl_spin).max() > 1e-9 and np.abs(dp).max() > 1e-6
    np.testing.assert_allclose(dp.sum(axis=0), 0.0, atol=1e-6 * np.abs(dp).max())
    dl = np.cross(x, dp).sum(axis=0) + dl_spin.sum(axis=0)
    np.testing.assert_allclose(dl, 0.0, atol=1e-5 * (np.abs(dl_spin).max()
                                                      + np.abs(np.cross(x, dp)).max()))


def test_spin_rotated_scene_gives_rotated_accelerations_and_spin_changes():
    window, _ = spinning_scene(2)
    terms, params, _ = terms_of(window, spin=True)
    rot = rotation_matrix(np.random.default_rng(1))
    window_r, _ = spinning_scene(2, rot)
    terms_r, _, _ = terms_of(window_r, up=rot @ np.array([0.0, 1.0, 0.0]),
                             gravity=rot @ np.array([0.0, -9.81, 0.0]), params=params, spin=True)
    for name in ("dv", "dw"):
        a, a_r = np.asarray(terms[name][:5]), np.asarray(terms_r[name][:5])
        np.testing.assert_allclose(a_r, a @ rot.T, atol=2e-5 * np.abs(a).max())
    # ...and permuting the balls permutes them
    perm = np.array([3, 0, 4, 1, 2])
    window_p = window.replace(positions=window.positions[:, perm], spins=window.spins[perm])
    terms_p, _, _ = terms_of(window_p, params=params, spin=True)
    np.testing.assert_allclose(np.asarray(terms_p["dw"][:5]), np.asarray(terms["dw"][:5])[perm],
                               rtol=1e-5, atol=1e-6 * float(jnp.abs(terms["dw"]).max()))


def test_spin_model_needs_spins_in_the_graph():
    from sgn_jax.surrogate.contact import ContactModelError

    window, _ = scene(np.random.default_rng(0))            # no spins
    with pytest.raises(ContactModelError, match="spins"):
        terms_of(window, spin=True)


def test_rolling_friction_brakes_a_twisting_ball_and_never_reverses_it():
    """A ball resting on the floor of a still jar and turning about the vertical: no slip at
    the contact point (w x n = 0), so only rolling friction acts: it slows the turn by at
    most mu_r R J_n / I per step and never reverses it."""
    r0 = R - 0.5e-6
    pos = np.tile(np.array([[0.0, r0, 0.0], [0.03, r0, 0.0], [0.06, r0, 0.0],
                            [0.09, r0, 0.0], [0.12, r0, 0.0]]), (W + 1, 1, 1))
    spins = np.array([[0.0, 5.0, 0.0], [0.0, 1e-3, 0.0], [0.0, -40.0, 0.0], [0, 0, 0],
                      [0, 0, 0]])
    window = Window(positions=jnp.asarray(pos), offsets=jnp.zeros((W, 3)),
                    offset_velocities=jnp.zeros((W, 3)), frequency_hz=jnp.asarray(5.0),
                    spins=jnp.asarray(spins))
    terms, _, _ = terms_of(window, spin=True)
    dw = np.asarray(terms["dw"][:3], np.float64)
    w_end = spins[:3] + dw
    assert (terms["du_n"] > 0).any()
    # never reversed (to float32 rounding of the cap I |w|)
    assert (w_end[:, 1] * np.sign(spins[:3, 1]) >= -1e-6 * np.abs(spins[:3, 1])).all()
    assert (np.abs(w_end[:, 1]) <= np.abs(spins[:3, 1]) + 1e-9).all()   # only braked
    np.testing.assert_allclose(dw[:, [0, 2]], 0.0, atol=1e-9)
    assert abs(dw[2, 1]) > 0


@pytest.mark.slow
def test_spin_energy_ledger_closes_over_a_rollout():
    """With spin, the ledger counts the rotational energy: jar work + gravity's work - change
    of translational and rotational kinetic energy = the model's dissipation, every step and
    over 200 steps (the rollout integrates the spins: w_{n+1} = w_n + dw). With the overlap
    limit and its sweeps and the friction sweeps on (the scene's cluster starts 0.1 mm deep),
    whose impulses and torques are in the ledger like the network's."""
    from sgn_jax.surrogate.graph import slide_window

    window, _ = spinning_scene(5)
    query = floor_query((0.0, 1.0, 0.0))
    graph, _ = build_graph(window, None, GRAPH_SPEC, query)
    net = net_with((0.0, -9.81, 0.0), spin=True)
    net = net.clone(physics=dataclasses.replace(net.physics, overlap_limit=5e-5,
                                                overlap_sweeps=2, friction_sweeps=2))
    params = random_params(net, graph, seed=4)
    first = net.apply({"params": params}, graph, method=ContactNet.step_terms)
    assert np.asarray(first["at_floor"]).any()
    g = np.array([0.0, -9.81, 0.0])
    m, inertia = PHYS.ball_mass, 0.4 * PHYS.ball_mass * R ** 2

    @jax.jit
    def step(window):
        graph, _ = build_graph(window, None, GRAPH_SPEC, query)
        return net.apply({"params": params}, graph, method=ContactNet.step_terms)

    rows, t = [], 0.0
    for _s in range(200):
        terms = step(window)
        pos = np.asarray(window.positions, np.float64)
        w_now = np.asarray(window.spins, np.float64)
        v_now = (pos[-1] - pos[-2]) / DT
        v_next = v_now + np.asarray(terms["dv"][:5], np.float64)
        w_next = w_now + np.asarray(terms["dw"][:5], np.float64)
        x_next = pos[-1] + v_next * DT
        d_ke = 0.5 * m * np.sum(v_next ** 2 - v_now ** 2)
        d_rot = 0.5 * inertia * np.sum(w_next ** 2 - w_now ** 2)
        w_grav = m * np.sum((0.5 * (v_now + v_next)) @ g) * DT
        rows.append((float(terms["work_wall"][0]), w_grav, d_ke, d_rot,
                     float(terms["diss_pp"][0]) + float(terms["diss_pw"][0])))
        t += DT
        jar_v = np.array([0.3 * np.cos(40 * t), 0.0, 0.3 * np.sin(40 * t)])
        jar_x = np.asarray(window.offsets[-1]) + jar_v * DT
        window = slide_window(window, jnp.asarray(x_next), jnp.asarray(jar_x),
                              jnp.asarray(jar_v)).replace(spins=jnp.asarray(w_next))
    w_wall, w_grav, d_ke, d_rot, diss = (np.array(c) for c in zip(*rows, strict=True))
    assert np.abs(d_rot).sum() > 1e-3 * np.abs(d_ke).sum()   # the spins carry energy
    assert np.isfinite(diss).all() and np.abs(diss).sum() > 0
    flow = np.abs(w_wall) + np.abs(d_ke) + np.abs(w_grav) + np.abs(d_rot)
    np.testing.assert_array_less(np.abs(w_wall + w_grav - d_ke - d_rot - diss),
                                 1e-4 * flow + 1e-12)
    assert diss.sum() == pytest.approx(w_wall.sum() + w_grav.sum() - d_ke.sum() - d_rot.sum(),
                                       rel=1e-4)
    # without the rotational energy the ledger would not close: the check can fail
    assert abs(d_rot.sum()) > 1e-3 * abs(diss.sum())


@pytest.mark.parametrize("rolling", [0.0, 0.045])
def test_the_per_contact_damping_target_splits_each_contacts_losses(rolling):
    """``damping_target = "contact"``: the target is each contact's normal loss whole and its
    tangential loss (less rolling friction's) by the kind's share. With the share 1 and no
    rolling friction it is the model's whole dissipation; with the share 0 the normal losses
    alone (positive, smaller); linear in the share between; rolling friction's loss (a
    spinning scene) is never counted. The per-kind target (the default) is share x losses."""
    window, _ = spinning_scene(3)
    graph, _ = build_graph(window, None, GRAPH_SPEC, floor_query((0.0, 1.0, 0.0)))
    net = net_with((0.0, -9.81, 0.0), spin=True)
    phys = dataclasses.replace(net.physics, rolling_friction=rolling)
    by_kind = net.clone(physics=phys)
    by_contact = net.clone(physics=dataclasses.replace(phys, damping_target="contact"))
    params = random_params(by_kind, graph, seed=2)

    def target(model, share):
        logit = np.log(share / (1.0 - share)) if 0 < share < 1 else 30.0 * (2 * share - 1)
        p = {**params, "share_logit": jnp.full((2,), logit, jnp.float32)}
        terms = model.apply({"params": p}, graph, method=ContactNet.step_terms)
        return (float(terms["dE_target"][0]),
                float(terms["diss_pp"][0]) + float(terms["diss_pw"][0]))

    whole, losses = target(by_contact, 1.0)
    normal, _ = target(by_contact, 0.0)
    half, _ = target(by_contact, 0.5)
    assert losses > 0 and 0 < normal < whole
    assert half == pytest.approx(0.5 * (normal + whole), rel=1e-4)
    if rolling == 0.0:
        assert whole == pytest.approx(losses, rel=1e-4)
    else:   # rolling friction brakes the spins: its loss is left out
        assert whole < losses * (1 - 1e-4)
    kind_half, _ = target(by_kind, 0.5)
    assert kind_half == pytest.approx(0.5 * losses, rel=1e-4)


def test_a_contact_config_refuses_an_unknown_damping_target_and_an_exact_rebound_alone():
    from sgn_jax.config import ConfigError, ModelConfig
    from sgn_jax.surrogate.contact import ContactModelError

    with pytest.raises(ConfigError, match="damping_target"):
        ModelConfig(kind="contact", hidden=8, mlp_layers=2, damping_target="share")
    with pytest.raises(ConfigError, match="law_rebound_exact"):
        ModelConfig(kind="contact", hidden=8, mlp_layers=2, overlap_limit=5e-5,
                    overlap_law_factor=1.5, law_rebound_exact="wall")
    with pytest.raises(ConfigError, match="law_rebound_exact"):
        ModelConfig(kind="contact", hidden=8, mlp_layers=2, overlap_limit=5e-5,
                    overlap_law_factor=1.5, law_rebound=True, law_rebound_exact="walls")
    with pytest.raises(ContactModelError, match="damping_target"):
        ContactPhysics(damping_target="share")


@pytest.mark.slow
def test_the_rollout_integrates_the_spins_of_a_spin_model():
    """The rollout carries the spins: w_{n+1} = w_n + dw of the model's step, saved per frame
    (``RolloutResult.spins``, the prediction's ``omega_model``); a window without spins starts
    from zeros."""
    from sgn_jax.motion import CircleMotion
    from sgn_jax.surrogate.rollout import jar_state_window, make_rollout, model_predictor

    window, _ = spinning_scene(7)
    query = floor_query((0.0, 1.0, 0.0))
    graph, _ = build_graph(window, None, GRAPH_SPEC, query)
    net = net_with((0.0, -9.81, 0.0), spin=True)
    params = random_params(net, graph, seed=2)
    motion = CircleMotion(rpm=jnp.asarray(300.0), amplitude=jnp.asarray(0.0))
    run = make_rollout(GRAPH_SPEC, model_predictor(net), 4, 1, snap_back=False, query=query)
    res = run(params, None, window, motion, None, 0.0)
    spins = np.asarray(res.spins)
    assert spins.shape == (5, 5, 3)
    np.testing.assert_array_equal(spins[0], np.asarray(window.spins))
    # the rollout's first step: the window's jar state recomputed from the motion (a still jar)
    graph0, _ = build_graph(jar_state_window(window, motion, 0.0, DT), None, GRAPH_SPEC, query)
    first = net.apply({"params": params}, graph0, method=ContactNet.step_terms)
    dw = np.asarray(first["dw"][:5], np.float64)
    assert np.abs(dw).max() > 1.0
    np.testing.assert_allclose(spins[1] - spins[0], dw, rtol=0, atol=1e-5 * np.abs(dw).max())
    assert np.abs(spins[-1] - spins[0]).max() > 0
    assert "omega_model" in res.prediction_arrays()
    bare = run(params, None, window.replace(spins=None), motion, None, 0.0)
    np.testing.assert_array_equal(np.asarray(bare.spins[0]), 0.0)


def test_a_fresh_spin_model_sticks_a_sliding_ball_into_rolling_within_the_cone():
    """With spin, Coulomb friction with sticking is built in: a freshly initialised model
    (share of the slip stopped per step s = 1) stops the contact point's slip of a ball that
    slides slowly on the floor within one step, by turning it (rolling, no slip: v = -w x R n),
    and a fast slide is limited by the cone (|du_t| = mu du_n, the slip only slowed)."""
    r0 = R - 0.5e-6
    slide = np.array([0.01, 0.0, 0.0, 2.0, 0.0, 0.0])        # m/s along x per ball (0, 3: test)
    base = np.array([[0.0, r0, 0.0], [0.03, r0, 0.0], [0.06, r0, 0.0], [0.09, r0, 0.0],
                     [0.12, r0, 0.0]])
    steps = np.arange(-W, 1)[:, None, None] * DT
    pos = base[None] + steps * np.stack([slide[:5], 0 * slide[:5], 0 * slide[:5]], -1)[None]
    window = Window(positions=jnp.asarray(pos), offsets=jnp.zeros((W, 3)),
                    offset_velocities=jnp.zeros((W, 3)), frequency_hz=jnp.asarray(5.0),
                    spins=jnp.zeros((5, 3)))
    graph, _ = build_graph(window, None, GRAPH_SPEC, floor_query((0.0, 1.0, 0.0)))
    net = net_with((0.0, -9.81, 0.0), spin=True)
    params = net.init(jax.random.PRNGKey(0), graph)["params"]
    terms = net.apply({"params": params}, graph, method=ContactNet.step_terms)
    v_end = slide[:5, None] * np.array([1.0, 0, 0]) + np.asarray(terms["dv"][:5], np.float64)
    w_end = np.asarray(terms["dw"][:5], np.float64)
    contact_slip = v_end + np.cross(w_end, np.array([0.0, -R, 0.0]))     # contact point at -R y
    assert abs(contact_slip[0, 0]) < 0.05 * 0.01        # the slow ball: stuck, now rolling
    assert w_end[0, 2] < 0 and v_end[0, 0] > 0          # turning the right way
    # the fast ball: friction at the cone, the slip only slowed
    du_n, du_t = np.asarray(terms["du_n"]), np.asarray(terms["du_t"])
    assert (np.abs(du_t) <= PHYS.friction * du_n * (1 + 1e-6) + 1e-12).all()
    assert contact_slip[3, 0] > 1.5


def test_the_stick_impulse_is_relaxed_by_the_balls_number_of_contacts():
    """A ball in a bed has several contacts, each computing its stick impulse as if it were the
    ball's only one: each is divided by the larger number of acting contacts of its balls."""
    window, _ = spinning_scene(0)
    graph, _ = build_graph(window, None, GRAPH_SPEC, floor_query((0.0, 1.0, 0.0)))
    geo = edge_geometry(graph, PHYS, primary_only=True, spin=True)
    gate, is_pp = np.asarray(geo["gate"]), np.asarray(geo["is_pp"])
    recv, send = np.asarray(geo["receivers"]), np.asarray(geo["senders"])
    count = np.zeros(graph.nodes["features"].shape[0])
    np.add.at(count, recv, gate)
    np.add.at(count, send, gate * is_pp)
    expected = np.maximum(np.maximum(count[recv], np.where(is_pp, count[send], 0.0)), 1.0)
    np.testing.assert_array_equal(np.asarray(geo["contacts_max"]), expected)
    assert expected[gate > 0].max() >= 2     # the cluster's balls touch two others


def test_friction_sweeps_stop_a_packed_clusters_slip_within_the_cone():
    """``friction_sweeps``: the one relaxed stick per contact leaves a packed cluster's
    contact points slipping (each ball's contacts fight); the projected Jacobi sweeps of
    Coulomb sticking stop most of that slip, and every contact's total tangential impulse
    stays inside its cone mu m* du_n. A model without spin refuses them before any work."""
    # five balls in a touching row on the floor of a still jar, sliding and turning slowly
    rng = np.random.default_rng(3)
    r0 = R - 1e-6
    base = np.array([[2 * k * (R - 0.5e-6), r0, 0.0] for k in range(5)])
    vel = rng.normal(0.0, 5e-3, (5, 3)) * np.array([1.0, 0.0, 1.0])     # m/s, along the floor
    pos = base[None] + np.arange(-W, 1)[:, None, None] * DT * vel[None]
    window = Window(positions=jnp.asarray(pos), offsets=jnp.zeros((W, 3)),
                    offset_velocities=jnp.zeros((W, 3)), frequency_hz=jnp.asarray(5.0),
                    spins=jnp.asarray(rng.normal(0.0, 2.0, (5, 3))))     # R w ~ 1 cm/s
    graph, _ = build_graph(window, None, GRAPH_SPEC, floor_query((0.0, 1.0, 0.0)))
    geo = edge_geometry(graph, PHYS, primary_only=True, spin=True)
    gate, normal = np.asarray(geo["gate"]) > 0, np.asarray(geo["normal"], np.float64)
    recv, send = np.asarray(geo["receivers"]), np.asarray(geo["senders"])
    is_pw, arm = np.asarray(geo["is_pw"]) > 0, np.asarray(geo["arm"], np.float64)
    v0 = np.asarray(geo["v_node"], np.float64)
    w0 = np.asarray(geo["w_node"], np.float64)
    wall_end = np.asarray(geo["u_wall"] + geo["jar_dv"], np.float64)
    net = net_with((0.0, -9.81, 0.0), spin=True)
    params = random_params(net, graph, seed=2)

    def end_slip_and_impulse(sweeps):
        model = net.clone(physics=dataclasses.replace(net.physics, friction_sweeps=sweeps))
        terms = model.apply({"params": params}, graph, method=ContactNet.step_terms)
        v = v0 + np.asarray(terms["dv"], np.float64)
        w = w0 + np.asarray(terms["dw"], np.float64)
        v_rel = np.where(is_pw[:, None], wall_end, v[send]) - v[recv]
        v_t = v_rel - np.sum(v_rel * normal, -1)[:, None] * normal
        slip = v_t - arm[:, None] * np.cross(w[recv] + np.where(is_pw[:, None], 0.0, w[send]),
                                             normal)
        return np.linalg.norm(slip, axis=-1)[gate], terms

    before, _ = end_slip_and_impulse(0)
    after, row_terms = end_slip_and_impulse(8)
    assert before.max() > 1e-3                                   # the single pass leaves slip
    assert np.sqrt(np.mean(after ** 2)) < 0.3 * np.sqrt(np.mean(before ** 2))
    # every contact's total tangential impulse (learned and swept) inside its cone; in a
    # cluster that spins fast (R w ~ 0.3 m/s) some contacts slide at it
    fast_terms = terms_of(spinning_scene(3)[0], spin=True, friction_sweeps=8)[0]
    for terms in (row_terms, fast_terms):
        du_n, du_t = np.asarray(terms["du_n"], np.float64), np.asarray(terms["du_t"], np.float64)
        assert (du_n >= 0).all()
        assert (du_t <= PHYS.friction * du_n * (1 + 1e-5) + 1e-12).all()
    du_n, du_t = np.asarray(fast_terms["du_n"], np.float64), np.asarray(fast_terms["du_t"],
                                                                         np.float64)
    assert (du_t[du_n > 0] >= PHYS.friction * du_n[du_n > 0] * (1 - 1e-4)).any()
    from sgn_jax.api import load_config, replace_section
    from sgn_jax.config import ConfigError

    with pytest.raises(ConfigError, match="friction_sweeps"):
        replace_section(load_config("emax_300rpm"), "model", kind="contact", friction_sweeps=2)


def test_the_sgn_refuses_spin_before_any_work():
    from sgn_jax.api import load_config, replace_section
    from sgn_jax.surrogate.model import ModelKindError

    cfg = replace_section(load_config("emax_300rpm"), "model", spin=True)   # kind "sgn"
    with pytest.raises(ModelKindError, match="spin"):
        model_factory("sgn").build_model(cfg)
    contact = replace_section(cfg, "model", kind="contact", hidden=8, mlp_layers=2)
    assert model_factory("contact").build_model(contact).spin


@pytest.mark.parametrize("spin, law_factor", [(False, 0.0), (True, 1.5)])
def test_the_overlap_limit_stops_fast_impacts_within_it_and_keeps_the_physics(spin, law_factor):
    """The rigid limit of the contact law (``overlap_limit``): a ball hitting the floor at 3 m/s
    and a head-on pair closing at 4 m/s, both 0.1 mm apart, end the step no deeper than the
    limit; a fresh network alone (du_n = 0.3 softplus(0) = 0.21 m/s) lets them sink past it.
    With ``overlap_law_factor`` c the limit of a fast impact is c times the DEM law's deepest
    overlap at its approach speed, deeper than the constant part (there: 8 m/s and 10 m/s). The raised impulse is still
    equal and opposite (the pair's momentum is conserved) and repulsive, and contacts the
    limit does not touch keep the network's impulse."""
    base, gap = 1e-4 if law_factor == 0 else 5e-5, 1e-4
    centres = np.array([[0.0, R + gap, 0.0],                           # onto the floor
                        [0.05, 0.05, 0.0], [0.05 + 2 * R + gap, 0.05, 0.0],  # head-on pair
                        [0.10, 0.05, 0.0], [0.10 + 2 * R - 2e-6, 0.05, 0.0]])  # slow, touching
    fall, closing = (3.0, 4.0) if law_factor == 0 else (8.0, 10.0)
    vel = np.array([[0.0, -fall, 0.0], [closing / 2, 0.0, 0.0], [-closing / 2, 0.0, 0.0],
                    [0.01, 0.0, 0.0], [-0.01, 0.0, 0.0]])
    pos = centres[None] + np.arange(-W, 1)[:, None, None] * DT * vel[None]
    window = Window(positions=jnp.asarray(pos), offsets=jnp.zeros((W, 3)),
                    offset_velocities=jnp.zeros((W, 3)), frequency_hz=jnp.asarray(5.0),
                    spins=jnp.zeros((5, 3)) if spin else None)
    graph, _ = build_graph(window, None, GRAPH_SPEC, floor_query((0.0, 1.0, 0.0)))
    limits = np.array([max(base, law_factor * PHYS.overlap_peak_pw * fall ** 0.8),
                       max(base, law_factor * PHYS.overlap_peak_pp * closing ** 0.8)])

    def end_of_step(overlap_limit):
        phys = ContactPhysics(**{**PHYS.__dict__, "overlap_limit": overlap_limit,
                                 "overlap_law_factor": law_factor if overlap_limit else 0.0})
        net = ContactNet(physics=phys, hidden=16, mlp_layers=2, spin=spin)
        params = net.init(jax.random.PRNGKey(0), graph)["params"]
        terms = net.apply({"params": params}, graph, method=ContactNet.step_terms)
        v_end = vel + np.asarray(terms["dv"][:5], np.float64)
        x_end = centres + v_end * DT
        gaps = np.array([x_end[0, 1] - R, x_end[2, 0] - x_end[1, 0] - 2 * R,
                         x_end[4, 0] - x_end[3, 0] - 2 * R])
        return gaps, v_end, terms

    free, v_free, _ = end_of_step(0.0)
    assert (free[:2] < -1.5 * limits).all()                        # the network alone sinks in
    limited, v_lim, terms = end_of_step(base)
    assert (limited[:2] >= -limits * (1 + 1e-3)).all()
    assert (limited[:2] < 0).all()                                 # a floor, not a bounce
    if law_factor:
        assert (limits > 2 * base).all()                           # fast: deeper than at rest
    # the pair: equal and opposite, so its momentum is unchanged (no gravity along x)
    assert abs(v_lim[1, 0] + v_lim[2, 0]) < 1e-5 * abs(v_lim[1, 0] - vel[1, 0])
    assert (np.asarray(terms["du_n"]) >= 0).all()
    # the slow touching pair is below its floor: the network's impulse, untouched
    np.testing.assert_allclose(v_lim[3:], v_free[3:], rtol=0, atol=1e-7)
    assert int(np.asarray(terms["at_floor"]).sum()) == 2


@pytest.mark.slow
def test_overlap_sweeps_keep_a_chain_within_the_limit(spin=False):
    """``overlap_sweeps``: a ball falls at 6 m/s onto a ball that rests on the floor. The
    per-contact floor stops the pair within the limit by pushing the resting ball down, and
    nothing stops that ball sinking into the floor (its own contact sees no approach). Jacobi
    sweeps over all contacts bring both contacts towards the limit (the network's own impulse
    on the resting ball, up into the falling one, also deepens the pair); the impulses stay
    repulsive, and a ball far from both keeps the network's impulse."""
    limit, gap = 5e-5, 1e-4
    centres = np.array([[0.0, R - 1e-6, 0.0], [0.0, 3 * R - 1e-6 + gap, 0.0],
                        [0.03, 0.02, 0.0]])                      # resting, falling, far
    vel = np.array([[0.0, 0.0, 0.0], [0.0, -6.0, 0.0], [0.1, 0.0, 0.0]])
    pos = centres[None] + np.arange(-W, 1)[:, None, None] * DT * vel[None]
    window = Window(positions=jnp.asarray(pos), offsets=jnp.zeros((W, 3)),
                    offset_velocities=jnp.zeros((W, 3)), frequency_hz=jnp.asarray(5.0),
                    spins=jnp.zeros((3, 3)) if spin else None)
    spec = dataclasses.replace(GRAPH_SPEC, n_particles=3)
    graph, _ = build_graph(window, None, spec, floor_query((0.0, 1.0, 0.0)))

    params = ContactNet(physics=PHYS, hidden=16, mlp_layers=2, spin=spin).init(
        jax.random.PRNGKey(0), graph)["params"]    # the sweeps add no parameters

    def end_of_step(sweeps):
        phys = dataclasses.replace(PHYS, overlap_limit=limit, overlap_sweeps=sweeps)
        net = ContactNet(physics=phys, hidden=16, mlp_layers=2, spin=spin)
        terms = net.apply({"params": params}, graph, method=ContactNet.step_terms)
        x_end = centres + (vel + np.asarray(terms["dv"][:3], np.float64)) * DT
        return np.array([x_end[0, 1] - R, x_end[1, 1] - x_end[0, 1] - 2 * R]), terms, x_end

    floor_only, _, x_free = end_of_step(0)
    assert floor_only[0] < -2 * limit                  # the resting ball pushed into the floor
    swept, terms, x_end = end_of_step(4)
    # Relaxed Jacobi sweeps converge slowly in a chain held by a wall (each sweep's
    # correction of one contact deepens the other), but surely, and never past the limit.
    assert swept.min() > 0.6 * floor_only.min()
    deeper, _, _ = end_of_step(8)
    assert (deeper >= -1.7 * limit).all() and deeper.min() > swept.min()
    assert (swept < 0).all() and (deeper < 0).all()             # a floor, not a bounce
    assert (np.asarray(terms["du_n"]) >= 0).all()
    np.testing.assert_allclose(x_end[2], x_free[2], rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="overlap_sweeps"):
        dataclasses.replace(PHYS, overlap_sweeps=2)     # no limit to sweep for


def test_the_law_scaled_limit_is_the_dem_laws_own_deepest_overlap():
    """``head_on_peak_overlap``: the DEM law's impact is self-similar (peak ~ v^0.8), and the
    contact model's config reads the peaks from its material; a law factor needs a limit at rest."""
    from sgn_jax.api import load_config, replace_section
    from sgn_jax.config import ConfigError
    from sgn_jax.dem.contact import head_on_peak_overlap, make_contact_law
    from sgn_jax.surrogate.contact import physics_from_config

    cfg = replace_section(load_config("emax_300rpm"), "model", kind="contact", hidden=8,
                          mlp_layers=2, overlap_limit=5e-5, overlap_law_factor=1.5)
    m = cfg.material
    phys = physics_from_config(cfg)
    law = make_contact_law(m.young, m.poisson, m.restitution, m.friction, m.rolling_friction,
                           phys.ball_radius, phys.ball_mass)
    assert phys.overlap_peak_pw == pytest.approx(head_on_peak_overlap(law), rel=1e-12)
    assert head_on_peak_overlap(law, 4.0) == pytest.approx(4.0 ** 0.8 * phys.overlap_peak_pw,
                                                          rel=2e-3)
    # two equal balls: half the reduced mass and radius, a shallower peak than on a wall
    assert 0.8 * phys.overlap_peak_pw < phys.overlap_peak_pp < phys.overlap_peak_pw
    with pytest.raises(ConfigError, match="overlap_limit"):
        replace_section(cfg, "model", overlap_limit=0.0)


def fresh_impact_scene(v):
    """(vel (5, 3), graph): balls 0 and 1 falling onto the floor at v, ball 0 in contact since
    1.8 slots (its gap open at the oldest slot: a fresh impact), ball 1 touching within this
    step, ball 2 resting, balls 3 and 4 far from everything."""
    vel = np.zeros((5, 3))
    vel[:2, 1] = -v
    centres = np.array([[0.0, R - 1.8 * v * DT, 0.0],     # fresh: open at the oldest slot
                        [0.03, R + 0.5 * v * DT, 0.0],    # will touch within this step
                        [0.06, R - 1e-6, 0.0],            # resting
                        [0.09, 0.05, 0.0], [0.12, 0.05, 0.0]])   # far from everything
    pos = centres[None] + np.arange(-W, 1)[:, None, None] * DT * vel[None]   # W + 1 positions
    window = Window(positions=jnp.asarray(pos), offsets=jnp.zeros((W, 3)),
                    offset_velocities=jnp.zeros((W, 3)), frequency_hz=jnp.asarray(5.0))
    return vel, build_graph(window, None, GRAPH_SPEC, floor_query((0.0, 1.0, 0.0)))[0]


def test_a_fresh_impact_ends_with_the_laws_rebound_once_its_contact_time_has_passed():
    """``law_rebound`` (``rebound_time_pp/pw``): a ball that met the floor at 0.3 m/s 2.8 slots
    before the end of the step, longer than the law's contact time there (t_c = ratio peak
    v^0.8 / v = 225 us), ends the step leaving the floor at e v at least; one whose contact
    began within the step (50 us before its end) and one resting on the floor keep the
    network's impulse, as without the rule."""
    v, e, ratio = 0.3, 0.74, 3.4
    vel, graph = fresh_impact_scene(v)

    def end_velocity(rebound_time):
        phys = ContactPhysics(**{**PHYS.__dict__, "overlap_limit": 5e-5,
                                 "overlap_law_factor": 1.5, "rebound_time_pp": rebound_time,
                                 "rebound_time_pw": rebound_time, "restitution": e})
        net = ContactNet(physics=phys, hidden=16, mlp_layers=2, spin=False)
        params = net.init(jax.random.PRNGKey(0), graph)["params"]
        terms = net.apply({"params": params}, graph, method=ContactNet.step_terms)
        return vel + np.asarray(terms["dv"][:5], np.float64)

    t_c = ratio * PHYS.overlap_peak_pw * v ** 0.8 / v
    assert 2.0 * DT < t_c < 2.8 * DT
    without, with_rule = end_velocity(0.0), end_velocity(ratio)
    assert without[0, 1] < e * v - 0.05                   # the network alone: no such rebound
    assert with_rule[0, 1] >= e * v - 1e-6                # leaving the floor at e v (float32)
    np.testing.assert_allclose(with_rule[1:], without[1:], rtol=0, atol=1e-12)


def hard_push_end_velocity(v, e, exact, ratio=3.4):
    """The balls' velocities (5, 3) at the end of the step of :func:`fresh_impact_scene` under
    a network whose ball-wall normal impulse is large everywhere, with ``rebound_exact``."""
    vel, graph = fresh_impact_scene(v)
    phys = ContactPhysics(**{**PHYS.__dict__, "overlap_limit": 5e-5,
                             "overlap_law_factor": 1.5, "rebound_time_pp": ratio,
                             "rebound_time_pw": ratio, "restitution": e,
                             "rebound_exact": exact})
    net = ContactNet(physics=phys, hidden=16, mlp_layers=2, spin=False)
    params = net.init(jax.random.PRNGKey(0), graph)["params"]
    last = max(k for k in params["pw_net"] if k.startswith("dense_"))
    bias = params["pw_net"][last]["bias"]
    params = {**params, "pw_net": {**params["pw_net"], last: {
        **params["pw_net"][last], "bias": bias.at[0].set(8.0)}}}   # pushes hard
    terms = net.apply({"params": params}, graph, method=ContactNet.step_terms)
    return vel + np.asarray(terms["dv"][:5], np.float64)


def test_the_exact_law_rebound_caps_a_network_that_pushes_harder():
    """``rebound_exact`` (``[model] law_rebound_exact``): the same fresh impact as above, with a
    network whose normal impulse is large everywhere, ends leaving the floor at e v exactly
    (not faster, as the floor alone lets it); the contact that began within the step and the
    resting one keep the network's impulse."""
    v, e = 0.3, 0.74
    floor_only, exact = (hard_push_end_velocity(v, e, x) for x in ("off", "all"))
    assert floor_only[0, 1] > e * v + 0.05                 # the network pushes past e v
    assert exact[0, 1] == pytest.approx(e * v, abs=1e-5)   # the law's rebound, exactly
    np.testing.assert_allclose(exact[1:], floor_only[1:], rtol=0, atol=1e-12)
    # "wall": the same at these ball-wall contacts (ball-ball ones: the next test) but the
    # resting ball's: closed over the whole window, it separates no faster than e times the
    # window's largest closing speed (here none), where "all" lets the network push it off
    wall = hard_push_end_velocity(v, e, "wall")
    np.testing.assert_array_equal(wall[:2], exact[:2])
    assert exact[2, 1] > 0.05 and wall[2, 1] < 1e-3
    np.testing.assert_array_equal(wall[3:], exact[3:])
    from sgn_jax.surrogate.contact import ContactModelError

    with pytest.raises(ContactModelError, match="rebound_exact"):
        ContactPhysics(rebound_exact="all")
    with pytest.raises(ContactModelError, match="rebound_exact"):
        ContactPhysics(rebound_exact=True)


def test_the_fresh_exact_rebound_caps_an_impact_from_its_first_step():
    """``rebound_exact = "fresh"``: the fresh impact past its contact time ends at e v, as with
    "all"; the ball that meets the floor within this step (fresh, before its contact time),
    which "all" leaves to a network that pushes hard, leaves the floor no faster than e times
    its closing speed either; the resting ball (closed over the window) keeps the network's
    push, and the far balls are untouched."""
    v, e = 0.3, 0.74
    exact, fresh = (hard_push_end_velocity(v, e, x) for x in ("all", "fresh"))
    assert fresh[0, 1] == pytest.approx(e * v, abs=1e-5)
    assert exact[1, 1] > e * v + 0.05                       # "all": the network's push
    assert 0.0 < fresh[1, 1] <= e * v + 1e-5                # "fresh": at most e v
    np.testing.assert_array_equal(fresh[2:], exact[2:])
    assert fresh[2, 1] > 0.05


def test_the_exact_law_rebound_on_walls_leaves_a_ball_ball_impact_to_the_network():
    """``rebound_exact = "wall"`` caps ball-wall contacts only: a ball falling at v onto a ball
    that rests on the floor (a fresh ball-ball impact past its contact time) gets the rebound's
    ceiling with "all" and none with "wall"; the resting ball's floor contact (closed over the
    window, not fresh) gets one with "wall" only: e times the closing speed that reached the
    ball through its struck ball-ball contact (alone on the floor it would be about zero, as
    the test above shows)."""
    v, e, ratio = 0.3, 0.74, 3.4
    vel = np.zeros((5, 3))
    vel[0, 1] = -v
    centres = np.array([[0.0, 3 * R - 1e-6 - 1.8 * v * DT, 0.0],   # falling onto ball 1
                        [0.0, R - 1e-6, 0.0],                     # resting on the floor
                        [0.05, 0.05, 0.0], [0.08, 0.05, 0.0], [0.11, 0.05, 0.0]])
    pos = centres[None] + np.arange(-W, 1)[:, None, None] * DT * vel[None]
    window = Window(positions=jnp.asarray(pos), offsets=jnp.zeros((W, 3)),
                    offset_velocities=jnp.zeros((W, 3)), frequency_hz=jnp.asarray(5.0))
    graph = build_graph(window, None, GRAPH_SPEC, floor_query((0.0, 1.0, 0.0)))[0]

    def ceilings(exact):
        phys = ContactPhysics(**{**PHYS.__dict__, "overlap_limit": 5e-5,
                                 "overlap_law_factor": 1.5, "rebound_time_pp": ratio,
                                 "rebound_time_pw": ratio, "restitution": e,
                                 "rebound_exact": exact})
        geo = edge_geometry(graph, phys, primary_only=True)
        pair = np.asarray(geo["is_pp"] & (geo["gate"] > 0))
        resting = np.asarray(geo["is_pw"] & (geo["gate"] > 0))
        assert pair.sum() == 1 and resting.sum() == 1
        ceiling = np.asarray(geo["ceiling"])
        return ceiling[pair][0], ceiling[resting][0]

    pair_all, resting_all = ceilings("all")
    pair_wall, resting_wall = ceilings("wall")
    assert np.isfinite(pair_all) and pair_all > 0       # the pair's rebound, capped
    assert np.isinf(pair_wall)                          # left to the network
    assert np.isinf(resting_all)
    assert resting_wall == pytest.approx(e * v, abs=2e-3)   # +- gravity over one step


@pytest.mark.parametrize("per_contact", [False, True])
def test_the_scaled_inputs_are_each_columns_clip_or_tanh(per_contact):
    """_scaled_inputs with constant scales (the contact kind) and with scales per contact (the
    charge kind, one elementwise expression over all columns) gives each column's own
    ``clip(x / coarse)`` or ``tanh(x / fine)``, in the documented order."""
    rng = np.random.default_rng(3)
    w, h, e = 7, 3, 5
    gap, u = (jnp.asarray(rng.normal(0, 1e-4, (w, e)), jnp.float32) for _ in range(2))
    speed_t, acc, slip = (jnp.asarray(np.abs(rng.normal(0, 0.5, e)), jnp.float32)
                          for _ in range(3))
    values = (1e-4, 5e-6, 1.0, 1e-2)
    scales = [jnp.asarray(rng.uniform(0.5, 2.0, e) * v, jnp.float32) if per_contact else v
              for v in values]
    sc = InputScales(*scales, 5.0)
    got = np.asarray(_scaled_inputs(gap, u, speed_t, acc, slip, sc, h))
    gc, gf, vc, vf = scales
    want = []
    for k in range(w - h, w):
        want += [jnp.clip(gap[k] / gc, -1.0, 3.0), jnp.tanh(gap[k] / gf),
                 jnp.clip(u[k] / vc, -5.0, 5.0), jnp.tanh(u[k] / vf)]
    want += [jnp.clip(speed_t / vc, 0.0, 5.0), jnp.tanh(speed_t / vf), jnp.tanh(acc / vf),
             jnp.clip(slip / vc, 0.0, 5.0), jnp.tanh(slip / vf)]
    np.testing.assert_allclose(got, np.stack(want, axis=-1), rtol=1e-6, atol=1e-7)
    assert got.shape == (e, 4 * h + 5)
