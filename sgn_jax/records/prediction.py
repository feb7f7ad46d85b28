"""The rollout prediction file: what ``sgn_jax.surrogate.rollout`` writes and ``sgn-jax evaluate``
reads.

One ``.npz`` per surrogate rollout. The rollout writes it with :func:`save_prediction`; metrics
and plots read it with :func:`load_prediction`, which returns a read-only :class:`Prediction`.
Both run the same checks (:func:`validate_prediction`), so a file that was written can be read,
and a bad file is refused with a :class:`PredictionError` that names the file, the array and the
problem, and says how to fix it.

Arrays (S surrogate steps, P saved position frames, N balls), SI units:

| name | shape | dtype | meaning |
|---|---|---|---|
| ``t_step`` | (S,) | float | s since the start of motion at the END of each surrogate step; uniformly spaced by meta dt |
| ``dE`` | (S,) | float | J, predicted dissipation of each step |
| ``energy_cum`` | (S,) | float | J, cumulative predicted dissipation since the rollout's start (= cumsum(dE)) |
| ``n_pp_edges``, ``n_pw_edges`` | (S,) | int | directed edge counts of the step's graph (n_pp_edges / 2 = ball-ball pairs) |
| ``overflow`` | (S,) | int | edges dropped by the static capacity |
| ``n_outside`` | (S,) | int | balls with phi > 0 after the step |
| ``n_snapped`` | (S,) | int | balls moved by the snap-back |
| ``t_pos`` | (P,) | float | s, times of the saved frames (strictly increasing, on the step grid) |
| ``pos`` | (P, N, 3) | float64 | ball positions (m, lab frame) |
| ``offset`` | (P, 3) | float | jar offset at those times (m) |

Optional extra arrays, written for a model kind that reports its own energy ledger (the
contact model, :mod:`sgn_jax.surrogate.contact`): ``diss_pp_model``, ``diss_pw_model`` (S,) J, what its
ball-ball and ball-wall impulses took out of the balls in each step, and ``work_wall_model``
(S,) J, the work of its ball-wall impulses at the jar's velocity; and ``omega_model`` (P, N, 3)
rad/s, the balls' spins at the frames (a model with spin state integrates them; zeros without),
whose rotational energy its ledger counts.

Optional collision table (a contact model's rollout with ``collisions=True``,
:mod:`sgn_jax.surrogate.collisions`): one row per collision event, E rows, the arrays
``collision_<key>`` for every key of :data:`sgn_jax.dem.collisions.COLLISION_FIELDS`
(``energy`` is (E, 5), the others (E,)); all of them or none. Its meta entry ``collisions`` says what the energies count.

The rollout starts at ``t_start = t_step[0] - dt``: the time of the newest true sample of the
initial window; step s ends at ``t_start + (s + 1) dt``. Frames may include ``t_start`` itself.
Extra arrays are allowed and kept. ``meta`` is a 0-d unicode array holding a JSON object with at
least :data:`REQUIRED_META`: ``dt`` (the surrogate step, s), ``save_every`` (steps between saved
frames), ``init_index`` (the index, in the initial dataset, of the sample at ``t_start``: the
newest sample of the initial window), ``config`` (``sgn_jax.config.config_to_dict`` of the
run's config). Recommended extra keys: ``checkpoint``, ``init_dataset``, ``code_version``,
``created`` (ISO 8601), ``wall_time_s``. Metrics align the prediction with a reference by time,
not by index, so any DEM file on the same time axis (s since the start of motion) can serve.

:func:`prediction_from_trajectory` turns a stretch of a DEM trajectory into a prediction (a
"perfect surrogate"): a baseline for the metrics (MSE 0, energy error 0) and test data.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from sgn_jax.dem.collisions import COLLISION_FIELDS, COLLISION_PREFIX
from sgn_jax.errors import SGNJaxError
from sgn_jax.pairs import pairs_within
from sgn_jax.records import base as records
from sgn_jax.records.base import ArrayRecord, ArraySpec, RecordFormat


class PredictionError(SGNJaxError, ValueError):
    """A prediction file or its arrays/meta are malformed; the message says what and how to fix."""


STEP_ARRAYS = ("t_step", "dE", "energy_cum", "n_pp_edges", "n_pw_edges", "overflow", "n_outside",
               "n_snapped")
COUNT_ARRAYS = ("n_pp_edges", "n_pw_edges", "overflow", "n_outside", "n_snapped")

REQUIRED_ARRAYS: dict[str, ArraySpec] = {
    "t_step": ArraySpec(("S",), "float", "time at the end of each surrogate step (s)"),
    "dE": ArraySpec(("S",), "float", "predicted dissipation of each step (J)"),
    "energy_cum": ArraySpec(("S",), "float", "cumulative predicted dissipation (J)"),
    "n_pp_edges": ArraySpec(("S",), "int", "directed ball-ball edges per step"),
    "n_pw_edges": ArraySpec(("S",), "int", "directed ball-wall edges per step"),
    "overflow": ArraySpec(("S",), "int", "edges dropped by the capacity per step"),
    "n_outside": ArraySpec(("S",), "int", "balls with phi > 0 per step"),
    "n_snapped": ArraySpec(("S",), "int", "balls moved by the snap-back per step"),
    "t_pos": ArraySpec(("P",), "float", "times of the saved frames (s)"),
    "pos": ArraySpec(("P", "N", 3), "float64", "ball positions (m)"),
    "offset": ArraySpec(("P", 3), "float", "jar offset (m)"),
}

REQUIRED_META: tuple[str, ...] = ("dt", "save_every", "init_index", "config")

# NaN there means "not known by this ledger" (the event table's convention)
_MAY_BE_NAN = ("collision_max_overlap", "collision_peak_force")

# Times are t_start + k * dt (rounding ~1e-16 t in float64); a wrong dt, a dropped step or a
# frame off the step grid is off by a large fraction of dt. Tolerance in steps (units of dt).
_GRID_TOL = 1e-3
# energy_cum must be cumsum(dE) up to the accumulation's rounding: a float32 running sum over
# 1e5 steps drifts ~sqrt(S) * 6e-8 ~ 2e-5 relative (worst case S * 6e-8 ~ 6e-3, never seen).
_CUMSUM_RTOL = 1e-3
_FIX_HINT = "regenerate it with `sgn-jax rollout` (sgn_jax.records.prediction.save_prediction)"

_FORMAT = RecordFormat(
    kind="prediction",
    error=PredictionError,
    arrays=REQUIRED_ARRAYS,
    meta_keys=REQUIRED_META,
    documented_in="see the sgn_jax.records.prediction module docstring",
    size_sources="S from 't_step', P from 't_pos', N from 'pos'",
    float64_hint=("positions must be float64 (differences of nearby positions lose digits in "
                  "float32); cast with .astype(np.float64) before saving"),
    fix_hint=_FIX_HINT,
    produce_hint="produce it with `sgn-jax rollout`",
    meta_hint=_FIX_HINT,
)


# --------------------------------------------------------------------------------------------
# Validation


def _is_int(value: Any) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


def _check_meta(meta: Any, where: str) -> None:
    if not records.is_positive_number(meta["dt"]):
        raise PredictionError(f"{where}: meta['dt'] (the surrogate step, s) must be a positive "
                              f"number, got {meta['dt']!r}")
    if not _is_int(meta["save_every"]) or meta["save_every"] < 1:
        raise PredictionError(f"{where}: meta['save_every'] (steps between saved frames) must be "
                              f"an integer >= 1, got {meta['save_every']!r}")
    if not _is_int(meta["init_index"]) or meta["init_index"] < 0:
        raise PredictionError(f"{where}: meta['init_index'] (the initial dataset's sample index) "
                              f"must be an integer >= 0, got {meta['init_index']!r}")
    records.check_config_entry(meta, _FORMAT, where)


def validate_prediction(arrays: Mapping[str, Any], meta: Mapping[str, Any],
                        path: str | Path | None = None) -> None:
    """Check names, shapes, dtypes, finiteness, the time grids, counts, cumsum and meta.

    Raises PredictionError that names ``path`` (if given) and the offending array or meta key,
    and says what was expected and what was found.
    """
    where, arrays = records.check_names_and_meta(arrays, meta, path, _FORMAT, _check_meta)

    t_step, t_pos = arrays["t_step"], arrays["t_pos"]
    if t_step.ndim != 1 or t_step.shape[0] < 1:
        raise PredictionError(f"{where}: array 't_step' must have shape (S,) with S >= 1 steps, "
                              f"got {t_step.shape}")
    if t_pos.ndim != 1 or t_pos.shape[0] < 1:
        raise PredictionError(f"{where}: array 't_pos' must have shape (P,) with P >= 1 saved "
                              f"frames, got {t_pos.shape}; save at least one frame (save_every "
                              "<= number of steps)")
    sizes: dict[str, int] = {"S": t_step.shape[0], "P": t_pos.shape[0]}
    if arrays["pos"].ndim == 3:
        sizes["N"] = arrays["pos"].shape[1]
    records.check_array_specs(arrays, _FORMAT, sizes, where)
    if sizes["N"] < 1:
        raise PredictionError(f"{where}: array 'pos' has no balls (N = 0)")

    for name, value in arrays.items():
        if not np.issubdtype(value.dtype, np.inexact) or name in _MAY_BE_NAN:
            continue
        bad = records.first_non_finite(value)
        if bad is not None:
            raise PredictionError(
                f"{where}: array {name!r} contains NaN or inf, first at index {bad}; the "
                "rollout diverged (check the model and the n_outside/overflow counts) or the "
                "array was not filled")
    for name in COUNT_ARRAYS:
        if arrays[name].min() < 0:
            first = int(np.flatnonzero(arrays[name] < 0)[0])
            raise PredictionError(f"{where}: array {name!r} is a count but holds a negative "
                                  f"value {int(arrays[name][first])} at step {first}")

    dt = float(meta["dt"])
    t_start = float(t_step[0]) - dt
    steps_from_start = (t_step - t_start) / dt
    off_grid = np.abs(steps_from_start - np.arange(1, t_step.size + 1))
    # In steps: _GRID_TOL, or a few roundings of the stored dtype at the largest time.
    t_max = max(float(np.abs(t_step).max()), float(np.abs(t_pos).max()))
    tol = max(_GRID_TOL, 8.0 * float(np.finfo(np.result_type(t_step.dtype, t_pos.dtype)).eps)
              * t_max / dt)
    if off_grid.max() > tol:
        worst = int(np.flatnonzero(off_grid > tol)[0])  # the first step off the grid
        raise PredictionError(
            f"{where}: array 't_step' is not uniformly spaced by meta['dt'] = {dt:g} s: "
            f"t_step[{worst}] = {float(t_step[worst]):.9g} s but expected "
            f"{t_start + (worst + 1) * dt:.9g} s; t_step[s] must be t_start + (s + 1) * dt "
            "(the time at the END of step s)")
    frame_steps = (t_pos - t_start) / dt
    if np.any(np.diff(t_pos) <= 0):
        raise PredictionError(f"{where}: array 't_pos' must be strictly increasing")
    if frame_steps.min() < -tol or frame_steps.max() > t_step.size + tol \
            or np.abs(frame_steps - np.round(frame_steps)).max() > tol:
        raise PredictionError(
            f"{where}: array 't_pos' must hold times on the step grid t_start + k * dt with "
            f"0 <= k <= S (t_start = {t_start:.9g} s, dt = {dt:g} s, S = {t_step.size}); got "
            f"t_pos in [{float(t_pos[0]):.9g}, {float(t_pos[-1]):.9g}] s")

    _check_collisions(arrays, where)

    cumsum = np.cumsum(arrays["dE"].astype(np.float64))
    scale = max(float(np.abs(cumsum).max()), float(np.abs(arrays["dE"]).sum()), 1e-300)
    drift = np.abs(arrays["energy_cum"] - cumsum)
    if drift.max() > _CUMSUM_RTOL * scale:
        worst = int(np.argmax(drift))
        raise PredictionError(
            f"{where}: array 'energy_cum' is not the running sum of 'dE': at step {worst} "
            f"energy_cum = {float(arrays['energy_cum'][worst]):.6g} J but cumsum(dE) = "
            f"{float(cumsum[worst]):.6g} J; store energy_cum = cumsum(dE) since the rollout start")


def _check_collisions(arrays: Mapping[str, np.ndarray], where: str) -> None:
    """The optional collision table: all its arrays or none, one length E, energy (E, 5)."""
    p = COLLISION_PREFIX
    present = [k for k in COLLISION_FIELDS if p + k in arrays]
    if not present:
        return
    missing = [p + k for k in COLLISION_FIELDS if k not in present]
    if missing:
        raise PredictionError(f"{where}: the collision table is incomplete, {missing} missing; "
                              "write all collision_* arrays or none (" + _FIX_HINT + ")")
    n_events = arrays[p + "ball"].shape[0] if arrays[p + "ball"].ndim else -1
    for key, (dtype, _) in COLLISION_FIELDS.items():
        value = arrays[p + key]
        shape = (n_events, 5) if key == "energy" else (n_events,)
        # the dtype's kind, not its width: a writer may store int64 or float32
        kind = {"i": "int", "b": "bool", "f": "float"}[np.dtype(dtype).kind]
        ok = {"int": np.issubdtype(value.dtype, np.integer) and value.dtype != bool,
              "bool": value.dtype == bool,
              "float": np.issubdtype(value.dtype, np.floating)}[kind]
        if value.shape != shape or not ok:
            raise PredictionError(f"{where}: array '{p}{key}' must be {kind} of shape "
                                  f"{shape} (E = {n_events} events, from '{p}ball'), "
                                  f"got {value.dtype} {value.shape}")


# --------------------------------------------------------------------------------------------
# Writing


def save_prediction(path: str | Path, arrays: Mapping[str, Any], meta: Mapping[str, Any],
                    *, compress: bool = False) -> None:
    """Check one rollout prediction with :func:`validate_prediction`, then write it atomically.

    ``path``: the ``.npz`` destination; ``arrays``: name -> numpy or jax array, all of
    :data:`REQUIRED_ARRAYS` and any extras (kept); ``meta``: a JSON-serialisable mapping with
    :data:`REQUIRED_META`, whose ``config`` is ``sgn_jax.config.config_to_dict`` of a valid
    config; ``compress``: write with ``np.savez_compressed``.

    Raises:
        PredictionError: on any problem, before anything is written.
    """
    records.write_npz_record(path, arrays, meta, _FORMAT, validate_prediction, compress=compress)


# --------------------------------------------------------------------------------------------
# Reading


@dataclasses.dataclass(frozen=True, eq=False)
class Prediction(ArrayRecord, record_format=_FORMAT):
    """A loaded rollout prediction (see :class:`ArrayRecord` for the read-only view, ``n_balls``,
    ``dt`` (the surrogate step, s) and ``config``): ``pred.pos`` (P, N, 3), ``pred.dE`` (S,),
    ...; adds the step and frame counts and the rollout's start time.
    """

    @property
    def n_steps(self) -> int:
        """S, the number of surrogate steps."""
        return self._length("t_step")

    @property
    def n_frames(self) -> int:
        """P, the number of saved position frames."""
        return self._length("t_pos")

    @property
    def t_start(self) -> float:
        """Time of the rollout's start (the newest true sample of the initial window), s."""
        return float(self.arrays["t_step"][0]) - self.dt


