"""``sgn-jax demo``: the DEM and the trained surrogate side by side on the standard case.

:func:`run_demo` does, in one call:

1. the DEM of the case (built-in ``emax_300rpm`` by default): place the balls from ``seed``,
   settle them (``[dem] settle_time``), then run the motion long enough to cover the rollout
   (W + S samples, rounded up to whole DEM chunks so that no second chunk size is compiled),
   written to ``OUT/dem.npz``;
2. from the DEM's initial window (samples 0 .. W, the first full window of the model's
   ``[graph] window`` W) a rollout of ``duration`` seconds (S = duration / dt steps) with the
   trained surrogate (the shipped default, the contact model, unless ``checkpoint`` names
   another), written to ``OUT/prediction.npz``. A case sampled finer than the model's step by
   a whole factor (the 1e-4 s built-in cases and the 2e-4 s contact model) is run at the
   model's step: the DEM records at it (its own step is unchanged), so that both are compared
   sample by sample;
3. the comparison of :func:`sgn_jax.analysis.metrics.compare` (cumulative dissipated energy,
   position MSE_t, balls outside the jar, edge overflow, regime indicators, the motion checks),
   the wall-time speed ratio (DEM seconds per simulated second / surrogate seconds per simulated
   second, compile time and settling apart), ``OUT/summary.json``, the plots of
   :func:`sgn_jax.analysis.plots.plot_run` and ``OUT/animation.gif``
   (:mod:`sgn_jax.analysis.animation`).

The energy compared is the surrogate's target, the DEM's normal + tangential damping (ball-ball
and ball-wall) summed over the rollout's interval (t_W, t_W + duration]; the DEM's total
dissipation of all kinds (with Coulomb slip and rolling friction) is reported beside it.

The energy can agree by accident (a surrogate whose balls run too fast, pile against a wall and
sink into each other dissipated within 1 % of the DEM), so beside it the report prints the
motion checks of :func:`sgn_jax.analysis.metrics.motion_checks`, each with the DEM's value next to
the surrogate's: mean ball speed in the jar frame, ball-steps snapped back to the wall, deepest
ball-ball overlap and the MSE_t plateau against the DEM's chaos floor. Each check out of the
DEM's range prints a ``WARNING:`` line, followed by one saying that the energy agreement alone
should not be trusted (docs/rollout.md, "The demo's honesty lines").

One trajectory is one sample of a multistable system (docs/conventions.md section 7): the demo shows
the method working; accuracy claims about dissipation belong to ensembles (``sgn-jax evaluate``
with several runs).

The model is the shipped default unless ``checkpoint`` names another
(:mod:`sgn_jax.records.shipped_models`).
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from sgn_jax.analysis.animation import select_frames, write_comparison_gif
from sgn_jax.analysis.collisions import (
    DEFAULT_THRESHOLD_J,
    collision_statistics,
    events_from_record,
)
from sgn_jax.analysis.metrics import (
    MOTION_MSE_FLOOR_MAX_RATIO,
    MOTION_OVERLAP_MAX_M,
    MOTION_SNAPPED_FRACTION_MAX,
    MOTION_SPEED_TOLERANCE,
    MetricsWarning,
    compare,
    motion_warning_lines,
    position_mse,
)
from sgn_jax.config import resolve_config
from sgn_jax.errors import SGNJaxError
from sgn_jax.pipelines.configure import jar_mesh_from_config
from sgn_jax.pipelines.dem_run import run_dem
from sgn_jax.pipelines.rollout_run import config_at_model_step, run_rollout
from sgn_jax.pipelines.validation import check_duration, warn_outside_envelope
from sgn_jax.records.checkpoint import CheckpointError, load_trained_model
from sgn_jax.records.io_utils import machine_info, write_json
from sgn_jax.records.prediction import load_prediction
from sgn_jax.records.shipped_models import resolve_checkpoint
from sgn_jax.records.trajectory import load_trajectory

DEFAULT_CASE = "emax_300rpm"
ANIMATION_FRAMES = 100


class DemoError(SGNJaxError, ValueError):
    """The demo cannot run with these inputs; the message says why and what to do."""


# --------------------------------------------------------------------------------------------
# Inputs


def _check_compatible(case_cfg: Any, model_cfg: Any, checkpoint: Path) -> None:
    """The DEM of ``case_cfg`` must produce what the model was trained on (balls, dt)."""
    for section, name in (("balls", "count"), ("balls", "radius"), ("dem", "dt")):
        case_value = getattr(getattr(case_cfg, section), name)
        model_value = getattr(getattr(model_cfg, section), name)
        if not math.isclose(float(case_value), float(model_value), rel_tol=1e-12):
            raise DemoError(
                f"the model in {checkpoint} was trained with [{section}] {name} = {model_value}, "
                f"but the demo case has {case_value}; use the model's case or a model trained "
                "on this one")


# --------------------------------------------------------------------------------------------
# The demo


def run_demo(
    out_dir: str | Path = "runs/demo",
    *,
    checkpoint: str | Path | None = None,
    duration: float = 1.0,
    seed: int | None = None,
    config: str | Path = DEFAULT_CASE,
    which: str = "best",
    animation_frames: int = ANIMATION_FRAMES,
    progress: bool = True,
    log: Callable[[str], None] = lambda message: None,
) -> dict[str, Any]:
    """Run the DEM and the surrogate on the same case and compare them (see module docstring).

    Args:
        out_dir: output directory (created): dem.npz, prediction.npz, summary.json,
            position_mse.png, cumulative_energy.png, trajectory_xz.png, animation.gif.
        checkpoint: training run or checkpoint directory; None: the shipped model.
        duration: seconds of surrogate rollout (a multiple of ``[rollout] save_every`` steps).
        seed: DEM placement seed (default ``[dem] seed``).
        config: built-in config name or TOML path of the case (its [jar], [motion], [sdf] and
            [rollout] also drive the rollout; balls and dt must match the model's).
        which: "best" or "latest" checkpoint of a training run directory.
        animation_frames: about this many frames in the GIF.
        progress: tqdm bars (DEM, rollout, animation).
        log: called with one line per stage (e.g. ``print``).

    Returns:
        the summary (also written to ``OUT/summary.json``): ``energy``, ``position``,
        ``speed``, ``dem``, ``surrogate``, ``checks``, ``regime``, ``motion_checks`` (list of
        dicts, :func:`sgn_jax.analysis.metrics.motion_checks`), ``motion_warnings`` (messages of the
        failed checks), ``files``, ``wall_time_s``.
    """
    # deferred: sgn_jax.analysis.plots imports matplotlib; api and cli import this module
    # without plotting
    from sgn_jax.analysis.plots import plot_run

    t_start = time.perf_counter()
    out = Path(out_dir)
    check_duration(duration, "--duration")
    if animation_frames < 2:
        raise DemoError(f"animation_frames must be >= 2, got {animation_frames}")
    case_cfg = resolve_config(config)
    try:
        ckpt = resolve_checkpoint(checkpoint)
        trained = load_trained_model(ckpt, which=which)
    except CheckpointError as exc:
        raise DemoError(str(exc)) from exc
    # A case sampled finer than the model's step by a whole factor (the 1e-4 s built-in cases
    # and the 2e-4 s contact model) runs at the model's step: the DEM records at it, so the
    # comparison is sample by sample at the model's step.
    case_cfg = config_at_model_step(case_cfg, float(trained.config.dem.dt))
    _check_compatible(case_cfg, trained.config, ckpt)
    warn_outside_envelope(case_cfg, trained.config, trained.meta)

    dt = float(case_cfg.dem.dt)
    window = int(trained.config.graph.window)
    save_every = int(case_cfg.rollout.save_every)
    n_steps = int(round(duration / dt))
    if n_steps < save_every or n_steps % save_every or not math.isclose(n_steps * dt, duration,
                                                                        rel_tol=1e-9):
        raise DemoError(f"--duration {duration:g} s must be a positive multiple of "
                        f"[rollout] save_every x dt = {save_every * dt:g} s")
    seed = case_cfg.dem.seed if seed is None else int(seed)
    # The DEM covers the rollout's interval [t_W, t_W + duration]; rounded up to whole chunks,
    # since a remainder chunk would cost a second compilation (several seconds) of the sampler.
    chunk = int(case_cfg.dem.chunk_samples)
    dem_samples = window + n_steps
    settle = int(round(case_cfg.dem.settle_time / dt))  # as the DEM driver counts them
    if settle % chunk == 0:
        dem_samples = -(-dem_samples // chunk) * chunk
    dem_duration = dem_samples * dt
    log(f"case {case_cfg.case.name}, seed {seed}; model {ckpt} (hidden "
        f"{trained.config.model.hidden}, window {window}, epoch {trained.meta.get('epoch')})")

    # ---- 1. DEM
    log(f"DEM: {case_cfg.dem.settle_time:g} s settling, then {dem_duration:g} s of motion")
    dem_path = out / "dem.npz"
    dem = run_dem(case_cfg, duration=dem_duration, out_path=dem_path, seed=seed,
                  progress=progress)
    traj = load_trajectory(dem_path)

    # ---- 2. surrogate rollout from the DEM's first full window
    log(f"model: {n_steps} steps of {dt:g} s from the DEM window ending at t = {window * dt:g} s")
    pred_path = out / "prediction.npz"
    # a model with a collision ledger (the contact kind) records its collisions too
    has_ledger = callable(getattr(trained.model, "collision_terms", None))
    rollout = run_rollout(trained, traj, window, n_steps * dt, pred_path, case_cfg,
                          progress=progress, checkpoint_path=str(ckpt), collisions=has_ledger)
    prediction = load_prediction(pred_path)

    # ---- 3. comparison, plots, animation
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", MetricsWarning)
        comparison = compare(prediction, traj)
    cmp = comparison.summary
    files = {name: str(p) for name, p in plot_run(comparison, prediction, traj, out).items()}
    gif = _write_animation(out / "animation.gif", prediction, traj, comparison, case_cfg,
                           animation_frames, progress)
    files.update(animation=str(gif), dem=str(dem_path), prediction=str(pred_path))

    dem_sim = float(dem.summary["duration_s"])
    dem_motion_s = float(dem.summary["motion_wall_s"])
    sgn_run_s = rollout["ms_per_step"] * 1e-3 * n_steps
    dem_per_sim = dem_motion_s / dem_sim
    sgn_per_sim = sgn_run_s / (n_steps * dt)
    e_dem = cmp["energy"]["E_ref_final_J"]
    e_sgn = cmp["energy"]["E_pred_final_J"]
    position = cmp["position"] or {}
    summary: dict[str, Any] = {
        "case": case_cfg.case.name,
        "seed": seed,
        "checkpoint": str(ckpt),
        "model": {"hidden": trained.config.model.hidden, "window": window,
                  "epoch": trained.meta.get("epoch"), "step": trained.meta.get("step")},
        "duration_s": n_steps * dt,
        "t_start_s": float(prediction.t_start),
        "t_end_s": float(prediction.t_step[-1]),
        "energy": {
            "what": "cumulative normal + tangential damping (ball-ball + ball-wall) over the "
                    "rollout interval, J",
            "dem_J": e_dem,
            "sgn_J": e_sgn,
            "relative_error": cmp["energy"]["relative_error_final"],
            "pearson_r": cmp["energy"]["pearson_r"],
            "dem_all_kinds_J": _interval_sum(traj.cumulative_dissipation("all", "all"),
                                             comparison.alignment),
        },
        "position": {
            "mse_plateau_m2": position.get("mse_plateau_m2"),
            "mse_final_m2": position.get("mse_final_m2"),
            "mse_max_m2": position.get("mse_max_m2"),
        },
        "speed": {
            "dem_s_per_sim_s": dem_per_sim,
            "sgn_s_per_sim_s": sgn_per_sim,
            "ratio": dem_per_sim / sgn_per_sim if sgn_per_sim > 0 else None,
            "dem_compile_s": float(dem.summary["compile_time_s"]),
            "sgn_compile_s": float(rollout["compile_time_s"]),
            "dem_settle_s": float(dem.summary["settle_wall_s"]),
            "dem_steps_per_s": dem.summary["steps_per_s"],
            "sgn_ms_per_step": float(rollout["ms_per_step"]),
            "note": "wall time without compilation; the DEM's motion only (settling apart)",
        },
        "dem": {
            "settle_s": float(case_cfg.dem.settle_time),
            "motion_s": dem_sim,
            "dt_dem": float(dem.summary["dt_dem"]),
            "steps": int(dem.summary["dem_steps"]),
            "motion_wall_s": dem_motion_s,
            "wall_time_s": float(dem.summary["wall_time_s"]),
            "balls_outside": int(dem.summary["balls_outside"]),
            "ledger_residual_J": float(dem.summary["ledger_residual_J"]),
        },
        "surrogate": {
            "steps": n_steps,
            "dt": dt,
            "run_s": sgn_run_s,
            "wall_time_s": float(rollout["wall_time_s"]),
            "snapped_ball_steps": int(rollout["snapped_ball_steps"]),
        },
        "checks": {
            "sgn_balls_outside_ball_steps": cmp["outside"]["total_ball_steps"],
            "sgn_balls_outside_max": cmp["outside"]["max"],
            "dem_balls_outside": int(dem.summary["balls_outside"]),
            "edge_overflow_total": cmp["overflow"]["total_edges"],
            "edge_overflow_steps": cmp["overflow"]["steps_with_any"],
            "reference_covers_prediction": cmp["overlap"]["complete"],
        },
        "regime": {
            "pairs_within_skin_per_ball_dem": _per_ball(
                cmp["regime"]["pp_pairs_within_skin_ref_mean"], traj.n_balls),
            "pairs_per_ball_sgn": _per_ball(cmp["regime"]["pp_contacts_pred_mean"],
                                            traj.n_balls),
            "jar_speed_dem_m_s": cmp["regime"].get("jar_speed_ref_mean_m_s"),
            "jar_speed_sgn_m_s": cmp["regime"].get("jar_speed_pred_mean_m_s"),
            "state_dem": cmp["regime"]["state_ref"],
            "state_sgn": cmp["regime"]["state_pred"],
        },
        "motion_checks": cmp["motion"]["checks"],
        "motion_warnings": cmp["motion"]["warnings"],
        "warnings": [str(w.message) for w in caught],
        "files": files,
    }
    # The MSE of the last frame, recomputed from the files: a consistency check on alignment.
    last_ref = int(round((float(prediction.t_pos[-1]) - float(traj.t[0])) / traj.dt))
    summary["position"]["mse_final_check_m2"] = float(
        position_mse(prediction.pos[-1:], traj.pos[last_ref:last_ref + 1])[0])
    summary["collisions"] = (_collision_summary(traj, prediction)
                             if has_ledger and "collision_ball" in traj.arrays else None)
    summary["machine"] = _machine()
    summary["wall_time_s"] = time.perf_counter() - t_start
    files["summary"] = str(out / "summary.json")
    write_json(out / "summary.json", summary)
    return summary


def _collision_summary(traj: Any, prediction: Any) -> dict[str, Any]:
    """The DEM's and the model's collision statistics over the rollout's interval (one
    packing; docs/collisions.md)."""
    model = events_from_record(prediction)
    start = model.record_start_s
    dem = events_from_record(traj).window(start, start + model.record_duration_s)
    out: dict[str, Any] = {"threshold_J": DEFAULT_THRESHOLD_J}
    for name, table in (("dem", dem), ("model", model)):
        stats = collision_statistics(table)
        out[name] = {"per_ball_per_s": stats["frequency_per_ball_hz[all]"],
                     "mean_stress_energy_J": stats["mean_stress_energy_J[all]"],
                     "normal_share": stats["normal_share[all]"],
                     "power_above_W": stats["power_above_W"],
                     "power_W": stats["power_W[all]"]}
    return out


def _interval_sum(cumulative: np.ndarray, alignment: Any) -> float:
    """A cumulative DEM curve's increase over the compared rollout interval (J)."""
    start = alignment.start_ref_index if alignment.start_ref_index >= 0 else \
        int(alignment.step_ref_index[0])
    return float(cumulative[int(alignment.step_ref_index[-1])] - cumulative[start])


