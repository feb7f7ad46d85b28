"""Design studies (sgn_jax.design, sgn_jax.api): named parameters, the ensemble-mean power and
its gradient estimator, errors, and `sgn-jax sensitivity` end to end (shipped model)."""

from __future__ import annotations

import contextlib
import io
import json

import jax
import numpy as np
import pytest

import sgn_jax.api as sj
from sgn_jax.cli import main
from sgn_jax.config import replace_section, save_config
from sgn_jax.design import DesignError, summarize_estimate


@pytest.fixture(scope="module")
def cfg(short_packings):
    # The standard case with a short settling, so that a packing costs seconds; the session's
    # packings (conftest.py) are of this config.
    cfg = replace_section(sj.load_config("emax_300rpm"), "dem", settle_time=0.02)
    assert short_packings[0] == cfg
    return cfg


@pytest.fixture(scope="module")
def model():
    # The paper-setting SGN (1e-4 s, the case's step): these tests check the study's machinery
    # with the model whose big matmuls vmap; the default (contact) model's study is checked
    # with contact_short_packings.
    return sj.load_surrogate("emax_300rpm")


@pytest.fixture(scope="module")
def packings(short_packings):
    return short_packings[1]  # seeds 0 and 1, settled once per session (conftest.py)


def test_packings_hold_one_window_per_seed(cfg, packings):
    w = cfg.graph.window
    assert len(packings) == 2
    assert packings.windows.positions.shape == (2, w + 1, cfg.balls.count, 3)
    assert packings.t0 == pytest.approx(w * cfg.dem.dt)
    np.testing.assert_allclose(packings.windows.frequency_hz, 300.0 / 60.0)  # rpm / 60


def test_one_segment_without_burn_in_is_the_exact_derivative(cfg, model, packings):
    """With no burn-in and one gradient horizon covering the whole measurement interval, the
    truncated-horizon estimator differentiates exactly the power that ``powers`` computes: it
    must agree with the ensemble central difference of that power. The horizon is 5 steps:
    over 20 steps the surrogate's power is already not smooth in rpm (edges appear and vanish;
    central differences with h = 5, 0.5, 0.05 rpm give 1.3e-4, 8.2e-5, 5.2e-5 W/rpm), which is
    why the estimator averages many short horizons (docs/design.md)."""
    n = 5
    study = sj.design_study(model, cfg, ["motion.rpm", "motion.amplitude"], packings,
                            duration=n * cfg.dem.dt, burn_in=0.0, horizon=n, n_segments=1,
                            estimator="horizon")
    power, grad = jax.value_and_grad(study.power)(study.theta0)
    assert np.isfinite(float(power)) and np.all(np.isfinite(np.asarray(grad)))
    np.testing.assert_allclose(float(power), study.powers().mean(), rtol=1e-9)
    for i, h in enumerate((0.5, 2e-5)):
        plus, minus = study.theta0.copy(), study.theta0.copy()
        plus[i] += h
        minus[i] -= h
        fd = (study.powers(plus).mean() - study.powers(minus).mean()) / (2 * h)
        assert abs(float(grad[i])) > 0
        assert float(grad[i]) == pytest.approx(fd, rel=0.05), (study.names[i], fd, grad[i])


# The horizon variant is in the slow tier (issue 20: 27-44 s of compiling). Its twin in the
# default run is test_one_segment_without_burn_in_is_the_exact_derivative, whose
# value_and_grad runs the same compiled horizon ``estimate`` (design.py: power's derivative is
# the estimate's) and must match finite differences.
@pytest.mark.parametrize("estimator", ["difference",
                                       pytest.param("horizon", marks=pytest.mark.slow)])
