"""Ensembles, the charge sweep and sensitivities of a surrogate that reads the charge (model
kind "contact_charge"; docs/design.md, docs/charge.md): the windows of an ensemble carry the
case's charge, the charge sweep gives the surrogate's power beside the DEM's, and the charge
parameters of a sensitivity are central differences of ensembles with packings of their own
charge, refused where they cannot apply.

The model is a tiny untrained one (its powers are arbitrary, finite numbers): these tests
check the machinery, not the physics. The DEM runs are a few balls for a few milliseconds."""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import sgn_jax.api as sj
from sgn_jax.config import ConfigError, config_from_dict, config_to_dict, replace_section
from sgn_jax.design import DesignError
from sgn_jax.pipelines.charge_points import charge_parameter_value, with_charge_parameter
from sgn_jax.pipelines.configure import charge_from_config, graph_spec_from_config
from sgn_jax.pipelines.contact_train_run import identity_stats
from sgn_jax.pipelines.studies import _surrogate_frame, ensemble_powers
from sgn_jax.records.checkpoint import TrainedModel
from sgn_jax.surrogate.contact_charge import ball_charge
from sgn_jax.surrogate.graph import Window, build_graph
from sgn_jax.surrogate.model import model_factory

DURATION, BURN_IN = 0.004, 0.002   # 40 steps of 1e-4 s, the power over the last 20
# the DEM's: 0.02 s of settling leaves the balls landing, so the DEM's power is measured later
DEM_DURATION, DEM_BURN_IN = 0.02, 0.01


def _floor(sdf, points, offset):
    del sdf
    height = points[:, 1] - offset[1]
    return -height, jnp.broadcast_to(jnp.asarray([0.0, -1.0, 0.0]), points.shape)


def _untrained(kind: str = "contact_charge") -> TrainedModel:
    """A tiny untrained model of ``kind`` at the standard case's 1e-4 s step, 10 mm balls."""
    cfg = replace_section(sj.load_config("emax_300rpm"), "model", kind=kind, hidden=16,
                          mlp_layers=3)
    net = model_factory(kind).build_model(cfg)
    w = int(cfg.graph.window)
    lattice = np.array([[0.0, 0.005, 0.0], [0.0099, 0.005, 0.0], [0.0, 0.005, 0.012]])
    window = Window(positions=jnp.broadcast_to(jnp.asarray(lattice), (w + 1, 3, 3)),
                    offsets=jnp.zeros((w, 3)), offset_velocities=jnp.zeros((w, 3)),
                    frequency_hz=jnp.asarray(5.0), spins=jnp.zeros((3, 3)),
                    charge=ball_charge(charge_from_config(
                        replace_section(cfg, "balls", count=3))) if kind == "contact_charge"
                    else None)
    graph, _ = build_graph(window, None, graph_spec_from_config(cfg, 3), _floor)
    params = model_factory(kind).init_params(net, graph, 0)
    return TrainedModel(model=net, params=params, norm_stats=identity_stats(w), config=cfg,
                        meta={})


@pytest.fixture(scope="module")
def model():
    return _untrained()


def _case(balls: dict) -> sj.Config:
    """The standard jar and motion with ``balls`` and 0.02 s of settling."""
    data = config_to_dict(sj.load_config("emax_300rpm"))
    data["balls"] = balls
    data["dem"]["settle_time"] = 0.02
    return config_from_dict(data)


# three 10 mm steel balls and four 8 mm balls of 6000 kg/m^3
MIXTURE = {"count": 3, "radius": 0.005, "density": 7700.0,
           "mix": [{"count": 4, "radius": 0.004, "density": 6000.0}]}
# five 10 mm steel balls (2 % of the jar's volume)
FIVE = {"count": 5, "radius": 0.005, "density": 7700.0}


@pytest.fixture(scope="module")
def mixture():
    """``(cfg, packings)``: the two-size charge and its DEM packings of seeds 0 and 1."""
    cfg = _case(MIXTURE)
    return cfg, sj.make_packings(cfg, seeds=[0, 1])


