"""What the scripts under ``experiments/`` and ``benchmarks/`` share beyond the public API.

The public API is :mod:`sgn_jax.api` (``import sgn_jax as sj``). The experiment scripts import
nothing else from the package but this module (``tests/test_architecture.py`` checks it): the
pieces of a rollout and of a graph, the ensembles file and the experiment runner, training and
probing the contact model, the motion envelope, the shipped models' files, the bed/agitated
regime rules, provenance and file helpers, and the figures. Each name is the object of the
module that defines it; this module only gathers them::

    import sgn_jax.experiment_tools as tools

    tools.write_json("out/provenance.json", {"commit": tools.git_commit(),
                                             "machine": tools.machine_info()})

The figure helpers import matplotlib on their first call only.
"""

from __future__ import annotations

import dataclasses
import tomllib
from pathlib import Path
from typing import Any

from sgn_jax.analysis.collisions import (
    collision_statistics,
    decade_comparison,
    ensemble_statistics,
    events_from_arrays,
    mean_and_se,
)
from sgn_jax.analysis.metrics import (
    align,
    contact_census,
    jar_frame_speed,
    mse_plateau,
    position_mse,
    pp_contact_counts,
    wall_contact_lifetimes,
)
from sgn_jax.config import (
    config_from_dict,
    config_to_dict,
    config_to_toml,
    replace_section,
    resolve_config,
    save_config,
)
from sgn_jax.dem.contact import head_on_normal_force
from sgn_jax.design import anchored_window, apply_parameters
from sgn_jax.geometry import jar_volume
from sgn_jax.geometry.jar import jar_mesh
from sgn_jax.motion import CircleMotion, HarmonicMotion
from sgn_jax.motion import offset as motion_offset
from sgn_jax.pairs import pairs_within
from sgn_jax.pipelines.configure import charge_from_config, surrogate_walls_from_config
from sgn_jax.pipelines.configure import params_from_config as dem_params_from_config
from sgn_jax.pipelines.contact_replay import (
    derive_contact_model,
    floor_activity_run,
    make_floor_replay,
)
from sgn_jax.pipelines.contact_train_run import train_contact
from sgn_jax.pipelines.dem_run import partial_dir
from sgn_jax.pipelines.dem_run import setup_from_config as dem_setup_from_config
from sgn_jax.pipelines.experiments import (
    ExperimentError,
    case_config,
    case_result,
    last_json_line,
    parse_rollout_settings,
    prediction_ok,
    rollout_duration,
    sgn_jax_command,
    usable_cores,
)
from sgn_jax.pipelines.features import windows_from_trajectory
from sgn_jax.pipelines.rollout_eval import (
    DAMPING,
    mean_se,
    motion_misses,
    reference_span,
    rollout_against_dem,
    summarize_runs,
)
from sgn_jax.pipelines.studies import over_packings, resolve_start
from sgn_jax.pipelines.validation import check_dem_config
from sgn_jax.records.cache import enable_compilation_cache
from sgn_jax.records.charge_envelope import latin_hypercube_charges, load_charge_envelope
from sgn_jax.records.checkpoint import load_trained_model
from sgn_jax.records.ensembles import Case, EnsembleError, load_ensembles, select_cases
from sgn_jax.records.envelope import latin_hypercube_motions, load_envelope, motion_label
from sgn_jax.records.io_utils import (
    append_jsonl,
    atomic_write,
    git_commit,
    machine_info,
    read_jsonl,
    sha256_file,
    write_json,
)
from sgn_jax.records.shipped_models import (
    best_checkpoint_step,
    resolve_checkpoint,
    ship_checkpoint,
)
from sgn_jax.regime import (
    AGITATED_SPEED_M_S,
    BED_PAIRS_PER_BALL,
    CLASSIFIERS,
    REGIME_PP_CONTACTS_PER_BALL,
    REGIME_WINDOW_S,
    classify_state,
    regime_of,
    regime_windows,
)
from sgn_jax.scene import analytic_jar_query
from sgn_jax.surrogate.contact_charge import ball_charge
from sgn_jax.surrogate.contact_train import UnrollSpec, tangential_damping_shares
from sgn_jax.surrogate.graph import GraphSpec, Window, build_graph
from sgn_jax.surrogate.model import model_factory, model_kind
from sgn_jax.surrogate.rollout import make_rollout_advance, model_predictor


def load_model_to_evaluate(name_or_path: str, assignments: list[str] | None = None) -> Any:
    """A shipped model's name or a run or checkpoint directory (:func:`resolve_checkpoint`),
    loaded at a training run's latest step (its stages' last; a derived model has only its
    best), with ``[model]`` keys replaced as :func:`with_model_keys` does."""
    checkpoint = resolve_checkpoint(name_or_path)
    which = "latest" if (Path(checkpoint) / "checkpoints" / "latest").exists() else "best"
    return with_model_keys(load_trained_model(checkpoint, which=which), assignments)


