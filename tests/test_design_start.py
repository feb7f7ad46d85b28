"""Where a design study's packings start in the jar it evaluates (``design_study(...,
start=...)``; docs/design.md, "What is differentiated", its paragraph "Where a packing starts in
a changed jar"): the DEM's placement as a jittable function of the jar, the surrogate's settle,
the DEM's start and the default.

A file of its own so that the test run's two workers share the design tests (``--dist
loadfile``)."""

from __future__ import annotations

import jax
import numpy as np
import pytest

import sgn_jax.api as sj
from sgn_jax.config import replace_section
from sgn_jax.design import DesignError
from sgn_jax.pipelines.studies import _packing_start, resolve_start
from sgn_jax.scene import analytic_jar_query


def test_the_traced_placement_is_the_dems_placement_in_any_jar():
    """``place_balls_traced`` (a design study's placement, jittable in the jar) places a seed's
    balls where the DEM's ``place_balls`` does, in the standard jar and 5 mm longer; a jar
    without room for them leaves the missing slots NaN and says how many it placed."""
    from sgn_jax.dem.placement import place_balls, place_balls_traced, placement_candidates
    from sgn_jax.geometry.jar import jar_sdf
    from sgn_jax.geometry.sdf_grid import cavity_box, jar_bounds

    cfg = sj.load_config("emax_300rpm")
    base = sj.jar_params_from_config(cfg.jar)
    n, radius = cfg.balls.count, cfg.balls.radius

    @jax.jit
    def traced(jar, candidates):
        lower, upper = cavity_box(jar)
        return place_balls_traced(lambda x: jar_sdf(jar, x), lower, upper, candidates, n,
                                  radius)

    for jar in (base, base.replace(straight_length=base.straight_length + 0.005)):
        lower, upper = jar_bounds(jar)
        for seed in (0, 7):
            expected = place_balls(lambda x, j=jar: jar_sdf(j, x), lower, upper, n, radius, seed)
            placed, count = traced(jar, placement_candidates(seed))
            assert int(count) == n
            np.testing.assert_allclose(np.asarray(placed), expected, rtol=0, atol=1e-15)
    tiny = base.replace(straight_length=0.0, radius=0.008)      # room for a few balls only
    placed, count = traced(tiny, placement_candidates(0))
    assert 0 < int(count) < n
    assert np.all(np.isfinite(np.asarray(placed)[:int(count)]))
    assert np.all(np.isnan(np.asarray(placed)[int(count):]))


def _settled_start(model, cfg, n_settle):
    import dataclasses

    from sgn_jax.design import make_settled_start
    from sgn_jax.pipelines.configure import graph_spec_from_config
    from sgn_jax.surrogate.rollout import model_predictor, single_rollout_model

    spec = graph_spec_from_config(dataclasses.replace(model.config, balls=cfg.balls,
                                                      dem=cfg.dem), n_particles=cfg.balls.count)
    return make_settled_start(
        spec, model_predictor(single_rollout_model(model.model)[0]), n_settle,
        snap_back=cfg.rollout.snap_back, phi_sb=model.config.graph.phi_sb,
        snap_velocity=cfg.rollout.snap_velocity, query=analytic_jar_query, jit=False)


@pytest.fixture(scope="module")
def contact_case():
    """The shipped contact model and the standard case at its 2e-4 s step (no packings)."""
    model = sj.load_surrogate("contact")
    cfg = replace_section(sj.load_config("emax_300rpm"), "dem", settle_time=0.02)
    return model, sj.at_surrogate_step(cfg, model)


def test_an_unsettled_start_is_the_dems_placement_at_rest_at_the_motions_origin(contact_case):
    """``make_settled_start`` with no settle steps (the slow test's short twin): the seed's
    DEM placement in the jar, every slot equal, the jar at the motion's offset at t = 0 and at
    rest, no spin."""
    from sgn_jax.dem.placement import place_balls, placement_candidates
    from sgn_jax.geometry.jar import jar_sdf
    from sgn_jax.geometry.sdf_grid import jar_bounds
    from sgn_jax.motion import offset
    from sgn_jax.pipelines.configure import motion_from_config

    model, cfg = contact_case
    start = _settled_start(model, cfg, 0)
    assert start.name == "settle" and start.t_start == 0.0
    motion = motion_from_config(cfg.motion)
    jar = sj.jar_params_from_config(cfg.jar)
    window = jax.jit(start.make)(model.params, model.norm_stats, placement_candidates(3),
                                 motion, jar)
    origin = np.asarray(offset(motion, 0.0))
    lower, upper = jar_bounds(jar)
    placed = place_balls(lambda x: jar_sdf(jar, x), lower, upper, cfg.balls.count,
                         cfg.balls.radius, 3)
    np.testing.assert_allclose(np.asarray(window.positions),
                               np.broadcast_to(placed + origin, window.positions.shape),
                               rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(window.offsets),
                               np.broadcast_to(origin, window.offsets.shape), atol=1e-15)
    assert not np.any(np.asarray(window.offset_velocities))
    assert not np.any(np.asarray(window.spins))


