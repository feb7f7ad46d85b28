"""Orbax checkpoints of an SGN training run: parameters, optimiser state, normalisation, config.

Layout of a checkpoint directory (one ``orbax.checkpoint.CheckpointManager``; each step is
written to a temporary directory and renamed when complete, so an interruption never leaves a
half-written step under its final name)::

    DIR/<step>/params      flax parameters (orbax standard pytree)
    DIR/<step>/opt_state   optax state (optional: absent in exported models)
    DIR/<step>/norm        normalisation statistics (nested dict of float64 arrays)
    DIR/<step>/meta        JSON: config, epoch, losses, SHA-256 digests of params and norm
    DIR/<step>/sgn_digest.json   SHA-256 and size of every other file of the step (orbax's
                           manifests, metadata and data files included), written after orbax
                           has finished the step (:func:`write_checkpoint_digest`)

A training run keeps two such directories, ``checkpoints/latest`` (the last two epochs) and
``checkpoints/best`` (lowest validation loss). Restoring first checks every file of the step
against ``sgn_digest.json`` (before orbax reads anything), then the digests of the restored
pytrees, so a damaged checkpoint is refused with :class:`CheckpointError` naming the damaged
file instead of silently giving other numbers. A step without ``sgn_digest.json`` (written
before the file existed) still loads, with a warning that its files cannot be verified.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jax
import numpy as np

from sgn_jax.config import ConfigError, saved_config_from_dict
from sgn_jax.errors import SGNJaxError, SGNJaxWarning
from sgn_jax.surrogate.model import ModelKindError, make_predict, model_factory, model_kind
from sgn_jax.surrogate.normalization import NormStats, stats_from_arrays, stats_to_arrays

ITEMS = ("params", "opt_state", "norm", "meta")
FORMAT_VERSION = 1
DIGEST_FILE = "sgn_digest.json"
DIGEST_FORMAT = "sgn-jax checkpoint file digest"
DIGEST_VERSION = 1
_SHIPPED_MODELS_DIR = Path(__file__).resolve().parents[1] / "data" / "models"


class CheckpointError(SGNJaxError, RuntimeError):
    """A checkpoint is missing, incomplete, corrupt or does not match what is asked of it."""


class CheckpointIntegrityWarning(SGNJaxWarning):
    """A checkpoint has no file digest (written by an older sgn-jax), so it is not verified."""


@dataclass
class RestoredCheckpoint:
    """What :func:`restore_checkpoint` returns (``opt_state`` is None unless requested)."""

    step: int
    params: Any
    norm_stats: NormStats
    meta: dict[str, Any]
    opt_state: Any = None


def tree_digest(tree: Any) -> str:
    """SHA-256 over the paths, dtypes, shapes and bytes of a pytree's leaves (order-stable)."""
    h = hashlib.sha256()
    leaves = jax.tree_util.tree_flatten_with_path(tree)[0]
    for path, leaf in sorted(leaves, key=lambda kv: jax.tree_util.keystr(kv[0])):
        arr = np.asarray(leaf)
        h.update(jax.tree_util.keystr(path).encode())
        h.update(f"{arr.dtype.str}{arr.shape}".encode())
        h.update(np.ascontiguousarray(arr).tobytes())
    return h.hexdigest()


def _sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _step_files(step_dir: Path) -> list[str]:
    """Relative POSIX paths of every file under ``step_dir`` except the digest file, sorted."""
    out = []
    for root, dirs, files in os.walk(step_dir):
        dirs.sort()
        for name in files:
            rel = (Path(root) / name).relative_to(step_dir).as_posix()
            if rel != DIGEST_FILE:
                out.append(rel)
    return sorted(out)