def _packings_at_rest(cfg: sj.Config, k: int = 2) -> sj.Packings:
    """K packings of ``cfg``'s 7 balls (three of 5 mm, four of 4 mm) at rest in the jar frame
    in the lower jar, clear of the wall, ball 0 touching ball 1 and ball 3 (0.1 mm deep), as
    ``make_packings`` gives them (a window ending at t0 = W dt in the lab frame of the config's
    motion), without a DEM run."""
    from sgn_jax.motion import offset, velocity

    lattice = np.array([[-0.012, 0.008, -0.006], [-0.012, 0.008, 0.0039],
                        [0.012, 0.020, 0.006], [-0.0031, 0.008, -0.006],
                        [0.0, 0.020, -0.006], [0.012, 0.008, -0.006], [0.012, 0.008, 0.0029]])
    w, dt = int(cfg.graph.window), float(cfg.dem.dt)
    motion = sj.motion_from_config(cfg.motion)
    times = dt * np.arange(w + 1)
    offs = np.asarray([offset(motion, t) for t in times])
    window = Window(positions=lattice[None] + offs[:, None], offsets=offs[1:],
                    offset_velocities=np.asarray([velocity(motion, t) for t in times[1:]]),
                    frequency_hz=np.asarray(cfg.motion.rpm / 60.0))
    windows = jax.tree_util.tree_map(lambda a: np.stack([np.asarray(a)] * k), window)
    return sj.Packings(windows=windows, t0=w * dt, seeds=tuple(range(k)), config=cfg)


@pytest.mark.slow   # ~40 s on one free core: a model setup and an ensemble compile
def test_an_ensemble_of_a_two_size_charge_carries_the_charge(model):
    cfg = _case(MIXTURE)
    packings = _packings_at_rest(cfg)
    frame = _surrogate_frame(model, cfg, packings)
    charge = charge_from_config(cfg)
    assert frame.windows.charge.radius.shape == (2, 7)
    for k in range(2):   # every packing's window carries the case's balls
        np.testing.assert_array_equal(frame.windows.charge.radius[k], charge.radii)
        np.testing.assert_allclose(frame.windows.charge.mass[k], charge.masses, rtol=1e-12)
    # the graph keeps the trained [balls] radius (its skins are set against it), N the case's
    assert frame.spec.ball_radius == model.config.balls.radius and frame.spec.n_particles == 7

    result = sj.rollout_ensemble(model, cfg, packings, duration=DURATION, save_every=10)
    assert result.positions.shape[:3] == (2, 5, 7)   # the initial frame and 4 saved
    assert np.isfinite(result.positions).all() and np.isfinite(result.steps.energy_cum).all()
    # The charge enters the rollout: another restitution of the balls' material (the same
    # packings) is another pair table, and other impulses at the touching pairs.
    softer = replace_section(cfg, "material", restitution=0.8)
    other = sj.rollout_ensemble(model, softer, packings, duration=DURATION, save_every=10)
    assert np.abs(other.positions - result.positions).max() > 1e-9

    sweep = sj.rollout_sweep(model, [cfg, replace_section(cfg, "motion", rpm=350.0)], packings,
                             duration=DURATION, save_every=10)
    assert sweep.positions.shape[:3] == (2, 2, 5)
    np.testing.assert_allclose(sweep.positions[0], result.positions, rtol=0, atol=1e-9)

    # packings of another charge are refused, naming the fix
    with pytest.raises(DesignError, match="another charge"):
        sj.rollout_ensemble(model, _case(FIVE), packings, duration=DURATION)


