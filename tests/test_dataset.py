"""Tests of sgn_jax.records.trajectory: the docs/conventions.md section 4 trajectory file, its round
trip and every refusal."""

import jax.numpy as jnp
import numpy as np
import pytest

from sgn_jax.config import builtin_config_path, load_config, replace_section
from sgn_jax.records.trajectory import (
    REQUIRED_ARRAYS,
    REQUIRED_META,
    DatasetError,
    Trajectory,
    build_meta,
    load_trajectory,
    save_trajectory,
    validate_trajectory,
)

T, N, K = 20, 4, 3
DT = 1e-4
DISS = [f"diss_{w}_{k}" for w in ("pp", "pw") for k in ("normal", "tangential", "slip", "rolling")]


def _config():
    cfg = load_config(builtin_config_path("emax_300rpm"))
    return replace_section(cfg, "balls", count=N)


def make_valid(seed: int = 0):
    """A small synthetic trajectory that satisfies docs/conventions.md section 4 (values random,
    energy balance exact)."""
    rng = np.random.default_rng(seed)
    arrays = {
        "t": np.arange(T) * DT,
        "pos": rng.normal(0, 0.01, (T, N, 3)),
        "vel": rng.normal(0, 0.5, (T, N, 3)),
        "omega": rng.normal(0, 50, (T, N, 3)),
        "offset": rng.normal(0, 0.01, (T, 3)),
        "offset_vel": rng.normal(0, 0.5, (T, 3)),
        "ke_trans": rng.uniform(0, 1e-2, T),
        "ke_rot": rng.uniform(0, 1e-3, T),
        "pe_grav": rng.uniform(0, 1e-2, T),
        "e_elastic": rng.uniform(0, 1e-4, T),
        "pp_pairs": np.full((T, K, 2), -1, dtype=np.int32),
        "pw_contact": rng.uniform(size=(T, N)) < 0.5,
    }
    arrays["pp_pairs"][:, 0] = [0, 1]
    arrays["pp_pairs"][5:9, 1] = [2, 3]
    for name in DISS:
        values = rng.uniform(0, 1e-4, T)
        values[0] = 0.0
        arrays[name] = values
    total_diss = np.cumsum(sum(arrays[name] for name in DISS))
    # work_wall such that the docs/conventions.md section 4 energy balance holds exactly (up to
    # 0.3 J of constant)
    arrays["work_wall"] = (arrays["ke_trans"] + arrays["ke_rot"] + arrays["pe_grav"]
                           + arrays["e_elastic"] + total_diss - 0.3)
    arrays["extra_per_sample"] = rng.normal(size=(T, 2))
    arrays["extra_static"] = np.arange(7)
    meta = build_meta(_config(), seed=11, extra={"note": "synthetic", "material": {"e": 0.3}})
    return arrays, meta


# ---------------------------------------------------------------------------------------------
# Round trip and conveniences


def test_round_trip_bit_identical(round_trip):
    traj = round_trip(save_trajectory, load_trajectory, *make_valid())
    assert isinstance(traj, Trajectory) and traj["vel"] is traj.arrays["vel"]
    assert traj.n_samples == T and traj.n_balls == N and traj.dt == DT
    assert traj.config == _config()
    assert traj.meta["ball_mass"] == pytest.approx(4 / 3 * np.pi * 0.005**3 * 7700, rel=1e-12)
    assert traj.meta["seed"] == 11 and traj.meta["n_balls"] == N
    with pytest.raises(AttributeError, match="no attribute or array 'poss'"):
        _ = traj.poss


def test_save_accepts_jax_arrays_and_compression(tmp_path):
    arrays, meta = make_valid()
    arrays["pos"] = jnp.asarray(arrays["pos"])
    save_trajectory(tmp_path / "c.npz", arrays, meta, compress=True)
    traj = load_trajectory(tmp_path / "c.npz")
    np.testing.assert_array_equal(traj.pos, np.asarray(arrays["pos"]))
    assert traj.pos.dtype == np.float64


def _saved_and_loaded(tmp_path):
    """(arrays, trajectory): a valid trajectory saved as tmp_path / "a.npz" and loaded back."""
    arrays, meta = make_valid()
    save_trajectory(tmp_path / "a.npz", arrays, meta)
    return arrays, load_trajectory(tmp_path / "a.npz")


def test_cumulative_dissipation_and_energy_balance(tmp_path):
    arrays, traj = _saved_and_loaded(tmp_path)
    target = np.cumsum(arrays["diss_pp_normal"] + arrays["diss_pp_tangential"]
                       + arrays["diss_pw_normal"] + arrays["diss_pw_tangential"])
    np.testing.assert_allclose(traj.cumulative_dissipation(), target, rtol=1e-15)
    assert traj.cumulative_dissipation()[0] == 0.0
    np.testing.assert_allclose(traj.cumulative_dissipation("slip", "pw"),
                               np.cumsum(arrays["diss_pw_slip"]), rtol=1e-15)
    everything = np.cumsum(sum(arrays[name] for name in DISS))
    np.testing.assert_allclose(traj.cumulative_dissipation("all", "all"), everything, rtol=1e-14)
    np.testing.assert_allclose(traj.energy_balance(), 0.0, atol=1e-15)
    with pytest.raises(ValueError, match="elastic"):
        traj.cumulative_dissipation("normal+elastic")
    with pytest.raises(ValueError, match="which"):
        traj.cumulative_dissipation(which="pp+wall")


