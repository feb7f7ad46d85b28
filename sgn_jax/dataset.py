"""The trajectory file (SPEC section 4): one ``.npz`` per DEM trajectory, sampled every ``dt``.

The DEM writes it with :func:`save_trajectory`; everything else reads it with
:func:`load_trajectory`, which returns a read-only :class:`Trajectory`. Both run the same checks
(:func:`validate_trajectory`), so a file that was written can be read, and a bad file is refused
with a :class:`DatasetError` that names the file, the array and the problem, and says how to fix it.

Arrays (T samples, N balls, K ball-ball contact slots), SI units:

==========================================  ===========  ========  ==============================
name                                        shape        dtype     meaning
==========================================  ===========  ========  ==============================
``t``                                       (T,)         float64   s since the start of motion,
                                                                   uniformly spaced by meta dt
``pos``, ``vel``, ``omega``                 (T, N, 3)    float64   ball state (m, m/s, rad/s)
``offset``, ``offset_vel``                  (T, 3)       float     jar offset (m), velocity (m/s)
``diss_{pp,pw}_{normal,tangential,          (T,)         float     J dissipated over the interval
slip,rolling}``                                                    ending at each sample; [0] = 0
``ke_trans``, ``ke_rot``, ``pe_grav``,      (T,)         float     J at the sample
``e_elastic``
``work_wall``                               (T,)         float     J, cumulative since t = 0
``pp_pairs``                                (T, K, 2)    int       ball indices, padded with -1
``pw_contact``                              (T, N)       bool      ball touches a wall
==========================================  ===========  ========  ==============================

Extra arrays are allowed and kept. ``meta`` is stored as a 0-d unicode array holding a JSON
object with at least :data:`REQUIRED_META` (``config`` is ``sgn_jax.config.config_to_dict`` of
the run's config; ``created`` an ISO 8601 time). :func:`build_meta` fills them in from a config.
"""

from __future__ import annotations

import dataclasses
import datetime
import json
import math
import zipfile
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from sgn_jax.io_utils import atomic_write


class DatasetError(ValueError):
    """A trajectory file or its arrays/meta are malformed; the message says what and how to fix."""


class ArraySpec(NamedTuple):
    """Expected shape (symbols "T", "N", "K" or fixed ints) and dtype of one required array.

    ``dtype`` is either an exact numpy dtype name ("float64") or a kind: "float", "int", "bool".
    """

    shape: tuple[str | int, ...]
    dtype: str
    description: str


_DISS_NAMES = tuple(
    f"diss_{which}_{kind}"
    for which in ("pp", "pw")
    for kind in ("normal", "tangential", "slip", "rolling")
)

REQUIRED_ARRAYS: dict[str, ArraySpec] = {
    "t": ArraySpec(("T",), "float64", "time since the start of motion (s)"),
    "pos": ArraySpec(("T", "N", 3), "float64", "ball positions (m)"),
    "vel": ArraySpec(("T", "N", 3), "float64", "ball velocities (m/s)"),
    "omega": ArraySpec(("T", "N", 3), "float64", "ball angular velocities (rad/s)"),
    "offset": ArraySpec(("T", 3), "float", "jar offset (m)"),
    "offset_vel": ArraySpec(("T", 3), "float", "jar velocity (m/s)"),
    **{name: ArraySpec(("T",), "float", "energy dissipated over the interval ending at the sample (J)")
       for name in _DISS_NAMES},
    "ke_trans": ArraySpec(("T",), "float", "translational kinetic energy (J)"),
    "ke_rot": ArraySpec(("T",), "float", "rotational kinetic energy (J)"),
    "pe_grav": ArraySpec(("T",), "float", "gravitational potential energy m g y (J)"),
    "e_elastic": ArraySpec(("T",), "float", "elastic energy in the contact springs (J)"),
    "work_wall": ArraySpec(("T",), "float", "cumulative work of the wall on the balls (J)"),
    "pp_pairs": ArraySpec(("T", "K", 2), "int", "ball-ball contacts, padded with -1"),
    "pw_contact": ArraySpec(("T", "N"), "bool", "ball-wall contact flags"),
}

REQUIRED_META: tuple[str, ...] = (
    "config", "dt", "dt_dem", "seed", "ball_radius", "ball_mass", "n_balls", "code_version",
    "created",
)

DISSIPATION_KINDS = ("normal", "tangential", "slip", "rolling")
DISSIPATION_WHICH = ("pp", "pw")