@pytest.mark.slow   # ~60 s on a loaded core: DEM runs of two charges, two ensemble compiles
def test_a_charge_sweep_with_a_surrogate_gives_its_power_beside_the_dems(model, session_cache,
                                                                            tmp_path):
    cfg = _case(FIVE)
    kwargs = dict(packings=2, first_seed=0, duration=DEM_DURATION, burn_in=DEM_BURN_IN)
    both = sj.charge_sweep(cfg, "fill", [0.02, 0.03], surrogate=model, **kwargs)
    assert both["simulator"] == "dem+surrogate" and both["seeds"] == [0, 1]
    assert [p["n_balls"] for p in both["points"]] == [5, 7]
    for p in both["points"]:
        assert p["power_total_W"] >= p["power_W"] > 0   # the DEM's
        assert len(p["surrogate_powers_W"]) == 2 and np.isfinite(p["surrogate_powers_W"]).all()
        assert p["surrogate_power_W"] == pytest.approx(np.mean(p["surrogate_powers_W"]))
        assert p["surrogate_power_se_W"] == pytest.approx(
            np.std(p["surrogate_powers_W"], ddof=1) / np.sqrt(2))
        assert p["surrogate_specific_W_per_kg"] == pytest.approx(p["surrogate_power_W"]
                                                                 / p["mass_kg"])
        assert p["specific_damping_W_per_kg"] == pytest.approx(p["power_W"] / p["mass_kg"])
    json.dumps(both)
    assert sj.plot_charge_sweep(both, tmp_path / "sweep.png").stat().st_size > 0

    # dem=False: the surrogate's ensembles of the same packings only
    alone = sj.charge_sweep(cfg, "fill", [0.02, 0.03], surrogate=model, dem=False, **kwargs)
    assert alone["simulator"] == "surrogate" and "power_W" not in alone["points"][0]
    for a, b in zip(alone["points"], both["points"], strict=True):
        np.testing.assert_allclose(a["surrogate_powers_W"], b["surrogate_powers_W"],
                                   rtol=1e-12)
    assert sj.plot_charge_sweep(alone, tmp_path / "alone.png").stat().st_size > 0

    with pytest.raises(ConfigError, match="needs a surrogate"):
        sj.charge_sweep(cfg, "fill", [0.02], dem=False, **kwargs)
    with pytest.raises(DesignError, match="must read the charge"):
        sj.charge_sweep(cfg, "fill", [0.02], surrogate=_untrained("contact"), **kwargs)


@pytest.mark.slow   # ~70 s on a loaded core: packings and DEM runs of three charges
def test_a_charge_parameter_is_a_central_difference_of_ensembles_of_its_own_charge(
        model, session_cache):
    cfg = _case(FIVE)
    h = 0.0005
    result = sj.sensitivity(cfg, ["balls.radius_fill"], duration=DEM_DURATION,
                            burn_in=DEM_BURN_IN,
                            packings=2, first_seed=0, checkpoint=model,
                            steps={"balls.radius_fill": h}, dem=True)
    curve = result["curves"]["balls.radius_fill"]
    assert result["charge_parameters"] == ["balls.radius_fill"] and result["units"] == {
        "balls.radius_fill": "m"}
    assert curve["theta"] == pytest.approx([0.0045, 0.005, 0.0055])
    assert curve["n_balls"] == [7, 5, 4]   # the filling held: the count follows the radius
    diff = np.asarray(result["gradient_per_packing"]["balls.radius_fill"])
    assert diff.shape == (2,) and np.isfinite(diff).all()
    g = result["gradient"]["balls.radius_fill"]
    assert g == pytest.approx((curve["power_W"][2] - curve["power_W"][0]) / (2 * h), rel=1e-9)
    assert result["gradient_se"]["balls.radius_fill"] == pytest.approx(
        np.std(diff, ddof=1) / np.sqrt(2))
    # the middle point is the design point's own ensemble, at the config's charge
    assert curve["power_W"][1] == result["power_W"]
    packings = sj.make_packings(cfg, seeds=[0, 1])
    np.testing.assert_allclose(ensemble_powers(model, cfg, packings, DEM_DURATION,
                                               DEM_BURN_IN),
                               result["power_per_packing_W"], rtol=1e-12)
    # the DEM's difference at the same two points and seeds
    dem = result["dem"]["balls.radius_fill"]
    assert dem["h"] == h and dem["n_balls"] == [7, 4] and dem["seeds"] == [0, 1]
    assert all(p > 0 for side in dem["powers_W"] for p in side)
    assert dem["central_difference"] == pytest.approx(
        (dem["power_W"][1] - dem["power_W"][0]) / (2 * h), rel=1e-9)
    json.dumps(result)


