"""Tests of sgn_jax.records.prediction: the rollout prediction file, its round trip and every
refusal."""

import numpy as np
import pytest

from sgn_jax.config import builtin_config_path, config_to_dict, load_config
from sgn_jax.records.prediction import (
    REQUIRED_ARRAYS,
    REQUIRED_META,
    Prediction,
    PredictionError,
    load_prediction,
    save_prediction,
    validate_prediction,
)

S, P, N = 30, 4, 5
DT = 1e-4
T_START = 0.25  # s: the rollout starts a quarter second into the motion


def make_valid(seed=0):
    rng = np.random.default_rng(seed)
    d_e = rng.uniform(0, 1e-4, S)
    arrays = {
        "t_step": T_START + DT * np.arange(1, S + 1),
        "dE": d_e,
        "energy_cum": np.cumsum(d_e),
        "n_pp_edges": rng.integers(0, 20, S) * 2,
        "n_pw_edges": rng.integers(0, 10, S),
        "overflow": np.zeros(S, dtype=np.int64),
        "n_outside": np.zeros(S, dtype=np.int32),
        "n_snapped": rng.integers(0, 2, S),
        "t_pos": T_START + DT * np.array([0, 10, 20, 30]),
        "pos": rng.normal(0, 0.01, (P, N, 3)),
        "offset": rng.normal(0, 0.01, (P, 3)),
        "wall_time_per_step": rng.uniform(size=S),  # an extra array: kept
    }
    meta = {"dt": DT, "save_every": 10, "init_index": 2500,
            "config": config_to_dict(load_config(builtin_config_path("emax_300rpm"))),
            "checkpoint": "ckpt/step_100", "created": "2025-01-01T00:00:00+00:00"}
    return arrays, meta


def test_round_trip(round_trip):
    pred = round_trip(save_prediction, load_prediction, *make_valid())
    assert isinstance(pred, Prediction)
    assert (pred.n_steps, pred.n_frames, pred.n_balls) == (S, P, N)
    assert pred.dt == DT and pred.t_start == pytest.approx(T_START, abs=1e-15)
    assert pred.config.balls.count == 24
    assert set(REQUIRED_ARRAYS) <= set(dir(pred))


def test_float32_times_and_jax_arrays_are_accepted(tmp_path):
    import jax.numpy as jnp

    arrays, meta = make_valid()
    arrays["t_step"] = arrays["t_step"].astype(np.float32)  # a float32 clock at t ~ 0.25 s
    arrays["dE"] = jnp.asarray(arrays["dE"], dtype=jnp.float32)
    arrays["energy_cum"] = jnp.cumsum(arrays["dE"])
    save_prediction(tmp_path / "p.npz", arrays, meta)
    assert load_prediction(tmp_path / "p.npz").dE.dtype == np.float32


def _refuse(arrays, meta, match):
    with pytest.raises(PredictionError, match=match):
        validate_prediction(arrays, meta)


def test_required_names_and_meta_keys():
    arrays, meta = make_valid()
    for name in REQUIRED_ARRAYS:
        broken = {k: v for k, v in arrays.items() if k != name}
        _refuse(broken, meta, rf"missing array\(s\) \['{name}'\]")
    for key in REQUIRED_META:
        _refuse(arrays, {k: v for k, v in meta.items() if k != key},
                rf"meta is missing key\(s\) \['{key}'\]")
    _refuse({**arrays, "meta": np.array("{}")}, meta, "'meta' is reserved")
    _refuse(arrays, [1, 2], "meta must be a JSON object")


@pytest.mark.parametrize("key, value, match", [
    ("dt", -1e-4, r"meta\['dt'\] .* must be a positive number"),
    ("dt", True, r"meta\['dt'\]"),
    ("save_every", 0, r"meta\['save_every'\] .* integer >= 1"),
    ("save_every", 2.0, r"meta\['save_every'\]"),
    ("init_index", -1, r"meta\['init_index'\]"),
    ("init_index", True, r"meta\['init_index'\]"),
    ("config", "emax.toml", r"meta\['config'\] must be a dict"),
])
def test_bad_meta_values(key, value, match):
    arrays, meta = make_valid()
    _refuse(arrays, {**meta, key: value}, match)