def _machine() -> dict[str, Any]:
    """Where the timings were taken (the demo's numbers are benchmarks too)."""
    return machine_info()


def _per_ball(value: Any, n_balls: int) -> float | None:
    return None if value is None else float(value) / n_balls


def _write_animation(path: Path, prediction: Any, traj: Any, comparison: Any, case_cfg: Any,
                     n_frames: int, progress: bool) -> Path:
    """About ``n_frames`` frames over the rollout: DEM and model at the prediction's frame times."""
    al = comparison.alignment
    if al.frame_index.size == 0:
        raise DemoError("no prediction frame has a DEM sample at the same time")
    pick = select_frames(al.frame_index.size, n_frames)
    frames, ref_frames = al.frame_index[pick], al.frame_ref_index[pick]
    t_pos = np.asarray(prediction.t_pos)[frames]
    # Cumulative energies at the frame times (the step ending at the frame, 0 at the start).
    e_pred = np.concatenate([[0.0], comparison.energy_pred])
    e_ref = np.concatenate([[0.0], comparison.energy_ref])
    step_of_frame = np.rint((t_pos - prediction.t_start) / prediction.dt).astype(np.int64)
    captions = [f"E_DEM = {1e3 * e_ref[s]:.2f} mJ   E_model = {1e3 * e_pred[s]:.2f} mJ"
                for s in step_of_frame]
    return write_comparison_gif(
        path, t_pos, np.asarray(traj.pos)[ref_frames], np.asarray(prediction.pos)[frames],
        np.asarray(prediction.offset)[frames], jar_mesh_from_config(case_cfg.jar),
        float(traj.meta["ball_radius"]), captions=captions, progress=progress)


