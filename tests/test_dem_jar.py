"""The DEM in the Emax-like jar: wall patches, energy ledger, no escapes, vmap.

One module-scoped fixture places and settles the standard case (24 balls, seed 0, 0.5 s with
the jar at rest); the tests then run motion from that state.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import sgn_jax  # noqa: F401
from sgn_jax.config import builtin_config_path, load_config, replace_section
from sgn_jax.dem.contact import make_contact_law
from sgn_jax.dem.engine import (
    DEMSpec,
    init_state,
    ledger_balance,
    make_advance,
    make_sampler,
    observe,
    reset_ledger_totals,
)
from sgn_jax.dem.placement import PlacementError, place_balls
from sgn_jax.motion import CircleMotion
from sgn_jax.motion import offset as jar_offset
from sgn_jax.pipelines.dem_run import initial_state, setup_from_config

SAMPLE_STEPS = 106  # dt_dem = 1e-4 / 106

# observe and the SDFs run jitted in these tests: one compiled program instead of
# dozens of op-by-op compiles; the same functions, the same numbers.
_observe = jax.jit(observe, static_argnums=(0, 1, 4))
_ledger_balance = jax.jit(ledger_balance, static_argnums=(0, 1))


@pytest.fixture(scope="module")
def standard():
    cfg = load_config(builtin_config_path("emax_300rpm"))
    setup = setup_from_config(cfg)
    state = initial_state(setup, seed=0)
    advance = make_advance(setup.spec, setup.jar.wall_fn)
    settled = reset_ledger_totals(advance(setup.params, state, int(-state.step)))
    assert int(settled.step) == 0
    return setup, settled


def _phi(setup, samples) -> np.ndarray:
    x_jar = samples["pos"] - samples["offset"][:, None, :]
    sdf = jax.jit(jax.vmap(lambda x: setup.jar.sdf_fn(setup.jar.geometry, x)))
    return np.asarray(sdf(jnp.asarray(x_jar)))


_SAMPLERS = {}


def _run_samples(setup, params, state, n_samples, chunk=1000):
    key = (setup.spec, setup.pp_capacity)
    if key not in _SAMPLERS:  # one jitted sampler (one compile) for all tests
        _SAMPLERS[key] = make_sampler(setup.spec, setup.jar.wall_fn, SAMPLE_STEPS,
                                      setup.pp_capacity)
    run = _SAMPLERS[key]
    parts = []
    while n_samples > 0:
        n = min(chunk, n_samples)
        state, samples = run(params, state, n)
        parts.append(jax.tree_util.tree_map(np.asarray, samples))
        n_samples -= n
    samples = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    return state, samples


def _balance(samples) -> np.ndarray:
    return (samples["ke_trans"] + samples["ke_rot"] + samples["pe_grav"] + samples["e_elastic"]
            + samples["diss_pp"].sum(axis=1) + samples["diss_pw"].sum(axis=1)
            - samples["work_wall"])


def test_settled_bed_is_at_rest_inside(standard):
    setup, settled = standard
    obs = _observe(setup.spec, setup.jar.wall_fn, setup.params, settled, setup.pp_capacity)
    assert float(obs["ke_trans"] + obs["ke_rot"]) < 1e-7  # J: at rest after 0.5 s
    phi = jax.jit(setup.jar.sdf_fn)(setup.jar.geometry, settled.pos - settled.offset)
    assert float(jnp.max(phi)) < -0.004  # every centre ~R from the nearest wall
    assert np.all(np.asarray(settled.pos[:, 1]) < 0.03)  # on the floor, not floating
    assert int(obs["n_pp_contacts"]) > 0 and bool(jnp.any(obs["pw_contact"]))


def _check_run(setup, params, settled, n_samples):
    """Run n_samples from the settled bed; check ledger closure and that no ball escapes."""
    base = float(_ledger_balance(setup.spec, setup.jar.wall_fn, params, settled))
    _, samples = _run_samples(setup, params, settled, n_samples)
    dissipation = samples["diss_pp"].sum(axis=1) + samples["diss_pw"].sum(axis=1)
    residual = _balance(samples)[-1] - base
    assert dissipation[-1] > 0.01  # J: the charge is being milled
    assert abs(residual) < 0.01 * dissipation[-1], (residual, dissipation[-1])
    assert np.all(np.diff(dissipation) > -1e-12)  # dissipation never decreases
    phi = _phi(setup, samples)
    assert np.max(phi) < 0.0, np.max(phi)  # every centre inside, at every sample
    assert not np.any(samples["pp_overflow"])
    return samples


# The default tier runs 0.1 s of motion from the settled bed; the slow tier runs the
# same checks over 0.5 s and 2 s. After 0.1 s at 300 rpm the charge has dissipated 0.033 J and
# the wall has done 0.050 J of work (0.5 s: > 0.05 J, the slow test's bar).


def test_ledger_closes_and_no_escape_300rpm_short(standard):
    """0.1 s at 300 rpm: the ledger closes within 1 % of the dissipation, no ball centre ever
    outside the jar (every dt = 1e-4 s); the short twin of the 0.5-s test below."""
    setup, settled = standard
    samples = _check_run(setup, setup.params, settled, 1000)
    assert samples["work_wall"][-1] > 0.03


@pytest.mark.slow
def test_ledger_closes_and_no_escape_300rpm(standard):
    """0.5 s at 300 rpm: work by the wall = d(KE + PE + elastic) + all dissipation within 1 %
    of the dissipation; no ball centre ever outside the jar (checked every dt = 1e-4 s)."""
    setup, settled = standard
    samples = _check_run(setup, setup.params, settled, 5000)
    assert samples["work_wall"][-1] > 0.05


@pytest.mark.slow
def test_no_escape_300rpm_2s(standard):
    setup, settled = standard
    _check_run(setup, setup.params, settled, 20000)


@pytest.mark.slow
def test_no_escape_2000rpm_short(standard):
    """0.1 s at the machine's maximum speed, from the settled bed (the short twin of the
    0.5-s test below: 19.7 J dissipated, centres at least 4.7 mm inside)."""
    setup, settled = standard
    fast = setup.params.replace(motion=CircleMotion(rpm=2000.0, amplitude=0.017, phase=0.0))
    _check_run(setup, fast, settled, 1000)


@pytest.mark.slow
def test_no_escape_2000rpm(standard):
    """0.5 s at the machine's maximum speed, from the settled bed."""
    setup, settled = standard
    fast = setup.params.replace(motion=CircleMotion(rpm=2000.0, amplitude=0.017, phase=0.0))
    _check_run(setup, fast, settled, 5000)


