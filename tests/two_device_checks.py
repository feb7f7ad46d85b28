"""The two-device checks of tests/test_sharding.py (sharded ensembles, data-parallel
training), run in a process of their own with two host CPU devices (``XLA_FLAGS=
--xla_force_host_platform_device_count=2`` must be set before JAX starts, so the rest of the
suite keeps one device).

``python tests/two_device_checks.py CHECK [CHECK ...]`` runs the named checks in this one
process and prints one JSON line ``{CHECK: result, ...}``; the tests assert on the results.
The default run's checks (``ensemble``, ``step``) share one process per test session
(conftest.py's ``two_device_results``: one JAX start); the slow tier's
(``ensemble_study``, ``loop``) run in processes of their own.

Checks:
    ensemble: the sharded ensemble rollout against each packing rolled out alone
        (tests/test_sharding.py says what "the same" means, measured);
    ensemble_study: the same plus the one-device batch, the mapped ensemble and the design
        study sharded (value and gradient);
    step: the data-parallel training step and evaluation against one device on the same
        samples, with SGD and with Adam (tests/test_sharding.py);
    loop: the training loop with ``[train] devices = 2``: runs, checkpoints, loads.
"""

from __future__ import annotations

import json
import sys


def ensemble(study: bool = False) -> dict:
    import dataclasses

    import jax
    import numpy as np

    import sgn_jax.api as sj
    from sgn_jax.config import replace_section

    assert len(jax.devices()) == 2, jax.devices()
    cfg = replace_section(sj.load_config("emax_300rpm"), "dem", settle_time=0.02)
    model = sj.load_surrogate("emax_300rpm")   # the paper-setting SGN, at the case's 1e-4 s
    packings = sj.make_packings(cfg, seeds=[0, 1])
    placed = sj.shard_packings(packings.windows)
    devices = sorted(str(d) for d in placed.positions.sharding.device_set)
    sharded = sj.rollout_ensemble(model, cfg, packings, 0.01, shard=True)
    p0 = p1 = float("nan")
    g0 = g1 = [float("nan")]
    mapped_diff = batched_diff = float("nan")
    if study:  # the one-device batch, the mapped ensemble and the design study (slow tier)
        plain = sj.rollout_ensemble(model, cfg, packings, 0.01)
        batched_diff = float(np.max(np.abs(plain.positions - sharded.positions)))
        mapped = sj.rollout_ensemble(model, cfg, packings, 0.01, shard=True, batching="map")
        mapped_diff = float(np.max(np.abs(plain.positions - mapped.positions)))
        # The horizon estimator: its gradient runs through the sharded placement (the
        # default difference estimator only runs forward: a difference of two powers that
        # the batch's rounding, amplified by the chaos, moves by more than the difference).
        study = sj.design_study(model, cfg, ["motion.rpm"], packings, duration=0.02,
                                burn_in=0.01, n_segments=1, estimator="horizon")
        study_sharded = sj.design_study(model, cfg, ["motion.rpm"], packings, duration=0.02,
                                        burn_in=0.01, n_segments=1, estimator="horizon",
                                        shard=True)
        p0, g0 = jax.value_and_grad(study.power)(study.theta0)
        p1, g1 = jax.value_and_grad(study_sharded.power)(study_sharded.theta0)
    singles = []
    for k in range(2):
        one = dataclasses.replace(packings, seeds=packings.seeds[k:k + 1],
                                  windows=jax.tree_util.tree_map(lambda a, k=k: a[k:k + 1],
                                                                 packings.windows))
        singles.append(sj.rollout_ensemble(model, cfg, one, 0.01))
    alone = np.concatenate([r.positions for r in singles])
    alone_energy = np.concatenate([r.steps.energy_cum[:, -1] for r in singles])
    try:
        sj.shard_packings(jax.tree_util.tree_map(lambda a: a[:1], packings.windows))
        odd = "no error"
    except sj.DesignError as exc:
        odd = str(exc)
    return {
        "devices": devices,
        "max_pos_diff": batched_diff,
        "max_pos_diff_alone": float(np.max(np.abs(alone - sharded.positions))),
        "energy_alone": np.asarray(alone_energy).tolist(),
        "energy_sharded": np.asarray(sharded.steps.energy_cum[:, -1]).tolist(),
        "power": [float(p0), float(p1)], "grad": [float(g0[0]), float(g1[0])], "odd": odd,
        "max_pos_diff_mapped": mapped_diff}


