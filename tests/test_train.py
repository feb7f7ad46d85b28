"""SGN training: packing, loss, noise, overfitting, the training loop, resume and the CLI."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import sgn_jax  # noqa: F401
from sgn_jax.config import builtin_config_path, load_config, replace_section
from sgn_jax.pipelines.configure import graph_spec_from_config, sdf_grid_from_config
from sgn_jax.pipelines.features import featurize_trajectory, windows_from_trajectory
from sgn_jax.pipelines.train_run import read_metrics, train
from sgn_jax.surrogate.graph import make_graph_builder
from sgn_jax.surrogate.model import make_apply, make_predict
from sgn_jax.surrogate.sgn import SGN
from sgn_jax.surrogate.train import (
    BatchPacker,
    TrainingError,
    TrainState,
    add_velocity_noise,
    batch_edge_capacity,
    huber_eq30,
    loss_sums,
    lr_at,
    make_optimizer,
    make_train_step,
    norm_stats_from_dataset,
    normalize_dataset,
)
from sgn_jax.testing import random_init_weights, synthetic_trajectory

N = 8


@pytest.fixture(scope="module")
def cfg():
    c = load_config(builtin_config_path("emax_300rpm"))
    c = replace_section(c, "balls", count=N)
    c = replace_section(c, "graph", window=3)
    c = replace_section(c, "model", hidden=24)
    return replace_section(c, "train", batch_size=6, epochs=2, lr_init=2e-3, lr_final=5e-4,
                           train_time=0.008, val_time=0.003, noise_std=0.005)


@pytest.fixture(scope="module")
def grid(cfg):
    return sdf_grid_from_config(cfg)


@pytest.fixture(scope="module")
def data(cfg, grid):
    traj = synthetic_trajectory(90, N, seed=11)
    spec = graph_spec_from_config(cfg)
    ends = np.arange(spec.window, 80)
    raw = featurize_trajectory(traj, spec, grid, ends, chunk=32)
    stats = norm_stats_from_dataset(raw)
    return traj, spec, raw, stats, normalize_dataset(raw, stats)


def test_packer_covers_every_sample_once_with_static_shapes(data):
    _, _, raw, _, ds = data
    assert raw.edges_per_sample.sum() > 0 and raw.edge_is_pp.any() and (~raw.edge_is_pp).any()
    cap = batch_edge_capacity(ds.edges_per_sample, 6)
    packer = BatchPacker(ds, 6, cap)
    order = np.random.default_rng(0).permutation(len(ds))
    plan = packer.plan(order)
    np.testing.assert_array_equal(np.concatenate(plan), order)
    shapes = set()
    for idx in plan:
        b = packer.make(idx)
        shapes.add(tuple(np.shape(x) for x in jax.tree_util.tree_leaves(b)))
        assert int(b.graph.n_edge.sum()) == cap
        assert int(b.graph.n_node.sum()) == 6 * (N + 1) + 1
        assert int(b.graph_mask.sum()) == len(idx)
        real = b.graph.edges["pp"] | b.graph.edges["pw"]
        assert real.sum() == ds.edges_per_sample[idx].sum()
        assert b.graph.nodes["particle"].sum() == N * len(idx)
    assert len(shapes) == 1


def test_tight_capacity_closes_batches_early(data):
    ds = data[4]
    cap = int(ds.edges_per_sample.max()) + 2
    packer = BatchPacker(ds, 6, cap)
    plan = packer.plan(np.arange(len(ds)))
    assert all(ds.edges_per_sample[idx].sum() <= cap for idx in plan)
    assert len(plan) > int(np.ceil(len(ds) / 6))


def _assert_batches_match_single_windows(traj, spec, raw, stats, grid, idx, seed):
    """Training batches (dataset path) and the rollout's build_graph + predict agree."""
    ds = normalize_dataset(raw, stats)
    model = SGN(hidden=24)
    packer = BatchPacker(ds, 6, batch_edge_capacity(ds.edges_per_sample, 6))
    batch = packer.make(idx)
    params = random_init_weights(model, batch.graph, seed)   # numpy: no eager init
    accel_b, de_b = jax.jit(make_apply(model))(params, batch.graph)
    predict = jax.jit(make_predict(model))
    builder = make_graph_builder(None, spec)
    wins, _, _ = windows_from_trajectory(traj, spec.window, ends=raw.window_end[idx])
    graphs, _ = builder(jax.tree_util.tree_map(jnp.asarray, wins), grid)
    for k in range(len(idx)):
        g = jax.tree_util.tree_map(lambda a, k=k: a[k], graphs)
        accel, de = predict(params, stats, g)
        rows = slice(k * (N + 1), k * (N + 1) + N)
        accel_phys = np.asarray(accel_b[rows]) * stats.accel.std + stats.accel.mean
        np.testing.assert_allclose(np.asarray(accel[:N]), accel_phys, rtol=1e-4, atol=1e-3)
        de_phys = float(de_b[k]) * stats.dissipation.std[0] + stats.dissipation.mean[0]
        np.testing.assert_allclose(float(de[0]), de_phys, rtol=1e-4)