def write_checkpoint_digest(step_dir: str | Path) -> Path:
    """Write ``<step_dir>/sgn_digest.json``: relative path -> sha256 and size of every file.

    Called by :func:`save_checkpoint` once orbax has finished the step, and used to give the
    shipped model its digest. Written to a temporary file and renamed (atomic). Returns its path.
    """
    step_dir = Path(step_dir)
    if not step_dir.is_dir():
        raise CheckpointError(f"no checkpoint step directory {step_dir}")
    files = {rel: {"sha256": _sha256_file(step_dir / rel), "size": (step_dir / rel).stat().st_size}
             for rel in _step_files(step_dir)}
    doc = {"format": DIGEST_FORMAT, "version": DIGEST_VERSION, "algorithm": "sha256",
           "files": files}
    target = step_dir / DIGEST_FILE
    tmp = step_dir / f".{DIGEST_FILE}.tmp{os.getpid()}"
    with open(tmp, "w") as f:
        json.dump(doc, f, indent=1, sort_keys=True)
        f.write("\n")
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, target)
    return target


def _repair_advice(step_dir: Path) -> str:
    try:
        step_dir.resolve().relative_to(_SHIPPED_MODELS_DIR)
    except ValueError:
        return ("restore it from a backup, or re-train (sgn-jax train) / re-export the model "
                "and use the new checkpoint")
    return ("this is the model shipped with the sgn-jax package: re-install the package "
            "(pip install --force-reinstall sgn-jax, or from the source tree)")


def verify_checkpoint_digest(step_dir: str | Path, *, directory: str | Path | None = None) -> bool:
    """Check every file of a step against its ``sgn_digest.json``.

    Returns True when verified, False when the step has no digest file (an older checkpoint).
    ``directory`` (default: the step's parent) is the checkpoint directory named in messages.

    Raises:
        CheckpointError: a file is missing, has another size or content, or is not part of the
            checkpoint; or the digest file itself is unreadable. The message names the file
            (relative to the checkpoint directory) and the checkpoint directory.
    """
    step_dir = Path(step_dir)
    directory = Path(directory) if directory is not None else step_dir.parent
    step = step_dir.name
    advice = _repair_advice(step_dir)
    digest_path = step_dir / DIGEST_FILE
    if not digest_path.is_file():
        return False
    try:
        doc = json.loads(digest_path.read_text())
        if doc.get("format") != DIGEST_FORMAT or doc.get("version") != DIGEST_VERSION:
            raise ValueError(f"not an sgn-jax digest file (format {doc.get('format')!r}, "
                             f"version {doc.get('version')!r})")
        expected = {str(k): (str(v["sha256"]), int(v["size"])) for k, v in doc["files"].items()}
    except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError, AttributeError) as exc:
        raise CheckpointError(
            f"checkpoint {directory} is damaged: {step}/{DIGEST_FILE} is unreadable "
            f"({type(exc).__name__}: {exc}); {advice}") from exc

    problems = []
    for rel, (sha, size) in sorted(expected.items()):
        path = step_dir / rel
        if not path.is_file():
            problems.append(f"{step}/{rel} is missing")
            continue
        actual = path.stat().st_size
        if actual != size:
            problems.append(f"{step}/{rel} has {actual} bytes, expected {size} "
                            f"({'truncated' if actual < size else 'extended'})")
        elif _sha256_file(path) != sha:
            problems.append(f"{step}/{rel} does not match its SHA-256 digest (modified)")
    for rel in _step_files(step_dir):
        if rel not in expected:
            problems.append(f"{step}/{rel} is not part of the checkpoint (unexpected file)")
    if problems:
        more = (f" (and {len(problems) - 1} more: " + "; ".join(problems[1:4])
                + ("; ..." if len(problems) > 4 else "") + ")") if len(problems) > 1 else ""
        raise CheckpointError(f"checkpoint {directory} is damaged: {problems[0]}{more}; {advice}")
    return True


def _check_meta_json(step_dir: Path, directory: Path) -> None:
    """An empty or invalid ``meta/metadata`` named explicitly (orbax's error does not name it)."""
    path = step_dir / "meta" / "metadata"
    if not path.is_file():
        return
    try:
        json.loads(path.read_text())
    except (UnicodeDecodeError, ValueError) as exc:
        raise CheckpointError(
            f"checkpoint {directory} is damaged: {step_dir.name}/meta/metadata is not valid JSON "
            f"({'empty file' if path.stat().st_size == 0 else exc}); "
            f"{_repair_advice(step_dir)}") from exc