# Relative tolerance on the spacing of t: t is computed as (index * dt) in float64, whose
# rounding is ~1e-16 * t_max, far below this; a wrong dt or a dropped sample is far above it.
_DT_RTOL = 1e-6
_FIX_HINT = "regenerate the file with `sgn-jax dem` (sgn_jax.dataset.save_trajectory)"


# --------------------------------------------------------------------------------------------
# Validation


def _where(path: str | Path | None) -> str:
    return f"trajectory file {str(path)!r}" if path is not None else "trajectory"


def _dtype_ok(dtype: np.dtype, expected: str) -> bool:
    if expected == "float":
        return np.issubdtype(dtype, np.floating)
    if expected == "int":
        return np.issubdtype(dtype, np.integer)
    if expected == "bool":
        return dtype == np.bool_
    return dtype == np.dtype(expected)


def _first_bad_sample(values: np.ndarray) -> int | None:
    finite = np.isfinite(values)
    if finite.all():
        return None
    bad_rows = ~finite.reshape(values.shape[0], -1).all(axis=1) if values.ndim > 1 else ~finite
    return int(np.flatnonzero(bad_rows)[0])


def _check_meta(meta: Any, where: str) -> None:
    if not isinstance(meta, Mapping):
        raise DatasetError(f"{where}: meta must be a JSON object (dict), got {type(meta).__name__}; "
                           "build it with sgn_jax.dataset.build_meta(config, ...)")
    missing = [key for key in REQUIRED_META if key not in meta]
    if missing:
        raise DatasetError(
            f"{where}: meta is missing key(s) {missing} (required: {list(REQUIRED_META)}); "
            "build it with sgn_jax.dataset.build_meta(config, ...)"
        )
    if not isinstance(meta["config"], Mapping):
        raise DatasetError(f"{where}: meta['config'] must be a dict "
                           "(sgn_jax.config.config_to_dict(cfg)), got "
                           f"{type(meta['config']).__name__}")
    for key in ("dt", "dt_dem", "ball_radius", "ball_mass"):
        value = meta[key]
        if isinstance(value, bool) or not isinstance(value, (int, float)) \
                or not math.isfinite(value) or value <= 0:
            raise DatasetError(f"{where}: meta[{key!r}] must be a positive number, got {value!r}")
    for key in ("seed", "n_balls"):
        if isinstance(meta[key], bool) or not isinstance(meta[key], int):
            raise DatasetError(f"{where}: meta[{key!r}] must be an integer, got {meta[key]!r}")
    if not isinstance(meta["code_version"], str):
        raise DatasetError(f"{where}: meta['code_version'] must be a string")
    try:
        datetime.datetime.fromisoformat(meta["created"])
    except (TypeError, ValueError):
        raise DatasetError(
            f"{where}: meta['created'] must be an ISO 8601 time string "
            f"(datetime.now(timezone.utc).isoformat()), got {meta['created']!r}"
        ) from None