@pytest.mark.parametrize("encoding", ["absolute", "differences"])
@pytest.mark.slow
def test_batch_predictions_equal_the_single_window_path(data, grid, encoding):
    """Training batches (dataset path) and the rollout's build_graph + predict agree."""
    traj, spec, raw, _, _ = data
    stats = norm_stats_from_dataset(raw, encoding)
    _assert_batches_match_single_windows(traj, spec, raw, stats, grid,
                                         np.array([3, 40, 17, 60]), 2)


def test_huber_is_paper_eq30():
    e = jnp.array([-5.0, -2.0, -0.5, 0.0, 1.0, 1.999, 3.0])
    expected = np.where(np.abs(e) < 2, np.asarray(e) ** 2 / 4, np.abs(e) - 1)
    np.testing.assert_allclose(np.asarray(huber_eq30(e, 2.0)), expected, rtol=1e-6)


@pytest.mark.slow
def test_loss_ignores_padding_and_noise_touches_only_ball_velocities(data):
    ds = data[4]
    model = SGN(hidden=24)
    packer = BatchPacker(ds, 6, batch_edge_capacity(ds.edges_per_sample, 6))
    batch = packer.make(np.array([1, 2]))  # 2 of 6 slots used
    params = random_init_weights(model, batch.graph, 0)
    apply = make_apply(model)
    sums = np.asarray(loss_sums(apply, params, batch, 2.0))
    assert sums[1] == 2 * N * 3 and sums[3] == 2
    accel, de = np.array(batch.accel), np.array(batch.dissipation)
    accel[2 * (N + 1):] = 99.0  # unused slots and the padding graph
    accel[N] = 99.0  # the wall row
    de[2:] = -99.0
    garbage = batch.replace(accel=accel, dissipation=de)
    np.testing.assert_array_equal(np.asarray(loss_sums(apply, params, garbage, 2.0)), sums)

    noisy = add_velocity_noise(batch.graph, jax.random.PRNGKey(0), 0.005, 3)
    diff = np.asarray(noisy.nodes["features"] - batch.graph.nodes["features"])
    changed_rows, changed_cols = np.nonzero(diff)
    assert set(changed_cols) == {0, 1, 2, 7, 8, 9, 14, 15, 16}
    assert np.all(np.asarray(batch.graph.nodes["particle"])[changed_rows])
    assert 0.003 < diff[diff != 0].std() < 0.007


def test_lr_schedule_is_exponential_between_the_ends():
    assert lr_at(0.0, 1e-4, 1e-6) == pytest.approx(1e-4)
    assert lr_at(1.0, 1e-4, 1e-6) == pytest.approx(1e-6)
    assert lr_at(0.5, 1e-4, 1e-6) == pytest.approx(1e-5)


@pytest.fixture(scope="module")
def tiny_batch(data):
    """One batch of 12 samples, for the two tests that train SGN(hidden=32) on it: their
    weight-1 train steps are then the same program, compiled once."""
    ds = data[4]
    sub = np.arange(0, 48, 4)  # 12 samples
    packer = BatchPacker(ds, 12, batch_edge_capacity(ds.edges_per_sample, 12))
    return packer.make(sub)