def test_estimate_matches_value_and_grad_and_is_finite(cfg, model, packings, estimator):
    # 50 burn-in and 100 measured steps (issue 20: was 100 + 200): what is checked is that
    # the estimate, value_and_grad and explicit evaluations agree, at any length; the CLI test
    # below runs the same program (compiled once per session).
    study = sj.design_study(model, cfg, ["motion.rpm"], packings, duration=0.015, burn_in=0.005,
                            horizon=10, n_segments=2, estimator=estimator)
    power, grad = jax.value_and_grad(study.power)(study.theta0)
    est = study.estimate()
    assert est["power_W"] == pytest.approx(float(power), rel=1e-9)
    assert est["gradient"]["motion.rpm"] == pytest.approx(float(grad[0]), rel=1e-6)
    assert np.isfinite(est["power_se_W"]) and np.isfinite(est["gradient_se"]["motion.rpm"])
    if estimator == "difference":
        # The default estimator is the ensemble central difference with common packings, step
        # 10 % of the value (30 rpm): the same number as two explicit evaluations.
        h = 30.0
        plus = study.powers(study.theta0 + h)
        fd = (plus - study.powers(study.theta0 - h)) / (2 * h)
        # (float32 network: batched and unbatched evaluations round differently at ~1e-8.)
        assert float(grad[0]) == pytest.approx(fd.mean(), rel=1e-6)
        np.testing.assert_allclose(est["side_powers_W"][0], plus, rtol=1e-6)


@pytest.mark.slow
def test_a_contact_models_difference_study_maps_its_packings_in_the_single_rollout_form(
        cfg, packings):
    """The difference estimator only runs rollouts forward, so a model with a single-rollout
    form (the contact kind) maps its packings one after another in it (``batching="map"``);
    sharded, the plain model runs vmapped. The same powers and gradient to the float32
    rounding a batch changes (the chaotic rollouts part slowly: 25 + 50 steps at 2e-4 s)."""
    model = sj.load_surrogate("contact")
    cfg = sj.at_surrogate_step(cfg, model)       # the shipped contact model runs at 2e-4 s
    packings = sj.make_packings(cfg, seeds=list(packings.seeds))
    est = {}
    for shard in (False, True):   # one device: shard=True is the vmapped plain model
        study = sj.design_study(model, cfg, ["motion.rpm"], packings, duration=0.015,
                                burn_in=0.005, n_segments=2, shard=shard)
        assert study.ensemble.batching == ("vmap" if shard else "map")
        est[shard] = study.estimate()
    assert est[False]["power_W"] == pytest.approx(est[True]["power_W"], rel=2e-3)
    assert est[False]["gradient"]["motion.rpm"] == pytest.approx(
        est[True]["gradient"]["motion.rpm"], rel=2e-2, abs=1e-6)


def test_a_non_finite_gradient_is_an_error_naming_packing_segment_and_parameter():
    from sgn_jax.design import PowerEstimate

    grad = np.zeros((3, 2, 1))
    grad[1, 1, 0] = np.nan
    est = PowerEstimate(power_W=np.ones(3), gradient=grad, horizon_energy_J=np.ones((3, 2)),
                        side_powers_W=np.zeros((0, 3)))
    with pytest.raises(DesignError, match="motion.rpm is not finite at packing 1, segment 1"):
        summarize_estimate(est, ["motion.rpm"])
    est = PowerEstimate(power_W=np.array([1.0, np.inf, 1.0]), gradient=np.zeros((3, 2, 1)),
                        horizon_energy_J=np.ones((3, 2)), side_powers_W=np.zeros((0, 3)))
    with pytest.raises(DesignError, match="packing 1 gave a non-finite power"):
        summarize_estimate(est, ["motion.rpm"])


@pytest.mark.parametrize("names,kwargs,match", [
    (["motion.speed"], {}, "unknown design parameter"),
    (["jar.post_radius"], {}, "needs a jar with a post"),
    (["motion.x_sin[0]"], {}, "needs a harmonic motion"),
    (["motion.rpm", "motion.rpm"], {}, "repeat"),
    (["motion.rpm"], {"duration": 0.01, "burn_in": 0.01}, "duration > burn_in"),
    (["motion.rpm"], {"duration": 0.03005, "burn_in": 0.01}, "whole number"),
    (["motion.rpm"], {"duration": 0.03, "burn_in": 0.01, "n_segments": 3}, "equal parts"),
    (["motion.rpm"], {"estimator": "adjoint"}, "estimator must be"),
    (["motion.rpm"], {"steps": {"motion.amplitude": 1e-3}}, "steps given for"),
    (["motion.rpm"], {"steps": {"motion.rpm": 0.0}}, "finite and > 0"),
])
def test_bad_design_input_is_refused_before_work(cfg, model, packings, names, kwargs, match):
    kwargs = {"duration": 0.03, "burn_in": 0.01, "horizon": 10, "n_segments": 2, **kwargs}
    with pytest.raises(DesignError, match=match):
        sj.design_study(model, cfg, names, packings, **kwargs)


