"""The rollout prediction file: what ``sgn_jax.rollout`` writes and ``sgn-jax evaluate`` reads.

One ``.npz`` per surrogate rollout. The rollout writes it with :func:`save_prediction`; metrics
and plots read it with :func:`load_prediction`, which returns a read-only :class:`Prediction`.
Both run the same checks (:func:`validate_prediction`), so a file that was written can be read,
and a bad file is refused with a :class:`PredictionError` that names the file, the array and the
problem, and says how to fix it.

Arrays (S surrogate steps, P saved position frames, N balls), SI units:

=================================  =========  =======  ==============================================
name                               shape      dtype    meaning
=================================  =========  =======  ==============================================
``t_step``                         (S,)       float    s since the start of motion at the END of each
                                                       surrogate step; uniformly spaced by meta dt
``dE``                             (S,)       float    J, predicted dissipation of each step
``energy_cum``                     (S,)       float    J, cumulative predicted dissipation since the
                                                       rollout's start (= cumsum(dE))
``n_pp_edges``, ``n_pw_edges``     (S,)       int      directed edge counts of the step's graph
                                                       (n_pp_edges / 2 = ball-ball pairs)
``overflow``                       (S,)       int      edges dropped by the static capacity
``n_outside``                      (S,)       int      balls with phi > 0 after the step
``n_snapped``                      (S,)       int      balls moved by the snap-back
``t_pos``                          (P,)       float    s, times of the saved frames (strictly
                                                       increasing, on the step grid)
``pos``                            (P, N, 3)  float64  ball positions (m, lab frame)
``offset``                         (P, 3)     float    jar offset at those times (m)
=================================  =========  =======  ==============================================

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
import json
import math
import zipfile
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from sgn_jax.io_utils import atomic_write


class PredictionError(ValueError):
    """A prediction file or its arrays/meta are malformed; the message says what and how to fix."""


class ArraySpec(NamedTuple):
    """Expected shape (symbols "S", "P", "N" or fixed ints) and dtype of one required array.

    ``dtype`` is an exact numpy dtype name ("float64") or a kind: "float", "int".
    """

    shape: tuple[str | int, ...]
    dtype: str
    description: str


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

# Times are t_start + k * dt (rounding ~1e-16 t in float64); a wrong dt, a dropped step or a
# frame off the step grid is off by a large fraction of dt. Tolerance in steps (units of dt).
_GRID_TOL = 1e-3
# energy_cum must be cumsum(dE) up to the accumulation's rounding: a float32 running sum over
# 1e5 steps drifts ~sqrt(S) * 6e-8 ~ 2e-5 relative (worst case S * 6e-8 ~ 6e-3, never seen).
_CUMSUM_RTOL = 1e-3
_FIX_HINT = "regenerate it with `sgn-jax rollout` (sgn_jax.prediction.save_prediction)"


# --------------------------------------------------------------------------------------------
# Validation


def _where(path: str | Path | None) -> str:
    return f"prediction file {str(path)!r}" if path is not None else "prediction"


def _dtype_ok(dtype: np.dtype, expected: str) -> bool:
    if expected == "float":
        return np.issubdtype(dtype, np.floating)
    if expected == "int":
        return np.issubdtype(dtype, np.integer)
    return dtype == np.dtype(expected)


def _is_int(value: Any) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


def _check_meta(meta: Any, where: str) -> None:
    if not isinstance(meta, Mapping):
        raise PredictionError(f"{where}: meta must be a JSON object (dict), got "
                              f"{type(meta).__name__}")
    missing = [key for key in REQUIRED_META if key not in meta]
    if missing:
        raise PredictionError(f"{where}: meta is missing key(s) {missing} (required: "
                              f"{list(REQUIRED_META)}); {_FIX_HINT}")
    dt = meta["dt"]
    if isinstance(dt, bool) or not isinstance(dt, (int, float)) or not math.isfinite(dt) \
            or dt <= 0:
        raise PredictionError(f"{where}: meta['dt'] (the surrogate step, s) must be a positive "
                              f"number, got {dt!r}")
    if not _is_int(meta["save_every"]) or meta["save_every"] < 1:
        raise PredictionError(f"{where}: meta['save_every'] (steps between saved frames) must be "
                              f"an integer >= 1, got {meta['save_every']!r}")
    if not _is_int(meta["init_index"]) or meta["init_index"] < 0:
        raise PredictionError(f"{where}: meta['init_index'] (the initial dataset's sample index) "
                              f"must be an integer >= 0, got {meta['init_index']!r}")
    if not isinstance(meta["config"], Mapping):
        raise PredictionError(f"{where}: meta['config'] must be a dict "
                              "(sgn_jax.config.config_to_dict(cfg)), got "
                              f"{type(meta['config']).__name__}")


def validate_prediction(arrays: Mapping[str, Any], meta: Mapping[str, Any],
                        path: str | Path | None = None) -> None:
    """Check names, shapes, dtypes, finiteness, the time grids, counts, cumsum and meta.

    Raises:
        PredictionError naming ``path`` (if given), the offending array or meta key, what was
        expected and what was found.
    """
    where = _where(path)
    if "meta" in arrays:
        raise PredictionError(f"{where}: 'meta' is reserved for the JSON metadata; pass it as the "
                              "meta argument, not as an array")
    _check_meta(meta, where)
    missing = [name for name in REQUIRED_ARRAYS if name not in arrays]
    if missing:
        raise PredictionError(f"{where}: missing array(s) {missing}; a prediction needs "
                              f"{list(REQUIRED_ARRAYS)}; {_FIX_HINT}")
    arrays = {name: np.asarray(value) for name, value in arrays.items()}

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
    for name, spec in REQUIRED_ARRAYS.items():
        value = arrays[name]
        expected = tuple(sizes.get(d, -1) if isinstance(d, str) else d for d in spec.shape)
        pattern = "(" + ", ".join(str(d) for d in spec.shape) + (",)" if len(spec.shape) == 1
                                                                  else ")")
        if value.shape != expected:
            raise PredictionError(
                f"{where}: array {name!r} ({spec.description}) has shape {value.shape}, expected "
                f"{pattern} = {expected} with {sizes} (S from 't_step', P from 't_pos', N from "
                f"'pos'); {_FIX_HINT}")
        if not _dtype_ok(value.dtype, spec.dtype):
            hint = ("positions must be float64 (differences of nearby positions lose digits in "
                    "float32); cast with .astype(np.float64) before saving"
                    if spec.dtype == "float64" else f"store it as {spec.dtype}")
            raise PredictionError(f"{where}: array {name!r} has dtype {value.dtype}, expected "
                                  f"{spec.dtype}; {hint}")
    if sizes["N"] < 1:
        raise PredictionError(f"{where}: array 'pos' has no balls (N = 0)")

    for name, value in arrays.items():
        if np.issubdtype(value.dtype, np.inexact) and not np.isfinite(value).all():
            bad = np.flatnonzero(~np.isfinite(value.reshape(value.shape[0], -1)).all(axis=1)) \
                if value.ndim >= 1 else [0]
            raise PredictionError(
                f"{where}: array {name!r} contains NaN or inf, first at index {int(bad[0])}; the "
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

    cumsum = np.cumsum(arrays["dE"].astype(np.float64))
    scale = max(float(np.abs(cumsum).max()), float(np.abs(arrays["dE"]).sum()), 1e-300)
    drift = np.abs(arrays["energy_cum"] - cumsum)
    if drift.max() > _CUMSUM_RTOL * scale:
        worst = int(np.argmax(drift))
        raise PredictionError(
            f"{where}: array 'energy_cum' is not the running sum of 'dE': at step {worst} "
            f"energy_cum = {float(arrays['energy_cum'][worst]):.6g} J but cumsum(dE) = "
            f"{float(cumsum[worst]):.6g} J; store energy_cum = cumsum(dE) since the rollout start")


# --------------------------------------------------------------------------------------------
# Writing


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, tuple):
        return list(obj)
    raise TypeError(f"meta value of type {type(obj).__name__} is not JSON serialisable")


def save_prediction(path: str | Path, arrays: Mapping[str, Any], meta: Mapping[str, Any],
                    *, compress: bool = False) -> None:
    """Validate and write one rollout prediction as ``.npz``, atomically.

    Args:
        path: destination, must end in ``.npz``.
        arrays: name -> array (numpy or jax), see :data:`REQUIRED_ARRAYS`; extra arrays are kept.
        meta: JSON-serialisable dict with at least :data:`REQUIRED_META`; ``meta['config']`` must
            rebuild into a ``sgn_jax.config.Config``.
        compress: use ``np.savez_compressed``.
    Raises:
        PredictionError if the arrays or meta fail :func:`validate_prediction`; nothing is
        written.
    """
    path = Path(path)
    if path.suffix != ".npz":
        raise PredictionError(f"prediction path {str(path)!r} must end in '.npz' "
                              f"(e.g. {str(path.with_suffix('.npz'))!r})")
    arrays = {name: np.asarray(value) for name, value in arrays.items()}
    validate_prediction(arrays, meta, path)
    _config_from_meta(meta, path)  # refuse to write a config that cannot be read back
    try:
        meta_json = json.dumps(dict(meta), default=_json_default, sort_keys=True, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise PredictionError(f"{_where(path)}: meta is not JSON serialisable: {exc}") from exc
    writer = np.savez_compressed if compress else np.savez
    with atomic_write(path, "wb") as fh:
        writer(fh, meta=np.array(meta_json), **arrays)


# --------------------------------------------------------------------------------------------
# Reading


def _config_from_meta(meta: Mapping[str, Any], path: str | Path | None) -> Any:
    from sgn_jax.config import ConfigError, config_from_dict

    try:
        return config_from_dict(dict(meta["config"]))
    except ConfigError as exc:
        raise PredictionError(f"{_where(path)}: meta['config'] is not a valid config: {exc}; "
                              "store sgn_jax.config.config_to_dict(cfg) of the run's config"
                              ) from exc


@dataclasses.dataclass(frozen=True, eq=False)
class Prediction:
    """A read-only rollout prediction: arrays by attribute (``pred.pos`` (P, N, 3)), meta, path.

    The arrays are marked non-writeable; copy one (``np.array(pred.pos)``) to modify it.
    """

    arrays: dict[str, np.ndarray]
    meta: dict[str, Any]
    path: str | None = None

    def __getattr__(self, name: str) -> np.ndarray:
        if name.startswith("__") or name == "arrays":
            raise AttributeError(name)
        try:
            return self.arrays[name]
        except KeyError:
            raise AttributeError(
                f"Prediction has no attribute or array {name!r}; arrays: {sorted(self.arrays)}"
            ) from None

    def __getitem__(self, name: str) -> np.ndarray:
        return self.arrays[name]

    def __dir__(self) -> Iterable[str]:
        return sorted(set(super().__dir__()) | set(self.arrays))

    @property
    def n_steps(self) -> int:
        """S, the number of surrogate steps."""
        return int(self.arrays["t_step"].shape[0])

    @property
    def n_frames(self) -> int:
        """P, the number of saved position frames."""
        return int(self.arrays["t_pos"].shape[0])

    @property
    def n_balls(self) -> int:
        """N, the number of balls."""
        return int(self.arrays["pos"].shape[1])

    @property
    def dt(self) -> float:
        """Surrogate step (s)."""
        return float(self.meta["dt"])

    @property
    def t_start(self) -> float:
        """Time of the rollout's start (the newest true sample of the initial window), s."""
        return float(self.arrays["t_step"][0]) - self.dt

    @property
    def config(self) -> Any:
        """The run's ``sgn_jax.config.Config``, rebuilt from ``meta['config']``."""
        return _config_from_meta(self.meta, self.path)