@pytest.mark.slow
def test_tiny_model_overfits_tiny_dataset(tiny_batch):
    batch = tiny_batch
    model = SGN(hidden=32)
    apply = make_apply(model)
    tx = make_optimizer(3e-3)
    params = random_init_weights(model, batch.graph, 0)
    state = TrainState(params=params, opt_state=tx.init(params), step=jnp.asarray(0))
    cfg = type("T", (), {"node_loss_weight": 3.0, "global_loss_weight": 1.0, "huber_delta": 2.0,
                         "noise_std": 0.0})
    step = make_train_step(apply, tx, cfg, 3)
    key = jax.random.PRNGKey(0)

    def total(sums):
        return 3.0 * sums[0] / sums[1] + sums[2] / sums[3]

    first = None
    for i in range(300):
        state, sums = step(state, batch, np.float32(lr_at(i / 300, 3e-3, 3e-4)), key)
        first = float(total(sums)) if first is None else first
    # the final loss as one program, not ~100 eager op compiles of the forward pass
    final = float(total(jax.jit(loss_sums, static_argnums=(0, 3))(apply, state.params, batch,
                                                                  2.0)))
    assert final < first / 10, (first, final)


@pytest.mark.slow
def test_no_global_loss_leaves_the_global_readout_untrained(tiny_batch):
    """global_loss_weight = 0 (the paper's appendix ablation): the dE head gets no gradient,
    so Adam leaves its parameters exactly as initialised, while the rest of the network moves.
    (The model and batch of test_tiny_model_overfits_tiny_dataset: the weight-1 step is its
    program, not compiled again.)"""
    batch = tiny_batch
    model = SGN(hidden=32)
    apply = make_apply(model)
    tx = make_optimizer(1e-3)
    params = random_init_weights(model, batch.graph, 0)
    before = jax.tree_util.tree_map(np.asarray, params)
    for weight, head_moves in ((0.0, False), (1.0, True)):
        state = TrainState(params=params, opt_state=tx.init(params), step=jnp.asarray(0))
        cfg = type("T", (), {"node_loss_weight": 3.0, "global_loss_weight": weight,
                             "huber_delta": 2.0, "noise_std": 0.0})
        step = make_train_step(apply, tx, cfg, 3)
        for _ in range(3):
            state, _ = step(state, batch, np.float32(1e-3), jax.random.PRNGKey(0))
        after = state.params
        head = jax.tree_util.tree_leaves(jax.tree_util.tree_map(
            lambda a, b: np.abs(np.asarray(a) - b).max(), after["global_readout"],
            before["global_readout"]))
        decoder = jax.tree_util.tree_leaves(jax.tree_util.tree_map(
            lambda a, b: np.abs(np.asarray(a) - b).max(), after["decoder"],
            before["decoder"]))
        assert (max(head) > 0) == head_moves, (weight, head)
        assert max(decoder) > 0


@pytest.mark.slow
def test_train_writes_metrics_checkpoints_and_resumes_identically(cfg, grid, tmp_path):
    from sgn_jax.records.checkpoint import load_trained_model

    trajs = [synthetic_trajectory(120, N, seed=s) for s in (1, 2)]
    quiet = {"sdf": grid, "progress": False, "log": lambda m: None}
    straight = tmp_path / "straight"
    summary = train(cfg, trajs, straight, epochs=3, **quiet)
    assert summary["epochs"] == 3 and summary["n_train"] > 0 and summary["n_val"] > 0
    rows = read_metrics(straight)
    assert [r["epoch"] for r in rows] == [1, 2, 3]
    assert all(np.isfinite(r["train_loss"]) and np.isfinite(r["val_loss"]) for r in rows)
    assert (straight / "metrics.csv").read_text().count("\n") == 4
    assert (straight / "loss.png").stat().st_size > 1000
    assert rows[-1]["lr"] == pytest.approx(cfg.train.lr_final, rel=0.3)

    with pytest.raises(TrainingError, match="--resume"):
        train(cfg, trajs, straight, epochs=4, **quiet)

    # Interrupt a 3-epoch run after its second epoch, then resume it.
    def interrupt_after_epoch_2(message):
        if '"epoch": 2' in message:
            raise KeyboardInterrupt

    split = tmp_path / "split"
    with pytest.raises(KeyboardInterrupt):
        train(cfg, trajs, split, epochs=3, sdf=grid, progress=False, log=interrupt_after_epoch_2)
    assert [r["epoch"] for r in read_metrics(split)] == [1, 2]
    train(cfg, trajs, split, epochs=3, resume=True, **quiet)
    rows_split = read_metrics(split)
    assert [r["epoch"] for r in rows_split] == [1, 2, 3]
    a = load_trained_model(straight, "latest")
    b = load_trained_model(split, "latest")
    for x, y in zip(jax.tree_util.tree_leaves(a.params), jax.tree_util.tree_leaves(b.params),
                    strict=True):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-5, atol=1e-7)
    assert rows_split[-1]["train_loss"] == pytest.approx(rows[-1]["train_loss"], rel=1e-4)

    best = load_trained_model(straight, "best")
    best_epoch = min(rows, key=lambda r: r["val_loss"])["epoch"]
    assert best.meta["epoch"] == best_epoch
    assert best.config.model.hidden == 24