@pytest.mark.slow   # ~90 s on a loaded core: DEM packings of two charges, a study's compile
def test_a_design_study_of_a_two_size_charge_and_a_motion_beside_a_charge_parameter(
        model, mixture, session_cache):
    """``design_study`` of a model that reads the charge rolls the packings out with their
    charge: its power at theta0 is ``rollout_ensemble``'s; and a sensitivity takes a motion
    parameter (the design study's) beside a charge parameter (its own ensembles)."""
    cfg, packings = mixture
    assert packings.windows.positions.shape[-2] == 7 and packings.windows.charge is None
    study = sj.design_study(model, cfg, ["motion.rpm"], packings, duration=DURATION,
                            burn_in=BURN_IN, n_segments=1)
    est = study.estimate()
    assert np.isfinite(est["power_W"]) and np.isfinite(est["gradient"]["motion.rpm"])
    np.testing.assert_allclose(est["power_per_packing_W"],
                               ensemble_powers(model, cfg, packings, DURATION, BURN_IN),
                               rtol=1e-6)

    five = _case(FIVE)
    result = sj.sensitivity(five, ["balls.density", "motion.rpm"], duration=DURATION,
                            burn_in=BURN_IN, packings=2, first_seed=0, checkpoint=model,
                            n_segments=1)
    assert list(result["gradient"]) == ["balls.density", "motion.rpm"]
    assert result["charge_parameters"] == ["balls.density"]
    density = result["curves"]["balls.density"]
    assert density["theta"] == pytest.approx([6930.0, 7700.0, 8470.0])   # h: 10 %
    assert density["n_balls"] == [5, 5, 5]
    assert density["power_W"][1] == result["power_W"] == result["curves"]["motion.rpm"][
        "power_W"][1]
    assert np.isfinite(list(result["gradient"].values())).all()


def test_charge_parameters_are_refused_where_they_cannot_apply(model):
    cfg = _case(FIVE)
    kwargs = dict(duration=DURATION, burn_in=BURN_IN, packings=2, first_seed=0)
    with pytest.raises(DesignError, match=r"balls.radius_fill is a charge parameter.*"
                                          r"estimator='horizon'.*estimator='difference'"):
        sj.sensitivity(cfg, ["motion.rpm", "balls.radius_fill"], checkpoint=model,
                       estimator="horizon", **kwargs)
    with pytest.raises(DesignError, match="start='settle'"):
        sj.sensitivity(cfg, ["balls.density"], checkpoint=model, start="settle", **kwargs)
    with pytest.raises(DesignError, match=r"model kind 'contact'.*contact_charge"):
        sj.sensitivity(cfg, ["balls.density"], checkpoint=_untrained("contact"), **kwargs)
    with pytest.raises(ConfigError, match=r"one ball class.*\[\[balls.mix\]\]"):
        sj.sensitivity(_case(MIXTURE), ["balls.radius_count"], checkpoint=model, **kwargs)
    with pytest.raises(ConfigError, match=r"restitution must be in \(0, 1\]"):
        sj.sensitivity(cfg, ["balls.restitution"], checkpoint=model,
                       steps={"balls.restitution": 0.8}, **kwargs)
    with pytest.raises(DesignError, match="steps given for"):
        sj.sensitivity(cfg, ["balls.density"], checkpoint=model,
                       steps={"balls.friction": 0.01}, **kwargs)
    # the DEM's start in every jar places one ball size: a mixture starts from its packings
    with pytest.raises(DesignError, match=r"one size.*start='packing'"):
        sj.design_study(model, _case(MIXTURE), ["jar.straight_length"],
                        sj.seed_packings(_case(MIXTURE), seeds=[0, 1]), duration=DURATION,
                        burn_in=BURN_IN, n_segments=1)
    # a design study's rollout has fixed balls: a charge parameter is not one of its parameters
    packings = sj.seed_packings(cfg, seeds=[0, 1])
    with pytest.raises(DesignError, match=r"balls.density is a charge parameter.*sensitivity"):
        sj.design_study(model, cfg, ["balls.density"], packings, duration=DURATION,
                        burn_in=BURN_IN, n_segments=1, start="dem")


