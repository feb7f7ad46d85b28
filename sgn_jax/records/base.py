"""What the project's ``.npz`` record files share: the DEM trajectory file
(:mod:`sgn_jax.records.trajectory`) and the rollout prediction file
(:mod:`sgn_jax.records.prediction`).

A record is a set of named numpy arrays plus ``meta``, a JSON object stored in the archive as a
0-d unicode array under the reserved name ``"meta"``. Each file kind describes itself with a
:class:`RecordFormat` (its name, error class, required arrays and meta keys, and the hints its
error messages end with) and keeps its own validation rules; this module holds what does not
depend on the kind:

- :class:`ArraySpec` and the checks the validations share (:func:`check_names_and_meta`,
  :func:`check_config_entry`, :func:`check_array_specs`, :func:`is_positive_number`,
  :func:`first_non_finite`);
- :func:`write_npz_record`: validate, check the config can be read back, encode the meta as
  JSON (``sgn_jax.records.io_utils.json_default``), write atomically;
- :func:`read_npz_record`: read every member (a missing file, a non-zip, a corrupt member, a
  missing or non-JSON meta each get a clear error) and return read-only arrays and the meta;
- :class:`ArrayRecord`: the read-only view (arrays by attribute or item, ``meta``, ``path``,
  ``n_balls``, ``dt``, ``config``) that ``Trajectory`` and ``Prediction`` extend.

Every error is raised as the kind's own error class and names the file (``RecordFormat.where``).
"""

from __future__ import annotations

import dataclasses
import json
import math
import zipfile
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any, ClassVar, NamedTuple

import numpy as np

from sgn_jax.config import ConfigError, saved_config_from_dict
from sgn_jax.records.io_utils import atomic_write, json_default


class ArraySpec(NamedTuple):
    """Expected shape (size symbols such as "T", "N" or fixed ints) and dtype of one array.

    ``dtype`` is either an exact numpy dtype name ("float64") or a kind: "float", "int", "bool".
    """

    shape: tuple[str | int, ...]
    dtype: str
    description: str


@dataclasses.dataclass(frozen=True)
class RecordFormat:
    """One kind of record file: what it must hold and what its error messages say.

    Attributes:
        kind: the file's name in messages ("trajectory" gives "trajectory file 'x.npz': ...").
        error: the exception class raised for every problem (a ``ValueError`` subclass).
        arrays: required array name -> :class:`ArraySpec`, in the order they are checked.
        meta_keys: required meta keys.
        documented_in: where the arrays are described (quoted when one is missing).
        size_sources: which array each size symbol is read from (quoted on a shape mismatch).
        float64_hint: why the "float64" arrays must be float64 and how to fix one that is not.
        fix_hint: how to make a good file; ends the messages about a bad one.
        produce_hint: how to make the file; ends the message about a missing one.
        meta_hint: how to build a good meta; ends the messages about a malformed one.
    """

    kind: str
    error: type[ValueError]
    arrays: Mapping[str, ArraySpec]
    meta_keys: tuple[str, ...]
    documented_in: str
    size_sources: str
    float64_hint: str
    fix_hint: str
    produce_hint: str
    meta_hint: str

    def where(self, path: str | Path | None) -> str:
        """How messages name the record: "<kind> file '<path>'", or just the kind."""
        return f"{self.kind} file {str(path)!r}" if path is not None else self.kind

    def config_from_meta(self, meta: Mapping[str, Any], path: str | Path | None) -> Any:
        """The run's ``sgn_jax.config.Config`` rebuilt from ``meta['config']``."""
        try:
            return saved_config_from_dict(dict(meta["config"]))
        except ConfigError as exc:
            raise self.error(f"{self.where(path)}: meta['config'] is not a valid config: {exc}; "
                             "store sgn_jax.config.config_to_dict(cfg) of the run's config"
                             ) from exc


# --------------------------------------------------------------------------------------------
# Checks shared by the validations


