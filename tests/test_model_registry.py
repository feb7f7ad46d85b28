"""The registries of models: ``[model] kind`` -> the flax module that training and checkpoints
use, and the shipped models' registry (``sgn_jax/data/models/registry.toml``).

A second kind (a per-node MLP without message passing, registered here) trains through the same
``train()`` loop and loads through the same ``load_trained_model`` as the SGN. A shipped model is
one registry entry beside its checkpoint folder.
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import sgn_jax  # noqa: F401
from sgn_jax.config import (
    ConfigError,
    ModelConfig,
    builtin_config_path,
    config_from_dict,
    config_to_dict,
    load_config,
    replace_section,
)
from sgn_jax.pipelines.configure import graph_spec_from_config, sdf_grid_from_config
from sgn_jax.pipelines.features import windows_from_trajectory
from sgn_jax.pipelines.train_run import _with_defaults, read_metrics, train
from sgn_jax.records.checkpoint import CheckpointError, load_trained_model
from sgn_jax.surrogate.graph import build_graph
from sgn_jax.surrogate.model import (
    MLP,
    ModelKindError,
    make_model,
    model_factory,
    register_model,
    registered_models,
    unregister_model,
)
from sgn_jax.surrogate.normalization import denormalize_accel, normalize_graph
from sgn_jax.surrogate.sgn import SGN
from sgn_jax.surrogate.train import TrainingError
from sgn_jax.testing import synthetic_trajectory

N = 8
KIND = "node_mlp_test"


class NodeMLP(nn.Module):
    """Each ball's acceleration from its own features; dE from the mean ball embedding."""

    hidden: int = 16
    layers: int = 2

    @nn.compact
    def __call__(self, graph):
        x = jnp.asarray(graph.nodes["features"], jnp.float32)
        particle = graph.nodes["particle"]
        h = nn.relu(nn.Dense(self.hidden, name="embed")(x))
        accel = jnp.where(particle[:, None], MLP(self.hidden, 3, self.layers, name="accel")(h),
                          0.0)
        n_graph = graph.n_node.shape[0]
        seg = jnp.repeat(jnp.arange(n_graph), graph.n_node, total_repeat_length=x.shape[0])
        w = particle.astype(jnp.float32)
        pooled = (jax.ops.segment_sum(h * w[:, None], seg, n_graph)
                  / jnp.maximum(jax.ops.segment_sum(w, seg, n_graph), 1.0)[:, None])
        return accel, MLP(self.hidden, 1, self.layers, name="de")(pooled)[:, 0]


@pytest.fixture
def node_mlp_kind():
    factory = register_model(KIND, lambda m: NodeMLP(hidden=m.hidden, layers=m.mlp_layers),
                             description="test: per-node MLP")
    yield factory
    unregister_model(KIND)


@pytest.fixture(scope="module")
def cfg():
    c = load_config(builtin_config_path("emax_300rpm"))
    c = replace_section(c, "balls", count=N)
    c = replace_section(c, "graph", window=3)
    c = replace_section(c, "model", hidden=12, mlp_layers=2)
    return replace_section(c, "train", batch_size=6, epochs=1, lr_init=2e-3, lr_final=5e-4,
                           train_time=0.008, val_time=0.003)


def test_sgn_is_the_default_kind_and_configs_without_a_kind_load():
    assert "sgn" in registered_models()
    assert ModelConfig().kind == "sgn"
    model = make_model(ModelConfig(hidden=8, mlp_layers=3, interaction_layers=2))
    assert isinstance(model, SGN)
    assert (model.hidden, model.mlp_layers, model.interaction_layers) == (8, 3, 2)
    # Every TOML and saved run config written before the key existed has no [model] kind.
    cfg = load_config(builtin_config_path("emax_300rpm"))
    saved = config_to_dict(cfg)
    del saved["model"]["kind"]
    assert config_from_dict(saved).model.kind == "sgn"
    assert _with_defaults(saved)["model"]["kind"] == "sgn"
    with pytest.raises(ConfigError, match="kind"):
        ModelConfig(kind="")


def test_unknown_and_duplicate_kinds_are_clear_errors(node_mlp_kind):
    with pytest.raises(ModelKindError, match=r"unknown model kind 'nope'.*node_mlp_test.*sgn"):
        model_factory("nope")
    with pytest.raises(ModelKindError, match="already registered"):
        register_model("sgn", lambda m: None)
    with pytest.raises(ModelKindError, match="cannot be unregistered"):
        unregister_model("sgn")
    assert model_factory(KIND) is node_mlp_kind
    assert isinstance(make_model(ModelConfig(kind=KIND, hidden=4)), NodeMLP)


