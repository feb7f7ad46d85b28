"""Rollout metrics: a surrogate prediction against a DEM reference.

The metrics are those of docs/conventions.md sections 6 and 7.

Pure numpy. The pieces (each usable alone):

- :func:`align` matches prediction steps and frames to reference samples by time (tolerance
  dt / 10); where the reference does not cover the prediction, the comparison uses the overlap,
  reports it and warns (:class:`CoverageWarning`).
- :func:`position_mse` (paper Eq. 33, balls matched by index) and :func:`mse_plateau` (median of
  MSE_t over the last half of the compared frames).
- :func:`relative_error`, :func:`pearson_r`: the cumulative-energy comparison. The reference
  E_ref(t) is the DEM's normal + tangential damping (ball-ball + ball-wall, the surrogate's dE
  target), summed over the samples after the rollout's start ``t_start``, so E_ref(t_start) = 0
  like the prediction's ``energy_cum``. If the reference starts after ``t_start``, both curves
  are re-based to zero at the first compared step (reported as ``energy.baseline``).
- regime indicators: :func:`pp_contact_counts` (the DEM's contact list),
  :func:`pairs_within` (pairs with centre distance <= 2 R + skin, the graph's own edge rule, so
  the DEM count computed this way is the apples-to-apples number for the surrogate's
  ``n_pp_edges / 2``; it and :func:`deepest_pair_overlap` are defined in :mod:`sgn_jax.pairs`),
  :func:`kinetic_energy_fd` (from finite-difference velocities) and the mean dissipation power.
- :func:`compare` -> :class:`Comparison` (full-length curves for plots and the summary),
  :func:`evaluate` -> JSON-able dict, :func:`ensemble_summary` over runs (docs/conventions.md
  section 7).
- motion checks (is the energy agreement right for the right reason?):
  :func:`deepest_pair_overlap`, :func:`motion_checks` (the DEM's value next to the surrogate's:
  jar-frame speed, snapped ball-steps, deepest ball-ball overlap, MSE_t plateau against the
  DEM's chaos floor), :func:`motion_warnings` (one ``WARNING:`` line per check out of the DEM's
  range, thresholds in the ``MOTION_*`` constants) and :func:`motion_checks_of` (the checks
  of a :func:`compare` summary, which stores them as ``motion``).

State classification (docs/conventions.md section 7, "bed" vs "agitated"): the rules, their
thresholds and where they come from live in :mod:`sgn_jax.regime` (:func:`classify_state`,
:data:`AGITATED_SPEED_M_S`, :data:`BED_PAIRS_PER_BALL`); this module applies them to the prediction
and to the reference at the same frame times. They are re-exported here under the same names.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import jax.numpy as jnp
import numpy as np

from sgn_jax.errors import SGNJaxWarning
from sgn_jax.geometry import jar_sdf
from sgn_jax.pairs import MetricsError, deepest_pair_overlap, pairs_within
from sgn_jax.records.prediction import load_prediction
from sgn_jax.records.trajectory import load_trajectory
from sgn_jax.regime import (
    AGITATED_SPEED_M_S,
    BED_PAIRS_PER_BALL,
    CLASSIFIERS,
    classify_state,
    default_threshold,
)

# --------------------------------------------------------------------------------------------
# Motion checks: the constants (one place; docs/rollout.md "The demo's honesty lines")

MSE_FLOOR_SAME_PACKING_M2 = 5.6e-4
"""The DEM's own chaos floor, standard case: MSE_t plateau between two DEM runs of the same
packing (seed 4) at dt and at dt/2 (median over the second half of 5 s). Source: docs/results.md
section 2 ("The MSE_t plateau: the DEM's own floor"), ``experiments/reproduce/mse_floor``
(``runs/mse_chaos.json``)."""

MSE_FLOOR_UNRELATED_M2 = 8.2e-4
"""MSE_t plateau between two unrelated DEM packings of the standard case, balls matched by index
(mean of 4 pairs, 7.0-8.8e-4). A surrogate at or above it tracks the DEM no better than an
independent run: its positions carry no information beyond the jar's size. Source:
docs/results.md section 2, ``experiments/reproduce/mse_floor``
(``runs/mse_baseline_standard.json``)."""

DEM_DEEPEST_OVERLAP_M = 62e-6
"""Deepest ball-ball overlap of the DEM in a 10-s run of the standard case
(:func:`deepest_pair_overlap` over the DEM record), for orientation; the motion checks report
each run's own DEM value beside the model's."""

MOTION_SPEED_TOLERANCE = 0.20
"""Warn when the surrogate's mean jar-frame ball speed differs from the DEM's by more than this
fraction of the DEM's."""

MOTION_SNAPPED_FRACTION_MAX = 0.01
"""Warn when more than this fraction of the surrogate's ball-steps were snapped back to the wall
(the DEM never needs it)."""

MOTION_OVERLAP_MAX_M = 0.5e-3
"""Warn when the surrogate's deepest ball-ball overlap exceeds this (m); the DEM's is ~62 um."""

MOTION_MSE_FLOOR_MAX_RATIO = 1.0
"""Warn when the surrogate's MSE_t plateau is at or above this multiple of
:data:`MSE_FLOOR_UNRELATED_M2`."""

ENERGY_TRUST_WARNING = (
    "the energy agreement alone should not be trusted: the surrogate's motion is outside the "
    "DEM's range (see the warnings above), so a small energy error is right by accident")
"""The line that follows the motion warnings when any fired."""

_ALIGN_TOL_FRACTION = 0.1  # match times within dt / 10
_OFFSET_WARN_M = 1e-5  # jar offsets of matched frames differ by more: wrong reference or motion


class MetricsWarning(SGNJaxWarning):
    """Something in the comparison deserves attention (the metrics are still computed)."""


class CoverageWarning(MetricsWarning):
    """The reference covers only part of the prediction; metrics use the overlap."""


# --------------------------------------------------------------------------------------------
# Small pure functions