def load_prediction(path: str | Path) -> Prediction:
    """Read and validate a prediction file; raises PredictionError saying what is wrong."""
    path = Path(path)
    arrays, meta = records.read_npz_record(path, _FORMAT)
    if isinstance(meta, Mapping) and "t_step" not in arrays and "pos" in arrays \
            and "pp_pairs" in arrays:
        raise PredictionError(f"{_FORMAT.where(path)} is a DEM trajectory file "
                              "(docs/conventions.md section 4), not a "
                              "rollout prediction; pass it as --reference instead")
    validate_prediction(arrays, meta, path)
    _FORMAT.config_from_meta(meta, path)
    return Prediction(arrays=arrays, meta=meta, path=str(path))


# --------------------------------------------------------------------------------------------
# A perfect surrogate


def prediction_from_trajectory(traj: Any, start_index: int, n_steps: int, *,
                               save_every: int = 1, extra_meta: Mapping[str, Any] | None = None
                               ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Arrays and meta of a prediction that replays the DEM exactly ("perfect surrogate").

    The rollout starts at sample ``start_index`` (t_start = traj.t[start_index]); step s ends at
    sample start_index + 1 + s; dE is the DEM's normal + tangential damping (pp + pw) of that
    interval; frames every ``save_every`` steps from t_start on. ``n_pp_edges`` follows the
    graph's rule (2 x pairs with centre distance <= 2 R + pp_skin); ``n_pw_edges`` is
    2 x the DEM's wall contacts (the SDF is not evaluated here); overflow, outside and snapped
    counts are 0.

    Args:
        traj: a ``sgn_jax.records.trajectory.Trajectory``; start_index: sample index >= 0;
        n_steps: S >= 1 with start_index + S < T; save_every: >= 1;
        extra_meta: added to the meta (may override).
    Returns:
        (arrays, meta) ready for :func:`save_prediction`.
    """
    if not 0 <= start_index or n_steps < 1 or start_index + n_steps >= traj.n_samples:
        raise PredictionError(
            f"need 0 <= start_index and n_steps >= 1 with start_index + n_steps < T = "
            f"{traj.n_samples}, got start_index={start_index}, n_steps={n_steps}")
    if save_every < 1:
        raise PredictionError(f"save_every must be >= 1, got {save_every}")
    steps = np.arange(start_index + 1, start_index + 1 + n_steps)
    frames = np.arange(start_index, start_index + n_steps + 1, save_every)
    config = traj.config
    cutoff = 2.0 * float(traj.meta["ball_radius"]) + float(config.graph.pp_skin)
    d_e = np.asarray(traj.dissipation("normal+tangential", "pp+pw"))[steps]
    zeros = np.zeros(n_steps, dtype=np.int64)
    arrays = {
        "t_step": np.asarray(traj.t, dtype=np.float64)[steps],
        "dE": d_e,
        "energy_cum": np.cumsum(d_e),
        "n_pp_edges": 2 * pairs_within(traj.pos[steps], cutoff),
        "n_pw_edges": 2 * np.sum(traj.pw_contact[steps], axis=1).astype(np.int64),
        "overflow": zeros,
        "n_outside": zeros.copy(),
        "n_snapped": zeros.copy(),
        "t_pos": np.asarray(traj.t, dtype=np.float64)[frames],
        "pos": np.array(traj.pos[frames], dtype=np.float64),
        "offset": np.array(traj.offset[frames], dtype=np.float64),
    }
    meta = {
        "dt": traj.dt,
        "save_every": int(save_every),
        "init_index": int(start_index),
        "config": dict(traj.meta["config"]),
        "init_dataset": traj.path,
        "checkpoint": None,
        "surrogate": "perfect (DEM replay)",
    }
    meta.update(extra_meta or {})
    return arrays, meta


__all__ = [
    "COUNT_ARRAYS",
    "REQUIRED_ARRAYS",
    "REQUIRED_META",
    "STEP_ARRAYS",
    "ArraySpec",
    "Prediction",
    "PredictionError",
    "load_prediction",
    "prediction_from_trajectory",
    "save_prediction",
    "validate_prediction",
]
