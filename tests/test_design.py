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
from sgn_jax.scene import analytic_jar_query


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


# The slow tier (to keep the default run under 6 minutes: 22-30 s, most of it
# compiling the horizon estimator's gradient). The horizon estimator is not the default (the
# ensemble difference is, docs/design.md); the default run checks autodiff through a rollout
# against finite differences in tests/test_rollout.py::test_gradients_match_finite_differences.
@pytest.mark.slow
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


# The horizon variant is in the slow tier (27-44 s of compiling), beside
# test_one_segment_without_burn_in_is_the_exact_derivative, whose value_and_grad runs the same
# compiled horizon ``estimate`` (design.py: power's derivative is the estimate's) and must
# match finite differences.
@pytest.mark.parametrize("estimator", ["difference",
                                       pytest.param("horizon", marks=pytest.mark.slow)])
def test_estimate_matches_value_and_grad_and_is_finite(cfg, model, packings, estimator):
    # 50 burn-in and 100 measured steps: what is checked is that
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


@pytest.mark.slow
def test_cli_sensitivity_prints_json_and_writes_plot(cfg, tmp_path, session_cache):
    # Seeds 0 and 1 (--first-seed 0) in the session's cache (conftest.py): the command reads
    # the packings the other tests use instead of settling two more.
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
    phi_short, _ = analytic_jar_query(short, jnp.asarray(centres), jnp.zeros(3))
    assert float(phi_short[0]) + radius > 2e-3                         # 2.5 mm inside the wall

    same = fit(window, base, radius)
    np.testing.assert_array_equal(np.asarray(same.positions), np.asarray(window.positions))
    moved = fit(window, short, radius)
    x = np.asarray(moved.positions[-1])
    phi, _ = analytic_jar_query(short, jnp.asarray(x), jnp.zeros(3))
    assert float(np.max(np.asarray(phi))) + radius < 1.5 * PACKING_FIT_TOLERANCE
    assert 2 * radius - np.linalg.norm(x[0] - x[1]) < 1.5 * PACKING_FIT_TOLERANCE
    np.testing.assert_allclose(np.diff(np.asarray(moved.positions), axis=0),
                               np.diff(np.asarray(window.positions), axis=0), atol=1e-15)
    np.testing.assert_array_equal(x[2], np.asarray(window.positions[-1, 2]))   # far: untouched