def with_model_keys(trained: Any, assignments: list[str] | None) -> Any:
    """``trained`` (a :class:`sgn_jax.records.checkpoint.TrainedModel`) with ``[model]`` keys
    of its config replaced, e.g. ``["friction_sweeps=12"]`` (each ``KEY=VALUE``, VALUE a TOML
    value) and the module rebuilt from them: the same weights with another setting of the
    built-in physics (the solver's sweeps), for an evaluation's ``--model-set``."""
    if not assignments:
        return trained
    values = {}
    for item in assignments:
        key, eq, raw = item.partition("=")
        if not eq or not key.strip():
            raise SystemExit(f"--model-set takes KEY=VALUE (a [model] key), got {item!r}")
        try:
            values[key.strip()] = tomllib.loads(f"value = {raw.strip()}")["value"]
        except tomllib.TOMLDecodeError as exc:
            raise SystemExit(f"--model-set {item!r}: VALUE must be a TOML value ({exc})") from None
    cfg = replace_section(trained.config, "model", **values)
    return dataclasses.replace(trained, config=cfg,
                               model=model_factory(model_kind(cfg.model)).build_model(cfg))


def new_figure(width: float, height: float, **kwargs: Any) -> Any:
    """:func:`sgn_jax.analysis.plots.new_figure`: a matplotlib ``Figure`` on the Agg canvas (no
    pyplot), ``width`` x ``height`` inches."""
    from sgn_jax.analysis import plots  # deferred: matplotlib loads on the first figure only

    return plots.new_figure(width, height, **kwargs)


def save_figure(fig: Any, path: str | Path) -> Path:
    """:func:`sgn_jax.analysis.plots.save_figure`: write ``fig`` to a ``.png`` atomically."""
    from sgn_jax.analysis import plots  # deferred: matplotlib loads on the first figure only

    return plots.save_figure(fig, path)


def plot_case_curves(title: str, preds: list[str | Path], refs: list[str | Path],
                     labels: list[str], path: str | Path) -> Path:
    """:func:`sgn_jax.analysis.plots.plot_case_curves`: every run of an ensemble case in one figure
    (cumulative dissipated energy in J, surrogate solid and DEM dashed; MSE_t in m^2)."""
    from sgn_jax.analysis import plots  # deferred: matplotlib loads on the first figure only

    return plots.plot_case_curves(title, preds, refs, labels, path)


__all__ = [
    "with_model_keys",
    "collision_statistics",
    "decade_comparison",
    "ensemble_statistics",
    "events_from_arrays",
    "mean_and_se",
    # configs, checkpoints and the shipped models
    "config_from_dict",
    "config_to_dict",
    "config_to_toml",
    "resolve_config",
    "save_config",
    # the charge envelope and its designs (docs/charge.md)
    "load_charge_envelope",
    "latin_hypercube_charges",
    "check_dem_config",
    "jar_volume",
    "charge_from_config",
    "ball_charge",
    # a run of the DEM in another code (experiments/tools/liggghts_compare.py)
    "dem_setup_from_config",
    "jar_mesh",
    "CircleMotion",
    "HarmonicMotion",
    "motion_offset",
    "load_trained_model",
    "resolve_checkpoint",
    "best_checkpoint_step",
    "ship_checkpoint",
    "enable_compilation_cache",
    # the pieces of a graph, a rollout and a design study
    "GraphSpec",
    "Window",
    "build_graph",
    "windows_from_trajectory",
    "analytic_jar_query",
    "surrogate_walls_from_config",
    "model_predictor",
    "make_rollout_advance",
    "over_packings",
    "anchored_window",
    "apply_parameters",
    "resolve_start",
    "partial_dir",
    # training and probing the contact model
    "train_contact",
    "UnrollSpec",
    "derive_contact_model",
    "tangential_damping_shares",
    "make_floor_replay",
    "floor_activity_run",
    "dem_params_from_config",
    "head_on_normal_force",
    # metrics of trajectories and predictions
    "align",
    "contact_census",
    "wall_contact_lifetimes",
    "load_model_to_evaluate",
    "rollout_against_dem",
    "DAMPING",
    "reference_span",
    "summarize_runs",
    "motion_misses",
    "mean_se",
    "jar_frame_speed",
    "mse_plateau",
    "position_mse",
    "pp_contact_counts",
    "pairs_within",
    # the bed / agitated regime
    "classify_state",
    "regime_of",
    "regime_windows",
    "CLASSIFIERS",
    "AGITATED_SPEED_M_S",
    "BED_PAIRS_PER_BALL",
    "REGIME_PP_CONTACTS_PER_BALL",
    "REGIME_WINDOW_S",
    # the motion envelope
    "load_envelope",
    "latin_hypercube_motions",
    "motion_label",
    # the ensembles file and the experiment runner
    "Case",
    "EnsembleError",
    "load_ensembles",
    "select_cases",
    "ExperimentError",
    "case_config",
    "case_result",
    "last_json_line",
    "parse_rollout_settings",
    "prediction_ok",
    "rollout_duration",
    "sgn_jax_command",
    "usable_cores",
    # files, provenance and figures
    "atomic_write",
    "write_json",
    "append_jsonl",
    "read_jsonl",
    "sha256_file",
    "git_commit",
    "machine_info",
    "new_figure",
    "save_figure",
    "plot_case_curves",
]