def _manager(directory: Path, keep: int | None, read_only: bool):
    import orbax.checkpoint as ocp

    # read_only only decides whether the directory may be created (orbax's own read_only mode
    # logs warnings on every open).
    options = ocp.CheckpointManagerOptions(
        max_to_keep=keep, enable_async_checkpointing=False, create=not read_only)
    return ocp.CheckpointManager(directory.absolute(), options=options, item_names=ITEMS)


def _quiet_orbax() -> None:
    # Orbax logs every save at INFO level through absl; keep the training output readable.
    logging.getLogger("absl").setLevel(logging.WARNING)


def save_checkpoint(directory: str | Path, step: int, *, params: Any, norm_stats: NormStats,
                    meta: dict[str, Any], opt_state: Any = None, keep: int | None = 2) -> Path:
    """Save one step; older steps beyond ``keep`` are deleted after the new one is complete.

    ``meta`` must be JSON-serialisable; the digests and format version are added to it.
    Returns the step's directory.
    """
    import orbax.checkpoint as ocp

    _quiet_orbax()
    directory = Path(directory)
    params = jax.device_get(params)
    norm = stats_to_arrays(norm_stats)
    full_meta = dict(meta)
    full_meta.update(format_version=FORMAT_VERSION, step=int(step),
                     velocity_encoding=norm_stats.velocity_encoding,
                     params_digest=tree_digest(params), norm_digest=tree_digest(norm),
                     has_opt_state=opt_state is not None)
    items = {"params": ocp.args.StandardSave(params), "norm": ocp.args.StandardSave(norm),
             "meta": ocp.args.JsonSave(json.loads(json.dumps(full_meta)))}
    if opt_state is not None:
        full_meta["opt_state_digest"] = tree_digest(jax.device_get(opt_state))
        items["meta"] = ocp.args.JsonSave(json.loads(json.dumps(full_meta)))
        items["opt_state"] = ocp.args.StandardSave(jax.device_get(opt_state))
    with _manager(directory, keep, read_only=False) as mngr:
        mngr.save(int(step), args=ocp.args.Composite(**items), force=True)
        mngr.wait_until_finished()
    step_dir = directory / str(int(step))
    write_checkpoint_digest(step_dir)
    return step_dir


def latest_step(directory: str | Path) -> int | None:
    """The newest complete step in ``directory``, or None if there is none."""
    directory = Path(directory)
    if not directory.is_dir():
        return None
    _quiet_orbax()
    with _manager(directory, None, read_only=True) as mngr:
        return mngr.latest_step()


