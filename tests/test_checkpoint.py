"""Orbax checkpoints: exact round trip, optimiser state, clear errors for missing or damaged ones."""

import json
import re
import shutil
import warnings
from pathlib import Path

import jax
import numpy as np
import pytest

import sgn_jax  # noqa: F401
from sgn_jax.config import builtin_config_path, config_to_dict, load_config, replace_section
from sgn_jax.pipelines.features import windows_from_trajectory
from sgn_jax.records.checkpoint import (
    DIGEST_FILE,
    CheckpointError,
    CheckpointIntegrityWarning,
    latest_step,
    load_trained_model,
    restore_checkpoint,
    save_checkpoint,
    verify_checkpoint_digest,
    write_checkpoint_digest,
)
from sgn_jax.surrogate.graph import GraphSpec, build_graph
from sgn_jax.surrogate.model import make_model, make_predict
from sgn_jax.surrogate.normalization import compute_norm_stats
from sgn_jax.surrogate.train import make_optimizer
from sgn_jax.testing import random_init_weights, synthetic_trajectory

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
    params = random_init_weights(model, g, 4)
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


@pytest.mark.slow
def test_optimiser_state_round_trip_and_keep(setup, tmp_path):
    params = setup[4]
    tx = make_optimizer(1e-3)
    # jitted: two programs instead of ~50 eager op compiles
    init = jax.jit(tx.init)
    opt_state = init(params)
    grads = jax.tree_util.tree_map(lambda p: 0.01 * np.ones_like(p), params)
    _, opt_state = jax.jit(tx.update)(grads, opt_state, params)
    for step in (1, 2, 3):
        _save(setup, tmp_path / "ck", step, opt_state=opt_state, keep=2)
    assert latest_step(tmp_path / "ck") == 3
    assert sorted(int(p.name) for p in (tmp_path / "ck").iterdir() if p.name.isdigit()) == [2, 3]
    restored = restore_checkpoint(tmp_path / "ck", opt_state_like=init(params))
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
        restore_checkpoint(tmp_path / "noopt",
                           opt_state_like=jax.jit(make_optimizer(1e-3).init)(setup[4]))


def _data_files(step_dir: Path, item: str):
    return sorted(p for p in (step_dir / item).rglob("*") if p.is_file()
                  and p.parent.name == "d" and p.stat().st_size > 0)


@pytest.mark.parametrize("legacy", [False, True], ids=["digest", "no_digest"])
@pytest.mark.parametrize("damage, message", [
    ("flip_bytes", "cannot read checkpoint"), ("truncate", "cannot read checkpoint"),
    ("delete_item", "norm"), ("bad_meta", "corrupt: parameter digest mismatch")])
def test_damaged_checkpoint_is_refused(setup, tmp_path, damage, message, legacy):
    """With the file digest the damaged file is named; without it (a checkpoint written before
    sgn_digest.json) orbax's read errors and the pytree digests still refuse it."""
    step_dir = _save(setup, tmp_path / "ck")
    if legacy:
        (step_dir / DIGEST_FILE).unlink()
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
        if not legacy:
            message = r"is damaged: 1/params/(ocdbt\.process_0/)?d/[0-9a-f]+ "
    elif damage == "delete_item":
        shutil.rmtree(step_dir / "norm")
        if not legacy:
            message = r"is damaged: 1/norm/\S+ is missing"
    else:
        meta_files = [p for p in (step_dir / "meta").rglob("*") if p.is_file()
                      and p.suffix != ".txt" and not p.name.startswith("_")]
        assert meta_files
        meta = json.loads(meta_files[0].read_text())
        meta["params_digest"] = "0" * 64
        meta_files[0].write_text(json.dumps(meta))
        if not legacy:
            message = "is damaged: 1/meta/metadata"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore" if legacy else "error")
        with pytest.raises(CheckpointError, match=message):
            restore_checkpoint(tmp_path / "ck")


# --- file digest (sgn_digest.json): every file of a step, checked before orbax reads it ---


@pytest.fixture(scope="module")
def saved(setup, tmp_path_factory):
    """One intact checkpoint; tests damage copies of it."""
    directory = tmp_path_factory.mktemp("saved") / "ck"
    _save(setup, directory)
    return directory


