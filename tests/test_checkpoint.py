"""Orbax checkpoints: exact round trip, optimiser state, clear errors for missing or damaged ones."""

import json
from pathlib import Path

import jax
import numpy as np
import pytest

import sgn_jax  # noqa: F401
from sgn_jax.checkpoint import (
    CheckpointError,
    latest_step,
    load_trained_model,
    restore_checkpoint,
    save_checkpoint,
)
from sgn_jax.config import builtin_config_path, config_to_dict, load_config, replace_section
from sgn_jax.graph import GraphSpec, build_graph, windows_from_trajectory
from sgn_jax.model import init_params, make_model, make_predict
from sgn_jax.normalization import compute_norm_stats
from sgn_jax.train import make_optimizer, synthetic_trajectory

N = 6


def _sphere_query(_, points, offset):
    """A spherical cavity of radius 3 cm centred 2 cm above the jar origin."""
    import jax.numpy as jnp

    d = jnp.asarray(points) - jnp.asarray(offset) - jnp.array([0.0, 0.02, 0.0])
    r = jnp.linalg.norm(d, axis=-1)
    return r - 0.03, d / r[..., None]


@pytest.fixture(scope="module")
def setup():
    cfg = load_config(builtin_config_path("emax_300rpm"))
    cfg = replace_section(cfg, "model", hidden=16)
    spec = GraphSpec(n_particles=N, window=3, ball_radius=0.005, dt=1e-4, pp_pair_capacity=8)
    wins, accel, de = windows_from_trajectory(synthetic_trajectory(20, N, seed=2), 3)
    build = jax.jit(lambda w: build_graph(w, None, spec, _sphere_query))
    graphs = [build(jax.tree_util.tree_map(lambda a, k=k: a[k], wins))[0] for k in (0, 5, 9)]
    g = graphs[0]
    stats = compute_norm_stats(np.asarray(g.nodes["features"][:N]),
                               np.asarray(g.nodes["features"][N:N + 1]),
                               np.asarray(g.edges["features"])[np.asarray(g.edges["pp"])],
                               np.asarray(g.edges["features"])[np.asarray(g.edges["pw"])],
                               accel.reshape(-1, 3), de, velocity_encoding="differences")
    model = make_model(cfg.model)
    params = init_params(model, g, 4)
    return cfg, graphs, stats, model, params


def _save(setup, directory, step=1, **kw):
    cfg, _, stats, _, params = setup
    return save_checkpoint(directory, step, params=params, norm_stats=stats,
                           meta={"config": config_to_dict(cfg), "epoch": step}, **kw)


def test_save_restore_gives_bit_identical_predictions(setup, tmp_path):
    cfg, graphs, stats, model, params = setup
    _save(setup, tmp_path / "ck")
    restored = restore_checkpoint(tmp_path / "ck")
    predict = jax.jit(make_predict(model))
    for g in graphs:
        a1, e1 = predict(params, stats, g)
        a2, e2 = predict(restored.params, restored.norm_stats, g)
        np.testing.assert_array_equal(np.asarray(a1), np.asarray(a2))
        np.testing.assert_array_equal(np.asarray(e1), np.asarray(e2))
    assert restored.meta["epoch"] == 1 and restored.step == 1
    assert restored.norm_stats.velocity_encoding == "differences"

    loaded = load_trained_model(tmp_path / "ck")
    assert loaded.config == cfg
    a3, _ = jax.jit(loaded.predict_fn())(loaded.params, loaded.norm_stats, graphs[1])
    np.testing.assert_array_equal(np.asarray(a3), np.asarray(predict(params, stats, graphs[1])[0]))


def test_optimiser_state_round_trip_and_keep(setup, tmp_path):
    params = setup[4]
    tx = make_optimizer(1e-3)
    opt_state = tx.init(params)
    grads = jax.tree_util.tree_map(lambda p: 0.01 * np.ones_like(p), params)
    _, opt_state = tx.update(grads, opt_state, params)
    for step in (1, 2, 3):
        _save(setup, tmp_path / "ck", step, opt_state=opt_state, keep=2)
    assert latest_step(tmp_path / "ck") == 3
    assert sorted(int(p.name) for p in (tmp_path / "ck").iterdir() if p.name.isdigit()) == [2, 3]
    restored = restore_checkpoint(tmp_path / "ck", opt_state_like=tx.init(params))
    assert jax.tree_util.tree_structure(restored.opt_state) == jax.tree_util.tree_structure(
        opt_state)
    for a, b in zip(jax.tree_util.tree_leaves(restored.opt_state),
                    jax.tree_util.tree_leaves(opt_state), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    with pytest.raises(CheckpointError, match="no step 1"):
        restore_checkpoint(tmp_path / "ck", step=1)


def test_missing_or_empty_checkpoint_is_a_clear_error(setup, tmp_path):
    with pytest.raises(CheckpointError, match="no checkpoint directory"):
        restore_checkpoint(tmp_path / "nothing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(CheckpointError, match="no complete checkpoint"):
        restore_checkpoint(tmp_path / "empty")
    with pytest.raises(CheckpointError, match="no checkpoint directory"):
        load_trained_model(tmp_path / "nothing")
    _save(setup, tmp_path / "noopt")
    with pytest.raises(CheckpointError, match="no optimiser state"):
        restore_checkpoint(tmp_path / "noopt", opt_state_like=make_optimizer(1e-3).init(setup[4]))


def _data_files(step_dir: Path, item: str):
    return sorted(p for p in (step_dir / item).rglob("*") if p.is_file()
                  and p.parent.name == "d" and p.stat().st_size > 0)


@pytest.mark.parametrize("damage, message", [
    ("flip_bytes", "cannot read checkpoint"), ("truncate", "cannot read checkpoint"),
    ("delete_item", "norm"), ("bad_meta", "corrupt: parameter digest mismatch")])
def test_damaged_checkpoint_is_refused(setup, tmp_path, damage, message):
    step_dir = _save(setup, tmp_path / "ck")
    if damage in ("flip_bytes", "truncate"):
        files = _data_files(step_dir, "params")
        assert files, "expected orbax data files under params/"
        for path in files:
            data = bytearray(path.read_bytes())
            if damage == "truncate":
                data = data[: len(data) // 2]
            else:
                for i in range(len(data) // 2, len(data), 97):
                    data[i] ^= 0xFF
            path.write_bytes(bytes(data))
    elif damage == "delete_item":
        import shutil

        shutil.rmtree(step_dir / "norm")
    else:
        meta_files = [p for p in (step_dir / "meta").rglob("*") if p.is_file()
                      and p.suffix != ".txt" and not p.name.startswith("_")]
        assert meta_files
        meta = json.loads(meta_files[0].read_text())
        meta["params_digest"] = "0" * 64
        meta_files[0].write_text(json.dumps(meta))
    with pytest.raises(CheckpointError, match=message):
        restore_checkpoint(tmp_path / "ck")