def step() -> dict:
    import jax
    import jax.numpy as jnp
    import numpy as np
    import optax

    import sgn_jax  # noqa: F401  (x64)
    from sgn_jax.surrogate.model import init_params, make_apply
    from sgn_jax.surrogate.sgn import SGN
    from sgn_jax.surrogate.train import (
        BatchPacker,
        DataParallel,
        GraphDataset,
        ShardedPacker,
        TrainState,
        batch_edge_capacity,
        evaluate,
        make_eval_step,
        make_optimizer,
        make_train_step,
    )

    assert len(jax.devices()) == 2, jax.devices()
    rng = np.random.default_rng(0)
    S, N, F = 40, 6, 21
    n_edges = rng.poisson(20, S)
    E = int(n_edges.sum())
    ds = GraphDataset(
        node_features=rng.standard_normal((S, N + 1, F), np.float32),
        edge_offsets=np.concatenate([[0], np.cumsum(n_edges)]).astype(np.int64),
        edge_features=rng.standard_normal((E, 3), np.float32),
        edge_senders=rng.integers(0, N + 1, E).astype(np.int32),
        edge_receivers=rng.integers(0, N, E).astype(np.int32), edge_is_pp=rng.random(E) < 0.7,
        accel=rng.standard_normal((S, N, 3), np.float32),
        dissipation=rng.standard_normal(S).astype(np.float32),
        source=np.zeros(S, np.int32), window_end=np.arange(S))
    g = 4
    cap = batch_edge_capacity(ds.edges_per_sample, g)
    dp = DataParallel.over(2)
    sharded_packer = ShardedPacker(BatchPacker(ds, g, cap), 2)
    one_packer = BatchPacker(ds, 2 * g, 2 * cap)          # one batch holding a step's samples
    model = SGN(hidden=16)
    apply = make_apply(model)
    cfg = type("T", (), {"node_loss_weight": 3.0, "global_loss_weight": 1.0, "huber_delta": 2.0,
                         "noise_std": 0.0})
    # (jitted: one compile instead of hundreds of eager ops; the weights are random either way)
    params0 = jax.tree_util.tree_map(
        np.array, jax.jit(lambda g: init_params(model, g))(one_packer.make(np.arange(8)).graph))
    plan = sharded_packer.plan(np.random.default_rng(1).permutation(S))
    key = jax.random.PRNGKey(0)
    out = {"plan": [[len(i) for i in group] for group in plan]}
    # The evaluation steps do not depend on the optimizer: compiled once for both.
    eval1, eval2 = make_eval_step(apply, cfg), make_eval_step(apply, cfg, dp)

    def fresh(tx):
        p = jax.tree_util.tree_map(np.array, params0)
        return TrainState(params=p, opt_state=tx.init(p), step=jnp.asarray(0))

    def max_diff(a, b):
        return max(float(np.max(np.abs(np.asarray(x) - np.asarray(y))))
                   for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b),
                                   strict=True))

    for name, tx in (("sgd", optax.inject_hyperparams(optax.sgd)(learning_rate=1e-3)),
                     ("adam", make_optimizer(1e-3))):
        one, rev, two = fresh(tx), fresh(tx), dp.replicate(fresh(tx))
        step1 = make_train_step(apply, tx, cfg, 3)
        step2 = make_train_step(apply, tx, cfg, 3, sharding=dp)
        sums_rel = 0.0
        for group in plan[:5]:
            idx = np.concatenate(group)
            one, s1 = step1(one, one_packer.make(idx), np.float32(1e-3), key)
            rev, _ = step1(rev, one_packer.make(idx[::-1]), np.float32(1e-3), key)
            two, s2 = step2(two, sharded_packer.make(group), np.float32(1e-3), key)
            sums_rel = max(sums_rel, float(np.max(np.abs(np.asarray(s1) - np.asarray(s2))
                                                  / np.abs(np.asarray(s1)))))
        leaf = jax.tree_util.tree_leaves(two.params)[0]
        out[name] = {"sharded": max_diff(one.params, two.params),
                     "reordered": max_diff(one.params, rev.params),
                     "moved": max_diff(one.params, params0), "sums_rel": sums_rel,
                     "replicated": leaf.sharding.is_fully_replicated,
                     "devices": len(leaf.sharding.device_set), "step": int(two.step)}
        ev1 = evaluate(eval1, one.params, one_packer, 3.0)
        ev2 = evaluate(eval2, one.params, sharded_packer, 3.0)
        out[name]["eval"] = [ev1["loss"], ev2["loss"]]
    return out


def loop() -> dict:
    import tempfile
    from pathlib import Path

    from sgn_jax.config import builtin_config_path, load_config, replace_section
    from sgn_jax.pipelines.configure import sdf_grid_from_config
    from sgn_jax.pipelines.train_run import read_metrics, train
    from sgn_jax.records.checkpoint import load_trained_model
    from sgn_jax.testing import synthetic_trajectory

    c = load_config(builtin_config_path("emax_300rpm"))
    c = replace_section(c, "balls", count=8)
    c = replace_section(c, "graph", window=3)
    c = replace_section(c, "model", hidden=12)
    c = replace_section(c, "train", batch_size=6, epochs=2, lr_init=2e-3, lr_final=5e-4,
                        train_time=0.008, val_time=0.003)
    with tempfile.TemporaryDirectory() as tmp:
        summary = train(c, [synthetic_trajectory(120, 8, seed=3)], tmp, devices=2,
                        sdf=sdf_grid_from_config(c), progress=False, log=lambda m: None)
        rows = read_metrics(Path(tmp))
        trained = load_trained_model(tmp, "latest")
        return {"devices": summary["devices"], "config_devices": trained.config.train.devices,
                "max_graphs": summary["max_graphs_per_batch"],
                "losses": [[r["train_loss"], r["val_loss"]] for r in rows],
                "n_params": summary["n_params"]}


CHECKS = {"ensemble": ensemble, "ensemble_study": lambda: ensemble(study=True), "step": step,
          "loop": loop}


def run_in_two_device_process(checks, *, timeout: float = 900) -> dict:
    """Run ``checks`` (names of :data:`CHECKS`) in one fresh two-device process; their results
    by name. The package's cache is the test session's folder (conftest.py), so the packings
    of seeds 0 and 1 that other tests settled are read, not settled again (bit-identical
    either way); outside a test session it is off."""
    import os
    import subprocess

    session = os.environ.get("SGN_JAX_TEST_SESSION_DIR")
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2",
               SGN_JAX_NO_CACHE="1")
    if session:
        env.update(SGN_JAX_NO_CACHE="0", SGN_JAX_CACHE_DIR=session)
    proc = subprocess.run([sys.executable, __file__, *checks], env=env, capture_output=True,
                          text=True, timeout=timeout)
    assert proc.returncode == 0, proc.stderr[-4000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


if __name__ == "__main__":
    print(json.dumps({name: CHECKS[name]() for name in sys.argv[1:]}))