@pytest.mark.parametrize("name, change, match", [
    ("dE", lambda a: a[:-1], r"'dE' .* has shape \(29,\), expected \(S,\) = \(30,\)"),
    ("pos", lambda a: a[:, :, :2], r"'pos' .* has shape \(4, 5, 2\)"),
    ("offset", lambda a: a[:3], r"'offset' .* expected \(P, 3\) = \(4, 3\)"),
    ("pos", lambda a: a.astype(np.float32), r"'pos' has dtype float32, expected float64"),
    ("n_outside", lambda a: a.astype(np.float64), r"'n_outside' has dtype float64, expected int"),
    ("t_step", lambda a: a[:0], r"'t_step' must have shape \(S,\) with S >= 1"),
    ("t_pos", lambda a: a[:0], r"P >= 1 saved frames"),
])
def test_bad_shapes_and_dtypes(name, change, match):
    arrays, meta = make_valid()
    arrays[name] = change(arrays[name])
    _refuse(arrays, meta, match)


def test_non_finite_and_negative_counts():
    arrays, meta = make_valid()
    arrays["pos"] = arrays["pos"].copy()
    arrays["pos"][2, 1, 0] = np.nan
    _refuse(arrays, meta, r"'pos' contains NaN or inf, first at index 2; the rollout diverged")
    arrays, meta = make_valid()
    arrays["overflow"] = arrays["overflow"].copy()
    arrays["overflow"][7] = -3
    _refuse(arrays, meta, r"'overflow' is a count but holds a negative value -3 at step 7")


def test_time_grids():
    arrays, meta = make_valid()
    dropped = arrays["t_step"].copy()
    dropped[10:] += DT  # a step missing after step 9
    _refuse({**arrays, "t_step": dropped}, meta,
            r"'t_step' is not uniformly spaced by meta\['dt'\] = 0.0001 s: t_step\[10\]")
    _refuse(arrays, {**meta, "dt": 2 * DT}, r"not uniformly spaced by meta\['dt'\] = 0.0002")
    off_grid = arrays["t_pos"] + 0.5 * DT
    _refuse({**arrays, "t_pos": off_grid}, meta, r"'t_pos' must hold times on the step grid")
    beyond = arrays["t_pos"] + np.array([0, 0, 0, DT])  # step 31 of 30
    _refuse({**arrays, "t_pos": beyond}, meta, r"on the step grid")
    before = arrays["t_pos"] - np.array([DT, 0, 0, 0])  # before the rollout's start
    _refuse({**arrays, "t_pos": before}, meta, r"on the step grid")
    _refuse({**arrays, "t_pos": arrays["t_pos"][::-1].copy()}, meta, "strictly increasing")


def test_energy_cum_must_be_running_sum():
    arrays, meta = make_valid()
    _refuse({**arrays, "energy_cum": arrays["dE"]}, meta,
            "'energy_cum' is not the running sum of 'dE'")
    _refuse({**arrays, "energy_cum": arrays["energy_cum"] + 1e-3}, meta, "not the running sum")
    # a float32 accumulation's rounding is fine
    save_ok = {**arrays, "energy_cum": np.cumsum(arrays["dE"].astype(np.float32))}
    validate_prediction(save_ok, meta)


def test_save_refuses_and_writes_nothing(tmp_path):
    arrays, meta = make_valid()
    with pytest.raises(PredictionError, match="must end in '.npz'"):
        save_prediction(tmp_path / "pred.npy", arrays, meta)
    bad = {**arrays, "dE": arrays["dE"][:-1]}
    with pytest.raises(PredictionError, match="'dE'"):
        save_prediction(tmp_path / "pred.npz", bad, meta)
    bad_config = {**meta, "config": {"case": {"name": "x"}}}
    with pytest.raises(PredictionError, match=r"meta\['config'\] is not a valid config"):
        save_prediction(tmp_path / "pred.npz", arrays, bad_config)
    with pytest.raises(PredictionError, match="not JSON serialisable"):
        save_prediction(tmp_path / "pred.npz", arrays, {**meta, "extra": object()})
    assert list(tmp_path.iterdir()) == []


def test_load_refuses_unreadable_file(load_refuses_unreadable):
    load_refuses_unreadable(save_prediction, load_prediction, PredictionError, *make_valid(),
                            kind="prediction", produce="sgn-jax rollout")


def test_load_refuses_bad_content(tmp_path, write_raw_npz):
    arrays, meta = make_valid()
    broken = {**arrays, "n_snapped": arrays["n_snapped"][:5]}
    with pytest.raises(PredictionError, match=r"badshape.npz'.*'n_snapped'"):
        load_prediction(write_raw_npz(tmp_path / "badshape.npz", broken, meta))
    traj_like = {"t": np.arange(3) * DT, "pos": np.zeros((3, 2, 3)),
                 "pp_pairs": -np.ones((3, 1, 2), dtype=int)}
    with pytest.raises(PredictionError, match="is a DEM trajectory file .* not a rollout"):
        load_prediction(write_raw_npz(tmp_path / "traj.npz", traj_like, {"dt": DT}))
