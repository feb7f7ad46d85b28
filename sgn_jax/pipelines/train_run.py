"""The training loop (``sgn-jax train``): config + trajectories -> a run directory.

The pure parts (dataset containers, static-shape batch packing, loss, optimiser, the jitted train
and eval steps) are :mod:`sgn_jax.surrogate.train`. This module featurizes the trajectories
(:mod:`sgn_jax.pipelines.features`), runs the epochs, and writes the run: ``config.toml``,
``metrics.jsonl`` / ``metrics.csv``, ``loss.png``, orbax checkpoints, ``run_summary.json``.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import math
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

import sgn_jax
from sgn_jax.config import (
    ConfigError,
    config_from_dict,
    config_to_dict,
    replace_section,
    save_config,
)
from sgn_jax.pipelines.configure import graph_spec_from_config, sdf_grid_from_config
from sgn_jax.pipelines.features import featurize_trajectory
from sgn_jax.records.checkpoint import latest_step, restore_checkpoint, save_checkpoint
from sgn_jax.records.envelope import ENVELOPE_PATH, MotionEnvelope, load_envelope
from sgn_jax.records.io_utils import atomic_write, git_commit, write_json
from sgn_jax.surrogate.graph import GraphError, GraphSpec, SDFQuery, make_graph_builder
from sgn_jax.surrogate.model import ModelKindError, count_params, model_factory, model_kind
from sgn_jax.surrogate.normalization import stats_to_arrays
from sgn_jax.surrogate.train import (
    BatchPacker,
    DataParallel,
    GraphDataset,
    ShardedPacker,
    TrainingError,
    TrainState,
    batch_edge_capacity,
    evaluate,
    losses_from_sums,
    lr_at,
    make_eval_step,
    make_optimizer,
    make_train_step,
    norm_stats_from_dataset,
    normalize_dataset,
    split_window_ends,
)

METRIC_FIELDS = ("epoch", "step", "lr", "train_loss", "train_node", "train_global", "val_loss",
                 "val_node", "val_global", "epoch_seconds", "samples_per_second", "batches",
                 "best")


def named_envelope(name: str) -> MotionEnvelope:
    """The motion envelope a ``[train] envelope`` value names: "default" (the shipped one,
    sgn_jax/data/envelope.toml) or a TOML path."""
    return load_envelope(ENVELOPE_PATH if name == "default" else Path(name))


def envelope_meta(train_cfg: Any) -> dict[str, Any]:
    """``{"envelope": ...}`` for a checkpoint's meta when the ``[train]`` section names the
    motion envelope the model is trained for (``envelope`` = "default" or a TOML path), else
    ``{}`` (the model then covers only its training motion: ``model_envelope``)."""
    if not getattr(train_cfg, "envelope", ""):
        return {}
    return {"envelope": named_envelope(train_cfg.envelope).to_meta()}


def write_metrics(out_dir: Path, history: list[dict[str, Any]],
                  fields: Sequence[str] = METRIC_FIELDS, loss_plot: bool = True) -> None:
    """``metrics.jsonl`` and ``metrics.csv`` (columns ``fields``; rewritten atomically) and,
    with ``loss_plot``, ``loss.png`` (losses per epoch)."""
    with atomic_write(out_dir / "metrics.jsonl", "w") as fh:
        for row in history:
            fh.write(json.dumps(row, sort_keys=True) + "\n")
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(fields), extrasaction="ignore")
    writer.writeheader()
    writer.writerows(history)
    with atomic_write(out_dir / "metrics.csv", "w") as fh:
        fh.write(buf.getvalue())
    if loss_plot:
        plot_losses(history, out_dir / "loss.png")


def read_metrics(out_dir: Path) -> list[dict[str, Any]]:
    path = out_dir / "metrics.jsonl"
    if not path.is_file():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def plot_losses(history: list[dict[str, Any]], path: Path) -> None:
    """Training and validation losses against epoch (log scale), written atomically as PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not history:
        return
    ep = [r["epoch"] for r in history]
    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    for key, style, label in (("train_loss", "-", "train (total)"),
                              ("val_loss", "-", "validation (total)"),
                              ("train_node", ":", "train node"), ("val_node", ":", "val node"),
                              ("train_global", "--", "train global"),
                              ("val_global", "--", "val global")):
        y = [r.get(key) for r in history]
        if all(v is not None and math.isfinite(v) and v > 0 for v in y):
            ax.plot(ep, y, style, label=label, marker="o" if len(ep) < 30 else None, ms=3)
    ax.set_yscale("log")
    ax.set_xlabel("epoch")
    ax.set_ylabel("Huber loss (normalised)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    with atomic_write(path, "wb") as fh:
        fig.savefig(fh, format="png", dpi=120)
    plt.close(fig)


def at_model_step(traj: Any, dt: float) -> Any:
    """``traj`` sampled at the surrogate step ``dt``: a record sampled finer by an integer
    factor is coarsened (``Trajectory.at_step``); look-alikes without that method are returned
    as they are (``check_trajectory_matches`` then compares their dt)."""
    meta = getattr(traj, "meta", None) or {}
    if "dt" in meta and hasattr(traj, "at_step") and not math.isclose(float(meta["dt"]), dt,
                                                                      rel_tol=1e-9):
        return traj.at_step(dt)
    return traj


def check_trajectory_matches(traj: Any, cfg: Any, name: str) -> None:
    """The data must have the config's dt, ball count and ball radius."""
    meta = getattr(traj, "meta", None) or {}
    n = np.asarray(traj.pos).shape[1]
    problems = []
    if n != cfg.balls.count:
        problems.append(f"{n} balls, config [balls] count = {cfg.balls.count}")
    if "dt" in meta and not math.isclose(float(meta["dt"]), cfg.dem.dt, rel_tol=1e-9):
        problems.append(f"dt = {meta['dt']}, config [dem] dt = {cfg.dem.dt}")
    if "ball_radius" in meta and not math.isclose(float(meta["ball_radius"]), cfg.balls.radius,
                                                  rel_tol=1e-9):
        problems.append(f"ball radius {meta['ball_radius']}, config {cfg.balls.radius}")
    saved = meta.get("config") if isinstance(meta, dict) else None
    if isinstance(saved, dict) and "jar" in saved:
        if saved["jar"] != config_to_dict(cfg)["jar"]:
            problems.append(f"jar {saved['jar']}, config [jar] {config_to_dict(cfg)['jar']} "
                            "(the featurizer would use the wrong SDF)")
    if problems:
        raise TrainingError(f"{name} does not match the config: " + "; ".join(problems))


def prepare_datasets(trajectories: Sequence[Any], cfg: Any, sdf: Any, *,
                     query: SDFQuery | None = None, names: Sequence[str] | None = None,
                     progress: bool = True) -> tuple[GraphDataset, GraphDataset | None, GraphSpec]:
    """Featurize the training and validation windows of all trajectories (raw, compact)."""
    spec = graph_spec_from_config(cfg)
    names = names or [f"trajectory {i}" for i in range(len(trajectories))]
    builder = make_graph_builder(query, spec)
    train_parts, val_parts = [], []
    for i, (traj, name) in enumerate(zip(trajectories, names, strict=True)):
        traj = at_model_step(traj, cfg.dem.dt)
        check_trajectory_matches(traj, cfg, name)
        t = np.asarray(traj.t, np.float64)
        tr, va = split_window_ends(t, spec.window, cfg.train.train_time, cfg.train.val_time)
        stride = cfg.train.window_stride
        tr, va = tr[::stride], va[::stride]
        if len(tr) == 0:
            raise TrainingError(f"{name}: no training window with t <= train_time = "
                                f"{cfg.train.train_time} s (the data cover {t[-1]:.4g} s)")
        # Noise on the training windows only: validation measures the clean one-step error.
        for ends, parts, noise in ((tr, train_parts, cfg.train.position_noise_std),
                                   (va, val_parts, 0.0)):
            if len(ends):
                parts.append(featurize_trajectory(traj, spec, sdf, ends, source=i,
                                                  builder=builder, progress=progress,
                                                  position_noise_std=noise,
                                                  noise_seed=cfg.train.seed))
    train_ds = GraphDataset.concatenate(train_parts)
    val_ds = GraphDataset.concatenate(val_parts) if val_parts else None
    dropped = train_ds.pp_dropped + (val_ds.pp_dropped if val_ds else 0)
    if dropped:
        raise GraphError(
            f"{dropped} directed ball-ball edges exceeded the graph capacity of "
            f"{spec.pp_capacity} per graph; raise [graph] pp_edges_per_particle "
            f"(now {cfg.graph.pp_edges_per_particle})")
    return train_ds, val_ds, spec


def _with_defaults(saved_cfg: dict[str, Any]) -> dict[str, Any]:
    """A saved config dict with the defaults of keys added since filled in (e.g. ``[model]
    kind``), so that a run saved before a key existed resumes; as saved if it does not parse."""
    try:
        return config_to_dict(config_from_dict(saved_cfg))
    except ConfigError:
        return saved_cfg


def train(cfg: Any, trajectories: Sequence[Any], out_dir: str | Path, *, sdf: Any = None,
          query: SDFQuery | None = None, epochs: int | None = None, resume: bool = False,
          names: Sequence[str] | None = None, progress: bool = True,
          log: Callable[[str], None] = print, devices: int | None = None) -> dict[str, Any]:
    """Train an SGN on ``trajectories`` and write the run to ``out_dir``.

    Args:
        cfg: the experiment :class:`sgn_jax.config.Config` ([graph], [model], [train]).
        trajectories: ``sgn_jax.records.trajectory.Trajectory`` objects (or look-alikes).
        out_dir: run directory (config.toml, metrics, loss.png, checkpoints/).
        sdf, query: the jar SDF for :func:`sgn_jax.surrogate.graph.build_graph` (default: the
            config's SDF grid and ``query_sdf_grid``).
        epochs: overrides ``cfg.train.epochs`` (total epochs of the run, also when resuming).
        resume: continue from ``out_dir/checkpoints/latest``; without it an existing run in
            ``out_dir`` is an error.
        devices: overrides ``cfg.train.devices``: data-parallel training over this many local
            devices (1: one device, the default; docs/sgn.md, "Data-parallel training").

    Returns:
        a summary dict (epochs done, best validation loss and epoch, timings, capacities).
    """
    from tqdm.auto import tqdm

    if epochs is not None:
        cfg = replace_section(cfg, "train", epochs=int(epochs))
    if devices is not None:
        cfg = replace_section(cfg, "train", devices=int(devices))
    tcfg = cfg.train
    out_dir = Path(out_dir)
    ckpt_latest, ckpt_best = out_dir / "checkpoints" / "latest", out_dir / "checkpoints" / "best"
    existing = latest_step(ckpt_latest)
    if existing is not None and not resume:
        raise TrainingError(f"{out_dir} already holds a training run (epoch {existing}); pass "
                            "--resume to continue it or choose another --out")
    if resume and existing is None:
        log(f"no checkpoint in {ckpt_latest}; starting a new run")
    if sdf is None:
        sdf = sdf_grid_from_config(cfg)

    # The model kind and the devices are checked before the (slow) featurization.
    try:
        factory = model_factory(model_kind(cfg.model))
    except ModelKindError as exc:
        raise TrainingError(f"[model] {exc}") from exc
    model = factory.build_model(cfg)
    apply = factory.make_apply(model)
    tx = make_optimizer(tcfg.lr_init)
    strategy = None
    if tcfg.devices > 1:
        try:
            strategy = DataParallel.over(tcfg.devices)
        except ValueError as exc:
            raise TrainingError(f"[train] devices = {tcfg.devices}: {exc}") from exc

    t0 = time.perf_counter()
    train_raw, val_raw, spec = prepare_datasets(trajectories, cfg, sdf, query=query, names=names,
                                                progress=progress)
    featurize_s = time.perf_counter() - t0

    restored = None
    if existing is not None:
        restored = restore_checkpoint(ckpt_latest)
        saved_cfg = _with_defaults(restored.meta.get("config", {}))
        for section in ("graph", "model", "balls"):
            if saved_cfg.get(section) != config_to_dict(cfg).get(section):
                raise TrainingError(
                    f"cannot resume: the [{section}] section differs from the run in {out_dir} "
                    f"(saved {saved_cfg.get(section)}, now {config_to_dict(cfg).get(section)})")
        stats = restored.norm_stats
    else:
        stats = norm_stats_from_dataset(train_raw, cfg.model.velocity_encoding)
    train_ds = normalize_dataset(train_raw, stats)
    val_ds = normalize_dataset(val_raw, stats) if val_raw is not None else None
    del train_raw, val_raw

    # With D devices every step packs D sub-batches of batch_size / D graphs (one per device).
    max_graphs = tcfg.batch_size // tcfg.devices
    per = train_ds.edges_per_sample
    capacity = batch_edge_capacity(per, max_graphs)
    if val_ds is not None:
        capacity = max(capacity, int(math.ceil(val_ds.edges_per_sample.max() / 16) * 16))
    train_packer = BatchPacker(train_ds, max_graphs, capacity)
    val_packer = BatchPacker(val_ds, max_graphs, capacity) if val_ds is not None else None

    example = train_packer.make(np.arange(min(max_graphs, len(train_ds))))
    params = factory.init_params(model, example.graph, tcfg.seed)
    if strategy is not None:
        train_packer = ShardedPacker(train_packer, strategy.n_devices)
        val_packer = (ShardedPacker(val_packer, strategy.n_devices) if val_packer is not None
                      else None)
    opt_state = tx.init(params)
    history: list[dict[str, Any]] = []
    start_epoch = 0
    if restored is not None:
        full = restore_checkpoint(ckpt_latest, opt_state_like=opt_state)
        params, opt_state = full.params, full.opt_state
        start_epoch = int(full.meta["epoch"])
        history = [r for r in read_metrics(out_dir) if r["epoch"] <= start_epoch]
        log(f"resuming {out_dir} after epoch {start_epoch}")
    state = TrainState(params=jax.tree_util.tree_map(jnp.asarray, params),
                       opt_state=jax.tree_util.tree_map(jnp.asarray, opt_state),
                       step=jnp.asarray(history[-1]["step"] if history else 0, jnp.int64))
    del params, opt_state
    if strategy is not None:
        state = strategy.replicate(state)

    out_dir.mkdir(parents=True, exist_ok=True)
    save_config(cfg, out_dir / "config.toml")
    write_json(out_dir / "norm_stats.json",
               {**stats_to_arrays(stats), "velocity_encoding": stats.velocity_encoding})
    info = {
        "n_train": len(train_ds), "n_val": len(val_ds) if val_ds is not None else 0,
        "n_params": count_params(state.params), "model_kind": factory.kind,
        "max_graphs_per_batch": max_graphs, "devices": tcfg.devices,
        "batch_edge_capacity": capacity, "mean_edges_per_sample": float(per.mean()),
        "max_edges_per_sample": int(per.max()), "featurize_seconds": featurize_s,
        "graph_spec": dataclasses.asdict(spec), "git_commit": git_commit(),
        "sgn_jax_version": sgn_jax.__version__,
    }
    write_json(out_dir / "run_info.json", info)
    log(f"train {info['n_train']} / validation {info['n_val']} windows, "
        f"{info['n_params']:,} parameters, batches of <= {max_graphs} graphs and <= {capacity} "
        f"edges (mean {per.mean():.1f} edges per graph)"
        + (f", {tcfg.devices} such batches per step, one per device" if strategy else ""))

    train_step = make_train_step(apply, tx, tcfg, spec.window, sharding=strategy)
    eval_step = make_eval_step(apply, tcfg, sharding=strategy)
    base_key = jax.random.PRNGKey(tcfg.seed)
    alpha, beta = tcfg.node_loss_weight, tcfg.global_loss_weight
    best = min((r["val_loss"] if r["val_loss"] is not None else r["train_loss"]
                for r in history), default=math.inf)
    meta_base = {"config": config_to_dict(cfg), "info": info, **envelope_meta(tcfg)}

    epoch_bar = tqdm(range(start_epoch, tcfg.epochs), desc="epochs", unit="epoch",
                     disable=not progress, initial=start_epoch, total=tcfg.epochs)
    for epoch in epoch_bar:
        t_epoch = time.perf_counter()
        order = np.random.default_rng([tcfg.seed, epoch]).permutation(len(train_ds))
        plan = train_packer.plan(order)
        sums = jnp.zeros(4, jnp.float32)
        lr = tcfg.lr_init
        step_bar = tqdm(plan, desc=f"epoch {epoch + 1}", unit="batch", leave=False,
                        disable=not progress)
        step_no = int(state.step)
        for i, idx in enumerate(step_bar):
            lr = lr_at((epoch + i / len(plan)) / tcfg.epochs, tcfg.lr_init, tcfg.lr_final)
            # Noise keys depend only on (seed, global step): a resumed run draws the same noise.
            key = jax.random.fold_in(base_key, step_no)
            step_no += 1
            state, batch_sums = train_step(state, train_packer.make(idx), np.float32(lr), key)
            sums = sums + batch_sums
        train_loss = losses_from_sums(np.asarray(sums, np.float64), alpha, beta)
        val_loss = (evaluate(eval_step, state.params, val_packer, alpha, beta)
                    if val_packer is not None else None)
        seconds = time.perf_counter() - t_epoch
        score = val_loss["loss"] if val_loss is not None else train_loss["loss"]
        improved = score < best
        best = min(best, score)
        row = {"epoch": epoch + 1, "step": int(state.step), "lr": lr,
               "train_loss": train_loss["loss"], "train_node": train_loss["node"],
               "train_global": train_loss["global"],
               "val_loss": val_loss["loss"] if val_loss else None,
               "val_node": val_loss["node"] if val_loss else None,
               "val_global": val_loss["global"] if val_loss else None,
               "epoch_seconds": seconds, "samples_per_second": len(train_ds) / seconds,
               "batches": len(plan), "best": improved}
        history.append(row)
        meta = {**meta_base, "epoch": epoch + 1, "global_step": int(state.step),
                "train_loss": train_loss["loss"], "val_loss": row["val_loss"]}
        save_checkpoint(ckpt_latest, epoch + 1, params=state.params, norm_stats=stats,
                        opt_state=state.opt_state, meta=meta, keep=2)
        if improved:
            save_checkpoint(ckpt_best, epoch + 1, params=state.params, norm_stats=stats,
                            meta=meta, keep=1)
        write_metrics(out_dir, history)
        epoch_bar.set_postfix(train=f"{train_loss['loss']:.4g}",
                              val=f"{row['val_loss']:.4g}" if val_loss else "-")
        log(json.dumps({k: row[k] for k in ("epoch", "train_loss", "val_loss", "lr",
                                             "epoch_seconds")}))
    summary = {
        "epochs": len(history), "best_loss": best,
        "best_epoch": next((r["epoch"] for r in reversed(history) if r["best"]), None),
        "final": history[-1] if history else None, **info,
    }
    write_json(out_dir / "summary.json", summary)
    return summary
