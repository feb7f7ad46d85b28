"""The trajectory file (docs/conventions.md section 4): one ``.npz`` per DEM trajectory, sampled
every ``dt``.

The DEM writes it with :func:`save_trajectory`; everything else reads it with
:func:`load_trajectory`, which returns a read-only :class:`Trajectory`. Both run the same checks
(:func:`validate_trajectory`), so a file that was written can be read, and a bad file is refused
with a :class:`DatasetError` that names the file, the array and the problem, and says how to fix it.

Arrays (T samples, N balls, K ball-ball contact slots), SI units:

| name | shape | dtype | meaning |
|---|---|---|---|
| ``t`` | (T,) | float64 | s since the start of motion, uniformly spaced by meta dt |
| ``pos``, ``vel``, ``omega`` | (T, N, 3) | float64 | ball state (m, m/s, rad/s) |
| ``offset``, ``offset_vel`` | (T, 3) | float | jar offset (m), velocity (m/s) |
| ``diss_{pp,pw}_{normal,tangential,slip,rolling}`` | (T,) | float | J dissipated over the interval ending at each sample; [0] = 0 |
| ``ke_trans``, ``ke_rot``, ``pe_grav``, ``e_elastic`` | (T,) | float | J at the sample |
| ``work_wall`` | (T,) | float | J, cumulative since t = 0 |
| ``pp_pairs`` | (T, K, 2) | int | ball indices, padded with -1 |
| ``pw_contact`` | (T, N) | bool | ball touches a wall |

Extra arrays are allowed and kept. ``meta`` is stored as a 0-d unicode array holding a JSON
object with at least :data:`REQUIRED_META` (``config`` is ``sgn_jax.config.config_to_dict`` of
the run's config; ``created`` an ISO 8601 time). :func:`build_meta` fills them in from a config.
"""

from __future__ import annotations

import dataclasses
import datetime
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

import sgn_jax
from sgn_jax.config import config_to_dict
from sgn_jax.dem.collisions import COLLISION_PREFIX
from sgn_jax.errors import SGNJaxError
from sgn_jax.records import base as records
from sgn_jax.records.base import ArrayRecord, ArraySpec, RecordFormat
from sgn_jax.records.io_utils import git_commit


class DatasetError(SGNJaxError, ValueError):
    """A trajectory file or its arrays/meta are malformed; the message says what and how to fix."""


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

_FORMAT = RecordFormat(
    kind="trajectory",
    error=DatasetError,
    arrays=REQUIRED_ARRAYS,
    meta_keys=REQUIRED_META,
    documented_in="docs/conventions.md section 4",
    size_sources="T from 't', N from 'pos', K from 'pp_pairs'",
    float64_hint=("positions and velocities must be float64 (the surrogate's finite "
                  "differences need them); cast with .astype(np.float64) before saving"),
    fix_hint="regenerate the file with `sgn-jax dem` (sgn_jax.records.trajectory.save_trajectory)",
    produce_hint="generate it with `sgn-jax dem --config CONFIG.toml`",
    meta_hint="build it with sgn_jax.records.trajectory.build_meta(config, ...)",
)


# --------------------------------------------------------------------------------------------
# Validation