def dtype_matches(dtype: np.dtype, expected: str) -> bool:
    """Whether ``dtype`` satisfies an :class:`ArraySpec` dtype (exact name or kind)."""
    if expected == "float":
        return np.issubdtype(dtype, np.floating)
    if expected == "int":
        return np.issubdtype(dtype, np.integer)
    if expected == "bool":
        return dtype == np.bool_
    return dtype == np.dtype(expected)


def is_positive_number(value: Any) -> bool:
    """A finite int or float > 0 (not a bool)."""
    return (not isinstance(value, bool) and isinstance(value, (int, float))
            and math.isfinite(value) and value > 0)


def first_non_finite(values: np.ndarray) -> int | None:
    """Index along the first axis of the first row holding NaN or inf (0 for a 0-d array), or
    None if every value is finite."""
    finite = np.isfinite(values)
    if finite.all():
        return None
    if values.ndim == 0:
        return 0
    bad_rows = ~finite.reshape(values.shape[0], -1).all(axis=1)
    return int(np.flatnonzero(bad_rows)[0])


def refuse_meta_array(arrays: Mapping[str, Any], fmt: RecordFormat, where: str) -> None:
    """'meta' names the JSON metadata in the archive, so it cannot also be an array."""
    if "meta" in arrays:
        raise fmt.error(f"{where}: 'meta' is reserved for the JSON metadata; pass it as the "
                        "meta argument, not as an array")


def _expect_mapping(value: Any, fmt: RecordFormat, where: str, expected: str, hint: str = ""
                    ) -> None:
    if not isinstance(value, Mapping):
        raise fmt.error(f"{where}: {expected}, got {type(value).__name__}"
                        + (f"; {hint}" if hint else ""))


def check_meta_object(meta: Any, fmt: RecordFormat, where: str) -> None:
    """``meta`` is a mapping holding every key of ``fmt.meta_keys``."""
    _expect_mapping(meta, fmt, where, "meta must be a JSON object (dict)", fmt.meta_hint)
    missing = [key for key in fmt.meta_keys if key not in meta]
    if missing:
        raise fmt.error(f"{where}: meta is missing key(s) {missing} (required: "
                        f"{list(fmt.meta_keys)}); {fmt.meta_hint}")


def check_config_entry(meta: Mapping[str, Any], fmt: RecordFormat, where: str) -> None:
    """``meta['config']`` is a dict (whether it is a valid config is checked on save and on
    access, :meth:`RecordFormat.config_from_meta`)."""
    _expect_mapping(meta["config"], fmt, where,
                    "meta['config'] must be a dict (sgn_jax.config.config_to_dict(cfg))")


def require_arrays(arrays: Mapping[str, Any], fmt: RecordFormat, where: str
                   ) -> dict[str, np.ndarray]:
    """Every array of ``fmt.arrays`` is present; returns all arrays as numpy arrays."""
    missing = [name for name in fmt.arrays if name not in arrays]
    if missing:
        raise fmt.error(f"{where}: missing array(s) {missing}; a {fmt.kind} needs "
                        f"{list(fmt.arrays)} ({fmt.documented_in}); {fmt.fix_hint}")
    return {name: np.asarray(value) for name, value in arrays.items()}


def check_names_and_meta(arrays: Mapping[str, Any], meta: Any, path: str | Path | None,
                         fmt: RecordFormat, check_meta: Callable[[Mapping[str, Any], str], None]
                         ) -> tuple[str, dict[str, np.ndarray]]:
    """The start of every validation, in this order: no array named 'meta'
    (:func:`refuse_meta_array`), meta an object with the required keys
    (:func:`check_meta_object`), the kind's own meta rules (``check_meta(meta, where)``), every
    required array present (:func:`require_arrays`).

    Returns:
        (where, arrays): how messages name the record, and the arrays as numpy arrays.
    """
    where = fmt.where(path)
    refuse_meta_array(arrays, fmt, where)
    check_meta_object(meta, fmt, where)
    check_meta(meta, where)
    return where, require_arrays(arrays, fmt, where)