# --------------------------------------------------------------------------------------------
# Report


def _fmt(value: Any, spec: str) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "n/a"
    return format(value, spec)


def format_report(summary: dict[str, Any]) -> str:
    """The human-readable lines that ``sgn-jax demo`` prints."""
    e, p, s, c, d, g, r = (summary[k] for k in ("energy", "position", "speed", "checks", "dem",
                                                "surrogate", "regime"))
    rel = e["relative_error"]
    checks = summary.get("motion_checks") or []
    motion_warnings = summary.get("motion_warnings") or []
    out = Path(summary["files"]["summary"]).parent
    names = ", ".join(Path(v).name for k, v in summary["files"].items() if k != "summary")
    lines = [
        f"sgn-jax demo: case {summary['case']}, seed {summary['seed']}, model "
        f"{summary['checkpoint']}",
        f"  DEM        {d['settle_s']:g} s settling + {d['motion_s']:g} s of motion, "
        f"{d['steps']:,} steps of {d['dt_dem']:.4g} s: {d['motion_wall_s']:.1f} s for the "
        f"motion ({_fmt(s['dem_steps_per_s'], ',.0f')} steps/s), {s['dem_settle_s']:.1f} s "
        f"settling, {s['dem_compile_s']:.1f} s compile",
        f"  model      {g['steps']:,} steps of {g['dt']:g} s from t = "
        f"{summary['t_start_s']:.4g} s: {g['run_s']:.1f} s ({s['sgn_ms_per_step']:.3f} ms/step), "
        f"{s['sgn_compile_s']:.1f} s compile",
        f"  energy     dissipated over the rollout (normal + tangential damping): DEM "
        f"{_fmt(e['dem_J'], '.4g')} J, model {_fmt(e['sgn_J'], '.4g')} J, relative error "
        f"{_fmt(None if rel is None else 100 * rel, '.2f')} % (Pearson r "
        f"{_fmt(e['pearson_r'], '.4f')}); DEM with slip and rolling friction "
        f"{e['dem_all_kinds_J']:.4g} J"
        + (f"; NOT to be trusted alone: {len(motion_warnings)} motion check(s) failed, see "
           "the WARNING lines" if motion_warnings else ""),
        *_motion_check_lines(checks),
        f"  positions  MSE_t plateau {_fmt(p['mse_plateau_m2'], '.3g')} m^2, final "
        f"{_fmt(p['mse_final_m2'], '.3g')} m^2",
        f"  speed      DEM {s['dem_s_per_sim_s']:.2f} s vs model {s['sgn_s_per_sim_s']:.2f} s per "
        f"simulated second: ratio {_fmt(s['ratio'], '.2f')}x (compile and settling apart)",
        f"  checks     balls outside the jar: model {c['sgn_balls_outside_ball_steps']} "
        f"ball-steps, DEM {c['dem_balls_outside']} balls; edge overflows "
        f"{c['edge_overflow_total']}; snapped ball-steps {g['snapped_ball_steps']}",
        f"  regime     mean ball speed in the jar frame: DEM "
        f"{_fmt(r['jar_speed_dem_m_s'], '.3f')} m/s ({r['state_dem']}), model "
        f"{_fmt(r['jar_speed_sgn_m_s'], '.3f')} m/s ({r['state_sgn']}); ball pairs within the "
        f"edge skin per ball: DEM {_fmt(r['pairs_within_skin_per_ball_dem'], '.2f')}, model "
        f"{_fmt(r['pairs_per_ball_sgn'], '.2f')}; one trajectory of a multistable charge: "
        "judge dissipation on ensembles (docs/conventions.md section 7)",
        *_collision_lines(summary.get("collisions")),
        f"  wrote      {out}/: summary.json, {names}",
        f"  total      {summary['wall_time_s']:.1f} s",
    ]
    lines += [f"  warning    {w}" for w in summary["warnings"]]
    lines += [f"  {line}" for line in motion_warning_lines(motion_warnings)]
    return "\n".join(lines)