@pytest.mark.slow
def test_a_settled_start_is_a_bed_at_rest_in_each_jar_and_the_motion_starts_at_zero(
        contact_short_packings):
    """``make_settled_start`` (a study's ``start="settle"``): the seed's balls placed as the
    DEM places them and settled by the shipped contact model for the DEM's 0.5 s with the jar
    at rest, in the standard jar and one 5 mm longer: a bed at rest on the floor (mean speed
    < 1 cm/s; the DEM's settled bed holds < 1e-7 J), every ball inside the walls and out of
    the others to 0.1 mm, the jar at the motion's offset at t = 0 and at rest."""
    from sgn_jax.dem.placement import placement_candidates
    from sgn_jax.geometry.jar import jar_sdf
    from sgn_jax.motion import offset
    from sgn_jax.pipelines.configure import motion_from_config

    model, cfg, _ = contact_short_packings
    dt = float(cfg.dem.dt)
    settle = jax.jit(_settled_start(model, cfg, round(0.5 / dt)).make)
    motion = motion_from_config(cfg.motion)
    origin = np.asarray(offset(motion, 0.0))
    base = sj.jar_params_from_config(cfg.jar)
    radius = cfg.balls.radius
    for jar in (base, base.replace(straight_length=base.straight_length + 0.005)):
        for seed in (0, 1):
            window = settle(model.params, model.norm_stats, placement_candidates(seed),
                            motion, jar)
            np.testing.assert_allclose(np.asarray(window.offsets), np.broadcast_to(
                origin, window.offsets.shape), atol=1e-15)
            assert not np.any(np.asarray(window.offset_velocities))
            x = np.asarray(window.positions[-1]) - origin
            speeds = np.linalg.norm(np.asarray(window.positions[-1] - window.positions[-2]),
                                    axis=-1) / dt
            assert speeds.mean() < 0.01, (seed, speeds)
            assert np.all(x[:, 1] < 0.03)                             # on the floor
            assert float(np.max(np.asarray(jar_sdf(jar, x)))) < -radius + 1e-4
            gaps = np.linalg.norm(x[:, None] - x[None], axis=-1) + np.eye(len(x))
            assert 2 * radius - gaps.min() < 1e-4


def test_a_jar_parameter_study_makes_its_packings_in_each_jar_by_default(contact_case):
    """``start="auto"`` is ``"dem"`` exactly when a jar parameter is studied; a study from
    seeds only (``seed_packings``) needs a start that makes its packings, and says so
    otherwise (the slow test below checks the DEM's start against ``make_packings``)."""
    model, cfg = contact_case
    assert resolve_start("auto", ["motion.rpm"]) == "packing"
    assert resolve_start("auto", ["motion.rpm", "jar.straight_length"]) == "dem"
    assert resolve_start("packing", ["jar.radius"]) == "packing"
    with pytest.raises(DesignError, match="start must be"):
        resolve_start("lid", ["motion.rpm"])
    seeds_only = sj.seed_packings(cfg, [0, 1])
    assert seeds_only.windows is None and seeds_only.seeds == (0, 1)
    with pytest.raises(DesignError, match="seeds only"):
        sj.design_study(model, cfg, ["motion.rpm"], seeds_only, duration=0.016, burn_in=0.0,
                        n_segments=1)
    study = sj.design_study(model, cfg, ["jar.straight_length"], seeds_only, duration=0.016,
                            burn_in=0.0, n_segments=1)
    assert study.ensemble.start == "dem"
    start = _packing_start("dem", model, cfg, sj.graph_spec_from_config(
        replace_section(model.config, "dem", dt=cfg.dem.dt), n_particles=cfg.balls.count),
        model.model, False)
    assert start.name == "dem"
    assert start.t_start == pytest.approx(model.config.graph.window * cfg.dem.dt, rel=1e-12)


@pytest.mark.slow
def test_the_dems_start_is_make_packings_packing_in_each_jar(contact_short_packings,
                                                            session_cache):
    """The DEM's start in the design point's jar is the packing ``make_packings`` makes (the
    same placement, settle and window), and in a jar 5 mm longer it is the packing
    ``make_packings`` makes for that jar (to 1e-9 m; the default tier's twin is the test
    above)."""
    from sgn_jax.dem.placement import placement_candidates
    from sgn_jax.pipelines.configure import jar_params_from_config, motion_from_config

    model, cfg, packings = contact_short_packings
    start = _packing_start("dem", model, cfg, sj.graph_spec_from_config(
        replace_section(model.config, "dem", dt=cfg.dem.dt), n_particles=cfg.balls.count),
        model.model, False)
    assert start.t_start == pytest.approx(packings.t0, rel=1e-12)
    make = jax.jit(start.make)
    longer = replace_section(cfg, "jar", straight_length=cfg.jar.straight_length + 0.005)
    for jar_cfg, expected in ((cfg, packings), (longer, None)):
        seed = packings.seeds[0]
        if expected is None:
            expected = sj.make_packings(jar_cfg, seeds=[seed])
        made = make(model.params, model.norm_stats, placement_candidates(seed),
                    motion_from_config(cfg.motion), jar_params_from_config(jar_cfg.jar))
        assert made.spins is None and expected.windows.spins is None
        for field in ("positions", "offsets", "offset_velocities"):
            np.testing.assert_allclose(np.asarray(getattr(made, field)),
                                       np.asarray(getattr(expected.windows, field))[0],
                                       rtol=0, atol=1e-9, err_msg=field)