def test_design_config_round_trips_the_parameters(cfg):
    names = ["motion.rpm", "motion.amplitude", "jar.straight_length"]
    theta = [350.0, 0.015, 0.03]
    moved = sj.design_config(cfg, names, theta)
    np.testing.assert_allclose(sj.parameter_values_of(moved, names), theta)
    m1 = sj.load_config("motion1")
    names = ["motion.base_frequency_hz", "motion.x_sin[0]"]
    theta = [5.5, 0.004]
    np.testing.assert_allclose(sj.parameter_values_of(sj.design_config(m1, names, theta), names),
                               theta)


def test_cli_sensitivity_prints_json_and_writes_plot(cfg, tmp_path, session_cache):
    # Seeds 0 and 1 (--first-seed 0) in the session's cache (conftest.py): the command reads
    # the packings the other tests use instead of settling two more (issue 20).
    config_path = tmp_path / "case.toml"
    save_config(cfg, config_path)
    out = tmp_path / "sens"
    stdout = io.StringIO()
    with contextlib.redirect_stdout(stdout):
        # The sizes and model of test_estimate_matches_value_and_grad_and_is_finite: the same
        # program (the default model's study compiles another, ~30 s of the default run; the
        # default's resolution is test_demo's).
        code = main(["sensitivity", "--config", str(config_path), "--param", "motion.rpm",
                     "--duration", "0.015", "--burn-in", "0.005", "--packings", "2",
                     "--first-seed", "0", "--horizon", "10", "--segments", "2",
                     "--checkpoint", "emax_300rpm", "--out", str(out), "--no-progress"])
    assert code == 0
    line = json.loads(stdout.getvalue().strip().splitlines()[-1])
    assert set(line) >= {"power_W", "power_se_W", "gradient"}
    assert np.isfinite(line["power_W"]) and np.isfinite(line["gradient"]["motion.rpm"])
    assert (out / "sensitivity.png").stat().st_size > 0
    saved = json.loads((out / "sensitivity.json").read_text())
    assert saved["gradient"] == line["gradient"] and saved["seeds"] == [0, 1]
    curve = saved["curves"]["motion.rpm"]
    assert len(curve["power_W"]) == 3 and curve["h"] == pytest.approx(30.0)
    # The default estimator's gradient is the curve's own central difference.
    assert curve["central_difference"] == pytest.approx(line["gradient"]["motion.rpm"], rel=1e-9)


def test_cli_sensitivity_refuses_bad_input(tmp_path, capsys):
    assert main(["sensitivity", "--config", "emax_300rpm", "--param", "motion.rpm",
                 "--packings", "1", "--out", str(tmp_path)]) == 2
    assert "packings must be >= 2" in capsys.readouterr().err


def test_a_packing_is_fitted_into_a_shorter_jar_and_left_alone_in_its_own():
    """A jar-shape parameter moves the walls under a packing settled in the base jar: 5 mm off
    ``straight_length`` puts a ball at the end wall 2.5 mm inside it. ``fit_packing_to_jar``
    moves it (and the ball it then presses) out to the tolerance, every slot by the same shift
    (the velocities are kept); in its own jar the packing is left exactly as it is."""
    import jax.numpy as jnp

    from sgn_jax.design import PACKING_FIT_TOLERANCE, fit_packing_to_jar
    from sgn_jax.surrogate.graph import Window

    base = sj.jar_params_from_config(sj.load_config("emax_300rpm").jar)
    short = base.replace(straight_length=base.straight_length - 0.005)
    radius, y = 0.005, 0.02
    end = base.straight_length / 2 + base.radius - radius - 1e-6        # touching the end wall
    centres = np.array([[end, y, 0.0], [end - 2 * radius + 1e-6, y, 0.0], [0.0, y, 0.0]])
    steps = np.arange(-3, 1)[:, None, None] * 1e-4 * np.array([0.1, 0.0, 0.05])
    window = Window(positions=jnp.asarray(centres[None] + steps), offsets=jnp.zeros((3, 3)),
                    offset_velocities=jnp.zeros((3, 3)), frequency_hz=jnp.asarray(5.0))
    fit = jax.jit(fit_packing_to_jar, static_argnums=2)
    phi_short, _ = sj.analytic_jar_query(short, jnp.asarray(centres), jnp.zeros(3))
    assert float(phi_short[0]) + radius > 2e-3                         # 2.5 mm inside the wall

    same = fit(window, base, radius)
    np.testing.assert_array_equal(np.asarray(same.positions), np.asarray(window.positions))
    moved = fit(window, short, radius)
    x = np.asarray(moved.positions[-1])
    phi, _ = sj.analytic_jar_query(short, jnp.asarray(x), jnp.zeros(3))
    assert float(np.max(np.asarray(phi))) + radius < 1.5 * PACKING_FIT_TOLERANCE
    assert 2 * radius - np.linalg.norm(x[0] - x[1]) < 1.5 * PACKING_FIT_TOLERANCE
    np.testing.assert_allclose(np.diff(np.asarray(moved.positions), axis=0),
                               np.diff(np.asarray(window.positions), axis=0), atol=1e-15)
    np.testing.assert_array_equal(x[2], np.asarray(window.positions[-1, 2]))   # far: untouched


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