@pytest.mark.slow
def test_a_registered_kind_trains_saves_and_loads_through_the_same_path(cfg, node_mlp_kind,
                                                                         tmp_path):
    grid = sdf_grid_from_config(cfg)
    mcfg = replace_section(cfg, "model", kind=KIND)
    trajs = [synthetic_trajectory(120, N, seed=3)]
    quiet = {"sdf": grid, "progress": False, "log": lambda m: None}
    summary = train(mcfg, trajs, tmp_path / "run", **quiet)
    assert summary["model_kind"] == KIND
    row = read_metrics(tmp_path / "run")[-1]
    assert np.isfinite(row["train_loss"]) and np.isfinite(row["val_loss"])

    trained = load_trained_model(tmp_path / "run", "latest")
    assert isinstance(trained.model, NodeMLP) and trained.config.model.kind == KIND
    assert set(trained.params) == {"embed", "accel", "de"}     # the MLP's tree, not the SGN's
    assert trained.model.hidden == 12 and trained.model.layers == 2

    # Its predictions (raw graph -> m/s^2, J) are the module's on the normalised graph.
    spec = graph_spec_from_config(cfg)
    wins, _, _ = windows_from_trajectory(trajs[0], spec.window)
    # (The graph and the module's side each one jitted program of their own, not hundreds of
    # eager op compiles.)
    graph, _ = jax.jit(build_graph, static_argnums=2)(
        jax.tree_util.tree_map(lambda a: a[5], wins), grid, spec)
    accel, de = jax.jit(trained.predict_fn())(trained.params, trained.norm_stats, graph)

    @jax.jit
    def module_on_normalised_graph(params, stats, graph):
        accel_n, de_n = trained.model.apply({"params": params}, normalize_graph(graph, stats))
        return denormalize_accel(accel_n, stats), de_n

    accel_m, de_n = module_on_normalised_graph(trained.params, trained.norm_stats, graph)
    np.testing.assert_allclose(np.asarray(accel[:N]), np.asarray(accel_m)[:N],
                               rtol=1e-5, atol=1e-6)
    assert np.isfinite(float(de[0])) and np.isfinite(float(de_n[0]))

    # A checkpoint of a kind this process has not registered is refused with the reason.
    unregister_model(KIND)
    with pytest.raises(CheckpointError, match="node_mlp_test.*register"):
        load_trained_model(tmp_path / "run", "latest")
    register_model(KIND, node_mlp_kind.build)


def test_training_an_unregistered_kind_is_a_training_error(cfg, tmp_path):
    with pytest.raises(TrainingError, match="unknown model kind 'nope'"):
        train(replace_section(cfg, "model", kind="nope"),
              [synthetic_trajectory(60, N, seed=0)], tmp_path / "x",
              sdf=sdf_grid_from_config(cfg), progress=False, log=lambda m: None)


# ---------------------------------------------------------------------------------------------
# The shipped models: sgn_jax/data/models/registry.toml, one entry per checkpoint folder beside it


def test_the_registry_names_every_shipped_folder_and_the_default_loads():
    from sgn_jax.records import shipped_models

    reg = shipped_models.registry()
    assert reg.default == "contact" and reg.names[0] == "contact"
    folders = sorted(p.name for p in shipped_models.SHIPPED_MODELS_DIR.iterdir() if p.is_dir())
    assert sorted(reg.names) == folders
    assert all(m.description for m in reg.models)
    assert shipped_models.resolve_checkpoint(None) == shipped_models.shipped_model_dir("contact")
    for name in reg.names:
        assert shipped_models.resolve_checkpoint(name) == shipped_models.shipped_model_dir(name)


def test_a_shipped_model_is_one_registry_entry_beside_its_folder(tmp_path, monkeypatch):
    from sgn_jax.records import shipped_models

    real = shipped_models.SHIPPED_MODELS_DIR
    models = tmp_path / "models"
    models.mkdir()
    monkeypatch.setattr(shipped_models, "SHIPPED_MODELS_DIR", models)
    (models / "mine").symlink_to(real / "contact")   # a checkpoint folder
    registry = models / shipped_models.REGISTRY_FILE
    registry.write_text('default = "mine"\n')
    with pytest.raises(shipped_models.ShippedModelError, match="default = 'mine' is not one"):
        shipped_models.resolve_checkpoint(None)
    registry.write_text('default = "mine"\n\n[[model]]\nname = "mine"\n'
                        'description = "a test model"\n')
    assert shipped_models.resolve_checkpoint(None) == models / "mine"
    assert shipped_models.resolve_checkpoint("mine") == models / "mine"
    with pytest.raises(shipped_models.ShippedModelError, match=r"shipped model's name \(mine\)"):
        shipped_models.resolve_checkpoint("contact")
    # shipping under a name without an entry is refused before anything is copied
    with pytest.raises(shipped_models.ShippedModelError, match="no entry in"):
        shipped_models.ship_checkpoint(real / "contact" / "300", "other", {})
    assert not (models / "other").exists()
    registry.write_text('default = "mine"\n\n[[model]]\nname = "mine"\n')
    with pytest.raises(shipped_models.ShippedModelError, match="entry 1 must have"):
        shipped_models.registry()