def _collision_lines(collisions: dict[str, Any] | None) -> list[str]:
    """The "collisions" line of the report (docs/collisions.md), DEM vs model."""
    if not collisions:
        return []
    d, m = collisions["dem"], collisions["model"]
    return [
        f"  collisions per ball per s: DEM {d['per_ball_per_s']:.0f}, model "
        f"{m['per_ball_per_s']:.0f}; mean stress energy DEM "
        f"{1e6 * d['mean_stress_energy_J']:.3g} uJ, model {1e6 * m['mean_stress_energy_J']:.3g} "
        f"uJ; normal share DEM {100 * d['normal_share']:.0f} %, model "
        f"{100 * m['normal_share']:.0f} %; power above {collisions['threshold_J']:g} J DEM "
        f"{d['power_above_W']:.3g} W, model {m['power_above_W']:.3g} W (`sgn-jax spectra` "
        "for the spectra)"]


def _motion_check_lines(checks: list[dict[str, Any]]) -> list[str]:
    """The "motion checks" block of the report: the DEM's value next to the surrogate's."""
    if not checks:
        return []
    by_name = {c["name"]: c for c in checks}
    verdict = {True: "ok", False: "OUT OF RANGE", None: "n/a"}
    lines = ["  motion     checks of the motion, DEM vs model (the energy can agree by accident):"]
    c = by_name.get("jar_speed")
    if c:
        off = c.get("relative_difference")
        lines.append(
            f"    jar-frame ball speed  DEM {_fmt(c['dem'], '.3f')} m/s, model "
            f"{_fmt(c['sgn'], '.3f')} m/s ({_fmt(None if off is None else 100 * off, '+.0f')} "
            f"%; limit +-{100 * MOTION_SPEED_TOLERANCE:g} %): {verdict[c['ok']]}")
    c = by_name.get("snapped")
    if c:
        count = c.get("sgn_ball_steps")
        lines.append(
            f"    snapped to the wall   DEM 0 (no snap), model "
            f"{_fmt(None if c['sgn'] is None else 100 * c['sgn'], '.2f')} % of ball-steps "
            f"({_fmt(count, ',d')} of {_fmt(c.get('ball_steps'), ',d')}; limit "
            f"{100 * MOTION_SNAPPED_FRACTION_MAX:g} %): {verdict[c['ok']]}")
    c = by_name.get("overlap")
    if c:
        lines.append(
            f"    deepest ball overlap  DEM {_fmt(c['dem'], ',.0f')} um, model "
            f"{_fmt(c['sgn'], ',.0f')} um (limit {1e6 * MOTION_OVERLAP_MAX_M:g} um): "
            f"{verdict[c['ok']]}")
    c = by_name.get("mse_plateau")
    if c:
        lines.append(
            f"    MSE_t plateau         DEM chaos floor {c['dem']:.1e} m^2 (same packing, dt vs "
            f"dt/2), unrelated packings {c['dem_unrelated_packings']:.1e} m^2; model "
            f"{_fmt(c['sgn'], '.2e')} m^2 = {_fmt(c.get('ratio_to_unrelated'), '.2f')}x the "
            f"unrelated level (limit < {MOTION_MSE_FLOOR_MAX_RATIO:g}x): {verdict[c['ok']]}")
    return lines


__all__ = [
    "DEFAULT_CASE",
    "DemoError",
    "format_report",
    "run_demo",
]