def test_a_settled_start_is_a_bed_at_rest_in_each_jar_and_the_motion_starts_at_zero(
        contact_short_packings):
    """``make_settled_start`` (a study's ``start="settle"``): the seed's balls placed as the
    DEM places them and settled by the shipped contact model for the DEM's 0.5 s with the jar
    at rest, in the standard jar and one 5 mm longer: a bed at rest on the floor (mean speed
    < 1 cm/s; the DEM's settled bed holds < 1e-7 J), every ball inside the walls and out of
    the others to 0.1 mm, the jar at the motion's offset at t = 0 and at rest."""
    import dataclasses

    from sgn_jax.dem.placement import placement_candidates
    from sgn_jax.design import make_settled_start
    from sgn_jax.geometry.jar import jar_sdf
    from sgn_jax.motion import offset
    from sgn_jax.pipelines.configure import graph_spec_from_config, motion_from_config
    from sgn_jax.surrogate.rollout import model_predictor, single_rollout_model

    model, cfg, _ = contact_short_packings
    dt = float(cfg.dem.dt)
    spec = graph_spec_from_config(dataclasses.replace(model.config, balls=cfg.balls,
                                                      dem=cfg.dem), n_particles=cfg.balls.count)
    start = make_settled_start(
        spec, model_predictor(single_rollout_model(model.model)[0]), round(0.5 / dt),
        snap_back=cfg.rollout.snap_back, phi_sb=model.config.graph.phi_sb,
        snap_velocity=cfg.rollout.snap_velocity, query=sj.analytic_jar_query, jit=False)
    assert start.name == "settle" and start.t_start == 0.0
    settle = jax.jit(start.make)
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


def test_a_jar_parameter_study_makes_its_packings_in_each_jar_by_default(
        contact_short_packings, session_cache):
    """``start="auto"`` is ``"dem"`` exactly when a jar parameter is studied; a study from
    seeds only (``seed_packings``) needs a start that makes its packings, and says so
    otherwise. The DEM's start in the design point's jar is the packing ``make_packings``
    makes (the same placement, settle and window), and in a jar 5 mm longer it is the packing
    ``make_packings`` makes for that jar."""
    from sgn_jax.dem.placement import placement_candidates

    model, cfg, packings = contact_short_packings
    assert sj.resolve_start("auto", ["motion.rpm"]) == "packing"
    assert sj.resolve_start("auto", ["motion.rpm", "jar.straight_length"]) == "dem"
    assert sj.resolve_start("packing", ["jar.radius"]) == "packing"
    with pytest.raises(DesignError, match="start must be"):
        sj.resolve_start("lid", ["motion.rpm"])
    seeds_only = sj.seed_packings(cfg, packings.seeds)
    with pytest.raises(DesignError, match="seeds only"):
        sj.design_study(model, cfg, ["motion.rpm"], seeds_only, duration=0.016, burn_in=0.0,
                        n_segments=1)
    study = sj.design_study(model, cfg, ["jar.straight_length"], seeds_only, duration=0.016,
                            burn_in=0.0, n_segments=1)
    assert study.ensemble.start == "dem"

    from sgn_jax.pipelines.configure import jar_params_from_config, motion_from_config

    start = sj._packing_start("dem", model, cfg, sj.graph_spec_from_config(
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
