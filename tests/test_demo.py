"""`sgn-jax demo` end to end on a tiny case, its input checks, and the animation helpers."""

import json

import jax
import numpy as np
import pytest

import sgn_jax  # noqa: F401  (x64)
from sgn_jax.config import (
    ConfigError,
    builtin_config_path,
    config_to_dict,
    load_config,
    replace_section,
)

WINDOW = 7
STEPS = 100  # 0.01 s of rollout
SEED = 3


def _hand_stats(window):
    """Normalisation scales of the standard case (m/s, m, Hz, m/s^2, J)."""
    from sgn_jax.surrogate.normalization import Moments, NormStats

    def m(mean, std):
        return Moments(mean=np.asarray(mean, np.float64), std=np.asarray(std, np.float64))

    return NormStats(
        particle=m(np.zeros(7 * window), [0.5, 0.5, 0.5, 0.01, 1.0, 1.0, 1.0] * window),
        wall=m([0, 0, 0, 0, 0, 0, 5.0] * window, [0.017, 0.017, 0.017, 0.5, 0.5, 0.5, 1.0] * window),
        pp_edge=m(np.zeros(3), [0.01] * 3), pw_edge=m(np.zeros(3), [0.005] * 3),
        accel=m(np.zeros(3), [0.5] * 3), dissipation=m([5e-6], [1e-6]))


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """A tiny case (standard case, 0.02 s settling, DEM chunks of 100 samples), saved as TOML,
    and a hidden-16 SGN with random weights saved as a training run's checkpoints/best."""
    from sgn_jax.config import save_config
    from sgn_jax.pipelines.configure import graph_spec_from_config, sdf_grid_from_config
    from sgn_jax.pipelines.rollout_run import initial_window
    from sgn_jax.records.checkpoint import save_checkpoint
    from sgn_jax.surrogate.graph import build_graph
    from sgn_jax.surrogate.model import init_params
    from sgn_jax.surrogate.normalization import normalize_graph
    from sgn_jax.surrogate.sgn import SGN
    from sgn_jax.testing import random_weights, synthetic_trajectory

    root = tmp_path_factory.mktemp("demo")
    cfg = load_config(builtin_config_path("emax_300rpm"))
    cfg = replace_section(cfg, "dem", settle_time=0.02, chunk_samples=100)
    cfg = replace_section(cfg, "graph", window=WINDOW)
    case_path = root / "case.toml"
    save_config(cfg, case_path)

    model_cfg = replace_section(cfg, "model", hidden=16)
    stats = _hand_stats(WINDOW)
    spec = graph_spec_from_config(model_cfg)
    synthetic = synthetic_trajectory(WINDOW + 2, cfg.balls.count, seed=0)
    window0 = initial_window(synthetic, WINDOW, WINDOW)
    # The graph and the weights' shapes without running the model's init (eager, hundreds of
    # op compiles; jitted, a compile of its random number generation): the
    # weights are drawn here as flax's defaults draw them (LeCun-normal kernels, truncated at
    # 2 std; zero biases), random either way.
    graph = jax.eval_shape(lambda w, grid: build_graph(w, grid, spec)[0], window0,
                           sdf_grid_from_config(model_cfg))
    shapes = jax.eval_shape(lambda g: init_params(SGN(hidden=16), normalize_graph(g, stats), 0),
                            graph)
    params = random_weights(shapes, 0)
    run_dir = root / "run"
    save_checkpoint(run_dir / "checkpoints" / "best", 1, params=jax.device_get(params),
                    norm_stats=stats, meta={"config": config_to_dict(model_cfg), "epoch": 1})
    return {"root": root, "cfg": cfg, "case": case_path, "run": run_dir}


@pytest.fixture(scope="module")
def demo(tiny):
    """The CLI demo on the tiny case: 0.01 s of DEM and of rollout, seed 3."""
    import contextlib
    import io

    from sgn_jax.cli import main

    out = tiny["root"] / "out"
    stdout = io.StringIO()
    with contextlib.redirect_stdout(stdout):
        code = main(["demo", "--out", str(out), "--checkpoint", str(tiny["run"]), "--config",
                     str(tiny["case"]), "--duration", str(STEPS * 1e-4), "--seed", str(SEED),
                     "--no-progress"])
    return {"code": code, "out": out, "stdout": stdout.getvalue(),
            "summary": json.loads((out / "summary.json").read_text())}