def restore_checkpoint(directory: str | Path, step: int | None = None, *,
                       opt_state_like: Any = None) -> RestoredCheckpoint:
    """Restore a step (default: the newest) and verify it.

    Args:
        directory: a checkpoint directory written by :func:`save_checkpoint`.
        step: which step; None for the newest.
        opt_state_like: a pytree with the optimiser state's structure (e.g. ``tx.init(params)``)
            to restore the optimiser state too; None to skip it.

    Before orbax reads the step, every file is checked against the step's ``sgn_digest.json``
    (see :func:`verify_checkpoint_digest`); a step without one (written before sgn-jax wrote
    it) is restored with a :class:`CheckpointIntegrityWarning`.

    Raises:
        CheckpointError: no checkpoint there, the step is missing, a file is damaged (the
            message names it), or a digest does not match.
    """
    import orbax.checkpoint as ocp

    _quiet_orbax()
    directory = Path(directory)
    if not directory.is_dir():
        raise CheckpointError(f"no checkpoint directory {directory} (train first, or check --out)")
    try:
        with _manager(directory, None, read_only=True) as mngr:
            steps = mngr.all_steps()
            if not steps:
                raise CheckpointError(f"{directory} contains no complete checkpoint")
            if step is None:
                step = max(steps)
            if step not in steps:
                raise CheckpointError(f"{directory} has no step {step}; available: {sorted(steps)}")
            step_dir = directory / str(step)
            if not verify_checkpoint_digest(step_dir, directory=directory):
                warnings.warn(
                    f"checkpoint {directory} (step {step}) has no {DIGEST_FILE}: its files' "
                    "integrity cannot be verified (written by an older sgn-jax; re-save it, or "
                    "call sgn_jax.records.checkpoint.write_checkpoint_digest on a copy you trust)",
                    CheckpointIntegrityWarning, stacklevel=2)
            _check_meta_json(step_dir, directory)
            meta = mngr.restore(step, args=ocp.args.Composite(meta=ocp.args.JsonRestore()))["meta"]
            if not isinstance(meta, dict) or meta.get("format_version") != FORMAT_VERSION:
                raise CheckpointError(f"{directory}/{step}: not an sgn-jax checkpoint "
                                      f"(format_version {meta and meta.get('format_version')})")
            items = {"params": ocp.args.StandardRestore(), "norm": ocp.args.StandardRestore()}
            if opt_state_like is not None:
                if not meta.get("has_opt_state"):
                    raise CheckpointError(f"{directory}/{step} has no optimiser state to resume")
                abstract = jax.tree_util.tree_map(ocp.utils.to_shape_dtype_struct,
                                                  jax.device_get(opt_state_like))
                items["opt_state"] = ocp.args.StandardRestore(abstract)
            restored = mngr.restore(step, args=ocp.args.Composite(**items))
    except CheckpointError:
        raise
    except Exception as exc:  # orbax / tensorstore raise many types for damaged files
        raise CheckpointError(
            f"cannot read checkpoint {directory} (step {step}): {type(exc).__name__}: {exc}"
        ) from exc

    params = jax.tree_util.tree_map(np.asarray, restored["params"])
    norm = jax.tree_util.tree_map(np.asarray, restored["norm"])
    if tree_digest(params) != meta.get("params_digest"):
        raise CheckpointError(f"checkpoint {directory}/{step} is corrupt: parameter digest "
                              "mismatch")
    if tree_digest(norm) != meta.get("norm_digest"):
        raise CheckpointError(f"checkpoint {directory}/{step} is corrupt: normalisation digest "
                              "mismatch")
    opt_state = None
    if opt_state_like is not None:
        opt_state = restored["opt_state"]
        if tree_digest(jax.device_get(opt_state)) != meta.get("opt_state_digest"):
            raise CheckpointError(f"checkpoint {directory}/{step} is corrupt: optimiser state "
                                  "digest mismatch")
    try:
        stats = stats_from_arrays(norm, meta.get("velocity_encoding", "absolute"))
    except ValueError as exc:
        raise CheckpointError(f"checkpoint {directory}/{step}: {exc}") from exc
    return RestoredCheckpoint(step=int(step), params=params, norm_stats=stats, meta=meta,
                              opt_state=opt_state)


@dataclass
class TrainedModel:
    """A trained surrogate ready for prediction (see :func:`load_trained_model`).

    ``model`` is the flax module of the config's ``[model] kind`` (an ``SGN`` by default),
    built by :func:`sgn_jax.surrogate.model.model_factory`."""

    model: Any
    params: Any
    norm_stats: NormStats
    config: Any
    meta: dict[str, Any]

    def predict_fn(self):
        """Pure ``predict(params, stats, raw_graph) -> (accel m/s^2, dE J)`` (see model.py)."""
        return make_predict(self.model)


def load_trained_model(path: str | Path, which: str = "best") -> TrainedModel:
    """Load the model of a training run directory (``which`` = "best" or "latest") or of a
    checkpoint directory, with its config and normalisation statistics."""
    path = Path(path)
    if which not in ("best", "latest"):
        raise CheckpointError(f"which must be 'best' or 'latest', got {which!r}")
    ckpt_dir = path / "checkpoints" / which if (path / "checkpoints").is_dir() else path
    restored = restore_checkpoint(ckpt_dir)
    try:
        cfg = saved_config_from_dict(restored.meta["config"])
    except (KeyError, ConfigError) as exc:
        raise CheckpointError(f"checkpoint {ckpt_dir} has no valid config: {exc}") from exc
    try:
        factory = model_factory(model_kind(cfg.model))
    except ModelKindError as exc:
        raise CheckpointError(
            f"checkpoint {ckpt_dir} holds a model of kind {model_kind(cfg.model)!r}: {exc}; "
            "import the module that registers it before loading") from exc
    return TrainedModel(model=factory.build_model(cfg), params=restored.params,
                        norm_stats=restored.norm_stats, config=cfg, meta=restored.meta)
