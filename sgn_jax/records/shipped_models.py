"""The trained models shipped with the package, and how a checkpoint argument finds one.

The models live in ``sgn_jax/data/models/<name>/`` (orbax checkpoint directories as written to
``checkpoints/best`` by a training run), each named by one entry of the registry beside them,
``sgn_jax/data/models/registry.toml``::

    default = "contact"

    [[model]]
    name = "contact"
    description = "the contact-impulse model (docs/contact.md), at 2e-4 s"

:func:`resolve_checkpoint` turns what a user passes (nothing, a shipped model's name, a
training run or checkpoint directory) into a checkpoint directory; :func:`ship_checkpoint`
installs a trained checkpoint as a registered model.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any, NamedTuple

from sgn_jax.config import read_toml
from sgn_jax.records.checkpoint import (
    DIGEST_FILE,
    CheckpointError,
    TrainedModel,
    latest_step,
    load_trained_model,
    write_checkpoint_digest,
)
from sgn_jax.records.io_utils import write_json

SHIPPED_MODELS_DIR = Path(__file__).resolve().parents[1] / "data" / "models"
"""Where the trained models shipped with the package live (one directory per model)."""
REGISTRY_FILE = "registry.toml"
"""The registry's file name in :data:`SHIPPED_MODELS_DIR`."""


class ShippedModelError(CheckpointError):
    """No shipped model of that name, none shipped, or a registry that cannot be read."""


class ShippedModel(NamedTuple):
    """One registry entry: the model's name (its folder) and what it is."""

    name: str
    description: str


class Registry(NamedTuple):
    """The registry: the default model's name and every shipped model, in the file's order."""

    default: str
    models: tuple[ShippedModel, ...]

    @property
    def names(self) -> tuple[str, ...]:
        """The models' names, the default first (none in an installation without models)."""
        rest = tuple(m.name for m in self.models if m.name != self.default)
        return (self.default, *rest) if self.models else ()


def registry() -> Registry:
    """The shipped models' registry (``SHIPPED_MODELS_DIR/registry.toml``), checked: every
    entry has a name and a description, the names are unique and the default is one of them.
    An installation without the file ships no model (an empty registry)."""
    path = SHIPPED_MODELS_DIR / REGISTRY_FILE
    if not path.is_file():
        return Registry(default="", models=())
    data = read_toml(path, ShippedModelError, "shipped-model registry")
    entries = data.get("model", [])
    models = []
    for i, entry in enumerate(entries if isinstance(entries, list) else [entries]):
        if not (isinstance(entry, dict) and set(entry) == {"name", "description"}
                and all(isinstance(entry[k], str) and entry[k] for k in entry)):
            raise ShippedModelError(f"{path}: [[model]] entry {i + 1} must have exactly a "
                                    "non-empty name and description")
        models.append(ShippedModel(entry["name"], entry["description"]))
    names = [m.name for m in models]
    if len(set(names)) != len(names):
        raise ShippedModelError(f"{path}: a model name appears twice: {names}")
    default = data.get("default")
    if default not in names:
        raise ShippedModelError(f"{path}: default = {default!r} is not one of the models "
                                f"{names}")
    return Registry(default=default, models=tuple(models))


def shipped_model_dir(name: str) -> Path:
    """The folder of the shipped model ``name`` (it may not exist in this installation)."""
    return SHIPPED_MODELS_DIR / name


def has_checkpoint(path: str | Path) -> bool:
    """True if ``path`` is a training run directory (with ``checkpoints/``) or a checkpoint
    directory holding at least one complete step."""
    path = Path(path)
    if (path / "checkpoints").is_dir():
        return True
    return path.is_dir() and latest_step(path) is not None


def _shipped_checkpoint(name: str) -> Path | None:
    shipped = shipped_model_dir(name)
    # The checkpoint directory itself (the documented layout), or a copied checkpoints/ folder.
    for candidate in (shipped, shipped / "best"):
        if has_checkpoint(candidate):
            return candidate
    return None