def test_demo_writes_every_output(demo):
    from sgn_jax.analysis.animation import gif_frame_count

    assert demo["code"] == 0
    out, summary = demo["out"], demo["summary"]
    for name in ("summary.json", "dem.npz", "prediction.npz", "position_mse.png",
                 "cumulative_energy.png", "trajectory_xz.png", "animation.gif"):
        assert (out / name).is_file(), name
    for name in ("position_mse.png", "cumulative_energy.png", "trajectory_xz.png"):
        assert (out / name).stat().st_size > 10_000, name
    gif = out / "animation.gif"
    assert 10_000 < gif.stat().st_size < 5_000_000
    # 100 steps saved every 10: 11 frames, fewer than the 100 asked for, so all of them.
    assert gif_frame_count(gif) == STEPS // 10 + 1
    assert set(summary["files"]) >= {"animation", "dem", "prediction", "position_mse",
                                     "cumulative_energy", "summary"}


def test_demo_numbers_are_consistent_with_its_files(demo):
    from sgn_jax.analysis.metrics import position_mse
    from sgn_jax.records.prediction import load_prediction
    from sgn_jax.records.trajectory import load_trajectory

    out, summary = demo["out"], demo["summary"]
    traj = load_trajectory(out / "dem.npz")
    pred = load_prediction(out / "prediction.npz")
    assert traj.meta["seed"] == SEED
    # The DEM covers the rollout; its 107 motion samples are rounded up to 2 chunks of 100.
    assert traj.n_samples == 201
    assert pred.n_steps == STEPS and pred.meta["init_index"] == WINDOW
    assert pred.t_start == pytest.approx(traj.t[WINDOW], abs=1e-12)
    end = WINDOW + STEPS
    assert summary["t_end_s"] == pytest.approx(traj.t[end], abs=1e-12)

    energy = summary["energy"]
    e_dem = traj.cumulative_dissipation("normal+tangential", "pp+pw")
    assert energy["dem_J"] == pytest.approx(e_dem[end] - e_dem[WINDOW], rel=1e-12)
    e_all = traj.cumulative_dissipation("all", "all")
    assert energy["dem_all_kinds_J"] == pytest.approx(e_all[end] - e_all[WINDOW], rel=1e-12)
    assert energy["dem_all_kinds_J"] >= energy["dem_J"] > 0
    assert energy["sgn_J"] == pytest.approx(float(np.sum(pred.dE)), rel=1e-12)
    assert energy["relative_error"] == pytest.approx(
        abs(energy["sgn_J"] - energy["dem_J"]) / energy["dem_J"], rel=1e-12)

    position = summary["position"]
    mse_final = float(position_mse(pred.pos[-1:], traj.pos[end:end + 1])[0])
    assert position["mse_final_m2"] == pytest.approx(mse_final, rel=1e-12)
    assert position["mse_final_check_m2"] == pytest.approx(mse_final, rel=1e-12)
    assert 0 < position["mse_plateau_m2"] <= position["mse_max_m2"]

    speed = summary["speed"]
    for key in ("dem_s_per_sim_s", "sgn_s_per_sim_s", "ratio", "dem_compile_s", "sgn_compile_s"):
        assert np.isfinite(speed[key]) and speed[key] > 0, key
    assert speed["ratio"] == pytest.approx(speed["dem_s_per_sim_s"] / speed["sgn_s_per_sim_s"])
    assert speed["sgn_s_per_sim_s"] == pytest.approx(
        summary["surrogate"]["run_s"] / (STEPS * 1e-4))

    checks = summary["checks"]
    assert checks["sgn_balls_outside_ball_steps"] == int(pred.n_outside.sum())
    assert checks["edge_overflow_total"] == int(pred.overflow.sum())
    assert checks["dem_balls_outside"] == 0
    assert checks["reference_covers_prediction"] is True