def validate_trajectory(arrays: Mapping[str, Any], meta: Mapping[str, Any],
                        path: str | Path | None = None) -> None:
    """Check names, shapes, dtypes, finiteness, time spacing, consistency and meta.

    Raises:
        DatasetError naming ``path`` (if given), the offending array or meta key, what was
        expected and what was found.
    """
    where = _where(path)
    if "meta" in arrays:
        raise DatasetError(f"{where}: 'meta' is reserved for the JSON metadata; pass it as the "
                           "meta argument, not as an array")
    _check_meta(meta, where)

    missing = [name for name in REQUIRED_ARRAYS if name not in arrays]
    if missing:
        raise DatasetError(
            f"{where}: missing array(s) {missing}; a trajectory needs "
            f"{list(REQUIRED_ARRAYS)} (SPEC section 4); {_FIX_HINT}"
        )
    arrays = {name: np.asarray(value) for name, value in arrays.items()}

    # Sizes: T from t, N from pos, K from pp_pairs; everything else must agree.
    t = arrays["t"]
    if t.ndim != 1 or t.shape[0] < 1:
        raise DatasetError(f"{where}: array 't' must have shape (T,) with T >= 1, got {t.shape}")
    sizes: dict[str, int] = {"T": t.shape[0]}
    if arrays["pos"].ndim == 3:
        sizes["N"] = arrays["pos"].shape[1]
    if arrays["pp_pairs"].ndim == 3:
        sizes["K"] = arrays["pp_pairs"].shape[1]
    for name, spec in REQUIRED_ARRAYS.items():
        value = arrays[name]
        expected = tuple(sizes.get(d, -1) if isinstance(d, str) else d for d in spec.shape)
        pattern = "(" + ", ".join(str(d) for d in spec.shape) + (",)" if len(spec.shape) == 1 else ")")
        if value.shape != expected:
            inconsistent = value.ndim == len(expected) and all(
                g == e or isinstance(d, str) for g, e, d in zip(value.shape, expected, spec.shape,
                                                                strict=True))
            reason = ("inconsistent sizes between arrays (T from 't', N from 'pos', K from "
                      "'pp_pairs')" if inconsistent else "wrong shape")
            raise DatasetError(
                f"{where}: array {name!r} ({spec.description}) has shape {value.shape}, expected "
                f"{pattern} = {expected} with {sizes}: {reason}; {_FIX_HINT}"
            )
        if not _dtype_ok(value.dtype, spec.dtype):
            hint = ("positions and velocities must be float64 (the surrogate's finite "
                    "differences need them); cast with .astype(np.float64) before saving"
                    if spec.dtype == "float64" else f"store it as {spec.dtype}")
            raise DatasetError(f"{where}: array {name!r} has dtype {value.dtype}, expected "
                               f"{spec.dtype}; {hint}")

    for name, value in arrays.items():
        if np.issubdtype(value.dtype, np.inexact) and value.ndim >= 1:
            bad = _first_bad_sample(value)
            if bad is not None:
                raise DatasetError(
                    f"{where}: array {name!r} contains NaN or inf, first at sample {bad} "
                    f"(t = {float(t[min(bad, t.size - 1)]):.6g} s); the DEM diverged or the "
                    "array was not filled; rerun with a smaller dt_dem or check the contact model"
                )

    n_balls = sizes["N"]
    if meta["n_balls"] != n_balls:
        raise DatasetError(f"{where}: meta['n_balls'] = {meta['n_balls']} but 'pos' has N = "
                           f"{n_balls} balls; {_FIX_HINT}")

    dt = float(meta["dt"])
    if t.size > 1:
        steps = np.diff(t)
        deviation = np.abs(steps - dt)
        worst = int(np.argmax(deviation))
        if deviation[worst] > _DT_RTOL * dt:
            raise DatasetError(
                f"{where}: array 't' is not uniformly spaced by meta['dt'] = {dt:g} s: "
                f"t[{worst + 1}] - t[{worst}] = {steps[worst]:.9g} s; samples must be "
                "t = t0 + i * dt with no gaps (write t as t0 + np.arange(T) * dt)"
            )

    for name in _DISS_NAMES:
        if arrays[name][0] != 0:
            raise DatasetError(
                f"{where}: array {name!r} must be 0 at the first sample (the dissipation is "
                f"over the interval ending at each sample), got {arrays[name][0]!r}"
            )

    pairs = arrays["pp_pairs"]
    if pairs.size and (pairs.min() < -1 or pairs.max() >= n_balls):
        raise DatasetError(
            f"{where}: array 'pp_pairs' holds indices outside [-1, N) = [-1, {n_balls}) "
            f"(min {pairs.min()}, max {pairs.max()}); pad unused slots with -1"
        )


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


def build_meta(config: Any, *, seed: int | None = None, extra: Mapping[str, Any] | None = None
               ) -> dict[str, Any]:
    """The required meta for a trajectory produced from ``config`` (a ``sgn_jax.config.Config``).

    ``dt``, ``dt_dem`` and ``seed`` come from ``config.dem`` (``seed`` may be overridden), the
    ball radius and mass from ``config.balls``, ``code_version`` is the package version and git
    commit, ``created`` the current UTC time. ``extra`` entries are added (and may override).
    """
    import sgn_jax
    from sgn_jax.config import config_to_dict
    from sgn_jax.io_utils import git_commit

    radius = float(config.balls.radius)
    meta = {
        "config": config_to_dict(config),
        "dt": float(config.dem.dt),
        "dt_dem": float(config.dem.dt_dem),
        "seed": int(config.dem.seed if seed is None else seed),
        "ball_radius": radius,
        "ball_mass": float(4.0 / 3.0 * math.pi * radius**3 * config.balls.density),
        "n_balls": int(config.balls.count),
        "code_version": f"sgn_jax {sgn_jax.__version__} ({git_commit()})",
        "created": datetime.datetime.now(datetime.UTC).isoformat(),
    }
    meta.update(extra or {})
    return meta