def test_slice(tmp_path):
    arrays, traj = _saved_and_loaded(tmp_path)
    part = traj.slice(5, 12)
    assert part.n_samples == 7
    np.testing.assert_array_equal(part.t, arrays["t"][5:12])
    np.testing.assert_array_equal(part.pos, arrays["pos"][5:12])
    np.testing.assert_array_equal(part.extra_per_sample, arrays["extra_per_sample"][5:12])
    np.testing.assert_array_equal(part.extra_static, arrays["extra_static"])
    assert part.diss_pp_normal[0] == 0.0
    np.testing.assert_array_equal(part.diss_pp_normal[1:], arrays["diss_pp_normal"][6:12])
    full = traj.cumulative_dissipation()
    np.testing.assert_allclose(part.cumulative_dissipation(), full[5:12] - full[5], rtol=1e-12)
    validate_trajectory(part.arrays, part.meta)  # a slice is itself a valid trajectory
    assert part.meta["sliced_from"] == {"path": str(tmp_path / "a.npz"), "start": 5, "stop": 12}
    assert traj.diss_pp_normal[5] != 0.0  # the original is untouched
    assert traj.slice(-3, None).n_samples == 3
    with pytest.raises(ValueError, match="empty"):
        traj.slice(10, 10)


def test_coarsen_keeps_states_and_sums_dissipation(tmp_path):
    arrays, traj = _saved_and_loaded(tmp_path)
    coarse = traj.coarsen(3)                       # samples 0, 3, ..., 18 of 20
    kept = np.arange(0, T, 3)
    assert coarse.n_samples == kept.size
    assert coarse.dt == pytest.approx(3 * DT, rel=1e-12)
    assert coarse.meta["config"]["dem"]["dt"] == pytest.approx(3 * DT, rel=1e-12)
    np.testing.assert_array_equal(coarse.pos, arrays["pos"][kept])
    np.testing.assert_array_equal(coarse.work_wall, arrays["work_wall"][kept])
    np.testing.assert_array_equal(coarse.extra_per_sample, arrays["extra_per_sample"][kept])
    np.testing.assert_array_equal(coarse.extra_static, arrays["extra_static"])
    # each coarse interval holds the three fine intervals that end at its sample
    assert coarse.diss_pw_slip[0] == 0.0
    assert coarse.diss_pw_slip[2] == pytest.approx(arrays["diss_pw_slip"][4:7].sum(), rel=1e-12)
    np.testing.assert_allclose(coarse.cumulative_dissipation("all", "all"),
                               traj.cumulative_dissipation("all", "all")[kept], rtol=1e-12)
    validate_trajectory(coarse.arrays, coarse.meta)   # a valid trajectory at 3 dt
    np.testing.assert_allclose(coarse.energy_balance(), traj.energy_balance()[kept], atol=1e-12)
    assert traj.at_step(DT) is traj
    assert traj.at_step(2 * DT).n_samples == 10
    with pytest.raises(DatasetError, match="not an integer multiple"):
        traj.at_step(1.5 * DT)
    with pytest.raises(ValueError, match="integer >= 1"):
        traj.coarsen(0)


def test_build_meta_has_required_keys():
    meta = build_meta(_config())
    assert set(REQUIRED_META) <= set(meta)
    assert meta["dt_dem"] == pytest.approx(1e-4 / 106, rel=1e-12)
    assert meta["seed"] == 0
    assert set(REQUIRED_ARRAYS) >= {"t", "pos", "pp_pairs", "pw_contact", *DISS}


# ---------------------------------------------------------------------------------------------
# Refusals


def _set(name, value_fn):
    def corrupt(arrays, meta):
        arrays[name] = value_fn(arrays[name])
        return arrays, meta
    return corrupt


def _drop(name):
    def corrupt(arrays, meta):
        del arrays[name]
        return arrays, meta
    return corrupt


def _meta(key, value=None, delete=False):
    def corrupt(arrays, meta):
        if delete:
            del meta[key]
        else:
            meta[key] = value
        return arrays, meta
    return corrupt


def _with_nan(index):
    def fn(a):
        a = a.copy()
        a[index] = np.nan
        return a
    return fn


def _shift_t(a):
    a = a.copy()
    a[6:] += 3e-6
    return a


def _first_nonzero(a):
    a = a.copy()
    a[0] = 1e-6
    return a


def _bad_pair(a):
    a = a.copy()
    a[3, 2] = [0, N]
    return a