def test_demo_prints_the_headline_numbers(demo):
    text, summary = demo["stdout"], demo["summary"]
    assert f"{100 * summary['energy']['relative_error']:.2f} %" in text
    assert f"ratio {summary['speed']['ratio']:.2f}x" in text
    assert "balls outside the jar" in text and "edge overflows" in text
    assert f"MSE_t plateau {summary['position']['mse_plateau_m2']:.3g}" in text
    regime = summary["regime"]
    # the state printed is the one of the speed rule, next to the speed it thresholds
    assert (f"DEM {regime['jar_speed_dem_m_s']:.3f} m/s ({regime['state_dem']})") in text
    assert (f"model {regime['jar_speed_sgn_m_s']:.3f} m/s ({regime['state_sgn']})") in text
    # the surrogate is "model" whatever its kind (the default is the contact model, not an SGN)
    assert f"DEM {summary['energy']['dem_J']:.4g} J, model {summary['energy']['sgn_J']:.4g} J" \
        in text
    assert f"vs model {summary['speed']['sgn_s_per_sim_s']:.2f} s per simulated second" in text
    assert "SGN" not in text


def test_demo_reports_motion_checks(demo):
    """Beside the energy: the motion checks (DEM next to the model) in the report and
    summary.json."""
    text, summary = demo["stdout"], demo["summary"]
    checks = {c["name"]: c for c in summary["motion_checks"]}
    assert list(checks) == ["jar_speed", "snapped", "overlap", "mse_plateau"]
    for check in checks.values():
        assert {"dem", "sgn", "unit", "limit", "ok"} <= set(check)
    regime = summary["regime"]
    assert checks["jar_speed"]["dem"] == regime["jar_speed_dem_m_s"]
    assert checks["jar_speed"]["sgn"] == regime["jar_speed_sgn_m_s"]
    assert checks["snapped"]["sgn_ball_steps"] == summary["surrogate"]["snapped_ball_steps"]
    assert checks["snapped"]["ball_steps"] == STEPS * 24
    assert 0 <= checks["overlap"]["dem"] < 500  # um; the DEM's deepest is ~62 um
    assert checks["mse_plateau"]["sgn"] == summary["position"]["mse_plateau_m2"]
    assert "motion     checks of the motion, DEM vs model" in text
    assert f"jar-frame ball speed  DEM {regime['jar_speed_dem_m_s']:.3f} m/s, model " \
           f"{regime['jar_speed_sgn_m_s']:.3f} m/s" in text
    assert "snapped to the wall   DEM 0 (no snap), model" in text
    assert f"deepest ball overlap  DEM {checks['overlap']['dem']:,.0f} um" in text
    assert "MSE_t plateau         DEM chaos floor 5.6e-04 m^2 (same packing, dt vs dt/2), " \
           "unrelated packings 8.2e-04 m^2" in text
    # one WARNING line per failed check, then the energy-trust line; none if all passed
    failed = [c for c in checks.values() if c["ok"] is False]
    assert len(summary["motion_warnings"]) == len(failed)
    warning_lines = [line for line in text.splitlines() if "WARNING:" in line]
    assert len(warning_lines) == (len(failed) + 1 if failed else 0)
    for message in summary["motion_warnings"]:
        assert f"WARNING: {message}" in text


def test_report_warns_when_the_motion_is_off(demo):
    """The user's case: energy within 1 % while the motion is wrong: the report says so."""
    from sgn_jax.analysis.metrics import ENERGY_TRUST_WARNING, motion_checks, motion_warnings
    from sgn_jax.pipelines.demo import format_report

    checks = motion_checks(jar_speed_dem_m_s=0.27, jar_speed_sgn_m_s=0.50,
                           snapped_ball_steps=118_702, ball_steps=240_000, overlap_dem_m=62e-6,
                           overlap_sgn_m=9.99e-3, mse_plateau_m2=1.25e-3)
    summary = dict(demo["summary"], motion_checks=checks, motion_warnings=motion_warnings(checks))
    summary["energy"] = dict(summary["energy"], relative_error=0.0087)
    text = format_report(summary)
    assert "relative error 0.87 %" in text
    assert "NOT to be trusted alone: 4 motion check(s) failed" in text
    lines = text.splitlines()
    warnings = [line.strip() for line in lines if "WARNING:" in line]
    assert len(warnings) == 5 and warnings[-1] == f"WARNING: {ENERGY_TRUST_WARNING}"
    assert lines[-1].strip() == warnings[-1]  # the last thing printed
    assert "model 0.500 m/s (+85 %; limit +-20 %): OUT OF RANGE" in text
    assert "model 49.46 % of ball-steps (118,702 of 240,000; limit 1 %): OUT OF RANGE" in text
    assert "DEM 62 um, model 9,990 um (limit 500 um): OUT OF RANGE" in text
    assert "model 1.25e-03 m^2 = 1.52x the unrelated level (limit < 1x): OUT OF RANGE" in text