def save_trajectory(path: str | Path, arrays: Mapping[str, Any], meta: Mapping[str, Any],
                    *, compress: bool = False) -> None:
    """Validate and write one trajectory as ``.npz``, atomically.

    Args:
        path: destination, must end in ``.npz``.
        arrays: name -> array (numpy or jax), see :data:`REQUIRED_ARRAYS`; extra arrays are kept.
        meta: JSON-serialisable dict with at least :data:`REQUIRED_META`; ``meta['config']`` must
            rebuild into a ``sgn_jax.config.Config``.
        compress: use ``np.savez_compressed`` (slower; float64 positions compress poorly).
    Raises:
        DatasetError if the arrays or meta fail :func:`validate_trajectory`; nothing is written.
    """
    path = Path(path)
    if path.suffix != ".npz":
        raise DatasetError(f"trajectory path {str(path)!r} must end in '.npz' "
                           f"(e.g. {str(path.with_suffix('.npz'))!r})")
    arrays = {name: np.asarray(value) for name, value in arrays.items()}
    validate_trajectory(arrays, meta, path)
    _config_from_meta(meta, path)  # refuse to write a config that cannot be read back
    try:
        meta_json = json.dumps(dict(meta), default=_json_default, sort_keys=True, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise DatasetError(f"{_where(path)}: meta is not JSON serialisable: {exc}") from exc
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
        raise DatasetError(f"{_where(path)}: meta['config'] is not a valid config: {exc}; "
                           "store sgn_jax.config.config_to_dict(cfg) of the run's config") from exc


def _split_kinds(spec: str, allowed: tuple[str, ...], argument: str) -> tuple[str, ...]:
    if spec == "all":
        return allowed
    parts = tuple(p.strip() for p in spec.split("+"))
    unknown = [p for p in parts if p not in allowed]
    if unknown or not parts:
        raise ValueError(f"{argument}={spec!r}: unknown part(s) {unknown}; use '+'-joined "
                         f"names from {list(allowed)} or 'all'")
    return parts


@dataclasses.dataclass(frozen=True, eq=False)
class Trajectory:
    """A read-only trajectory: arrays by attribute (``traj.pos`` (T, N, 3) float64), meta, path.

    The arrays are marked non-writeable; copy one (``np.array(traj.pos)``) to modify it.
    """

    arrays: dict[str, np.ndarray]
    meta: dict[str, Any]
    path: str | None = None

    def __getattr__(self, name: str) -> np.ndarray:
        # Only called when normal lookup fails; guard against recursion before __init__ ran.
        if name.startswith("__") or name == "arrays":
            raise AttributeError(name)
        try:
            return self.arrays[name]
        except KeyError:
            raise AttributeError(
                f"Trajectory has no attribute or array {name!r}; arrays: {sorted(self.arrays)}"
            ) from None

    def __getitem__(self, name: str) -> np.ndarray:
        return self.arrays[name]

    def __dir__(self) -> Iterable[str]:
        return sorted(set(super().__dir__()) | set(self.arrays))

    @property
    def n_samples(self) -> int:
        """T, the number of samples."""
        return int(self.arrays["t"].shape[0])

    @property
    def n_balls(self) -> int:
        """N, the number of balls."""
        return int(self.arrays["pos"].shape[1])

    @property
    def dt(self) -> float:
        """Sampling step (s)."""
        return float(self.meta["dt"])

    @property
    def config(self) -> Any:
        """The run's ``sgn_jax.config.Config``, rebuilt from ``meta['config']``."""
        return _config_from_meta(self.meta, self.path)

    def dissipation(self, kind: str = "normal+tangential", which: str = "pp+pw") -> np.ndarray:
        """Dissipation per interval (T,) J, summed over ``kind`` and ``which``.

        Args:
            kind: '+'-joined subset of normal, tangential, slip, rolling, or "all".
            which: '+'-joined subset of pp (ball-ball), pw (ball-wall), or "all".
        """
        kinds = _split_kinds(kind, DISSIPATION_KINDS, "kind")
        whiches = _split_kinds(which, DISSIPATION_WHICH, "which")
        total = np.zeros(self.n_samples, dtype=np.float64)
        for w in whiches:
            for k in kinds:
                total = total + self.arrays[f"diss_{w}_{k}"]
        return total

    def cumulative_dissipation(self, kind: str = "normal+tangential", which: str = "pp+pw"
                               ) -> np.ndarray:
        """Cumulative dissipated energy since the first sample (T,) J; [0] = 0.

        The default (normal + tangential damping, ball-ball + ball-wall) is the surrogate's dE
        target (SPEC section 3); ``kind="all"`` adds Coulomb slip and rolling friction.
        """
        return np.cumsum(self.dissipation(kind, which))

    def energy_balance(self) -> np.ndarray:
        """``ke_trans + ke_rot + pe_grav + e_elastic + all dissipation - work_wall`` minus its
        first value, (T,) J: zero up to the integrator's error (SPEC section 4)."""
        a = self.arrays
        total = (a["ke_trans"] + a["ke_rot"] + a["pe_grav"] + a["e_elastic"]
                 + self.cumulative_dissipation("all", "all") - a["work_wall"])
        return total - total[0]

    def slice(self, start: int | None, stop: int | None) -> Trajectory:
        """Samples ``start:stop`` (Python slice semantics, step 1) as a new Trajectory.

        Required arrays and extra arrays whose first dimension is T are sliced; other extra
        arrays are kept whole. The dissipation arrays of the first kept sample are set to 0
        (the interval before it is not part of the slice), so the SPEC's "first sample 0" still
        holds and ``cumulative_dissipation`` starts at 0. ``work_wall`` stays cumulative since
        t = 0 of the original run.
        """
        first, last, _ = slice(start, stop).indices(self.n_samples)
        if last <= first:
            raise ValueError(f"slice({start}, {stop}) of a trajectory with {self.n_samples} "
                             "samples is empty")
        n_samples = self.n_samples
        arrays = {}
        for name, value in self.arrays.items():
            if name in REQUIRED_ARRAYS or (value.ndim >= 1 and value.shape[0] == n_samples):
                value = np.array(value[first:last])
            if name in _DISS_NAMES:
                value[0] = 0.0
            value.flags.writeable = False
            arrays[name] = value
        meta = dict(self.meta)
        meta["sliced_from"] = {"path": self.path, "start": first, "stop": last}
        return Trajectory(arrays=arrays, meta=meta, path=None)


def load_trajectory(path: str | Path) -> Trajectory:
    """Read and validate a trajectory file; raises DatasetError saying what is wrong."""
    path = Path(path)
    where = _where(path)
    if not path.exists():
        raise DatasetError(f"{where} not found; check the path, or generate it with "
                           "`sgn-jax dem --config CONFIG.toml`")
    if not path.is_file():
        raise DatasetError(f"{where} is not a file")
    arrays: dict[str, np.ndarray] = {}
    try:
        npz = np.load(path, allow_pickle=False)
    except (zipfile.BadZipFile, OSError, EOFError, ValueError) as exc:
        raise DatasetError(f"{where} is not an .npz archive or is corrupt "
                           f"({type(exc).__name__}: {exc}); {_FIX_HINT}") from exc
    if not isinstance(npz, np.lib.npyio.NpzFile):
        raise DatasetError(f"{where} is a single .npy array, not an .npz archive; {_FIX_HINT}")
    try:
        with npz:
            # Read every member now: a corrupt member only fails (CRC, truncation) on access.
            for name in npz.files:
                arrays[name] = npz[name]
    except (zipfile.BadZipFile, OSError, EOFError, ValueError, KeyError) as exc:
        raise DatasetError(f"{where} is a corrupt or truncated .npz archive "
                           f"({type(exc).__name__}: {exc}); {_FIX_HINT}") from exc

    if "meta" not in arrays:
        raise DatasetError(f"{where} has no 'meta' entry (the JSON metadata); {_FIX_HINT}")
    meta_array = arrays.pop("meta")
    if meta_array.ndim != 0 or meta_array.dtype.kind != "U":
        raise DatasetError(f"{where}: 'meta' must be a JSON string (0-d unicode array), got "
                           f"dtype {meta_array.dtype} shape {meta_array.shape}; {_FIX_HINT}")
    try:
        meta = json.loads(str(meta_array))
    except json.JSONDecodeError as exc:
        raise DatasetError(f"{where}: 'meta' is not valid JSON ({exc}); {_FIX_HINT}") from exc

    validate_trajectory(arrays, meta, path)
    for value in arrays.values():
        value.flags.writeable = False
    return Trajectory(arrays=arrays, meta=meta, path=str(path))


__all__ = [
    "DISSIPATION_KINDS",
    "DISSIPATION_WHICH",
    "REQUIRED_ARRAYS",
    "REQUIRED_META",
    "ArraySpec",
    "DatasetError",
    "Trajectory",
    "build_meta",
    "load_trajectory",
    "save_trajectory",
    "validate_trajectory",
]
