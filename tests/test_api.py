"""The public API at the package root: ``import sgn_jax as sj`` (docs/api.md).

The root module loads :mod:`sgn_jax.api` only when a public name is first used (PEP 562), so
``import sgn_jax`` stays light; every public name is the same object as in ``sgn_jax.api``.
"""

from __future__ import annotations

import subprocess
import sys

import pytest

import sgn_jax
import sgn_jax.api as api


def test_the_root_imports_no_package_module():
    code = ("import sys, sgn_jax; "
            "print(sorted(m for m in sys.modules if m.startswith('sgn_jax')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout
    assert out.strip() == "['sgn_jax']"


def test_every_public_name_resolves_to_the_api_object():
    names = [n for n in sgn_jax.__all__ if n != "__version__"]
    assert len(names) == len(set(names)) >= 25
    for name in names:
        assert name in api.__all__, name
        assert getattr(sgn_jax, name) is getattr(api, name), name


def test_the_api_exports_what_it_lists():
    assert len(api.__all__) == len(set(api.__all__))
    for name in api.__all__:
        assert hasattr(api, name), name


def test_dir_lists_the_public_names():
    listed = dir(sgn_jax)
    for name in sgn_jax.__all__:
        assert name in listed, name


def test_an_unknown_attribute_raises_attribute_error():
    with pytest.raises(AttributeError, match="no_such_name"):
        sgn_jax.no_such_name  # noqa: B018
    # submodules still import through the root (the import system falls back to them)
    from sgn_jax import regime

    assert regime.REGIME_WINDOW_S == api.REGIME_WINDOW_S


def test_the_issue_s_entry_points_are_public():
    """Config, the shipped model, the DEM (in memory and to a file), the rollout (init/step
    pair, whole scan, files), records, the design study, metrics and the regime classifier."""
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
    # the regime classifier: sgn_jax.regime, re-exported by sgn_jax.api
    assert api.classify_state(0.3, api.AGITATED_SPEED_M_S) == "agitated"
    assert api.regime_of(15 / 24) == "bed" and api.regime_of(10 / 24) == "agitated"
    assert issubclass(api.EnvelopeWarning, sj.SGNJaxWarning)
    assert issubclass(sj.SGNJaxWarning, sj.SGNJaxError)
    assert issubclass(api.EnvelopeWarning, UserWarning)


def test_regime_windows_follow_the_contact_rule():
    import numpy as np

    contacts = np.array([0] + [20] * 10 + [5] * 10)  # sample 0 is left out
    states, length = api.regime_windows(contacts, 24, 2.0)
    assert states == ["bed", "agitated"] and length == 1.0
    states, length = api.regime_windows(contacts, 24, 2.0, window_s=2.0)
    assert states == ["agitated"] and length == 2.0  # 12.5 contacts on average < 14