CORRUPTIONS = {
    "missing array": (_drop("omega"), r"missing array\(s\) \['omega'\]"),
    "wrong shape": (_set("pos", lambda a: a[..., :2]),
                    r"'pos'.*shape \(20, 4, 2\), expected \(T, N, 3\) = \(20, 4, 3\).*wrong shape"),
    "inconsistent T": (_set("vel", lambda a: a[:-1]),
                       r"'vel'.*shape \(19, 4, 3\).*\(20, 4, 3\).*inconsistent sizes"),
    "inconsistent N": (_set("pw_contact", lambda a: np.concatenate([a, a[:, :1]], axis=1)),
                       r"'pw_contact'.*shape \(20, 5\).*\(20, 4\).*inconsistent"),
    "pos float32": (_set("pos", lambda a: a.astype(np.float32)),
                    r"'pos' has dtype float32, expected float64.*astype\(np.float64\)"),
    "vel float32": (_set("vel", lambda a: a.astype(np.float32)), r"'vel' has dtype float32"),
    "pairs float": (_set("pp_pairs", lambda a: a.astype(np.float64)),
                    r"'pp_pairs' has dtype float64, expected int"),
    "contact int": (_set("pw_contact", lambda a: a.astype(np.int8)),
                    r"'pw_contact' has dtype int8, expected bool"),
    "nan vel": (_set("vel", _with_nan((7, 2, 1))), r"'vel' contains NaN or inf, first at sample 7"),
    "inf energy": (_set("ke_rot", lambda a: np.where(np.arange(T) >= 3, np.inf, a)),
                   r"'ke_rot' contains NaN or inf, first at sample 3"),
    "nan extra": (_set("extra_per_sample", _with_nan((12, 0))),
                  r"'extra_per_sample' contains NaN or inf, first at sample 12"),
    "t gap": (_set("t", _shift_t), r"'t' is not uniformly spaced.*t\[6\] - t\[5\]"),
    "wrong dt": (_meta("dt", 2e-4), r"'t' is not uniformly spaced by meta\['dt'\] = 0.0002"),
    "diss first": (_set("diss_pw_rolling", _first_nonzero),
                   r"'diss_pw_rolling' must be 0 at the first sample"),
    "pair range": (_set("pp_pairs", _bad_pair), r"'pp_pairs' holds indices outside \[-1, N\)"),
    "meta missing key": (_meta("seed", delete=True), r"meta is missing key\(s\) \['seed'\]"),
    "meta not object": (lambda arrays, meta: (arrays, [1, 2]),
                        r"meta must be a JSON object \(dict\), got list"),
    "meta bad created": (_meta("created", "yesterday"), r"meta\['created'\] must be an ISO 8601"),
    "meta bad dt": (_meta("dt", -1.0), r"meta\['dt'\] must be a positive number"),
    "meta config not dict": (_meta("config", "emax"), r"meta\['config'\] must be a dict"),
    "n_balls mismatch": (_meta("n_balls", 5), r"meta\['n_balls'\] = 5 but 'pos' has N = 4"),
}


@pytest.mark.parametrize("case", sorted(CORRUPTIONS))
def test_load_refuses_corrupted_trajectory(tmp_path, write_raw_npz, case):
    corrupt, message = CORRUPTIONS[case]
    arrays, meta = corrupt(*make_valid())
    path = write_raw_npz(tmp_path / "bad.npz", arrays, meta)
    with pytest.raises(DatasetError, match=message) as info:
        load_trajectory(path)
    assert str(path) in str(info.value)  # the message names the file
    # save refuses the same input and writes nothing
    with pytest.raises(DatasetError, match=message):
        save_trajectory(tmp_path / "refused.npz", arrays, meta)
    assert not (tmp_path / "refused.npz").exists()


def test_load_refuses_unreadable_file(load_refuses_unreadable):
    # once per case of the fixture: missing, not a zip, corrupt, no meta entry, ...
    load_refuses_unreadable(save_trajectory, load_trajectory, DatasetError, *make_valid(),
                            kind="trajectory", produce="sgn-jax dem --config CONFIG.toml")


def test_save_refuses_bad_path_meta_and_config(tmp_path):
    arrays, meta = make_valid()
    with pytest.raises(DatasetError, match=r"must end in '\.npz'"):
        save_trajectory(tmp_path / "traj.h5", arrays, meta)
    with pytest.raises(DatasetError, match="reserved"):
        save_trajectory(tmp_path / "m.npz", dict(arrays, meta=np.zeros(1)), meta)
    bad_config = dict(meta, config=dict(meta["config"], balls={"count": N, "radius": 0.005}))
    with pytest.raises(DatasetError, match=r"not a valid config.*balls\.density"):
        save_trajectory(tmp_path / "c.npz", arrays, bad_config)
    with pytest.raises(DatasetError, match="not JSON serialisable"):
        save_trajectory(tmp_path / "j.npz", arrays, dict(meta, note=object()))
    assert list(tmp_path.iterdir()) == []


def test_loaded_config_error_is_reported(tmp_path, write_raw_npz):
    arrays, meta = make_valid()
    meta["config"] = {"case": {"name": "x"}}  # a dict, but not a whole config
    path = write_raw_npz(tmp_path / "cfg.npz", arrays, meta)
    traj = load_trajectory(path)  # loading does not need the config...
    with pytest.raises(DatasetError, match=r"cfg\.npz': meta\['config'\] is not a valid config"):
        _ = traj.config  # ...but asking for it says what is wrong