def test_missing_shipped_model_is_a_clear_error(tiny, tmp_path, monkeypatch, capsys):
    from sgn_jax.cli import main
    from sgn_jax.records import shipped_models

    registry_file = shipped_models.SHIPPED_MODELS_DIR / shipped_models.REGISTRY_FILE
    models = tmp_path / "models"
    monkeypatch.setattr(shipped_models, "SHIPPED_MODELS_DIR", models)
    out = tmp_path / "out"
    assert main(["demo", "--out", str(out), "--config", str(tiny["case"])]) == 2
    err = capsys.readouterr().err
    assert "no trained model is shipped" in err and "--checkpoint" in err
    assert not out.exists()  # refused before the DEM ran

    # A shipped model is found (a checkpoint directory, as the package ships it).
    models.mkdir()
    (models / shipped_models.REGISTRY_FILE).write_bytes(registry_file.read_bytes())
    (models / "emax_300rpm").symlink_to(tiny["run"] / "checkpoints" / "best")
    assert shipped_models.resolve_checkpoint(None) == models / "emax_300rpm"
    # ... also when a whole checkpoints/ folder (best, latest) was copied there.
    (models / "emax_300rpm").unlink()
    (models / "emax_300rpm").symlink_to(tiny["run"] / "checkpoints")
    assert shipped_models.resolve_checkpoint(None) == models / "emax_300rpm" / "best"
    assert shipped_models.has_checkpoint(tiny["run"])
    assert not shipped_models.has_checkpoint(models)
    # The registry's default (the contact model) is loaded when it is shipped; then the others
    # in the registry's order; each is found by name.
    assert shipped_models.registry().names == ("contact", "contact_rebound",
                                                "contact_collisions", "contact_charge",
                                                "emax_300rpm", "envelope")
    (models / "envelope").symlink_to(tiny["run"] / "checkpoints" / "best")
    assert shipped_models.resolve_checkpoint(None) == models / "emax_300rpm" / "best"
    (models / "contact").symlink_to(tiny["run"] / "checkpoints" / "best")
    assert shipped_models.resolve_checkpoint(None) == models / "contact"
    assert shipped_models.resolve_checkpoint("envelope") == models / "envelope"
    (models / "contact").unlink()
    (models / "emax_300rpm").unlink()
    assert shipped_models.resolve_checkpoint(None) == models / "envelope"
    with pytest.raises(shipped_models.ShippedModelError, match="shipped model's name"):
        shipped_models.resolve_checkpoint("no_such_model")


def test_bad_inputs_are_refused_before_the_dem(tiny, tmp_path):
    from sgn_jax.config import save_config
    from sgn_jax.pipelines.demo import DemoError, run_demo

    with pytest.raises(DemoError, match="multiple of"):
        run_demo(tmp_path / "a", checkpoint=tiny["run"], config=tiny["case"], duration=0.00105)
    other = tmp_path / "other.toml"
    save_config(replace_section(tiny["cfg"], "balls", count=23), other)
    with pytest.raises(DemoError, match=r"\[balls\] count = 24"):
        run_demo(tmp_path / "b", checkpoint=tiny["run"], config=other, duration=0.01)
    with pytest.raises(DemoError, match="does not exist"):
        run_demo(tmp_path / "c", checkpoint=tmp_path / "nothing", config=tiny["case"])
    with pytest.raises(ConfigError, match="does not exist"):
        run_demo(tmp_path / "d", checkpoint=tiny["run"], config=tmp_path / "missing.toml")
    assert not any((tmp_path / name).exists() for name in "abcd")


# --------------------------------------------------------------------------------------------
# Animation helpers