def position_mse(pred_pos: np.ndarray, ref_pos: np.ndarray) -> np.ndarray:
    """MSE_t = mean over balls of |x_pred - x_ref|^2 (paper Eq. 33), m^2.

    Args:
        pred_pos: (P, N, 3) predicted positions (m).
        ref_pos: (P, N, 3) reference positions (m), balls matched by index.
    Returns:
        (P,) float64.
    """
    pred_pos = np.asarray(pred_pos, dtype=np.float64)
    ref_pos = np.asarray(ref_pos, dtype=np.float64)
    if pred_pos.shape != ref_pos.shape or pred_pos.ndim != 3 or pred_pos.shape[-1] != 3:
        raise MetricsError(f"position_mse needs two (P, N, 3) arrays of the same shape, got "
                           f"{pred_pos.shape} and {ref_pos.shape}")
    return np.mean(np.sum((pred_pos - ref_pos) ** 2, axis=-1), axis=-1)


def mse_plateau(mse: np.ndarray) -> float:
    """Median of MSE_t over the last half of the frames (NaNs ignored); NaN if there are none."""
    mse = np.asarray(mse, dtype=np.float64)
    mse = mse[np.isfinite(mse)]
    if mse.size == 0:
        return math.nan
    return float(np.median(mse[mse.size // 2:]))


def relative_error(e_pred: np.ndarray, e_ref: np.ndarray) -> np.ndarray:
    """|E_pred - E_ref| / E_ref where E_ref > 0, NaN elsewhere; same shape as the inputs."""
    e_pred = np.asarray(e_pred, dtype=np.float64)
    e_ref = np.asarray(e_ref, dtype=np.float64)
    positive = np.isfinite(e_ref) & (e_ref > 0)
    safe = np.where(positive, e_ref, 1.0)
    return np.where(positive, np.abs(e_pred - e_ref) / safe, np.nan)


def pearson_r(a: np.ndarray, b: np.ndarray) -> float:
    """Pearson correlation of two equal-length curves (pairs with a NaN are skipped).

    NaN when fewer than two pairs remain or either curve is constant.
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.shape != b.shape:
        raise MetricsError(f"pearson_r needs curves of equal shape, got {a.shape} and {b.shape}")
    keep = np.isfinite(a) & np.isfinite(b)
    a, b = a[keep], b[keep]
    if a.size < 2:
        return math.nan
    da, db = a - a.mean(), b - b.mean()
    denominator = math.sqrt(float(np.dot(da, da)) * float(np.dot(db, db)))
    if denominator == 0.0:
        return math.nan
    return float(np.clip(np.dot(da, db) / denominator, -1.0, 1.0))


def pp_contact_counts(pp_pairs: np.ndarray) -> np.ndarray:
    """Ball-ball contacts per sample from a DEM contact list (T, K, 2) padded with -1 -> (T,)."""
    pp_pairs = np.asarray(pp_pairs)
    return np.sum(np.all(pp_pairs >= 0, axis=-1), axis=-1).astype(np.int64)


def kinetic_energy_fd(t: np.ndarray, pos: np.ndarray, ball_mass: float
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Translational kinetic energy from finite-difference velocities between frames.

    v = (x_{k+1} - x_k) / (t_{k+1} - t_k) (the velocity of docs/conventions.md section 5 when
    frames are dt apart; an interval average, hence an underestimate, for coarser frames).

    Args:
        t: (P,) frame times (s), strictly increasing; pos: (P, N, 3) m; ball_mass: kg.
    Returns:
        (t_mid (P-1,) s, ke (P-1,) J) at the interval midpoints.
    """
    t = np.asarray(t, dtype=np.float64)
    pos = np.asarray(pos, dtype=np.float64)
    if t.size < 2:
        return np.zeros(0), np.zeros(0)
    velocity = np.diff(pos, axis=0) / np.diff(t)[:, None, None]
    ke = 0.5 * ball_mass * np.sum(velocity**2, axis=(1, 2))
    return 0.5 * (t[1:] + t[:-1]), ke


def jar_frame_speed(t: np.ndarray, pos: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """Mean ball speed in the jar frame between consecutive frames.

    Args:
        t: (P,) frame times (s), strictly increasing; pos: (P, N, 3) ball positions (m, lab
            frame); offset: (P, 3) jar offsets (m) at those times.
    Returns:
        (P-1,) mean over balls of |d(pos - offset)/dt| (m/s), one per frame interval.
    """
    t = np.asarray(t, dtype=np.float64)
    if t.size < 2:
        return np.zeros(0)
    rel = np.asarray(pos, dtype=np.float64) - np.asarray(offset, dtype=np.float64)[:, None, :]
    velocity = np.diff(rel, axis=0) / np.diff(t)[:, None, None]
    return np.linalg.norm(velocity, axis=-1).mean(axis=1)


def contact_census(pos: np.ndarray, offset: np.ndarray, jar: Any, radius: float | np.ndarray,
                   chunk: int = 2000) -> dict[str, float]:
    """How the balls touch, counted the same way for a DEM record and a surrogate rollout.

    Args:
        pos: (P, N, 3) ball centres (m, lab frame), one frame per step for contact lifetimes;
        offset: (P, 3) jar offsets (m); jar: the ``JarParams`` (exact SDF of the cavity);
        radius: ball radius R (m), or (N,) each ball's radius r_i (a charge of several sizes).
    Returns:
        ``pp_touching_mean`` (ball-ball pairs with |x_i - x_j| < r_i + r_j per frame),
        ``pw_touching_mean`` (balls with phi > -r_i, i.e. touching the nearest wall, per frame),
        ``deepest_pp_overlap_m`` and ``deepest_pw_overlap_m`` (max over frames, m; <= 0 when
        nothing touches), ``deepest_pp_overlap_rel`` (the deepest ball-ball overlap as a
        fraction of the smaller radius of its pair), ``pp_contact_frames_mean`` (mean run
        length, in frames, of a touching pair: how long a ball-ball contact lasts).
    """
    pos = np.asarray(pos, np.float64)
    rel = pos - np.asarray(offset, np.float64)[:, None, :]
    n = pos.shape[1]
    r = np.broadcast_to(np.asarray(radius, np.float64), (n,))
    i, j = np.triu_indices(n, k=1)
    reach, smaller = r[i] + r[j], np.minimum(r[i], r[j])
    pp_count, pw_count, pp_deep, pw_deep, pp_deep_rel = [], [], -np.inf, -np.inf, -np.inf
    touching_runs = []
    for start in range(0, len(pos), chunk):
        x = pos[start:start + chunk]
        d = np.linalg.norm(x[:, i] - x[:, j], axis=-1)
        touch = d < reach
        pp_count.append(touch.sum(axis=1))
        pp_deep = max(pp_deep, float((reach - d).max()))
        pp_deep_rel = max(pp_deep_rel, float(((reach - d) / smaller).max()))
        phi = np.asarray(jar_sdf(jar, jnp.asarray(rel[start:start + chunk])))
        pw_count.append((phi > -r).sum(axis=1))
        pw_deep = max(pw_deep, float((phi + r).max()))
        touching_runs.append(touch)
    lengths = _touching_runs(np.concatenate(touching_runs, axis=0))
    return {"pp_touching_mean": float(np.concatenate(pp_count).mean()),
            "pw_touching_mean": float(np.concatenate(pw_count).mean()),
            "deepest_pp_overlap_m": pp_deep, "deepest_pw_overlap_m": pw_deep,
            "deepest_pp_overlap_rel": pp_deep_rel,
            "pp_contact_frames_mean": float(lengths.mean()) if lengths.size else 0.0}


def wall_contact_lifetimes(pos: np.ndarray, offset: np.ndarray, jar: Any,
                           radius: float | np.ndarray, longest: int = 20) -> dict[str, Any]:
    """How long the balls' wall contacts last, counted as :func:`contact_census` counts them.

    Args:
        pos: (P, N, 3) ball centres (m, lab frame), one frame per step; offset: (P, 3) jar
            offsets (m); jar: the ``JarParams``; radius: R (m) or (N,) each ball's r_i.
        longest: the last bin of the histogram holds contacts of this many frames or more.
    Returns:
        ``pw_touching_mean`` (balls touching the wall per frame), ``pw_contacts`` (touching
        runs: a ball's frames with phi > -r_i in a row; a run cut by the record's ends counts),
        ``pw_contact_frames_mean`` (their mean length, frames), ``pw_contact_frames_hist``
        (``longest`` counts: runs of 1, 2, ..., ``longest`` or more frames) and
        ``pw_fraction_per_ball`` (N,) (the fraction of frames each ball touches the wall).
    """
    rel = np.asarray(pos, np.float64) - np.asarray(offset, np.float64)[:, None, :]
    r = np.broadcast_to(np.asarray(radius, np.float64), (rel.shape[1],))
    phi = np.asarray(jar_sdf(jar, jnp.asarray(rel)))
    touch = phi > -r                                                    # (P, N)
    lengths = _touching_runs(touch)
    return {"pw_touching_mean": float(touch.sum(axis=1).mean()),
            "pw_contacts": int(lengths.size),
            "pw_contact_frames_mean": float(lengths.mean()) if lengths.size else 0.0,
            "pw_contact_frames_hist": np.bincount(np.minimum(lengths, longest),
                                                  minlength=longest + 1)[1:].tolist(),
            "pw_fraction_per_ball": touch.mean(axis=0)}


def _touching_runs(touch: np.ndarray) -> np.ndarray:
    """The lengths (frames) of every run of True in each column of ``touch`` (P, K) bool, column
    by column (a run cut by either end of the record counts)."""
    edges = np.diff(np.pad(touch.astype(np.int8), ((1, 1), (0, 0))), axis=0)
    return np.nonzero(edges.T == -1)[1] - np.nonzero(edges.T == 1)[1]


def _state_value(regime: Mapping[str, Any], which: str, classify_by: str,
                 n_balls: int) -> float:
    """The number a state rule thresholds, for ``which`` in ("pred", "ref")."""
    if classify_by == "speed":
        value = regime.get(f"jar_speed_{which}_mean_m_s")
    elif classify_by == "contacts":
        key = "pp_contacts_pred_mean" if which == "pred" else "pp_pairs_within_skin_ref_mean"
        value = None if regime.get(key) is None else regime[key] / n_balls
    else:
        value = regime.get(f"power_{which}_W")
    return math.nan if value is None else float(value)


def _num(value: Any) -> float | None:
    """A JSON-able float: NaN/inf -> None."""
    if value is None:
        return None
    value = float(value)
    return value if math.isfinite(value) else None


def _mean(values: np.ndarray) -> float | None:
    values = np.asarray(values, dtype=np.float64)
    return _num(values.mean()) if values.size else None


# --------------------------------------------------------------------------------------------
# Alignment


class Alignment(NamedTuple):
    """Which prediction steps/frames have a reference sample at the same time (within tol).

    step_index (S',), step_ref_index (S',): compared steps and their reference samples;
    frame_index (P',), frame_ref_index (P',): the same for the saved frames;
    start_ref_index: the reference sample at the rollout's start ``t_start``, or -1 if the
    reference does not reach back to it; overlap: a JSON-able report.
    """

    step_index: np.ndarray
    step_ref_index: np.ndarray
    frame_index: np.ndarray
    frame_ref_index: np.ndarray
    start_ref_index: int
    overlap: dict[str, Any]


def _match(t_query: np.ndarray, t_ref: np.ndarray, dt_ref: float, tol: float
           ) -> tuple[np.ndarray, np.ndarray]:
    """Indices (into t_query, into t_ref) of query times with a reference time within tol."""
    t_query = np.asarray(t_query, dtype=np.float64)
    nearest = np.rint((t_query - t_ref[0]) / dt_ref).astype(np.int64)
    inside = (nearest >= 0) & (nearest < t_ref.size)
    clipped = np.clip(nearest, 0, t_ref.size - 1)
    ok = inside & (np.abs(t_ref[clipped] - t_query) <= tol)
    query_index = np.flatnonzero(ok)
    return query_index, clipped[query_index]


def _load(prediction: Any, reference: Any) -> tuple[Any, Any]:
    if isinstance(prediction, (str, Path)):
        prediction = load_prediction(prediction)
    if isinstance(reference, (str, Path)):
        reference = load_trajectory(reference)
    return prediction, reference


def align(prediction: Any, reference: Any) -> Alignment:
    """Match the prediction's steps and frames to reference samples by time.

    Args:
        prediction: a ``sgn_jax.records.prediction.Prediction`` (or its path).
        reference: a ``sgn_jax.records.trajectory.Trajectory`` (or its path), the DEM ground truth.
    Returns:
        :class:`Alignment`. Times match within min(dt_pred, dt_ref) / 10. If some steps or
        frames have no reference sample, a :class:`CoverageWarning` says which time range is
        compared, and ``overlap['complete']`` is False.
    Raises:
        MetricsError if the ball counts differ or no step at all overlaps the reference.
    """
    prediction, reference = _load(prediction, reference)
    if prediction.n_balls != reference.n_balls:
        raise MetricsError(f"the prediction has {prediction.n_balls} balls but the reference "
                           f"has {reference.n_balls}; compare with the DEM run of the same case")
    t_ref = np.asarray(reference.t, dtype=np.float64)
    dt_ref = reference.dt
    tol = _ALIGN_TOL_FRACTION * min(prediction.dt, dt_ref)
    t_step = np.asarray(prediction.t_step, dtype=np.float64)
    t_pos = np.asarray(prediction.t_pos, dtype=np.float64)
    step_index, step_ref_index = _match(t_step, t_ref, dt_ref, tol)
    frame_index, frame_ref_index = _match(t_pos, t_ref, dt_ref, tol)
    start_index, start_ref = _match(np.array([prediction.t_start]), t_ref, dt_ref, tol)

    described = (f"prediction steps end at t in [{t_step[0]:.6g}, {t_step[-1]:.6g}] s "
                 f"(dt {prediction.dt:g} s), reference samples cover [{t_ref[0]:.6g}, "
                 f"{t_ref[-1]:.6g}] s (dt {dt_ref:g} s)")
    if step_index.size == 0:
        raise MetricsError(f"no prediction step has a reference sample at the same time: "
                           f"{described}; pass the DEM trajectory that the rollout started from "
                           "(same time axis: s since the start of motion)")
    complete = step_index.size == t_step.size and frame_index.size == t_pos.size
    overlap = {
        "complete": bool(complete),
        "t_first_s": float(t_step[step_index[0]]),
        "t_last_s": float(t_step[step_index[-1]]),
        "n_steps_compared": int(step_index.size),
        "n_steps": int(t_step.size),
        "n_frames_compared": int(frame_index.size),
        "n_frames": int(t_pos.size),
        "reference_covers_start": bool(start_index.size == 1),
        "tolerance_s": tol,
    }
    if not complete:
        overlap["message"] = (
            f"the reference covers only part of the prediction ({described}); comparing "
            f"{step_index.size}/{t_step.size} steps and {frame_index.size}/{t_pos.size} frames "
            f"on t in [{overlap['t_first_s']:.6g}, {overlap['t_last_s']:.6g}] s")
        warnings.warn(overlap["message"], CoverageWarning, stacklevel=2)
    return Alignment(step_index=step_index, step_ref_index=step_ref_index,
                     frame_index=frame_index, frame_ref_index=frame_ref_index,
                     start_ref_index=int(start_ref[0]) if start_ref.size else -1,
                     overlap=overlap)


# --------------------------------------------------------------------------------------------
# Comparison of one run


class Comparison(NamedTuple):
    """Curves of one prediction against its reference, full length (NaN where not compared),
    plus the JSON-able ``summary`` (what :func:`evaluate` returns).

    t_step (S,) s; energy_pred (S,) J (re-based like energy_ref); energy_ref (S,) J, NaN
    outside the overlap; energy_rel_error (S,), NaN where E_ref <= 0 or not compared;
    t_pos (P,) s; mse (P,) m^2, NaN for frames without a reference sample.
    """

    t_step: np.ndarray
    energy_pred: np.ndarray
    energy_ref: np.ndarray
    energy_rel_error: np.ndarray
    t_pos: np.ndarray
    mse: np.ndarray
    alignment: Alignment
    summary: dict[str, Any]


def _count_stats(counts: np.ndarray, t_step: np.ndarray, unit: str) -> dict[str, Any]:
    counts = np.asarray(counts, dtype=np.int64)
    hit = np.flatnonzero(counts > 0)
    return {
        f"total_{unit}": int(counts.sum()),
        "max": int(counts.max()) if counts.size else 0,
        "steps_with_any": int(hit.size),
        "first_time_s": float(t_step[hit[0]]) if hit.size else None,
    }


def compare(prediction: Any, reference: Any, *, classify_by: str = "speed",
            threshold: float | None = None) -> Comparison:
    """Align a prediction with its DEM reference and compute every metric of docs/conventions.md
    sections 6 and 7.

    Args:
        prediction: ``Prediction`` or path.
        reference: ``Trajectory`` or path.
        classify_by: the state rule, see :func:`classify_state`.
        threshold: the state rule's threshold (default :func:`default_threshold`).
    Returns:
        :class:`Comparison`; its ``summary`` keys: prediction, reference, overlap, position,
        energy, outside, overflow, snapped, regime, motion (:func:`motion_checks` and
        :func:`motion_warnings`), offset_max_abs_diff_m, spec_checks.
    """
    if threshold is None:
        threshold = default_threshold(classify_by)
    elif classify_by not in CLASSIFIERS:
        raise MetricsError(f"classify_by must be one of {CLASSIFIERS}, got {classify_by!r}")
    prediction, reference = _load(prediction, reference)
    al = align(prediction, reference)
    n_steps, n_frames = prediction.n_steps, prediction.n_frames
    t_step = np.asarray(prediction.t_step, dtype=np.float64)
    t_pos = np.asarray(prediction.t_pos, dtype=np.float64)
    ball_radius = float(reference.meta["ball_radius"])
    ball_mass = float(reference.meta["ball_mass"])
    pp_skin = float(prediction.config.graph.pp_skin)
    cutoff = 2.0 * ball_radius + pp_skin

    # ---- cumulative energy (docs/conventions.md section 6)
    cum_ref = np.asarray(reference.cumulative_dissipation("normal+tangential", "pp+pw"))
    energy_cum = np.asarray(prediction.energy_cum, dtype=np.float64)
    s_idx, r_idx = al.step_index, al.step_ref_index
    if al.start_ref_index >= 0:
        baseline = "rollout start"
        ref_zero, pred_zero = cum_ref[al.start_ref_index], 0.0
    else:
        baseline = "first compared step (the reference starts after the rollout's start)"
        ref_zero, pred_zero = cum_ref[r_idx[0]], energy_cum[s_idx[0]]
    energy_pred = energy_cum - pred_zero
    energy_ref = np.full(n_steps, np.nan)
    energy_ref[s_idx] = cum_ref[r_idx] - ref_zero
    rel = relative_error(energy_pred, energy_ref)
    rel_compared = rel[s_idx]
    last_half = rel_compared[rel_compared.size // 2:]
    last_half = last_half[np.isfinite(last_half)]
    duration = t_step[s_idx[-1]] - (prediction.t_start if al.start_ref_index >= 0
                                     else t_step[s_idx[0]])
    energy = {
        "baseline": baseline,
        "E_pred_final_J": _num(energy_pred[s_idx[-1]]),
        "E_ref_final_J": _num(energy_ref[s_idx[-1]]),
        "relative_error_final": _num(rel_compared[-1]),
        "relative_error_median_last_half": _num(np.median(last_half)) if last_half.size else None,
        "relative_error_max_last_half": _num(last_half.max()) if last_half.size else None,
        "pearson_r": _num(pearson_r(energy_pred[s_idx], energy_ref[s_idx])),
        "E_pred_full_J": _num(energy_cum[-1]),
    }

    # ---- positions (docs/conventions.md section 6, Eq. 33)
    mse = np.full(n_frames, np.nan)
    f_idx, fr_idx = al.frame_index, al.frame_ref_index
    pred_pos = np.asarray(prediction.pos)
    if f_idx.size:
        mse[f_idx] = position_mse(pred_pos[f_idx], reference.pos[fr_idx])
        mse_compared = mse[f_idx]
        position = {
            "mse_final_m2": _num(mse_compared[-1]),
            "mse_plateau_m2": _num(mse_plateau(mse_compared)),
            "mse_max_m2": _num(mse_compared.max()),
            "mse_mean_m2": _num(mse_compared.mean()),
            "n_frames": int(f_idx.size),
        }
        offset_diff = _num(np.abs(np.asarray(prediction.offset)[f_idx]
                                  - reference.offset[fr_idx]).max())
        if offset_diff is not None and offset_diff > _OFFSET_WARN_M:
            warnings.warn(f"the jar offsets of the prediction and the reference differ by up to "
                          f"{offset_diff:.3g} m at the same times: the reference is probably not "
                          "the DEM run of this rollout's motion", MetricsWarning, stacklevel=2)
    else:
        position = None
        offset_diff = None

    # ---- regime indicators (docs/conventions.md section 7), on the compared interval
    pred_pairs = np.asarray(prediction.n_pp_edges, dtype=np.float64) / 2.0
    ref_pos_steps = reference.pos[r_idx]
    ref_within = pairs_within(ref_pos_steps, cutoff)
    n_balls = prediction.n_balls
    # Both curves are zero at the baseline, so their last compared values are the increments.
    power_pred = energy_pred[s_idx[-1]] / duration if duration > 0 else math.nan
    power_ref = energy_ref[s_idx[-1]] / duration if duration > 0 else math.nan
    regime: dict[str, Any] = {
        "pp_skin_m": pp_skin,
        "pp_cutoff_m": cutoff,
        "pp_contacts_pred_mean": _mean(pred_pairs[s_idx]),
        "pp_contacts_pred_mean_full": _mean(pred_pairs),
        "pp_contacts_ref_dem_mean": _mean(pp_contact_counts(reference.pp_pairs[r_idx])),
        "pp_pairs_within_skin_ref_mean": _mean(ref_within),
        "power_pred_W": _num(power_pred),
        "power_ref_W": _num(power_ref),
        "power_pred_full_W": _num(energy_cum[-1] / (n_steps * prediction.dt)),
        "ke_trans_ref_mean_J": _mean(reference.ke_trans[r_idx]),
        "duration_compared_s": float(duration),
    }
    if f_idx.size:
        regime["pp_pairs_within_skin_pred_frames_mean"] = _mean(
            pairs_within(pred_pos[f_idx], cutoff))
        regime["pp_pairs_within_skin_ref_frames_mean"] = _mean(
            pairs_within(reference.pos[fr_idx], cutoff))
    _, ke_pred = kinetic_energy_fd(t_pos[f_idx], pred_pos[f_idx], ball_mass)
    _, ke_ref = kinetic_energy_fd(t_pos[f_idx], reference.pos[fr_idx], ball_mass)
    regime["ke_fd_pred_mean_J"] = _mean(ke_pred)
    regime["ke_fd_ref_mean_J"] = _mean(ke_ref)
    regime["ke_fd_interval_s"] = _num(np.median(np.diff(t_pos[f_idx]))) if f_idx.size > 1 \
        else None
    speed_pred = jar_frame_speed(t_pos[f_idx], pred_pos[f_idx],
                                 np.asarray(prediction.offset)[f_idx])
    speed_ref = jar_frame_speed(t_pos[f_idx], reference.pos[fr_idx], reference.offset[fr_idx])
    regime["jar_speed_pred_mean_m_s"] = _mean(speed_pred)
    regime["jar_speed_ref_mean_m_s"] = _mean(speed_ref)
    regime["state_rule"] = classify_by
    regime["state_threshold"] = threshold
    regime["state_pred"] = classify_state(_state_value(regime, "pred", classify_by, n_balls),
                                          threshold, classify_by)
    regime["state_ref"] = classify_state(_state_value(regime, "ref", classify_by, n_balls),
                                         threshold, classify_by)

    outside = _count_stats(prediction.n_outside, t_step, "ball_steps")
    overflow = _count_stats(prediction.overflow, t_step, "edges")
    snapped = _count_stats(prediction.n_snapped, t_step, "ball_steps")
    # ---- motion checks (is the energy agreement right for the right reason?)
    if f_idx.size and n_balls >= 2:  # deepest over the run, 0 if no pair ever touches
        overlap_pred = _num(np.maximum(0.0, np.max(deepest_pair_overlap(pred_pos[f_idx],
                                                                         ball_radius))))
        overlap_ref = _num(np.maximum(0.0, np.max(deepest_pair_overlap(reference.pos[fr_idx],
                                                                        ball_radius))))
    else:
        overlap_pred = overlap_ref = None
    checks = motion_checks(
        jar_speed_dem_m_s=regime["jar_speed_ref_mean_m_s"],
        jar_speed_sgn_m_s=regime["jar_speed_pred_mean_m_s"],
        snapped_ball_steps=snapped["total_ball_steps"], ball_steps=n_steps * n_balls,
        overlap_dem_m=overlap_ref, overlap_sgn_m=overlap_pred,
        mse_plateau_m2=None if position is None else position["mse_plateau_m2"])
    motion = {"checks": checks, "warnings": motion_warnings(checks),
              "overlap_frames": "the compared frames (every save_every steps)"}
    summary = {
        "prediction": {
            "path": prediction.path,
            "n_steps": n_steps, "n_frames": n_frames, "n_balls": n_balls,
            "dt_s": prediction.dt, "t_start_s": prediction.t_start, "t_end_s": float(t_step[-1]),
            "init_index": prediction.meta.get("init_index"),
            "checkpoint": prediction.meta.get("checkpoint"),
        },
        "reference": {
            "path": reference.path, "n_samples": reference.n_samples, "dt_s": reference.dt,
            "t_first_s": float(reference.t[0]), "t_last_s": float(reference.t[-1]),
            "seed": reference.meta.get("seed"),
        },
        "overlap": al.overlap,
        "position": position,
        "energy": energy,
        "outside": outside,
        "overflow": overflow,
        "snapped": snapped,
        "regime": regime,
        "motion": motion,
        "offset_max_abs_diff_m": offset_diff,
        "spec_checks": {
            "no_balls_outside": outside["total_ball_steps"] == 0,
            "no_edge_overflow": overflow["total_edges"] == 0,
            "reference_covers_prediction": al.overlap["complete"],
        },
    }
    return Comparison(t_step=t_step, energy_pred=energy_pred, energy_ref=energy_ref,
                      energy_rel_error=rel, t_pos=t_pos, mse=mse, alignment=al, summary=summary)


def evaluate(prediction: Any, reference: Any, *, classify_by: str = "speed",
             threshold: float | None = None) -> dict[str, Any]:
    """JSON-able summary of every metric (docs/conventions.md sections 6 and 7) of one run (see
    :func:`compare`)."""
    return compare(prediction, reference, classify_by=classify_by, threshold=threshold).summary


def headline(summary: Mapping[str, Any]) -> dict[str, Any]:
    """The headline numbers of one run's summary (from :func:`evaluate`), for one-line reports."""
    return {
        "mse_plateau_m2": (summary["position"] or {}).get("mse_plateau_m2"),
        "energy_pred_J": summary["energy"].get("E_pred_final_J"),
        "energy_ref_J": summary["energy"].get("E_ref_final_J"),
        "energy_relative_error_final": summary["energy"]["relative_error_final"],
        "pearson_r": summary["energy"]["pearson_r"],
        "balls_outside_total": summary["outside"]["total_ball_steps"],
        "overflow_total": summary["overflow"]["total_edges"],
        "state_pred": summary["regime"]["state_pred"],
        "state_ref": summary["regime"]["state_ref"],
        "reference_covers_prediction": summary["overlap"]["complete"],
        "motion_warnings": list((summary.get("motion") or {}).get("warnings") or []),
    }


# --------------------------------------------------------------------------------------------
# Motion checks


def _fraction_off(sgn: float | None, dem: float | None) -> float | None:
    if sgn is None or dem is None or not dem > 0:
        return None
    return (sgn - dem) / dem


def motion_checks(*, jar_speed_dem_m_s: float | None, jar_speed_sgn_m_s: float | None,
                  snapped_ball_steps: int | None, ball_steps: int | None,
                  overlap_dem_m: float | None, overlap_sgn_m: float | None,
                  mse_plateau_m2: float | None) -> list[dict[str, Any]]:
    """The motion checks of one run: the DEM's value next to the surrogate's (pure function).

    Args:
        jar_speed_dem_m_s: the DEM's mean ball speed in the jar frame (m/s)
            (:func:`jar_frame_speed`).
        jar_speed_sgn_m_s: the surrogate's, at the same frame times (m/s).
        snapped_ball_steps: the surrogate's ball-steps moved by the snap-back.
        ball_steps: steps x balls of the rollout.
        overlap_dem_m: the DEM's deepest ball-ball overlap over the run (m, >= 0;
            :func:`deepest_pair_overlap`).
        overlap_sgn_m: the surrogate's (m, >= 0).
        mse_plateau_m2: the surrogate's MSE_t plateau (m^2).
    Returns:
        one JSON-able dict per check, in a fixed order (jar_speed, snapped, overlap,
        mse_plateau): ``name``, ``what``, ``unit``, ``dem``, ``sgn`` (in ``unit``),
        ``limit`` (what is out of range), ``ok`` (True, False, or None when a value is
        missing), and per check the numbers its warning quotes. None values stay None.
    """
    speed_off = _fraction_off(_num(jar_speed_sgn_m_s), _num(jar_speed_dem_m_s))
    fraction = (None if snapped_ball_steps is None or not ball_steps
                else int(snapped_ball_steps) / int(ball_steps))
    overlap_sgn = None if _num(overlap_sgn_m) is None else 1e6 * float(overlap_sgn_m)
    overlap_dem = None if _num(overlap_dem_m) is None else 1e6 * float(overlap_dem_m)
    plateau = _num(mse_plateau_m2)
    ratio = None if plateau is None else plateau / MSE_FLOOR_UNRELATED_M2
    return [
        {"name": "jar_speed", "what": "mean ball speed in the jar frame", "unit": "m/s",
         "dem": _num(jar_speed_dem_m_s), "sgn": _num(jar_speed_sgn_m_s),
         "relative_difference": speed_off,
         "limit": f"differs from the DEM's by more than {100 * MOTION_SPEED_TOLERANCE:g} %",
         "ok": None if speed_off is None else abs(speed_off) <= MOTION_SPEED_TOLERANCE},
        {"name": "snapped", "what": "fraction of ball-steps snapped back to the wall",
         "unit": "fraction", "dem": 0.0, "sgn": fraction,
         "sgn_ball_steps": None if snapped_ball_steps is None else int(snapped_ball_steps),
         "ball_steps": None if ball_steps is None else int(ball_steps),
         "limit": f"more than {100 * MOTION_SNAPPED_FRACTION_MAX:g} % (the DEM needs no snap)",
         "ok": None if fraction is None else fraction <= MOTION_SNAPPED_FRACTION_MAX},
        {"name": "overlap", "what": "deepest ball-ball overlap over the run", "unit": "um",
         "dem": overlap_dem, "sgn": overlap_sgn,
         "limit": f"above {1e6 * MOTION_OVERLAP_MAX_M:g} um (the DEM's is ~"
                  f"{1e6 * DEM_DEEPEST_OVERLAP_M:g} um)",
         "ok": None if overlap_sgn is None else overlap_sgn <= 1e6 * MOTION_OVERLAP_MAX_M},
        {"name": "mse_plateau", "what": "MSE_t plateau against the DEM's chaos floor",
         "unit": "m^2", "dem": MSE_FLOOR_SAME_PACKING_M2, "sgn": plateau,
         "dem_unrelated_packings": MSE_FLOOR_UNRELATED_M2, "ratio_to_unrelated": ratio,
         "limit": f"at or above {MOTION_MSE_FLOOR_MAX_RATIO:g}x the unrelated-packings level "
                  f"{MSE_FLOOR_UNRELATED_M2:.1e} m^2 (the DEM's own floor: same packing at dt "
                  f"vs dt/2, {MSE_FLOOR_SAME_PACKING_M2:.1e} m^2; standard case)",
         "ok": None if ratio is None else ratio < MOTION_MSE_FLOOR_MAX_RATIO},
    ]


def motion_warnings(checks: Sequence[Mapping[str, Any]]) -> list[str]:
    """One message per failed check of :func:`motion_checks` (``ok`` is False), in order.

    Print each as ``WARNING: <message>``, then :data:`ENERGY_TRUST_WARNING` when any fired
    (:func:`motion_warning_lines` does both).
    """
    messages = []
    for check in checks:
        if check.get("ok") is not False:
            continue
        name, dem, sgn = check["name"], check["dem"], check["sgn"]
        if name == "jar_speed":
            messages.append(
                f"the surrogate's balls move at {sgn:.3f} m/s in the jar frame, the DEM's at "
                f"{dem:.3f} m/s ({100 * check['relative_difference']:+.0f} %; limit +-"
                f"{100 * MOTION_SPEED_TOLERANCE:g} %): the charge is in a different state")
        elif name == "snapped":
            messages.append(
                f"{check['sgn_ball_steps']:,} of {check['ball_steps']:,} ball-steps "
                f"({100 * sgn:.1f} %) were snapped back to the wall (limit "
                f"{100 * MOTION_SNAPPED_FRACTION_MAX:g} %; the DEM needs none): the network "
                "pushes balls into the wall")
        elif name == "overlap":
            dem_text = "n/a" if dem is None else f"{dem:.0f} um"
            messages.append(
                f"balls of the surrogate overlap by up to {sgn:,.0f} um (DEM {dem_text}; limit "
                f"{1e6 * MOTION_OVERLAP_MAX_M:g} um): balls sink into each other")
        elif name == "mse_plateau":
            messages.append(
                f"the MSE_t plateau {sgn:.2e} m^2 is {check['ratio_to_unrelated']:.2f}x the "
                f"level of two unrelated DEM packings ({MSE_FLOOR_UNRELATED_M2:.1e} m^2): the "
                "positions carry no information beyond the jar's size")
        else:
            messages.append(f"{check.get('what', name)} out of range: {check.get('limit')}")
    return messages


def motion_warning_lines(messages: Sequence[str]) -> list[str]:
    """``WARNING: <message>`` per message, then the energy-trust line; [] when none."""
    if not messages:
        return []
    return [f"WARNING: {m}" for m in messages] + [f"WARNING: {ENERGY_TRUST_WARNING}"]


def motion_checks_of(summary: Mapping[str, Any]) -> list[dict[str, Any]]:
    """The motion checks stored in a :func:`compare` / :func:`evaluate` summary ([] for a
    summary written before they existed)."""
    return list((summary.get("motion") or {}).get("checks") or [])


# --------------------------------------------------------------------------------------------
# Ensembles (docs/conventions.md section 7)


def _spread(values: Sequence[float | None]) -> dict[str, Any]:
    array = np.asarray([np.nan if v is None else v for v in values], dtype=np.float64)
    array = array[np.isfinite(array)]
    if array.size == 0:
        return {"mean": None, "std": None, "min": None, "max": None, "n": 0}
    return {
        "mean": float(array.mean()),
        # sample standard deviation: the spread of the states a new packing may fall into
        "std": float(array.std(ddof=1)) if array.size > 1 else 0.0,
        "min": float(array.min()),
        "max": float(array.max()),
        "n": int(array.size),
    }


MIN_ENSEMBLE_RUNS = 8  # docs/conventions.md section 7: at least 8 initial packings per case


def ensemble_summary(runs: Sequence[Any], references: Sequence[Any] | None = None, *,
                     classify_by: str = "speed",
                     threshold: float | None = None,
                     labels: Sequence[str] | None = None) -> dict[str, Any]:
    """Ensemble statistics over runs: power spread, states, contact counts.

    The ensemble rules are those of docs/conventions.md section 7.

    Args:
        runs: per-run summaries (dicts from :func:`evaluate`), or predictions (objects or
            paths) when ``references`` is given.
        references: the DEM reference of each prediction, same length as ``runs``.
        classify_by: "speed" (mean ball speed in the jar frame, default threshold
            :data:`AGITATED_SPEED_M_S`), "contacts" (pairs within the skin per ball, default
            threshold :data:`BED_PAIRS_PER_BALL`) or "power" (mean dissipation power in W;
            ``threshold`` required, e.g. the midpoint between the two states' powers).
        threshold: the classification threshold in the unit of ``classify_by``.
        labels: a name per run (default: the prediction path or the run's index).
    Returns:
        JSON-able dict: n_runs, meets_spec_minimum, power (pred/ref spread, relative error of the
        ensemble means), states (threshold, counts, mean power per state), contacts (ensemble
        means), energy and position (single-trajectory errors over runs), runs (per-run rows).
    """
    if threshold is None:
        threshold = default_threshold(classify_by)
    elif classify_by not in CLASSIFIERS:
        raise MetricsError(f"classify_by must be one of {CLASSIFIERS}, got {classify_by!r}")
    if len(runs) == 0:
        raise MetricsError("ensemble_summary needs at least one run")
    if references is not None:
        if len(references) != len(runs):
            raise MetricsError(f"got {len(runs)} predictions but {len(references)} references; "
                               "give one reference per prediction")
        from tqdm.auto import tqdm

        summaries = [evaluate(p, r, classify_by=classify_by, threshold=threshold)
                     for p, r in tqdm(list(zip(runs, references, strict=True)),
                                                      desc="evaluate runs", unit="run")]
    else:
        summaries = list(runs)
        for i, summary in enumerate(summaries):
            if not isinstance(summary, Mapping) or "regime" not in summary:
                raise MetricsError(f"run {i} is not a summary from "
                                   "sgn_jax.analysis.metrics.evaluate; pass summaries, or "
                                   "predictions together with references=")
    if labels is not None and len(labels) != len(summaries):
        raise MetricsError(f"got {len(labels)} labels for {len(summaries)} runs")

    rows = []
    for i, summary in enumerate(summaries):
        regime = summary["regime"]
        n_balls = summary["prediction"]["n_balls"]
        contacts_pred = regime["pp_contacts_pred_mean"]
        contacts_ref = regime["pp_pairs_within_skin_ref_mean"]
        value_pred = _state_value(regime, "pred", classify_by, n_balls)
        value_ref = _state_value(regime, "ref", classify_by, n_balls)
        label = (labels[i] if labels is not None
                 else summary["prediction"].get("path") or f"run {i}")
        rows.append({
            "label": label,
            "n_balls": n_balls,
            "power_pred_W": regime["power_pred_W"],
            "power_ref_W": regime["power_ref_W"],
            "pp_contacts_pred_mean": contacts_pred,
            "pp_pairs_within_skin_ref_mean": contacts_ref,
            "pp_contacts_ref_dem_mean": regime["pp_contacts_ref_dem_mean"],
            "jar_speed_pred_mean_m_s": regime.get("jar_speed_pred_mean_m_s"),
            "jar_speed_ref_mean_m_s": regime.get("jar_speed_ref_mean_m_s"),
            "state_pred": classify_state(value_pred, threshold, classify_by),
            "state_ref": classify_state(value_ref, threshold, classify_by),
            "energy_relative_error_final": summary["energy"]["relative_error_final"],
            "pearson_r": summary["energy"]["pearson_r"],
            "mse_plateau_m2": (summary["position"] or {}).get("mse_plateau_m2"),
            "balls_outside_total": summary["outside"]["total_ball_steps"],
            "overflow_total": summary["overflow"]["total_edges"],
        })

    power_pred = _spread([r["power_pred_W"] for r in rows])
    power_ref = _spread([r["power_ref_W"] for r in rows])
    rel_means = (abs(power_pred["mean"] - power_ref["mean"]) / power_ref["mean"]
                 if power_pred["mean"] is not None and power_ref["mean"] else None)

    def states(key: str, power_key: str) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for state in ("bed", "agitated", "unknown"):
            chosen = [r for r in rows if r[key] == state]
            out[state] = {"count": len(chosen),
                          "power_W": _spread([r[power_key] for r in chosen])}
        out["fraction_agitated"] = out["agitated"]["count"] / len(rows)
        return out

    return {
        "n_runs": len(rows),
        "meets_spec_minimum": len(rows) >= MIN_ENSEMBLE_RUNS,
        "power": {"pred_W": power_pred, "ref_W": power_ref,
                  "relative_error_of_means": _num(rel_means)},
        "states": {
            "classify_by": classify_by,
            "threshold": threshold,
            "threshold_unit": {"speed": "m/s, mean ball speed in the jar frame (agitated if >=)",
                               "contacts": "ball pairs within the edge skin per ball (bed if >=)",
                               "power": "W (agitated if >=)"}[classify_by],
            "pred": states("state_pred", "power_pred_W"),
            "ref": states("state_ref", "power_ref_W"),
            "agreement": sum(r["state_pred"] == r["state_ref"] for r in rows) / len(rows),
        },
        "contacts": {
            "pred_mean": _spread([r["pp_contacts_pred_mean"] for r in rows])["mean"],
            "ref_within_skin_mean": _spread([r["pp_pairs_within_skin_ref_mean"]
                                             for r in rows])["mean"],
            "ref_dem_mean": _spread([r["pp_contacts_ref_dem_mean"] for r in rows])["mean"],
        },
        "jar_speed_m_s": {"pred": _spread([r["jar_speed_pred_mean_m_s"] for r in rows]),
                          "ref": _spread([r["jar_speed_ref_mean_m_s"] for r in rows])},
        "energy": {"relative_error_final": _spread([r["energy_relative_error_final"]
                                                    for r in rows]),
                   "pearson_r": _spread([r["pearson_r"] for r in rows])},
        "position": {"mse_plateau_m2": _spread([r["mse_plateau_m2"] for r in rows])},
        "runs": rows,
    }


__all__ = [
    "AGITATED_SPEED_M_S",
    "BED_PAIRS_PER_BALL",
    "CLASSIFIERS",
    "DEM_DEEPEST_OVERLAP_M",
    "ENERGY_TRUST_WARNING",
    "MIN_ENSEMBLE_RUNS",
    "MOTION_MSE_FLOOR_MAX_RATIO",
    "MOTION_OVERLAP_MAX_M",
    "MOTION_SNAPPED_FRACTION_MAX",
    "MOTION_SPEED_TOLERANCE",
    "MSE_FLOOR_SAME_PACKING_M2",
    "MSE_FLOOR_UNRELATED_M2",
    "Alignment",
    "Comparison",
    "CoverageWarning",
    "MetricsError",
    "MetricsWarning",
    "align",
    "classify_state",
    "compare",
    "deepest_pair_overlap",
    "default_threshold",
    "ensemble_summary",
    "evaluate",
    "headline",
    "jar_frame_speed",
    "kinetic_energy_fd",
    "motion_checks",
    "motion_checks_of",
    "motion_warning_lines",
    "motion_warnings",
    "mse_plateau",
    "pairs_within",
    "pearson_r",
    "position_mse",
    "pp_contact_counts",
    "relative_error",
]
