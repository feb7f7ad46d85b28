"""The public Python API: configs, the shipped surrogates, the DEM, rollouts, ensembles, design
studies, metrics and the package's errors (docs/api.md).

``import sgn_jax as sj`` gives the same names. A design study in five lines::

    import jax, sgn_jax as sj
    model = sj.load_surrogate()                       # the shipped default (contact) model
    cfg = sj.at_surrogate_step(sj.load_config("emax_300rpm"), model)  # at the model's step
    packings = sj.make_packings(cfg, seeds=range(8))  # DEM settle + first window, per seed
    study = sj.design_study(model, cfg, ["motion.rpm"], packings, duration=1.5, burn_in=0.5)
    power, grad = jax.value_and_grad(study.power)(study.theta0)   # W, W/rpm

``study.power`` is a jitted function of the flat parameter vector alone; its gradient is, by
default, the ensemble central difference with common packings (:func:`design_study`'s
``estimator``). ``study.estimate(theta)`` returns the same with standard errors;
``study.powers(theta)`` the per-packing powers without gradient work.

Each name is the object of the module that defines it: the packings, ensembles, sweeps and
design studies are :mod:`sgn_jax.pipelines.studies`, the DEM runs :mod:`sgn_jax.pipelines.dem_run`,
the shipped models :mod:`sgn_jax.records.shipped_models`. What the experiment and benchmark
scripts use beyond this list is gathered in :mod:`sgn_jax.experiment_tools`.
"""

from __future__ import annotations

from pathlib import Path

from sgn_jax.analysis.collisions import CollisionDataError, EventTable, load_events
from sgn_jax.analysis.metrics import ensemble_summary, evaluate
from sgn_jax.config import Config, ConfigError, replace_section, resolve_config
from sgn_jax.design import DesignError, default_step, parameter_unit
from sgn_jax.errors import EnvelopeWarning, SGNJaxError, SGNJaxWarning
from sgn_jax.pipelines.charge_sweep import charge_sweep, plot_charge_sweep
from sgn_jax.pipelines.configure import (
    graph_spec_from_config,
    jar_params_from_config,
    motion_from_config,
    sdf_grid_from_config,
)
from sgn_jax.pipelines.dem_run import DEMRun, run_dem, simulate_dem
from sgn_jax.pipelines.rollout_run import run_rollout
from sgn_jax.pipelines.spectra import CollisionSpectra, collision_spectra
from sgn_jax.pipelines.studies import (
    DEMEnsemble,
    DesignStudy,
    Packings,
    at_surrogate_step,
    design_config,
    design_study,
    ensemble_mean,
    make_packings,
    parameter_values_of,
    rollout_ensemble,
    rollout_sweep,
    seed_packings,
    sensitivity,
    shard_packings,
)
from sgn_jax.records.cache import enable_compilation_cache
from sgn_jax.records.checkpoint import CheckpointError, TrainedModel
from sgn_jax.records.prediction import Prediction, PredictionError, load_prediction, save_prediction
from sgn_jax.records.shipped_models import load_surrogate
from sgn_jax.records.trajectory import DatasetError, Trajectory, load_trajectory, save_trajectory
from sgn_jax.scene import Scene
from sgn_jax.surrogate.rollout import (
    RolloutError,
    RolloutResult,
    RolloutState,
    init_state,
    make_rollout,
    make_rollout_step,
)

# A design study in a new process reuses the programs compiled by an earlier one
# (sgn_jax.records.cache; off with SGN_JAX_NO_CACHE=1).
enable_compilation_cache()


def load_config(name_or_path: str | Path) -> Config:
    """A built-in config by name (``"emax_300rpm"``, ``"motion1"``, ...) or a TOML file."""
    return resolve_config(name_or_path)


__all__ = [
    # configs and the trained models
    "Config",
    "load_config",
    "replace_section",
    "TrainedModel",
    "load_surrogate",
    "at_surrogate_step",
    # the scene both simulators share, and its parts from a config
    "Scene",
    "motion_from_config",
    "jar_params_from_config",
    "graph_spec_from_config",
    "sdf_grid_from_config",
    # the DEM: in memory, to a file, packings, ensembles at design points
    "simulate_dem",
    "run_dem",
    "DEMRun",
    "make_packings",
    "seed_packings",
    "Packings",
    "DEMEnsemble",
    "charge_sweep",
    "plot_charge_sweep",
    # the surrogate rollout: the init/step pair, the whole scan, ensembles, sweeps, files
    "init_state",
    "make_rollout_step",
    "make_rollout",
    "RolloutState",
    "RolloutResult",
    "rollout_ensemble",
    "rollout_sweep",
    "shard_packings",
    "run_rollout",
    # records
    "Trajectory",
    "load_trajectory",
    "save_trajectory",
    "Prediction",
    "load_prediction",
    "save_prediction",
    # design studies: the power function and its gradient
    "design_study",
    "DesignStudy",
    "sensitivity",
    "design_config",
    "parameter_values_of",
    "parameter_unit",
    "default_step",
    "ensemble_mean",
    # metrics
    "evaluate",
    "ensemble_summary",
    # collision statistics: the events of a record, the spectra of DEM and surrogate records
    "load_events",
    "EventTable",
    "collision_spectra",
    "CollisionSpectra",
    # errors and warnings
    "SGNJaxError",
    "SGNJaxWarning",
    "EnvelopeWarning",
    "ConfigError",
    "CheckpointError",
    "DatasetError",
    "PredictionError",
    "DesignError",
    "RolloutError",
    "CollisionDataError",
]
