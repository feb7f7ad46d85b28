"""A surrogate's free rollout against the DEM record it starts from: power, motion, contacts.

What the evaluation scripts (experiments/tools/evaluate_contact.py for motions and the standard
charge, experiments/charges/evaluate.py for charges) share: one rollout from a record's first
window compared with the DEM over the same interval (:func:`rollout_against_dem`), and a
case's summary over its packings (:func:`summarize_runs`). A charge of several sizes (a model
that reads the charge) is counted with each ball's own radius and mass.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

from sgn_jax.analysis.metrics import contact_census, jar_frame_speed
from sgn_jax.pipelines.configure import jar_params_from_config
from sgn_jax.pipelines.rollout_run import run_rollout

DAMPING = ("diss_pp_normal", "diss_pp_tangential", "diss_pw_normal", "diss_pw_tangential")
ALL_LOSSES = DAMPING + ("diss_pp_slip", "diss_pp_rolling", "diss_pw_slip", "diss_pw_rolling")


def rollout_against_dem(model: Any, cfg: Any, traj: Any, duration: float, window: int,
                        dem_ref: dict[str, Any] | None = None) -> dict[str, Any]:
    """One free rollout from sample ``window`` of ``traj`` against the DEM over the same
    interval; with ``dem_ref`` (an earlier evaluation's row of the same case and seed) the
    DEM's numbers are that row's and ``traj`` need only hold the first window."""
    dt = float(cfg.dem.dt)
    start = window
    n_steps = int(round(duration / dt))
    t0 = time.perf_counter()
    res = run_rollout(model, traj, start, n_steps * dt, None, cfg, save_every=1,
                      progress=False)
    wall = time.perf_counter() - t0
    a = res["arrays"]
    pos, off = np.asarray(a["pos"]), np.asarray(a["offset"])
    t_pos = np.asarray(a["t_pos"])
    finite = bool(np.isfinite(pos).all())
    jar = jar_params_from_config(cfg.jar)
    if "ball_radii" in res["meta"]:   # a charge-reading kind: each ball's radius and mass (N,)
        radius, mass = (np.asarray(res["meta"][k], np.float64) for k in ("ball_radii",
                                                                         "ball_masses"))
    else:
        radius = float(cfg.balls.radius)
        mass = float(cfg.balls.density) * 4 / 3 * math.pi * radius ** 3
    mass_n = np.broadcast_to(mass, (pos.shape[1],))    # (N,) kg
    radius_n = np.broadcast_to(radius, (pos.shape[1],))
    # The DEM over the same interval (samples start .. start + n_steps).
    sl = slice(start, start + n_steps + 1)
    span = n_steps * dt
    # dt_s: the step the steps count, so that a later model of another step compares over the
    # same interval when it takes this row as its DEM reference (reference_span)
    row = {"seed": int(traj.meta.get("seed", -1)), "steps": n_steps, "dt_s": dt, "wall_s": wall,
           "finite": finite,
           "model_power_W": float(np.sum(a["dE"])) / span,
           "outside_ball_steps": int(np.sum(a["n_outside"])),
           "snapped_fraction": float(np.sum(a["n_snapped"])) / (n_steps * pos.shape[1]),
           }
    if dem_ref is None:
        dem_pos, dem_off = np.asarray(traj.pos[sl]), np.asarray(traj.offset[sl])
        dem_target = sum(float(np.sum(traj[k][start + 1: start + n_steps + 1])) for k in DAMPING)
        dem_total = sum(float(np.sum(traj[k][start + 1: start + n_steps + 1])) for k in ALL_LOSSES)
        row.update({"dem_power_W": dem_target / span, "dem_total_power_W": dem_total / span,
                    "dem_speed_m_s": float(np.mean(jar_frame_speed(
                        np.asarray(traj.t[sl]), dem_pos, dem_off)))})
    else:
        row.update({k: v for k, v in dem_ref.items() if k.startswith("dem_")})
    if "diss_pp_model" in a:
        d_pp, d_pw, w_wall = (np.asarray(a[k]) for k in ("diss_pp_model", "diss_pw_model",
                                                         "work_wall_model"))
        row["model_total_power_W"] = float(np.sum(d_pp + d_pw)) / span
        row["model_pp_share_of_total"] = float(np.sum(d_pp) / max(np.sum(d_pp + d_pw), 1e-30))
        if finite:
            v = np.diff(pos, axis=0) / dt                      # v_{k+1}, k = 0 .. S-1
            ke = 0.5 * np.einsum("n,snk->s", mass_n, v ** 2)
            if "omega_model" in a:   # a model with spin state: its rotational energy too
                spin = np.asarray(a["omega_model"])[1:]        # w_{k+1}, k = 0 .. S-1
                ke = ke + 0.5 * 0.4 * np.einsum("n,snk->s", mass_n * radius_n ** 2, spin ** 2)
            g = np.asarray(cfg.dem.gravity, np.float64)
            pe = -(pos @ g) @ mass_n
            # jar work + gravity's work (from the positions) - d(KE) over steps 2 .. S
            lhs = float(np.sum(w_wall[1:]) - (ke[-1] - ke[0]) - (pe[-1] - pe[1]))
            rhs = float(np.sum(d_pp[1:] + d_pw[1:]))
            row["ledger_residual"] = (lhs - rhs) / max(abs(rhs), 1e-30)
    if "omega_model" in a:
        # The spin a model with spin state carries against the DEM's: mean contact-point
        # speed of the rotation, R |w| (m/s), over the same samples (docs/contact.md).
        row["model_spin_speed_m_s"] = float(np.mean(radius_n * np.linalg.norm(
            np.asarray(a["omega_model"]), axis=-1)))
        if traj.omega is not None and dem_ref is None:
            row["dem_spin_speed_m_s"] = float(np.mean(radius_n * np.linalg.norm(
                np.asarray(traj.omega[sl]), axis=-1)))
    if finite:
        row["model_speed_m_s"] = float(np.mean(jar_frame_speed(t_pos, pos, off)))
        census_m = contact_census(pos, off, jar, radius)
        row.update({f"model_{k}": v for k, v in census_m.items()})
        if dem_ref is None:
            census_d = contact_census(dem_pos, dem_off, jar, radius)
            row.update({f"dem_{k}": v for k, v in census_d.items()})
    return row


def reference_span(ref: dict[str, Any], model_dt: float, source: str = "the reference") -> float:
    """The interval (s) that an earlier evaluation's row (``ref``, a row of
    :func:`rollout_against_dem`) compared over, ``steps`` at that row's own step ``dt_s``, as a
    whole number of steps ``model_dt`` (s) of the model that reuses its DEM numbers.

    A row's ``steps`` count ITS model's steps: a model at half the step that rolled out
    ``steps`` of its own would cover half the DEM's interval. ValueError for a row without
    ``dt_s`` (written before rows recorded it: add the step of the model that made it) and for
    an interval that is not a whole number of ``model_dt``."""
    if "dt_s" not in ref:
        raise ValueError(f"{source}: the row has no dt_s, the step its {ref.get('steps')} steps "
                         "count; add dt_s (the step of the model that made the row) to its rows")
    span = int(ref["steps"]) * float(ref["dt_s"])
    n = round(span / model_dt)
    if not (n > 0 and math.isclose(n * model_dt, span, rel_tol=1e-9)):
        raise ValueError(f"{source}: its interval, {ref['steps']} steps of {ref['dt_s']} s, is "
                         f"not a whole number of the model's {model_dt} s steps")
    return n * model_dt


def mean_se(values: Any) -> tuple[float, float]:
    """Mean and standard error (ddof 1) of the finite values; NaN SE for fewer than two."""
    v = np.asarray([x for x in values if x is not None and np.isfinite(x)], np.float64)
    if v.size == 0:
        return float("nan"), float("nan")
    return float(v.mean()), float(v.std(ddof=1) / math.sqrt(v.size)) if v.size > 1 else float("nan")


def summarize_runs(name: str, runs: list[dict[str, Any]]) -> dict[str, Any]:
    """One case's summary of :func:`rollout_against_dem` rows: the means and SEs of every
    number, the deepest overlaps, outside and non-finite counts, and the signed errors of the
    power (with its bar max(10 %, 2 SE)), speed and contacts."""
    out = {"case": name, "runs": len(runs)}
    for key in ("dem_power_W", "dem_total_power_W", "model_power_W", "model_total_power_W",
                "dem_speed_m_s", "model_speed_m_s", "dem_pp_touching_mean", "model_pp_touching_mean",
                "dem_pw_touching_mean", "model_pw_touching_mean", "dem_pp_contact_frames_mean",
                "model_pp_contact_frames_mean", "snapped_fraction", "ledger_residual",
                "dem_spin_speed_m_s", "model_spin_speed_m_s"):
        m, se = mean_se([r.get(key) for r in runs])
        out[key], out[key + "_se"] = m, se
    out["deepest_pp_overlap_m"] = max((r.get("model_deepest_pp_overlap_m", float("nan")) for r in runs), default=float("nan"))
    out["dem_deepest_pp_overlap_m"] = max((r.get("dem_deepest_pp_overlap_m", float("nan")) for r in runs), default=float("nan"))
    # As a fraction of the smaller radius of the pair (a charge of several sizes; runs that
    # predate the census's relative overlap have none).
    for side in ("model", "dem"):
        rel = [r[f"{side}_deepest_pp_overlap_rel"] for r in runs if f"{side}_deepest_pp_overlap_rel" in r]
        out[f"{side}_deepest_pp_overlap_rel"] = max(rel) if rel else float("nan")
    out["outside_ball_steps"] = sum(r["outside_ball_steps"] for r in runs)
    out["non_finite_runs"] = sum(not r["finite"] for r in runs)
    dem, model = out["dem_power_W"], out["model_power_W"]
    se = math.sqrt(np.nan_to_num(out["dem_power_W_se"]) ** 2 + np.nan_to_num(out["model_power_W_se"]) ** 2)
    out["power_error"] = (model - dem) / dem
    out["power_bar"] = max(0.10, 2 * se / dem)
    if not math.isnan(out.get("model_total_power_W", float("nan"))):
        out["total_power_error"] = (out["model_total_power_W"] - out["dem_total_power_W"]) / out["dem_total_power_W"]
    out["speed_error"] = (out["model_speed_m_s"] - out["dem_speed_m_s"]) / out["dem_speed_m_s"]
    out["pp_touching_error"] = (out["model_pp_touching_mean"] - out["dem_pp_touching_mean"]) / out["dem_pp_touching_mean"]
    out["pw_touching_error"] = (out["model_pw_touching_mean"] - out["dem_pw_touching_mean"]) / out["dem_pw_touching_mean"]
    return out


def motion_misses(summary: dict[str, Any], speed_bar: float = 0.15,
                  contacts_bar: float = 0.25) -> list[str]:
    """The motion bars a case summary (:func:`summarize_runs`) misses: its mean jar-frame speed
    and its touching ball-ball (``pp``) and ball-wall (``pw``) contacts per step against the
    DEM's, each as "speed +x %" / "pp contacts +x %"."""
    out = []
    if abs(summary["speed_error"]) > speed_bar:
        out.append(f"speed {summary['speed_error']:+.1%}")
    for kind in ("pp", "pw"):
        if abs(summary[f"{kind}_touching_error"]) > contacts_bar:
            out.append(f"{kind} contacts {summary[f'{kind}_touching_error']:+.1%}")
    return out