def load_prediction(path: str | Path) -> Prediction:
    """Read and validate a prediction file; raises PredictionError saying what is wrong."""
    path = Path(path)
    where = _where(path)
    if not path.exists():
        raise PredictionError(f"{where} not found; check the path, or produce it with "
                              "`sgn-jax rollout`")
    if not path.is_file():
        raise PredictionError(f"{where} is not a file")
    arrays: dict[str, np.ndarray] = {}
    try:
        npz = np.load(path, allow_pickle=False)
    except (zipfile.BadZipFile, OSError, EOFError, ValueError) as exc:
        raise PredictionError(f"{where} is not an .npz archive or is corrupt "
                              f"({type(exc).__name__}: {exc}); {_FIX_HINT}") from exc
    if not isinstance(npz, np.lib.npyio.NpzFile):
        raise PredictionError(f"{where} is a single .npy array, not an .npz archive; {_FIX_HINT}")
    try:
        with npz:
            for name in npz.files:  # read all now: a corrupt member only fails on access
                arrays[name] = npz[name]
    except (zipfile.BadZipFile, OSError, EOFError, ValueError, KeyError) as exc:
        raise PredictionError(f"{where} is a corrupt or truncated .npz archive "
                              f"({type(exc).__name__}: {exc}); {_FIX_HINT}") from exc
    if "meta" not in arrays:
        raise PredictionError(f"{where} has no 'meta' entry (the JSON metadata); a trajectory "
                              f"file is not a prediction; {_FIX_HINT}")
    meta_array = arrays.pop("meta")
    if meta_array.ndim != 0 or meta_array.dtype.kind != "U":
        raise PredictionError(f"{where}: 'meta' must be a JSON string (0-d unicode array), got "
                              f"dtype {meta_array.dtype} shape {meta_array.shape}; {_FIX_HINT}")
    try:
        meta = json.loads(str(meta_array))
    except json.JSONDecodeError as exc:
        raise PredictionError(f"{where}: 'meta' is not valid JSON ({exc}); {_FIX_HINT}") from exc
    if isinstance(meta, Mapping) and "t_step" not in arrays and "pos" in arrays \
            and "pp_pairs" in arrays:
        raise PredictionError(f"{where} is a DEM trajectory file (SPEC 4), not a rollout "
                              "prediction; pass it as --reference instead")
    validate_prediction(arrays, meta, path)
    _config_from_meta(meta, path)
    for value in arrays.values():
        value.flags.writeable = False
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
        traj: a ``sgn_jax.dataset.Trajectory``; start_index: sample index >= 0;
        n_steps: S >= 1 with start_index + S < T; save_every: >= 1;
        extra_meta: added to the meta (may override).
    Returns:
        (arrays, meta) ready for :func:`save_prediction`.
    """
    from sgn_jax.metrics import pairs_within

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
