"""Orbax checkpoints of an SGN training run: parameters, optimiser state, normalisation, config.

Layout of a checkpoint directory (one ``orbax.checkpoint.CheckpointManager``; each step is
written to a temporary directory and renamed when complete, so an interruption never leaves a
half-written step under its final name)::

    DIR/<step>/params      flax parameters (orbax standard pytree)
    DIR/<step>/opt_state   optax state (optional: absent in exported models)
    DIR/<step>/norm        normalisation statistics (nested dict of float64 arrays)
    DIR/<step>/meta        JSON: config, epoch, losses, SHA-256 digests of params and norm

A training run keeps two such directories, ``checkpoints/latest`` (the last two epochs) and
``checkpoints/best`` (lowest validation loss). Restoring verifies the digests, so a damaged
checkpoint is refused with :class:`CheckpointError` instead of silently giving other numbers.
"""

from __future__ import annotations

import hashlib
import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jax
import numpy as np

from sgn_jax.normalization import NormStats, stats_from_arrays, stats_to_arrays

ITEMS = ("params", "opt_state", "norm", "meta")
FORMAT_VERSION = 1


class CheckpointError(RuntimeError):
    """A checkpoint is missing, incomplete, corrupt or does not match what is asked of it."""


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
    return directory / str(int(step))


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

    Raises:
        CheckpointError: no checkpoint there, the step is missing, a file is damaged, or a
            digest does not match.
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
    """A trained SGN ready for prediction (see :func:`load_trained_model`)."""

    model: Any
    params: Any
    norm_stats: NormStats
    config: Any
    meta: dict[str, Any]

    def predict_fn(self):
        """Pure ``predict(params, stats, raw_graph) -> (accel m/s^2, dE J)`` (see model.py)."""
        from sgn_jax.model import make_predict

        return make_predict(self.model)


def load_trained_model(path: str | Path, which: str = "best") -> TrainedModel:
    """Load the model of a training run directory (``which`` = "best" or "latest") or of a
    checkpoint directory, with its config and normalisation statistics."""
    from sgn_jax.config import ConfigError, config_from_dict
    from sgn_jax.model import make_model

    path = Path(path)
    if which not in ("best", "latest"):
        raise CheckpointError(f"which must be 'best' or 'latest', got {which!r}")
    ckpt_dir = path / "checkpoints" / which if (path / "checkpoints").is_dir() else path
    restored = restore_checkpoint(ckpt_dir)
    try:
        cfg = config_from_dict(restored.meta["config"])
    except (KeyError, ConfigError) as exc:
        raise CheckpointError(f"checkpoint {ckpt_dir} has no valid config: {exc}") from exc
    return TrainedModel(model=make_model(cfg.model), params=restored.params,
                        norm_stats=restored.norm_stats, config=cfg, meta=restored.meta)
