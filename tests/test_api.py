"""The public API: ``import sgn_jax as sj`` is ``sgn_jax.api`` (docs/api.md).

The root module loads :mod:`sgn_jax.api` only when a public name is first used (PEP 562), so
``import sgn_jax`` stays light; every public name is the same object as in ``sgn_jax.api``.
What the experiment scripts use beyond it is :mod:`sgn_jax.experiment_tools`.
"""

from __future__ import annotations

import subprocess
import sys

import pytest

import sgn_jax
import sgn_jax.api as api
import sgn_jax.experiment_tools as tools


def test_the_root_imports_no_package_module():
    code = ("import sys, sgn_jax; "
            "print(sorted(m for m in sys.modules if m.startswith('sgn_jax')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout
    assert out.strip() == "['sgn_jax']"


def test_the_root_and_the_api_list_the_same_names():
    names = [n for n in sgn_jax.__all__ if n != "__version__"]
    assert len(names) == len(set(names))
    assert names == api.__all__
    for name in names:
        assert getattr(sgn_jax, name) is getattr(api, name), name


def test_the_api_is_of_its_own_size():
    """The public API holds what a user calls (load, simulate, rollout, ensembles, design
    studies, sweeps, metrics, errors); the experiment scripts' helpers are not in it."""
    assert 40 <= len(api.__all__) <= 60
    assert not set(api.__all__) & set(tools.__all__)
    for name in ("load_config", "load_surrogate", "at_surrogate_step", "make_packings",
                 "design_study", "simulate_dem", "rollout_ensemble", "rollout_sweep",
                 "DEMEnsemble", "evaluate", "SGNJaxError"):
        assert name in api.__all__, name
    for name in ("write_json", "git_commit", "select_cases", "sgn_jax_command", "build_graph"):
        assert name in tools.__all__ and name not in api.__all__, name


def test_each_module_exports_what_it_lists():
    for module in (api, tools):
        assert len(module.__all__) == len(set(module.__all__)), module.__name__
        for name in module.__all__:
            assert hasattr(module, name), f"{module.__name__}.{name}"


def test_replace_section_is_the_config_module_s():
    from sgn_jax.config import replace_section

    assert api.replace_section is replace_section


def test_dir_lists_the_public_names():
    listed = dir(sgn_jax)
    for name in sgn_jax.__all__:
        assert name in listed, name


def test_an_unknown_attribute_raises_attribute_error():
    with pytest.raises(AttributeError, match="no_such_name"):
        sgn_jax.no_such_name  # noqa: B018
    with pytest.raises(AttributeError, match="write_json"):
        sgn_jax.write_json  # noqa: B018   (an experiment helper, not public)
    # submodules still import through the root (the import system falls back to them)
    from sgn_jax import regime

    assert regime.REGIME_WINDOW_S == tools.REGIME_WINDOW_S


def test_the_entry_points_are_public():
    """Config, the shipped model, the DEM (in memory and to a file), the rollout (init/step
    pair, whole scan, files), records, the design study, metrics and the errors."""
    from sgn_jax.pipelines.dem_run import run_dem
    from sgn_jax.pipelines.rollout_run import run_rollout
    from sgn_jax.surrogate.rollout import init_state, make_rollout, make_rollout_step

    sj = sgn_jax
    assert sj.run_dem is run_dem and sj.run_rollout is run_rollout
    assert sj.init_state is init_state and sj.make_rollout_step is make_rollout_step
    assert sj.make_rollout is make_rollout
    for name in ("load_config", "load_surrogate", "simulate_dem", "load_trajectory",
                 "save_trajectory", "load_prediction", "save_prediction", "design_study",
                 "sensitivity", "evaluate", "ensemble_summary"):
        assert callable(getattr(sj, name)), name
    for error in (sj.ConfigError, sj.CheckpointError, sj.DatasetError, sj.PredictionError,
                  sj.DesignError, sj.RolloutError, sj.SGNJaxWarning, sj.EnvelopeWarning):
        assert issubclass(error, sj.SGNJaxError), error
    assert issubclass(sj.EnvelopeWarning, sj.SGNJaxWarning)
    assert issubclass(sj.EnvelopeWarning, UserWarning)


def test_the_regime_rules_classify_as_documented():
    import numpy as np

    from sgn_jax.regime import AGITATED_SPEED_M_S, classify_state, regime_of, regime_windows

    assert classify_state(0.3, AGITATED_SPEED_M_S) == "agitated"
    assert regime_of(15 / 24) == "bed" and regime_of(10 / 24) == "agitated"
    contacts = np.array([0] + [20] * 10 + [5] * 10)  # sample 0 is left out
    states, length = regime_windows(contacts, 24, 2.0)
    assert states == ["bed", "agitated"] and length == 1.0
    states, length = regime_windows(contacts, 24, 2.0, window_s=2.0)
    assert states == ["agitated"] and length == 2.0  # 12.5 contacts on average < 14