def _copy(saved, tmp_path):
    target = tmp_path / "ck"
    shutil.copytree(saved, target)
    return target


def test_checkpoint_error_is_an_sgn_jax_error():
    from sgn_jax.errors import SGNJaxError

    assert issubclass(CheckpointError, SGNJaxError) and issubclass(CheckpointError, RuntimeError)


def test_intact_checkpoint_is_verified_and_loads(setup, saved, tmp_path):
    ck = _copy(saved, tmp_path)
    step_dir = ck / "1"
    digest = json.loads((step_dir / DIGEST_FILE).read_text())
    names = set(digest["files"])
    # orbax's own files are covered, not only the data files
    for name in ("_CHECKPOINT_METADATA", "meta/metadata", "params/manifest.ocdbt",
                 "params/_METADATA", "params/ocdbt.process_0/manifest.ocdbt", "norm/_METADATA"):
        assert name in names, name
    assert any(n.startswith("params/ocdbt.process_0/d/") for n in names)
    assert all(len(v["sha256"]) == 64 and v["size"] >= 0 for v in digest["files"].values())
    # the extra file does not disturb orbax's listing of steps
    assert latest_step(ck) == 1
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        restored = restore_checkpoint(ck)
    assert restored.step == 1
    assert verify_checkpoint_digest(step_dir) is True  # restoring wrote nothing into the step


@pytest.mark.parametrize("name", ["contact", "contact_rebound", "contact_collisions",
                                  "contact_charge", "emax_300rpm", "envelope"])
def test_shipped_model_verifies(name):
    from sgn_jax.records.shipped_models import registry, shipped_model_dir

    assert name in registry().names
    ck = Path(shipped_model_dir(name))
    steps = [p for p in ck.iterdir() if p.is_dir() and p.name.isdigit()]
    assert len(steps) == 1 and (steps[0] / DIGEST_FILE).is_file()
    assert verify_checkpoint_digest(steps[0]) is True


@pytest.mark.parametrize("manifest", ["params/manifest.ocdbt",
                                      "params/ocdbt.process_0/manifest.ocdbt",
                                      "norm/ocdbt.process_0/manifest.ocdbt"])
def test_truncated_manifest_is_named(saved, tmp_path, manifest):
    ck = _copy(saved, tmp_path)
    path = ck / "1" / manifest
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(CheckpointError) as info:
        restore_checkpoint(ck)
    msg = str(info.value)
    assert f"1/{manifest} has {len(data) // 2} bytes, expected {len(data)} (truncated)" in msg
    assert str(ck) in msg and "re-train" in msg