@pytest.mark.slow
def test_pair_modes_agree(standard):
    """Verlet list, static pair list and dense N x N give the same motion.

    The Verlet list and the pair list add the same contacts in the same order: equal to
    1e-12 m over 3000 steps. The dense N x N mode sums each ball's forces over all partners in
    XLA's reduction order, which depends on the CPU's vector width: it matches the pair list
    exactly for the first 300 steps and then, on some CPUs, a last-bit difference appears and
    the packed bed amplifies it (measured on an AMD EPYC: 2e-12 m after 1000 steps, 1.6e-8 m
    after 3000; bitwise equal on another). So after 3000 steps N x N is held to 1e-6 m: a
    missing or wrong contact moves a ball by more (gravity alone: 4e-5 m in those 2.8 ms).
    """
    setup, settled = standard
    results: dict[tuple[str, int], np.ndarray] = {}
    for mode in ("neighbour", "pairs", "nxn"):
        spec = dataclasses.replace(setup.spec, pair_mode=mode, collision_capacity=0)
        # Fresh ball-ball histories (their layout differs between modes), settled wall ones.
        state = init_state(spec, setup.params, settled.pos, settled.vel, settled.omega, step=0)
        state = state.replace(pw_history=settled.pw_history)
        advance = make_advance(spec, setup.jar.wall_fn)
        early = advance(setup.params, state, 300)
        # The remaining 2700 steps as nine more calls of the same compiled 300-step scan (one
        # compile per mode instead of two): the same 3000 steps, step by step.
        final = early
        for _ in range(9):
            final = advance(setup.params, final, 300)
        assert int(final.step) == 3000
        results[mode, 300] = np.asarray(early.pos)
        results[mode, 3000] = np.asarray(final.pos)
    np.testing.assert_allclose(results["neighbour", 3000], results["pairs", 3000], atol=1e-12)
    np.testing.assert_allclose(results["nxn", 300], results["pairs", 300], rtol=0, atol=1e-12)
    np.testing.assert_allclose(results["nxn", 3000], results["pairs", 3000], rtol=0, atol=1e-6)


def test_verlet_list_overflow_is_flagged(standard):
    setup, settled = standard
    spec = dataclasses.replace(setup.spec, neighbour_capacity=1)  # 12 slots for 24 balls
    state = init_state(spec, setup.params, settled.pos, step=0)
    assert bool(state.pairs.overflow)
    obs = _observe(spec, setup.jar.wall_fn, setup.params, state, setup.pp_capacity)
    assert bool(obs["pp_overflow"])