def test_jar_sections_lie_on_the_jar_walls():
    import jax.numpy as jnp

    from sgn_jax.analysis.animation import jar_sections
    from sgn_jax.geometry import jar_sdf
    from sgn_jax.pipelines.configure import jar_mesh_from_config, jar_params_from_config

    jar = replace_section(load_config(builtin_config_path("emax_300rpm")), "jar",
                          post_radius=0.006).jar
    sections = jar_sections(jar_mesh_from_config(jar))
    params = jar_params_from_config(jar)
    top = sections.top.reshape(-1, 2)
    points = np.stack([top[:, 0], np.full(len(top), 0.5 * jar.height), top[:, 1]], -1)
    phi = np.asarray(jax.vmap(lambda x: jar_sdf(params, x))(jnp.asarray(points)))
    # The mesh is a 256-gon per arc: its vertices lie on the wall, chords within ~2 um.
    assert np.abs(phi).max() < 5e-6
    radius_from_axis = np.hypot(top[:, 0], top[:, 1])
    assert radius_from_axis.min() == pytest.approx(0.006, abs=5e-6)  # the post is drawn
    side = sections.side.reshape(-1, 2)
    half_length = 0.5 * jar.straight_length + jar.radius
    f32 = 1e-8  # manifold3d keeps float32 vertices: 0.04 m to ~3e-9 m
    assert side[:, 0].min() == pytest.approx(-half_length, abs=f32)
    assert side[:, 0].max() == pytest.approx(half_length, abs=f32)
    assert side[:, 1].min() == pytest.approx(0.0, abs=f32)
    assert side[:, 1].max() == pytest.approx(jar.height, abs=f32)


def test_select_frames():
    from sgn_jax.analysis.animation import select_frames

    picked = select_frames(1001, 100)
    assert picked[0] == 0 and picked[-1] == 1000 and len(picked) == 100
    assert np.all(np.diff(picked) > 0)
    np.testing.assert_array_equal(select_frames(7, 100), np.arange(7))
    with pytest.raises(ValueError, match="no frames"):
        select_frames(0, 10)


def test_gif_input_shapes_are_checked(tmp_path):
    from sgn_jax.analysis.animation import write_comparison_gif
    from sgn_jax.pipelines.configure import jar_mesh_from_config

    jar = jar_mesh_from_config(load_config(builtin_config_path("emax_300rpm")).jar)
    pos = np.zeros((2, 3, 3))
    with pytest.raises(ValueError, match="pos_sgn"):
        write_comparison_gif(tmp_path / "a.gif", [0.0, 1.0], pos, pos[:, :2], np.zeros((2, 3)),
                             jar, 0.005)
    with pytest.raises(ValueError, match=".gif"):
        write_comparison_gif(tmp_path / "a.png", [0.0, 1.0], pos, pos, np.zeros((2, 3)), jar,
                             0.005)


def test_a_case_sampled_finer_than_the_model_runs_at_the_models_step(tiny, tmp_path,
                                                                       monkeypatch):
    """The demo of a model whose step is a whole multiple of the case's ``[dem] dt`` (the
    2e-4 s contact model, the default, on the 1e-4 s built-in cases) asks the DEM to record at
    the model's step, so that both are compared sample by sample; a step that is not a whole
    multiple is still refused before the DEM."""
    import sgn_jax.pipelines.demo as demo_module
    from sgn_jax.config import save_config

    class Stop(Exception):
        pass

    asked = {}

    def dem_stub(cfg, **kwargs):
        asked["dt"] = float(cfg.dem.dt)
        raise Stop

    monkeypatch.setattr(demo_module, "run_dem", dem_stub)
    finer = tmp_path / "finer.toml"
    save_config(replace_section(tiny["cfg"], "dem", dt=0.5e-4), finer)
    with pytest.raises(Stop):
        demo_module.run_demo(tmp_path / "a", checkpoint=tiny["run"], config=finer,
                             duration=0.01, progress=False)
    assert asked["dt"] == pytest.approx(1e-4, rel=1e-12)
    odd = tmp_path / "odd.toml"
    save_config(replace_section(tiny["cfg"], "dem", dt=0.3e-4), odd)
    with pytest.raises(demo_module.DemoError, match=r"\[dem\] dt"):
        demo_module.run_demo(tmp_path / "b", checkpoint=tiny["run"], config=odd,
                             duration=0.01, progress=False)