def resolve_checkpoint(checkpoint: str | Path | None) -> Path:
    """The checkpoint directory ``checkpoint`` names: a path (a training run or checkpoint
    directory), or a shipped model's name (``"emax_300rpm"``, ``"envelope"``); with None the
    registry's default model, else the first other shipped one. Refused with a message that
    lists the shipped models when neither exists."""
    names = registry().names
    if checkpoint is not None:
        path = Path(checkpoint)
        if not path.exists() and str(checkpoint) in names:
            found = _shipped_checkpoint(str(checkpoint))
            if found is not None:
                return found
        if not path.exists():
            raise ShippedModelError(
                f"--checkpoint {str(path)!r} does not exist; pass a training run directory "
                "(written by `sgn-jax train --out DIR`), its checkpoints/best directory, or a "
                f"shipped model's name ({', '.join(names) or 'none is shipped'})")
        return path
    for name in names:
        found = _shipped_checkpoint(name)
        if found is not None:
            return found
    raise ShippedModelError(
        f"no trained model is shipped with this installation (looked in {SHIPPED_MODELS_DIR}); "
        "pass one with --checkpoint DIR: a training run directory written by `sgn-jax train "
        "--out DIR` (its checkpoints/best is used) or a checkpoint directory")


def load_surrogate(checkpoint: str | Path | None = None, which: str = "best") -> TrainedModel:
    """The trained surrogate that ``checkpoint`` names (:func:`resolve_checkpoint`: the shipped
    default model, a shipped model's name, a training run or a checkpoint directory); ``which``
    is "best" or "latest" for a training run."""
    return load_trained_model(resolve_checkpoint(checkpoint), which=which)


def best_checkpoint_step(run: str | Path) -> Path:
    """The one step directory of a training run's ``checkpoints/best`` (what is shipped)."""
    best = Path(run) / "checkpoints" / "best"
    steps = sorted(d for d in best.iterdir() if d.is_dir()) if best.is_dir() else []
    if len(steps) != 1:
        raise ShippedModelError(f"expected one checkpoint under {best}, found {len(steps)}")
    return steps[0]


def ship_checkpoint(step_dir: str | Path, name: str, provenance: dict[str, Any],
                    extra_files: tuple[str | Path, ...] | list[str | Path] = ()) -> Path:
    """Install a checkpoint step as the shipped model ``name`` (``SHIPPED_MODELS_DIR/name``),
    which must have its entry in the registry.

    Copies ``step_dir`` (writing its file digests if it has none), the ``extra_files`` that
    exist (loss plot, metrics) and ``PROVENANCE.json`` into a staging folder, loads the staged
    model back (refusing to ship what does not load) and only then replaces the old model, so
    a failed copy never leaves the package without one. Returns the model's folder.
    """
    names = registry().names
    if name not in names:
        raise ShippedModelError(
            f"{name!r} has no entry in {SHIPPED_MODELS_DIR / REGISTRY_FILE} (registered: "
            f"{', '.join(names)}); add a [[model]] entry with its name and description first")
    step_dir = Path(step_dir)
    target = shipped_model_dir(name)
    staging = target.with_name(target.name + ".new")
    if staging.exists():
        shutil.rmtree(staging)
    staging.mkdir(parents=True)
    shutil.copytree(step_dir, staging / step_dir.name)
    if not (staging / step_dir.name / DIGEST_FILE).is_file():
        write_checkpoint_digest(staging / step_dir.name)
    for extra in map(Path, extra_files):
        if extra.is_file():
            shutil.copy2(extra, staging / extra.name)
    write_json(staging / "PROVENANCE.json", provenance)
    load_trained_model(staging)
    if target.exists():
        shutil.rmtree(target)
    staging.rename(target)
    return target


__all__ = [
    "REGISTRY_FILE",
    "SHIPPED_MODELS_DIR",
    "Registry",
    "ShippedModel",
    "ShippedModelError",
    "best_checkpoint_step",
    "has_checkpoint",
    "load_surrogate",
    "registry",
    "resolve_checkpoint",
    "ship_checkpoint",
    "shipped_model_dir",
]