def test_charge_parameters_in_a_config():
    cfg = _case(FIVE)
    names = ["balls.radius_fill", "balls.density", "balls.restitution", "balls.friction",
             "motion.rpm"]
    np.testing.assert_allclose(sj.parameter_values_of(cfg, names),
                               [0.005, 7700.0, cfg.material.restitution, cfg.material.friction,
                                300.0])
    assert [sj.parameter_unit(n) for n in names] == ["m", "kg/m^3", "1", "1", "rpm"]
    moved = sj.design_config(cfg, names, [0.004, 6000.0, 0.5, 0.2, 330.0])
    np.testing.assert_allclose(sj.parameter_values_of(moved, names),
                               [0.004, 6000.0, 0.5, 0.2, 330.0])
    assert moved.balls.count == 10   # 5 (5/4)^3 = 9.8: the filling held
    same_count = with_charge_parameter(cfg, "balls.radius_count", 0.004)
    assert same_count.balls.count == 5 and same_count.balls.radius == 0.004
    # the balls' own material when they name one; the jar's [material] is left alone
    data = config_to_dict(cfg)
    data["balls"]["material"] = "zirconia"
    data["materials"] = [{"name": "zirconia", "young": 1.6e9, "poisson": 0.3,
                          "restitution": 0.5, "friction": 0.2, "rolling_friction": 0.02}]
    zirconia = config_from_dict(data)
    assert charge_parameter_value(zirconia, "balls.restitution") == 0.5
    softer = with_charge_parameter(zirconia, "balls.restitution", 0.6)
    assert softer.material_named("zirconia").restitution == 0.6
    assert softer.material == zirconia.material


@pytest.mark.slow   # ~40 s on a loaded core: the DEM packings of one charge and its ensemble
def test_cli_charge_sweep_with_a_surrogate_checkpoint(model, tmp_path, session_cache, capsys):
    """``sgn-jax charge-sweep --surrogate DIR --no-dem`` loads a checkpoint of a model that
    reads the charge, prints its table and a JSON line with the surrogate's power and SE, and
    writes the plot; ``sgn-jax sensitivity`` refuses a charge parameter with the horizon
    estimator before any work (exit 2, the reason on stderr)."""
    import contextlib
    import io

    from sgn_jax.cli import main
    from sgn_jax.config import save_config
    from sgn_jax.records.checkpoint import save_checkpoint

    checkpoint = tmp_path / "model"
    save_checkpoint(checkpoint, 0, params=model.params, norm_stats=model.norm_stats,
                    meta={"config": config_to_dict(model.config)})
    config = tmp_path / "five.toml"
    save_config(_case(FIVE), config)
    stdout = io.StringIO()
    with contextlib.redirect_stdout(stdout):
        code = main(["charge-sweep", "--config", str(config), "--parameter", "fill",
                     "--values", "0.02", "--packings", "2", "--first-seed", "0",
                     "--duration", str(DURATION), "--burn-in", str(BURN_IN),
                     "--surrogate", str(checkpoint), "--no-dem", "--out", str(tmp_path / "sw"),
                     "--no-progress"])
    assert code == 0
    lines = stdout.getvalue().strip().splitlines()
    assert "surrogate W" in lines[0] and "DEM" not in lines[0]
    line = json.loads(lines[-1])
    assert line["simulator"] == "surrogate" and line["points"][0]["n_balls"] == 5
    assert np.isfinite([line["points"][0]["surrogate_power_W"],
                        line["points"][0]["surrogate_power_se_W"]]).all()
    assert (tmp_path / "sw" / "charge_sweep.png").stat().st_size > 0

    assert main(["sensitivity", "--config", str(config), "--param", "balls.radius_fill",
                 "--estimator", "horizon", "--packings", "2", "--checkpoint", str(checkpoint),
                 "--out", str(tmp_path / "sens"), "--no-progress"]) == 2
    assert "balls.radius_fill is a charge parameter" in capsys.readouterr().err


def test_a_model_that_reads_the_charge_has_no_training_charge_in_its_envelope():
    """The envelope of a contact_charge model names no training charge (it covers the charge
    envelope, whose notes are the charge envelope's); a model of another kind names every ball
    count or radius that differs from its training charge."""
    from sgn_jax.pipelines.validation import envelope_notes, model_envelope

    std = sj.load_config("emax_300rpm")
    five = _case(FIVE)
    charged = replace_section(std, "model", kind="contact_charge")
    assert model_envelope(charged).charge is None
    assert not [n for n in envelope_notes(five, model_envelope(charged))
                if "model's charge" in n]
    plain = replace_section(std, "model", kind="contact")
    assert any("[balls] count = 5 differs from the model's charge (24)" in n
               for n in envelope_notes(five, model_envelope(plain)))