def _check_meta(meta: Any, where: str) -> None:
    records.check_config_entry(meta, _FORMAT, where)
    for key in ("dt", "dt_dem", "ball_radius", "ball_mass"):
        if not records.is_positive_number(meta[key]):
            raise DatasetError(f"{where}: meta[{key!r}] must be a positive number, got "
                               f"{meta[key]!r}")
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
        DatasetError: naming ``path`` (if given), the offending array or meta key, what was
            expected and what was found.
    """
    where, arrays = records.check_names_and_meta(arrays, meta, path, _FORMAT, _check_meta)

    # Sizes: T from t, N from pos, K from pp_pairs; everything else must agree.
    t = arrays["t"]
    if t.ndim != 1 or t.shape[0] < 1:
        raise DatasetError(f"{where}: array 't' must have shape (T,) with T >= 1, got {t.shape}")
    sizes: dict[str, int] = {"T": t.shape[0]}
    if arrays["pos"].ndim == 3:
        sizes["N"] = arrays["pos"].shape[1]
    if arrays["pp_pairs"].ndim == 3:
        sizes["K"] = arrays["pp_pairs"].shape[1]
    records.check_array_specs(arrays, _FORMAT, sizes, where)

    for name, value in arrays.items():
        if np.issubdtype(value.dtype, np.inexact) and value.ndim >= 1:
            bad = records.first_non_finite(value)
            if bad is not None:
                raise DatasetError(
                    f"{where}: array {name!r} contains NaN or inf, first at sample {bad} "
                    f"(t = {float(t[min(bad, t.size - 1)]):.6g} s); the DEM diverged or the "
                    "array was not filled; rerun with a smaller dt_dem or check the contact model"
                )

    n_balls = sizes["N"]
    if meta["n_balls"] != n_balls:
        raise DatasetError(f"{where}: meta['n_balls'] = {meta['n_balls']} but 'pos' has N = "
                           f"{n_balls} balls; {_FORMAT.fix_hint}")

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


def build_meta(config: Any, *, seed: int | None = None, extra: Mapping[str, Any] | None = None
               ) -> dict[str, Any]:
    """The required meta for a trajectory produced from ``config`` (a ``sgn_jax.config.Config``).

    ``dt``, ``dt_dem`` and ``seed`` come from ``config.dem`` (``seed`` may be overridden), the
    ball radius and mass from ``config.balls``, ``code_version`` is the package version and git
    commit, ``created`` the current UTC time. ``extra`` entries are added (and may override).
    """
    classes = config.balls.classes
    counts = [c.count for c in classes]
    radii = np.repeat([float(c.radius) for c in classes], counts)
    masses = np.repeat([float(4.0 / 3.0 * math.pi * c.radius**3 * c.density) for c in classes],
                       counts)
    meta = {
        "config": config_to_dict(config),
        "dt": float(config.dem.dt),
        "dt_dem": float(config.dem.dt_dem),
        "seed": int(config.dem.seed if seed is None else seed),
        # A mixed charge: the largest radius and the mean mass (n_balls * ball_mass is the
        # charge's mass), and every ball's own in ball_radii / ball_masses.
        "ball_radius": float(radii.max()),
        "ball_mass": float(masses.mean()) if len(classes) > 1 else float(masses[0]),
        "n_balls": int(config.balls.n_balls),
        "code_version": f"sgn_jax {sgn_jax.__version__} ({git_commit()})",
        "created": datetime.datetime.now(datetime.UTC).isoformat(),
    }
    if len(classes) > 1:
        meta["ball_radii"] = radii.tolist()
        meta["ball_masses"] = masses.tolist()
    meta.update(extra or {})
    return meta


def save_trajectory(path: str | Path, arrays: Mapping[str, Any], meta: Mapping[str, Any],
                    *, compress: bool = False) -> None:
    """Validate (:func:`validate_trajectory`) and write one trajectory as ``.npz``, atomically.

    ``path`` must end in ``.npz``. ``arrays`` (numpy or jax) hold at least
    :data:`REQUIRED_ARRAYS`; extra arrays are kept. ``meta`` is JSON-serialisable with at least
    :data:`REQUIRED_META` (:func:`build_meta` makes it); its ``config`` must rebuild into a
    ``sgn_jax.config.Config``. ``compress=True`` uses ``np.savez_compressed`` (slower; float64
    positions compress poorly).

    Raises:
        DatasetError: saying what is wrong; nothing is written then.
    """
    records.write_npz_record(path, arrays, meta, _FORMAT, validate_trajectory,
                             compress=compress)


# --------------------------------------------------------------------------------------------
# Reading


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
class Trajectory(ArrayRecord, record_format=_FORMAT):
    """A DEM trajectory as loaded: read-only arrays by attribute (``traj.pos`` (T, N, 3)
    float64), ``meta`` and ``path``, with ``n_balls``, ``dt`` (the sampling step, s) and
    ``config`` from :class:`ArrayRecord`; adds the sample count, the dissipation and energy
    sums and slicing in time.
    """

    @property
    def n_samples(self) -> int:
        """T, the number of samples."""
        return self._length("t")

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
        target (docs/conventions.md section 3); ``kind="all"`` adds Coulomb slip and rolling
        friction.
        """
        return np.cumsum(self.dissipation(kind, which))

    def energy_balance(self) -> np.ndarray:
        """``ke_trans + ke_rot + pe_grav + e_elastic + all dissipation - work_wall`` minus its
        first value, (T,) J: zero up to the integrator's error (docs/conventions.md section 4)."""
        a = self.arrays
        total = (a["ke_trans"] + a["ke_rot"] + a["pe_grav"] + a["e_elastic"]
                 + self.cumulative_dissipation("all", "all") - a["work_wall"])
        return total - total[0]

    def slice(self, start: int | None, stop: int | None) -> Trajectory:
        """Samples ``start:stop`` (Python slice semantics, step 1) as a new Trajectory.

        Required arrays and extra arrays whose first dimension is T are sliced; other extra
        arrays are kept whole, except the collision table (``collision_*``, one row per contact
        event, not per sample), which is left out. The dissipation arrays of the first kept sample are set to 0
        (the interval before it is not part of the slice), so the record format's "first sample 0"
        still holds and ``cumulative_dissipation`` starts at 0. ``work_wall`` stays cumulative since
        t = 0 of the original run.
        """
        first, last, _ = slice(start, stop).indices(self.n_samples)
        if last <= first:
            raise ValueError(f"slice({start}, {stop}) of a trajectory with {self.n_samples} "
                             "samples is empty")
        n_samples = self.n_samples
        arrays = {}
        for name, value in self.arrays.items():
            if name.startswith(COLLISION_PREFIX):
                continue
            if name in REQUIRED_ARRAYS or (value.ndim >= 1 and value.shape[0] == n_samples):
                value = np.array(value[first:last])
            if name in _DISS_NAMES:
                value[0] = 0.0
            value.flags.writeable = False
            arrays[name] = value
        meta = dict(self.meta)
        meta["sliced_from"] = {"path": self.path, "start": first, "stop": last}
        return Trajectory(arrays=arrays, meta=meta, path=None)

    def coarsen(self, factor: int) -> Trajectory:
        """Every ``factor``-th sample (from the first) as a trajectory sampled at ``factor * dt``.

        States (positions, velocities, energies, ``work_wall``, contacts) are those at the kept
        samples; the dissipation of each kept sample is the sum over the ``factor`` intervals
        that end at it, so the cumulative dissipation at every kept sample is unchanged and the
        first sample stays 0. Samples after the last multiple of ``factor`` are dropped. The
        collision table (``collision_*``, time-stamped events) is kept whole.
        ``meta['dt']`` (and ``[dem] dt`` of a stored config dict) become ``factor * dt``. This
        is how a surrogate with a coarser step than the DEM's sampling trains and starts from
        the same records (docs/sgn.md, "Surrogate step").
        """
        if isinstance(factor, bool) or not isinstance(factor, (int, np.integer)) or factor < 1:
            raise ValueError(f"coarsen factor must be an integer >= 1, got {factor!r}")
        factor = int(factor)
        if factor == 1:
            return self
        n_samples = self.n_samples
        kept = np.arange(0, n_samples, factor)
        if kept.size < 2:
            raise ValueError(f"coarsening a trajectory of {n_samples} samples by {factor} leaves "
                             f"{kept.size} sample; it needs at least {factor + 1} samples")
        arrays = {}
        for name, value in self.arrays.items():
            if name in _DISS_NAMES:
                # cumulative sums at the kept samples, differenced: the dissipation of each
                # coarse interval (first sample 0, as in the original).
                cum = np.cumsum(np.asarray(value, np.float64))[kept]
                value = np.concatenate([[0.0], np.diff(cum)]).astype(value.dtype)
            elif name.startswith(COLLISION_PREFIX):
                pass
            elif name in REQUIRED_ARRAYS or (value.ndim >= 1 and value.shape[0] == n_samples):
                value = np.array(value[kept])
            value.flags.writeable = False
            arrays[name] = value
        meta = dict(self.meta)
        meta["dt"] = float(self.meta["dt"]) * factor
        config = meta.get("config")
        if isinstance(config, dict) and isinstance(config.get("dem"), dict):
            meta["config"] = {**config, "dem": {**config["dem"], "dt": meta["dt"]}}
        meta["coarsened_from"] = {"path": self.path, "factor": factor,
                                  "dt": float(self.meta["dt"])}
        return Trajectory(arrays=arrays, meta=meta, path=None)

    def at_step(self, dt: float) -> Trajectory:
        """This trajectory sampled at ``dt`` (s): itself when ``dt`` is its own step, else
        :meth:`coarsen` by the integer ``dt / self.dt``; a ``dt`` that is not an integer
        multiple of the sampling step raises :class:`DatasetError`."""
        ratio = float(dt) / self.dt
        factor = int(round(ratio))
        if factor < 1 or abs(ratio - factor) > 1e-6 * max(ratio, 1.0):
            raise DatasetError(
                f"{self.path or 'trajectory'}: a step of {dt:g} s is not an integer multiple of "
                f"the record's sampling step {self.dt:g} s; sample the DEM at {dt:g} s or at a "
                "divisor of it (`[dem] dt`)")
        return self.coarsen(factor)


def load_trajectory(path: str | Path) -> Trajectory:
    """Read and validate a trajectory file; raises DatasetError saying what is wrong."""
    path = Path(path)
    arrays, meta = records.read_npz_record(path, _FORMAT)
    validate_trajectory(arrays, meta, path)
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