def check_array_specs(arrays: Mapping[str, np.ndarray], fmt: RecordFormat, sizes: Mapping[str, int],
                      where: str) -> None:
    """Every required array has the shape and dtype of its spec.

    Args:
        sizes: size symbol -> size, read from the arrays named in ``fmt.size_sources``; a
            symbol left out (its source array had the wrong rank) matches no size.
    """
    for name, spec in fmt.arrays.items():
        value = arrays[name]
        expected = tuple(sizes.get(d, -1) if isinstance(d, str) else d for d in spec.shape)
        pattern = "(" + ", ".join(str(d) for d in spec.shape) + (",)" if len(spec.shape) == 1
                                                                  else ")")
        if value.shape != expected:
            # Right rank and fixed sizes: only the sizes shared with other arrays disagree.
            inconsistent = value.ndim == len(expected) and all(
                g == e or isinstance(d, str) for g, e, d in zip(value.shape, expected, spec.shape,
                                                                strict=True))
            reason = "inconsistent sizes between arrays" if inconsistent else "wrong shape"
            raise fmt.error(
                f"{where}: array {name!r} ({spec.description}) has shape {value.shape}, expected "
                f"{pattern} = {expected} with {dict(sizes)} ({fmt.size_sources}): {reason}; "
                f"{fmt.fix_hint}")
        if not dtype_matches(value.dtype, spec.dtype):
            hint = fmt.float64_hint if spec.dtype == "float64" else f"store it as {spec.dtype}"
            raise fmt.error(f"{where}: array {name!r} has dtype {value.dtype}, expected "
                            f"{spec.dtype}; {hint}")


# --------------------------------------------------------------------------------------------
# Writing and reading


Validator = Callable[[Mapping[str, Any], Mapping[str, Any], Path], None]