def test_flipped_byte_in_data_file_is_named(saved, tmp_path):
    ck = _copy(saved, tmp_path)
    path = max(_data_files(ck / "1", "params"), key=lambda p: p.stat().st_size)
    data = bytearray(path.read_bytes())
    data[len(data) // 3] ^= 0x01
    path.write_bytes(bytes(data))
    rel = path.relative_to(ck).as_posix()
    with pytest.raises(CheckpointError, match=rf"{rel} does not match its SHA-256 digest"):
        restore_checkpoint(ck)


@pytest.mark.parametrize("legacy", [False, True], ids=["digest", "no_digest"])
def test_emptied_meta_is_named(saved, tmp_path, legacy):
    ck = _copy(saved, tmp_path)
    if legacy:
        (ck / "1" / DIGEST_FILE).unlink()
    (ck / "1" / "meta" / "metadata").write_bytes(b"")
    expected = ("1/meta/metadata is not valid JSON (empty file)" if legacy
                else "1/meta/metadata has 0 bytes")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(CheckpointError, match=re.escape(f"{ck} is damaged: {expected}")):
            restore_checkpoint(ck)


def test_extra_file_or_bad_digest_file_is_refused(saved, tmp_path):
    ck = _copy(saved, tmp_path)
    (ck / "1" / "params" / "d" / "stray").write_bytes(b"x")
    with pytest.raises(CheckpointError, match="1/params/d/stray is not part of the checkpoint"):
        restore_checkpoint(ck)
    (ck / "1" / "params" / "d" / "stray").unlink()
    (ck / "1" / DIGEST_FILE).write_text("{")
    with pytest.raises(CheckpointError, match=f"1/{DIGEST_FILE} is unreadable"):
        restore_checkpoint(ck)


def test_checkpoint_without_digest_loads_with_warning(saved, tmp_path):
    ck = _copy(saved, tmp_path)
    (ck / "1" / DIGEST_FILE).unlink()
    with pytest.warns(CheckpointIntegrityWarning, match="integrity cannot be verified"):
        restored = restore_checkpoint(ck)
    assert restored.step == 1
    write_checkpoint_digest(ck / "1")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        restore_checkpoint(ck)


def test_damaged_shipped_model_says_reinstall(saved, tmp_path, monkeypatch):
    import sgn_jax.records.checkpoint as checkpoint

    ck = _copy(saved, tmp_path)
    monkeypatch.setattr(checkpoint, "_SHIPPED_MODELS_DIR", tmp_path.resolve())
    (ck / "1" / "meta" / "metadata").write_bytes(b"")
    with pytest.raises(CheckpointError, match="re-install the package"):
        restore_checkpoint(ck)


def test_the_collision_model_is_the_contact_model_at_half_the_step_with_the_wall_rebound():
    """``contact_collisions`` (docs/collisions.md): the default's network at half its step,
    with the law rebound exact at the wall and the per-contact dissipation target; it loads
    and its damping shares are the tangential ones (a probability each)."""
    from sgn_jax.records.checkpoint import load_trained_model
    from sgn_jax.records.shipped_models import resolve_checkpoint

    default = load_trained_model(resolve_checkpoint(None))
    model = load_trained_model(resolve_checkpoint("contact_collisions"))
    m = model.config.model
    assert (m.kind, m.law_rebound, m.law_rebound_exact, m.damping_target) == (
        "contact", True, "wall", "contact")
    assert float(model.config.dem.dt) == pytest.approx(0.5 * float(default.config.dem.dt))
    assert (m.hidden, m.mlp_layers, m.spin) == (default.config.model.hidden,
                                                default.config.model.mlp_layers, True)
    shares = jax.nn.sigmoid(np.asarray(model.params["share_logit"]))
    assert np.all((shares > 0.5) & (shares < 1.0))


def test_the_charge_model_reads_the_charge_at_half_the_step_and_states_its_envelope():
    """``contact_charge`` (docs/contact_charge.md): the charge-conditioned kind at 1e-4 s with
    spin, the sweeps and the law rebound; its checkpoint states the charge envelope it covers
    (diameters 6-15 mm, densities 2,600-7,800 kg/m^3, restitution 0.3-0.8) and the motions."""
    from sgn_jax.records.checkpoint import load_trained_model
    from sgn_jax.records.shipped_models import resolve_checkpoint

    model = load_trained_model(resolve_checkpoint("contact_charge"))
    m = model.config.model
    assert (m.kind, m.spin, m.law_rebound) == ("contact_charge", True, True)
    assert m.overlap_sweeps > 0 and m.friction_sweeps > 0
    assert float(model.config.dem.dt) == pytest.approx(1e-4)
    charge = model.meta["envelope"]["charge"]
    assert charge["diameter"] == [0.006, 0.015] and charge["density"] == [2600.0, 7800.0]
    assert charge["restitution"] == [0.3, 0.8] and charge["fill"] == [0.05, 0.2]
    assert model.meta["envelope"]["circle_rpm"] == [150.0, 500.0]   # the motion envelope too


def test_the_rebound_model_is_the_contact_model_with_the_law_rebound():
    """``contact_rebound`` (docs/collisions.md) differs from the default only by the rule and
    its fine-tuned weights: same network, same step, the rule on."""
    from sgn_jax.records.checkpoint import load_trained_model
    from sgn_jax.records.shipped_models import resolve_checkpoint

    default = load_trained_model(resolve_checkpoint(None))
    rebound = load_trained_model(resolve_checkpoint("contact_rebound"))
    assert rebound.config.model.law_rebound and not default.config.model.law_rebound
    assert rebound.config.model.kind == default.config.model.kind == "contact"
    assert float(rebound.config.dem.dt) == float(default.config.dem.dt)
    assert (rebound.config.graph, rebound.config.model.hidden) == (
        default.config.graph, default.config.model.hidden)
