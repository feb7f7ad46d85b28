"""sgn-jax: a differentiable SDF graph-network surrogate and a Hertz-Mindlin DEM for ball mills.

The public API (docs/api.md)::

    import sgn_jax as sj
    model = sj.load_surrogate()
    cfg = sj.at_surrogate_step(sj.load_config("emax_300rpm"), model)
    packings = sj.make_packings(cfg, seeds=range(8))
    study = sj.design_study(model, cfg, ["motion.rpm"], packings)

Its names (``__all__``) are those of :mod:`sgn_jax.api`, loaded on first use (PEP 562 module
``__getattr__``): ``import sgn_jax`` itself imports no package module, so the pure core
(:mod:`sgn_jax.motion`, :mod:`sgn_jax.dem`, ...) imports nothing through the root and
``import sgn_jax.motion`` stays light.

Importing the package enables 64-bit floats in JAX (``jax_enable_x64``): the DEM runs in
float64 by default and the surrogate's finite-difference features need float64 positions.
Every module therefore passes explicit dtypes; the surrogate casts to float32 itself. This is
the one process-wide setting the package touches, and it must happen before any array is made.
"""

import importlib
from typing import Any

import jax

jax.config.update("jax_enable_x64", True)

__version__ = "0.1.0"

__all__ = [
    "__version__",
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

_API_MODULE = "sgn_jax.api"


def __getattr__(name: str) -> Any:
    """A public name of :mod:`sgn_jax.api`, imported on first access and cached here."""
    if name in __all__:
        value = getattr(importlib.import_module(_API_MODULE), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