def test_ball_in_floor_side_edge_stays_put():
    """A ball pressed into the floor/side-wall edge feels both patches and does not move."""
    cfg = load_config(builtin_config_path("emax_300rpm"))
    cfg = replace_section(cfg, "dem", gravity=(0.0, -9.81 / np.sqrt(2), 9.81 / np.sqrt(2)))
    setup = setup_from_config(cfg)
    spec = dataclasses.replace(setup.spec, n_balls=1)
    params = setup.params
    law = make_contact_law(2.05e9, 0.235, 0.3, 0.3, 0.045, radius_1=0.005,
                           mass_1=float(params.mass))
    load = float(params.mass) * 9.81 / np.sqrt(2)  # N on each wall
    overlap = (load / (4 / 3 * law.young_eff * np.sqrt(law.radius_eff))) ** (2 / 3)
    r = cfg.jar.radius
    x_jar = np.array([[0.0, 0.005 - overlap, r - 0.005 + overlap]])
    offset0 = np.asarray(jar_offset(params.motion, 0.0))
    state = init_state(spec, params, x_jar + offset0, step=-100_000)  # jar at rest
    final = make_advance(spec, setup.jar.wall_fn)(params, state, 20_000)
    moved = np.linalg.norm(np.asarray(final.pos - state.pos))
    assert moved < 1e-8, moved
    assert float(jnp.max(jnp.abs(final.vel))) < 1e-4
    obs = _observe(spec, setup.jar.wall_fn, params, final, 3)
    phi, _ = jax.jit(setup.jar.wall_fn)(setup.jar.geometry, final.pos - final.offset)
    touching = np.asarray(phi[0] > -0.005)
    names = setup.jar.patch_names
    assert touching[names.index("floor")] and touching[names.index("side")]
    assert not touching[names.index("lid")]
    assert bool(obs["pw_contact"][0])


@pytest.mark.slow
def test_vmap_over_seeds_and_motions():
    """Independent runs batch with vmap: same result as one at a time."""
    cfg = load_config(builtin_config_path("emax_300rpm"))
    cfg = replace_section(cfg, "balls", count=4)
    setup = setup_from_config(cfg)
    states = [initial_state(setup, seed=s).replace(step=jnp.asarray(-200, jnp.int64))
              for s in (1, 2)]
    motions = [CircleMotion(rpm=300.0, amplitude=0.017, phase=0.0),
               CircleMotion(rpm=900.0, amplitude=0.017, phase=1.0)]
    params = [setup.params.replace(motion=m) for m in motions]
    stack = lambda *xs: jnp.stack([jnp.asarray(x) for x in xs])  # noqa: E731
    batched_state = jax.tree_util.tree_map(stack, *states)
    batched_params = jax.tree_util.tree_map(stack, *params)
    advance = make_advance(setup.spec, setup.jar.wall_fn)
    step = 3000
    batched = jax.jit(jax.vmap(lambda p, s: advance(p, s, step)))(batched_params, batched_state)
    for k in range(2):
        single = advance(params[k], states[k], step)
        np.testing.assert_allclose(np.asarray(batched.pos[k]), np.asarray(single.pos), atol=1e-12)
        np.testing.assert_allclose(np.asarray(batched.ledger.work_wall[k]),
                                   np.asarray(single.ledger.work_wall), rtol=1e-9, atol=1e-15)
    assert not np.allclose(np.asarray(batched.pos[0]), np.asarray(batched.pos[1]))


def test_placement_is_seeded_non_overlapping_and_inside():
    cfg = load_config(builtin_config_path("emax_300rpm"))
    setup = setup_from_config(cfg)
    jar = setup.jar

    def sdf(x):
        return jar.sdf_fn(jar.geometry, x)

    a = place_balls(sdf, jar.lower, jar.upper, 24, 0.005, seed=7, gap=5e-4)
    b = place_balls(sdf, jar.lower, jar.upper, 24, 0.005, seed=7, gap=5e-4)
    c = place_balls(sdf, jar.lower, jar.upper, 24, 0.005, seed=8, gap=5e-4)
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)
    d = np.linalg.norm(a[:, None] - a[None], axis=-1) + np.eye(24)
    assert d.min() >= 0.0105 - 1e-12
    assert float(jnp.max(jax.jit(sdf)(jnp.asarray(a)))) < -0.0055 + 1e-12
    with pytest.raises(PlacementError, match="could place only"):
        place_balls(sdf, jar.lower, jar.upper, 250, 0.005, seed=0, max_candidates=20_000)


def test_spec_rejects_bad_input():
    with pytest.raises(ValueError, match="dt_dem"):
        DEMSpec(n_balls=2, n_patches=1, dt_dem=0.0)
    with pytest.raises(ValueError, match="pair_mode"):
        DEMSpec(n_balls=2, n_patches=1, dt_dem=1e-6, pair_mode="octree")