def write_npz_record(path: str | Path, arrays: Mapping[str, Any], meta: Mapping[str, Any],
                     fmt: RecordFormat, validate: Validator, *, compress: bool = False) -> None:
    """Validate and write one record as ``.npz``, atomically; on any error nothing is written.

    Args:
        path: destination, must end in ``.npz``.
        arrays: name -> array (numpy or jax); converted with ``np.asarray``.
        meta: JSON-serialisable mapping; ``meta['config']`` must rebuild into a Config.
        validate: the kind's ``validate(arrays, meta, path)``, raising ``fmt.error``.
        compress: use ``np.savez_compressed``.
    """
    path = Path(path)
    if path.suffix != ".npz":
        raise fmt.error(f"{fmt.kind} path {str(path)!r} must end in '.npz' "
                        f"(e.g. {str(path.with_suffix('.npz'))!r})")
    arrays = {name: np.asarray(value) for name, value in arrays.items()}
    validate(arrays, meta, path)
    fmt.config_from_meta(meta, path)  # refuse to write a config that cannot be read back
    try:
        meta_json = json.dumps(dict(meta), default=json_default, sort_keys=True, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise fmt.error(f"{fmt.where(path)}: meta is not JSON serialisable: {exc}") from exc
    writer = np.savez_compressed if compress else np.savez
    with atomic_write(path, "wb") as fh:
        writer(fh, meta=np.array(meta_json), **arrays)


def read_npz_record(path: str | Path, fmt: RecordFormat) -> tuple[dict[str, np.ndarray], Any]:
    """Read every member of a record file and decode its meta; nothing is validated yet.

    Returns:
        (arrays, meta): the arrays, other than 'meta', marked read-only; the decoded JSON meta
        (any JSON value: the kind's validation checks it is an object with the right keys).
    Raises:
        ``fmt.error`` if the file is missing, not a file, not an ``.npz`` archive (or a single
        ``.npy`` array), corrupt or truncated, or has no 'meta' entry or one that is not a JSON
        string.
    """
    path = Path(path)
    where = fmt.where(path)
    if not path.exists():
        raise fmt.error(f"{where} not found; check the path, or {fmt.produce_hint}")
    if not path.is_file():
        raise fmt.error(f"{where} is not a file")
    arrays: dict[str, np.ndarray] = {}
    try:
        npz = np.load(path, allow_pickle=False)
    except (zipfile.BadZipFile, OSError, EOFError, ValueError) as exc:
        raise fmt.error(f"{where} is not an .npz archive or is corrupt "
                        f"({type(exc).__name__}: {exc}); {fmt.fix_hint}") from exc
    if not isinstance(npz, np.lib.npyio.NpzFile):
        raise fmt.error(f"{where} is a single .npy array, not an .npz archive; {fmt.fix_hint}")
    try:
        with npz:
            # Read every member now: a corrupt member only fails (CRC, truncation) on access.
            for name in npz.files:
                arrays[name] = npz[name]
    except (zipfile.BadZipFile, OSError, EOFError, ValueError, KeyError) as exc:
        raise fmt.error(f"{where} is a corrupt or truncated .npz archive "
                        f"({type(exc).__name__}: {exc}); {fmt.fix_hint}") from exc

    if "meta" not in arrays:
        raise fmt.error(f"{where} has no 'meta' entry (the JSON metadata); {fmt.fix_hint}")
    meta_array = arrays.pop("meta")
    if meta_array.ndim != 0 or meta_array.dtype.kind != "U":
        raise fmt.error(f"{where}: 'meta' must be a JSON string (0-d unicode array), got "
                        f"dtype {meta_array.dtype} shape {meta_array.shape}; {fmt.fix_hint}")
    try:
        meta = json.loads(str(meta_array))
    except json.JSONDecodeError as exc:
        raise fmt.error(f"{where}: 'meta' is not valid JSON ({exc}); {fmt.fix_hint}") from exc
    for value in arrays.values():
        value.flags.writeable = False
    return arrays, meta


# --------------------------------------------------------------------------------------------
# The read-only view


@dataclasses.dataclass(frozen=True, eq=False)
class ArrayRecord:
    """A read-only record: arrays by attribute (``rec.pos``) or item (``rec["pos"]``), meta, path.

    A subclass names its format in its header, ``class Trajectory(ArrayRecord,
    record_format=...)``; it becomes :attr:`record_format`. Arrays loaded from a file are marked
    non-writeable; copy one (``np.array(rec.pos)``) to modify it. Every record has ``pos``
    (., N, 3), ``meta['dt']`` and ``meta['config']``.
    """

    arrays: dict[str, np.ndarray]
    meta: dict[str, Any]
    path: str | None = None

    record_format: ClassVar[RecordFormat]

    def __init_subclass__(cls, *, record_format: RecordFormat, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        cls.record_format = record_format

    def _length(self, name: str) -> int:
        """Size of the first axis of array ``name``."""
        return int(self.arrays[name].shape[0])

    def __getattr__(self, name: str) -> np.ndarray:
        # Only called when normal lookup fails; guard against recursion before __init__ ran.
        if name.startswith("__") or name == "arrays":
            raise AttributeError(name)
        try:
            return self.arrays[name]
        except KeyError:
            raise AttributeError(
                f"{type(self).__name__} has no attribute or array {name!r}; arrays: "
                f"{sorted(self.arrays)}"
            ) from None

    def __getitem__(self, name: str) -> np.ndarray:
        return self.arrays[name]

    def __dir__(self) -> Iterable[str]:
        return sorted(set(super().__dir__()) | set(self.arrays))

    @property
    def n_balls(self) -> int:
        """N, the number of balls."""
        return int(self.arrays["pos"].shape[1])

    @property
    def dt(self) -> float:
        """Sampling step (s): the spacing of the record's time axis."""
        return float(self.meta["dt"])

    @property
    def config(self) -> Any:
        """The run's ``sgn_jax.config.Config``, rebuilt from ``meta['config']``."""
        return self.record_format.config_from_meta(self.meta, self.path)


__all__ = [
    "ArrayRecord",
    "ArraySpec",
    "RecordFormat",
    "check_array_specs",
    "check_config_entry",
    "check_meta_object",
    "check_names_and_meta",
    "dtype_matches",
    "first_non_finite",
    "is_positive_number",
    "read_npz_record",
    "refuse_meta_array",
    "require_arrays",
    "write_npz_record",
]
