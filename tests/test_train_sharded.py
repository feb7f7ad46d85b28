"""Data-parallel training (sgn_jax.surrogate.train.DataParallel) gives the one-device update.

As in tests/test_sharding.py the check runs in a fresh process with two host CPU devices
(``XLA_FLAGS=--xla_force_host_platform_device_count=2`` must be set before JAX starts), so the
rest of the suite keeps one device.

What "the same" means, measured (hidden 16, 5 steps at lr 1e-3, 2 x 4 graphs per step, no
noise): the sharded step sums the two devices' gradients, the one-device step sums over one
batch of the same 8 samples, so they differ only in float32 summation order. With plain SGD
the parameters differ by 2.9e-11 after 5 steps, exactly as much as the one-device step on the
same samples in reverse order. Adam divides each gradient component by its own running RMS, so
a component that is nearly zero by cancellation (rounding noise ~1e-9 against eps = 1e-8)
turns its rounding into a visible update: the parameters differ by 1.6e-6 (one device on the
reversed samples: 1.7e-6). Tolerances: 1e-9 with SGD, 1e-5 with Adam (1 % of one step's lr).
SGD is the sharp check (Adam is blind to a gradient's scale): a gradient counted once per
device instead of once moved the SGD parameters by 2.8e-4.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

SCRIPT = r"""
import json
import jax, jax.numpy as jnp, numpy as np, optax
import sgn_jax
from sgn_jax.surrogate.model import init_params, make_apply
from sgn_jax.surrogate.sgn import SGN
from sgn_jax.surrogate.train import (BatchPacker, DataParallel, GraphDataset, ShardedPacker,
                                    TrainState, batch_edge_capacity, evaluate, make_eval_step,
                                    make_optimizer, make_train_step)

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
params0 = jax.tree_util.tree_map(np.array, init_params(model, one_packer.make(np.arange(8)).graph))
plan = sharded_packer.plan(np.random.default_rng(1).permutation(S))
key = jax.random.PRNGKey(0)
out = {"plan": [[len(i) for i in group] for group in plan]}

def fresh(tx):
    p = jax.tree_util.tree_map(np.array, params0)
    return TrainState(params=p, opt_state=tx.init(p), step=jnp.asarray(0))

def max_diff(a, b):
    return max(float(np.max(np.abs(np.asarray(x) - np.asarray(y))))
               for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)))

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
    ev1 = evaluate(make_eval_step(apply, cfg), one.params, one_packer, 3.0)
    ev2 = evaluate(make_eval_step(apply, cfg, dp), one.params, sharded_packer, 3.0)
    out[name]["eval"] = [ev1["loss"], ev2["loss"]]

print(json.dumps(out))
"""

# The training loop with [train] devices = 2 (slow tier, issue 20): runs, checkpoints, loads.
LOOP_SCRIPT = r"""
import json
out = {}
import tempfile
from pathlib import Path
from sgn_jax.records.checkpoint import load_trained_model
from sgn_jax.config import builtin_config_path, load_config, replace_section
from sgn_jax.pipelines.configure import sdf_grid_from_config
from sgn_jax.pipelines.train_run import read_metrics, train
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
    out["run"] = {"devices": summary["devices"], "config_devices": trained.config.train.devices,
                  "max_graphs": summary["max_graphs_per_batch"],
                  "losses": [[r["train_loss"], r["val_loss"]] for r in rows],
                  "n_params": summary["n_params"]}
print(json.dumps(out))
"""


def _two_devices(script: str) -> dict:
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2",
               SGN_JAX_NO_CACHE="1")
    proc = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True,
                          text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-4000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def result():
    return _two_devices(SCRIPT)


def test_the_sharded_step_gives_the_one_device_update_on_the_same_samples(result):
    assert all(group == [4, 4] for group in result["plan"][:5])    # 8 samples a step
    for name, tol in (("sgd", 1e-9), ("adam", 1e-5)):
        r = result[name]
        assert r["replicated"] and r["devices"] == 2 and r["step"] == 5
        assert r["moved"] > 1e-4                  # the steps did move the parameters
        assert r["sharded"] < tol, (name, r)
        assert r["sums_rel"] < 1e-5, (name, r)    # the loss sums, summed over the devices
        assert r["eval"][1] == pytest.approx(r["eval"][0], rel=1e-5)


# Slow tier (issue 20): a second two-device process that trains through the whole loop. Its
# twin in the default run is the step check above (the loop calls that same sharded step and
# packer) and test_more_devices_than_there_are_is_a_clear_error (the loop's device check).
@pytest.mark.slow
def test_the_training_loop_runs_data_parallel():
    run = _two_devices(LOOP_SCRIPT)["run"]
    assert run["devices"] == 2 and run["config_devices"] == 2
    assert run["max_graphs"] == 3                 # batch_size 6 over 2 devices
    assert len(run["losses"]) == 2
    assert all(v is not None and v == v and v < 1e3 for row in run["losses"] for v in row)


def test_more_devices_than_there_are_is_a_clear_error(tmp_path):
    from sgn_jax.config import builtin_config_path, load_config, replace_section
    from sgn_jax.pipelines.train_run import train
    from sgn_jax.surrogate.train import TrainingError

    cfg = load_config(builtin_config_path("emax_300rpm"))
    cfg = replace_section(cfg, "train", batch_size=4)
    with pytest.raises(TrainingError, match="xla_force_host_platform_device_count"):
        train(cfg, [], tmp_path / "x", devices=4, sdf=object(), progress=False,
              log=lambda m: None)
