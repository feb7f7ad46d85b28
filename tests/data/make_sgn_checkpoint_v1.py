"""Write tests/data/sgn_checkpoint_v1: a checkpoint and its predictions made by the SGN code
before the forward-pass restructuring (commit 66433cc), to check that old checkpoints still load
and predict the same."""
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import sgn_jax  # noqa
from sgn_jax.config import builtin_config_path, config_to_dict, load_config, replace_section
from sgn_jax.pipelines.features import windows_from_trajectory
from sgn_jax.records.checkpoint import save_checkpoint
from sgn_jax.records.io_utils import git_commit
from sgn_jax.surrogate.graph import GraphSpec, build_graph
from sgn_jax.surrogate.model import init_params, make_model, make_predict
from sgn_jax.surrogate.normalization import compute_norm_stats
from sgn_jax.testing import synthetic_trajectory

N = 6
def q(_, points, offset):
    d = jnp.asarray(points) - jnp.asarray(offset) - jnp.array([0.0, 0.02, 0.0])
    r = jnp.linalg.norm(d, axis=-1)
    return r - 0.03, d / r[..., None]

cfg = load_config(builtin_config_path("emax_300rpm"))
cfg = replace_section(cfg, "model", hidden=32, interaction_layers=2)
spec = GraphSpec(n_particles=N, window=3, ball_radius=0.005, dt=1e-4, pp_pair_capacity=8)
wins, accel, de = windows_from_trajectory(synthetic_trajectory(20, N, seed=2), 3)
build = jax.jit(lambda w: build_graph(w, None, spec, q))
graphs = [build(jax.tree_util.tree_map(lambda a, k=k: a[k], wins))[0] for k in (0, 5, 9)]
g = graphs[0]
stats = compute_norm_stats(np.asarray(g.nodes["features"][:N]), np.asarray(g.nodes["features"][N:N + 1]),
                           np.asarray(g.edges["features"])[np.asarray(g.edges["pp"])],
                           np.asarray(g.edges["features"])[np.asarray(g.edges["pw"])],
                           accel.reshape(-1, 3), de, velocity_encoding="differences")
model = make_model(cfg.model)
params = init_params(model, g, 4)
# Non-zero biases so that the bias paths of the fused layers are exercised.
key = jax.random.PRNGKey(11)
leaves, tree = jax.tree_util.tree_flatten_with_path(params)
new = []
for i, (path, leaf) in enumerate(leaves):
    if "bias" in jax.tree_util.keystr(path):
        leaf = 0.1 * jax.random.normal(jax.random.fold_in(key, i), leaf.shape, leaf.dtype)
    new.append(leaf)
params = jax.tree_util.tree_unflatten(tree, new)
out = Path("tests/data/sgn_checkpoint_v1")
save_checkpoint(out, 1, params=params, norm_stats=stats, meta={"config": config_to_dict(cfg), "epoch": 1}, keep=1)
predict = jax.jit(make_predict(model))
preds = []
for k, gr in zip((0, 5, 9), graphs, strict=False):
    a, d = predict(params, stats, gr)
    preds.append({"window": k, "n_edge": int(gr.n_edge[0]),
                  "accel": np.asarray(a, np.float64).tolist(),
                  "dE": np.asarray(d, np.float64).tolist()})
(out / "expected_predictions.json").write_text(json.dumps({"commit": git_commit(), "model": {"hidden": 32, "mlp_layers": 4, "interaction_layers": 2}, "predictions": preds}, indent=1))
print([p["n_edge"] for p in preds])