def test_train_refuses_data_that_do_not_match_the_config(cfg, grid, tmp_path):
    traj = synthetic_trajectory(60, N + 1, seed=0)
    with pytest.raises(TrainingError, match="balls"):
        train(cfg, [traj], tmp_path / "x", sdf=grid, progress=False, log=lambda m: None)


@pytest.mark.slow
def test_cli_train_on_trajectory_files(cfg, tmp_path):
    from sgn_jax.cli import main
    from sgn_jax.config import save_config
    from sgn_jax.records.trajectory import build_meta, save_trajectory

    paths = []
    for seed in (3, 4):
        s = synthetic_trajectory(120, N, seed=seed)
        t_len = len(s.t)
        zeros = np.zeros(t_len)
        arrays = {"t": s.t, "pos": s.pos, "vel": np.zeros_like(s.pos),
                  "omega": np.zeros_like(s.pos), "offset": s.offset, "offset_vel": s.offset_vel,
                  "diss_pp_normal": s.diss_pp_normal, "diss_pp_tangential": s.diss_pp_tangential,
                  "diss_pw_normal": s.diss_pw_normal, "diss_pw_tangential": s.diss_pw_tangential,
                  "ke_trans": zeros, "ke_rot": zeros, "pe_grav": zeros, "e_elastic": zeros,
                  "work_wall": zeros, "pp_pairs": -np.ones((t_len, 4, 2), np.int64),
                  "pw_contact": np.zeros((t_len, N), bool)}
        for kind in ("pp", "pw"):
            for extra in ("slip", "rolling"):
                arrays[f"diss_{kind}_{extra}"] = zeros
        path = tmp_path / f"traj{seed}.npz"
        save_trajectory(path, arrays, build_meta(cfg, seed=seed))
        paths.append(str(path))
    cfg_path = tmp_path / "cfg.toml"
    save_config(cfg, cfg_path)
    out = tmp_path / "run"
    argv = ["train", "--config", str(cfg_path), "--data", ",".join(paths), "--out", str(out),
            "--epochs", "1", "--quiet"]
    assert main(argv) == 0
    assert [r["epoch"] for r in read_metrics(out)] == [1]
    assert main(argv) == 2  # an existing run needs --resume
    assert main(argv[:-2] + ["2", "--resume", "--quiet"]) == 0
    assert [r["epoch"] for r in read_metrics(out)] == [1, 2]
    info = json.loads((out / "run_info.json").read_text())
    # Windows end at n = W .. 79 (target step ends at t[n + 1] <= train_time = 80 dt).
    assert info["n_train"] == 2 * (79 - 3 + 1)
    assert main(["train", "--config", str(cfg_path), "--data", str(tmp_path / "nope.npz"),
                 "--out", str(out / "x")]) == 2


# The slow tier: [graph] contact_features is arm C of the envelope study, an SGN
# variant no shipped model uses (docs/envelope.md).
@pytest.mark.slow
def test_contact_features_train_batches_equal_the_single_window_path(data, grid):
    """With [graph] contact_features the 5-column edges pack, normalise and predict the same in
    a training batch as in the rollout's build_graph + predict path."""
    import dataclasses

    traj, spec0, _, _, _ = data
    spec = dataclasses.replace(spec0, contact_features=True)
    raw = featurize_trajectory(traj, spec, grid, np.arange(spec.window, 80), chunk=32)
    assert raw.edge_features.shape[1] == 5
    stats = norm_stats_from_dataset(raw, "differences")
    assert np.asarray(stats.pp_edge.mean).shape == (5,)
    _assert_batches_match_single_windows(traj, spec, raw, stats, grid, np.array([5, 33, 71]), 3)
