"""Host driver of the contact-impulse surrogate's training (``[model] kind = "contact"``).

``train_contact(cfg, trajectories, out_dir)`` draws stretches of the DEM trajectories, runs the
jitted unrolled-loss step of :mod:`sgn_jax.surrogate.contact_train` for a budget of steps (or minutes),
shows progress (rate, ETA), and writes the run like :func:`sgn_jax.pipelines.train_run.train`:
``config.toml``, ``metrics.csv``, ``run_info.json``, ``checkpoints/latest`` (with the
optimiser state, every ``checkpoint_every`` steps and at the end) and ``checkpoints/best``
(lowest validation loss). A killed run resumes from ``checkpoints/latest`` with ``resume=True``
(the batches are drawn from ``(seed, step)``, so a resumed run draws what an unbroken one would).
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax

import sgn_jax
from sgn_jax.config import config_to_dict, save_config
from sgn_jax.pipelines.configure import (
    graph_spec_from_config,
    params_from_config,
    surrogate_walls_from_config,
)
from sgn_jax.pipelines.train_run import (
    at_model_step,
    check_trajectory_matches,
    envelope_meta,
    read_metrics,
    write_metrics,
)
from sgn_jax.records.checkpoint import latest_step, restore_checkpoint, save_checkpoint
from sgn_jax.records.io_utils import git_commit, write_json
from sgn_jax.records.shipped_models import ShippedModelError, resolve_checkpoint
from sgn_jax.records.trajectory import load_trajectory
from sgn_jax.surrogate.contact import make_contact_net
from sgn_jax.surrogate.contact_train import (
    ContactTrainState,
    StretchSource,
    UnrollSpec,
    dissipation_shares,
    impact_stretches,
    init_on_first_stretch,
    make_optimizer,
    make_train_step,
    make_unroll_loss,
    share_logits,
    tangential_damping_shares,
    velocity_change_scale,
)
from sgn_jax.surrogate.normalization import Moments, NormStats
from sgn_jax.surrogate.train import TrainingError


def identity_stats(window: int) -> NormStats:
    """Normalisation statistics that change nothing: the contact model reads the raw graph
    (fixed physical scales), but checkpoints and the rollout API carry a ``NormStats``."""
    def ident(d: int) -> Moments:
        return Moments(mean=np.zeros(d), std=np.ones(d))
    return NormStats(particle=ident(7 * window), wall=ident(7 * window), pp_edge=ident(3),
                     pw_edge=ident(3), accel=ident(3), dissipation=ident(1))


# The columns of metrics.csv (metrics.jsonl keeps every row as written, for resuming).
CONTACT_METRIC_FIELDS = ("step", "train_loss", "val_loss", "lr", "seconds")


def _warm_start(params: dict[str, Any], donor: dict[str, Any], source: Any
                ) -> tuple[dict[str, Any], list[str]]:
    """``params`` with each top-level entry (a submodule's parameters) that ``donor`` has with
    the same tree structure and shapes taken from ``donor``; the dissipation shares stay the
    data's. Raises when nothing matches (the wrong checkpoint).

    A leaf with MORE rows than the donor's (a first layer that takes inputs appended after
    the donor's, as a spin model's contact-point slip after a spinless model's inputs) takes the
    donor's rows and zeros for the new ones: the new inputs start without effect, so the model
    starts as its donor."""
    out, names = dict(params), []

    def fits(a: Any, b: Any) -> bool:   # donor leaf a into leaf b
        sa, sb = np.shape(a), np.shape(b)
        return sa == sb or (len(sa) == len(sb) == 2 and sa[1] == sb[1] and sa[0] < sb[0])

    def take(a: Any, b: Any) -> jax.Array:
        a = jnp.asarray(a)
        if a.shape == np.shape(b):
            return a
        return jnp.zeros(np.shape(b), a.dtype).at[: a.shape[0]].set(a)

    for name, value in donor.items():
        if name == "share_logit" or name not in params:
            continue
        same = (jax.tree_util.tree_structure(value) == jax.tree_util.tree_structure(params[name])
                and all(fits(a, b) for a, b in zip(
                    jax.tree_util.tree_leaves(value), jax.tree_util.tree_leaves(params[name]),
                    strict=True)))
        if same:
            out[name] = jax.tree_util.tree_map(take, value, params[name])
            names.append(name)
    if not names:
        raise TrainingError(f"init_from={source}: no parameter of this model ({sorted(params)}) "
                            "matches the checkpoint's in name and shape")
    return out, sorted(names)


def train_contact(cfg: Any, trajectories: Sequence[Any], out_dir: str | Path, *,
                  val_trajectories: Sequence[Any] = (), steps: int = 4000,
                  batch_size: int = 32, unroll: UnrollSpec | None = None,
                  lr_init: float = 1e-3, lr_final: float = 3e-5, seed: int = 0,
                  minutes: float | None = None, checkpoint_every: int = 250,
                  impact_weight: float = 0.0, n_impacts: int = 64,
                  init_from: str | Path | None = None, schedule_steps: int | None = None,
                  resume: bool = False, progress: bool = True,
                  log: Callable[[str], None] = print) -> dict[str, Any]:
    """Train a contact-impulse surrogate; see the module docstring.

    ``steps`` is the run's total number of optimiser steps (also when resuming); the learning
    rate decays from ``lr_init`` to ``lr_final`` over ``schedule_steps`` (default ``steps``:
    a longer schedule stops the run part-way down it); ``minutes``
    stops earlier (after a checkpoint) when the wall-clock budget is spent. ``impact_weight``
    > 0 adds ``impact_weight`` x the same unrolled loss on ``n_impacts`` isolated head-on
    impacts whose answer is the DEM contact law's (:func:`impact_stretches`, seeded by
    ``seed``; the same set every step). ``init_from`` (a checkpoint directory, e.g. a trained
    1-pass model's ``checkpoints/best``) starts every parameter of the same name and shape from
    it (warm start: a 2-pass model from a trained first pass, its correction at zero); the rest
    start fresh. Returns a summary.
    """
    from tqdm.auto import tqdm

    unroll = UnrollSpec() if unroll is None else unroll
    out_dir = Path(out_dir)
    ckpt_latest, ckpt_best = out_dir / "checkpoints" / "latest", out_dir / "checkpoints" / "best"
    existing = latest_step(ckpt_latest)
    if existing is not None and not resume:
        raise TrainingError(f"{out_dir} already holds a training run (step {existing}); pass "
                            "resume=True (--resume) to continue it or choose another --out")
    if cfg.model.kind != "contact":
        raise TrainingError(f"train_contact trains [model] kind = 'contact', got {cfg.model.kind!r}")
    if not trajectories:
        raise TrainingError("no training trajectories")
    spec = graph_spec_from_config(cfg)
    # the records' files, before a coarser model step replaces the records (and their path)
    train_files = [str(getattr(t, "path", "")) for t in trajectories]
    trajectories = [at_model_step(t, spec.dt) for t in trajectories]
    val_trajectories = [at_model_step(t, spec.dt) for t in val_trajectories]
    for i, t in enumerate([*trajectories, *val_trajectories]):
        check_trajectory_matches(t, cfg, f"trajectory {i}")
    sdf, query = surrogate_walls_from_config(cfg)
    net = make_contact_net(cfg)

    if net.spin:
        lacking = [str(getattr(t, "path", i)) for i, t in
                   enumerate([*trajectories, *val_trajectories]) if getattr(t, "omega", None) is None]
        if lacking:
            raise TrainingError(f"[model] spin = true trains on the DEM's spins (omega), which "
                                f"these records lack: {lacking[:3]}")

    def source(trajs: Sequence[Any]) -> StretchSource:
        return StretchSource(
            positions=[np.asarray(t.pos, np.float64) for t in trajs],
            offsets=[np.asarray(t.offset, np.float64) for t in trajs],
            offset_velocities=[np.asarray(t.offset_vel, np.float64) for t in trajs],
            scales=np.array([velocity_change_scale(np.asarray(t.pos), spec.dt) for t in trajs]),
            window=spec.window, unroll=unroll.unroll,
            spins=[np.asarray(t.omega, np.float64) for t in trajs] if net.spin else None)

    train_src = source(trajectories)
    val_src = source(val_trajectories) if val_trajectories else None
    shares = (tangential_damping_shares(trajectories)
              if net.physics.damping_target == "contact" else dissipation_shares(trajectories))

    example = train_src.draw(np.random.default_rng(0), 1)
    params = init_on_first_stretch(net, spec, sdf, query, example, jax.random.PRNGKey(seed))
    params = {**params, "share_logit": share_logits(shares)}
    if init_from is not None and existing is None:
        params, warm_names = _warm_start(params, restore_checkpoint(init_from).params, init_from)
        log(f"warm start from {init_from}: {', '.join(warm_names)}")

    if schedule_steps is not None and schedule_steps < steps:
        raise TrainingError(f"schedule_steps {schedule_steps} < steps {steps}")
    schedule = optax.cosine_decay_schedule(lr_init, schedule_steps or steps,
                                           alpha=lr_final / lr_init)
    tx = make_optimizer(schedule)
    opt_state = tx.init(params)
    history: list[dict[str, Any]] = []
    start = 0
    if existing is not None:
        full = restore_checkpoint(ckpt_latest, opt_state_like=opt_state)
        params, opt_state = full.params, full.opt_state
        start = int(full.meta["global_step"])
        history = [r for r in read_metrics(out_dir) if r["step"] <= start]
        log(f"resuming {out_dir} after step {start}")
    state = ContactTrainState(jax.tree_util.tree_map(jnp.asarray, params),
                              jax.tree_util.tree_map(jnp.asarray, opt_state),
                              jnp.asarray(start, jnp.int32))

    loss = make_unroll_loss(net, spec, sdf, query, unroll)
    eval_loss = jax.jit(loss)
    if impact_weight > 0:
        laws = params_from_config(cfg)
        impacts = jax.tree_util.tree_map(jnp.asarray, impact_stretches(
            laws.pw, laws.pp, cfg.balls.radius, spec.dt, spec.window, unroll.unroll, n_impacts,
            seed, gravity=-float(cfg.dem.gravity[1])))
        pair_spec = dataclasses.replace(spec, n_particles=2, pp_pair_capacity=1)
        impact_loss = make_unroll_loss(net, pair_spec, sdf, query,
                                       dataclasses.replace(unroll, position_noise=0.0))
        data_loss = loss

        def loss(params, batch, key):  # noqa: F811  (the data's loss plus the impacts')
            value, per_step = data_loss(params, batch, key)
            return value + impact_weight * impact_loss(params, impacts, key)[0], per_step

    train_step = make_train_step(loss, tx)

    out_dir.mkdir(parents=True, exist_ok=True)
    save_config(cfg, out_dir / "config.toml")
    info = {"n_train_trajectories": len(trajectories),
            "train_files": train_files,
            "n_val_trajectories": len(val_trajectories),
            "n_params": int(sum(p.size for p in jax.tree_util.tree_leaves(params))),
            "model_kind": "contact", "steps": steps,
            "schedule_steps": schedule_steps or steps, "batch_size": batch_size,
            "unroll": unroll.unroll, "pushforward": unroll.pushforward,
            "position_noise": unroll.position_noise,
            "relative_floor": unroll.relative_floor, "lr_init": lr_init, "lr_final": lr_final,
            "impact_weight": impact_weight, "n_impacts": n_impacts if impact_weight > 0 else 0,
            "spin": net.spin, "spin_weight": unroll.spin_weight,
            "init_from": None if init_from is None else str(init_from),
            "damping_target": net.physics.damping_target,
            "dissipation_shares": {"pp": shares[0], "pw": shares[1]},
            "loss_scales": train_src.scales.tolist(), "git_commit": git_commit(),
            "sgn_jax_version": sgn_jax.__version__}
    write_json(out_dir / "run_info.json", info)
    stats = identity_stats(spec.window)
    meta_base = {"config": config_to_dict(cfg), "info": info, **envelope_meta(cfg.train)}
    val_batches = ([val_src.draw(np.random.default_rng([seed, 7, i]), batch_size)
                    for i in range(8)] if val_src is not None else [])
    best = min((r["val_loss"] if r.get("val_loss", -1) >= 0 else r["train_loss"]
                for r in history), default=math.inf)

    def save(step_no: int, train_value: float) -> None:
        nonlocal best
        val_value = (float(np.mean([float(eval_loss(state.params, b, jax.random.PRNGKey(0))[0])
                                    for b in val_batches])) if val_batches else -1.0)
        score = val_value if val_batches else train_value
        improved = score < best
        best = min(best, score)
        history.append({"step": step_no, "train_loss": train_value, "val_loss": val_value,
                        "lr": float(schedule(step_no)), "seconds": time.perf_counter() - t0})
        meta = {**meta_base, "global_step": step_no, "epoch": step_no,
                "train_loss": train_value, "val_loss": val_value}
        save_checkpoint(ckpt_latest, step_no, params=state.params, norm_stats=stats,
                        opt_state=state.opt_state, meta=meta, keep=2)
        if improved:
            save_checkpoint(ckpt_best, step_no, params=state.params, norm_stats=stats,
                            meta=meta, keep=1)
        write_metrics(out_dir, history, CONTACT_METRIC_FIELDS, loss_plot=False)
        log(json.dumps({"step": step_no, "train_loss": round(train_value, 5),
                        "val_loss": round(val_value, 5), "best": improved}))

    t0 = time.perf_counter()
    bar = tqdm(range(start, steps), desc="steps", unit="step", initial=start, total=steps,
               disable=not progress)
    running: list[float] = []
    step_no = start
    for step_no in bar:
        batch = train_src.draw(np.random.default_rng([seed, step_no]), batch_size)
        state, value, _ = train_step(state, batch, jax.random.PRNGKey(step_no))
        running.append(float(value))
        if not math.isfinite(running[-1]):
            raise TrainingError(f"non-finite training loss at step {step_no}")
        done = step_no + 1
        if done % checkpoint_every == 0 or done == steps:
            save(done, float(np.mean(running)))
            running = []
            bar.set_postfix(loss=f"{history[-1]['train_loss']:.4g}")
            if minutes is not None and time.perf_counter() - t0 > 60 * minutes:
                log(f"time budget of {minutes} min spent after step {done}; resume to go on")
                break
    summary = {"steps_done": int(state.step), "best_loss": best,
               "seconds": time.perf_counter() - t0, **info}
    write_json(out_dir / "summary.json", summary)
    return summary


def stage_records(data_dir: str | Path, patterns: Sequence[str]) -> list[Path]:
    """The record files of a stage: each glob pattern of ``patterns`` relative to ``data_dir``,
    sorted per pattern, in the patterns' order, without repeats. A pattern that matches no
    file raises :class:`TrainingError` naming it (before any training)."""
    data_dir = Path(data_dir)
    files: list[Path] = []
    for pattern in patterns:
        matched = sorted(data_dir.glob(pattern))
        if not matched:
            raise TrainingError(f"records pattern {pattern!r} matches no file in {data_dir}; "
                                "make the DEM records first (docs/training.md) or pass the "
                                "folder that holds them as --data")
        files += [f for f in matched if f not in files]
    return files


def stage_start(init_from: str) -> Path:
    """The checkpoint directory a stage's ``init_from`` names (a shipped model's name, a
    training run, whose ``checkpoints/best`` it takes, or a checkpoint directory); refused
    before any work when it does not exist."""
    try:
        path = resolve_checkpoint(init_from)
    except ShippedModelError as exc:
        raise TrainingError(f"[[train.stages]] init_from = {init_from!r}: {exc}") from exc
    best = path / "checkpoints" / "best"
    return best if best.is_dir() else path


def train_stages(cfg: Any, data_dir: str | Path, out_dir: str | Path, *,
                 resume: bool = False, progress: bool = True,
                 load: Callable[[Path], Any] | None = None,
                 log: Callable[[str], None] = print) -> dict[str, Any]:
    """Run the config's ``[[train.stages]]`` in order (docs/training.md).

    Stage ``k`` trains in ``out_dir/<name>/`` with :func:`train_contact` on the records its
    globs match under ``data_dir``; a stage after the first warm-starts from the previous
    stage's ``checkpoints/best``, a stage with ``init_from`` from that checkpoint
    (:func:`stage_start`). Every stage's record patterns are checked before the first
    step. With ``resume=True`` a finished stage (its ``summary.json`` written with all its
    steps) is skipped and an interrupted one goes on from its latest checkpoint, so a killed
    run continues where it stopped. ``load`` reads a record (default
    :func:`sgn_jax.records.trajectory.load_trajectory`).

    Returns a summary: per stage its directory, steps, best loss and wall time, the total wall
    time and ``model``, the final stage's best checkpoint (the trained model).
    """
    stages = cfg.train.stages
    if not stages:
        raise TrainingError("the config has no [[train.stages]]: the contact-impulse surrogate "
                            "trains in stages (see sgn_jax/configs/contact_train.toml)")
    load = load_trajectory if load is None else load
    out_dir = Path(out_dir)
    files_of = {stage.name: stage_records(data_dir, stage.records) for stage in stages}
    starts = {stage.name: stage_start(stage.init_from) for stage in stages if stage.init_from}
    if out_dir.exists() and any(out_dir.iterdir()) and not resume:
        raise TrainingError(f"{out_dir} already holds a training run; pass resume=True "
                            "(--resume) to continue it or choose another --out")
    out_dir.mkdir(parents=True, exist_ok=True)
    save_config(cfg, out_dir / "config.toml")
    cache: dict[Path, Any] = {}
    done: list[dict[str, Any]] = []
    previous_best: Path | None = None
    for k, stage in enumerate(stages):
        stage_dir = out_dir / stage.name
        summary_path = stage_dir / "summary.json"
        if resume and summary_path.is_file():
            finished = json.loads(summary_path.read_text())
            if finished.get("steps_done") == stage.steps:
                log(f"stage {k + 1}/{len(stages)} {stage.name}: done, skipped")
                done.append(_stage_line(stage, stage_dir, finished))
                previous_best = stage_dir / "checkpoints" / "best"
                continue
        files = files_of[stage.name]
        previous_best = starts.get(stage.name, previous_best)
        log(f"stage {k + 1}/{len(stages)} {stage.name}: {stage.steps} steps, unroll "
            f"{stage.unroll}, {len(files)} records"
            + (f", from {previous_best}" if previous_best is not None else ", from scratch"))
        for f in files:
            if f not in cache:
                cache[f] = load(f)
        summary = train_contact(
            cfg, [cache[f] for f in files], stage_dir, steps=stage.steps,
            schedule_steps=stage.schedule_steps or None, batch_size=stage.batch_size,
            unroll=UnrollSpec(unroll=stage.unroll, pushforward=stage.pushforward,
                              position_noise=stage.position_noise,
                              relative_floor=stage.relative_floor,
                              spin_weight=stage.spin_weight),
            lr_init=stage.lr_init, lr_final=stage.lr_final, seed=cfg.train.seed,
            checkpoint_every=stage.checkpoint_every, init_from=previous_best,
            resume=resume,
            progress=progress, log=log)
        if summary["steps_done"] != stage.steps:
            raise TrainingError(f"stage {stage.name} stopped after {summary['steps_done']} of "
                                f"{stage.steps} steps")
        done.append(_stage_line(stage, stage_dir, summary))
        previous_best = stage_dir / "checkpoints" / "best"
    result = {"model": str(previous_best), "stages": done,
              "seconds": float(sum(line["seconds"] for line in done))}
    write_json(out_dir / "summary.json", result)
    return result


def _stage_line(stage: Any, stage_dir: Path, summary: dict[str, Any]) -> dict[str, Any]:
    return {"name": stage.name, "dir": str(stage_dir), "steps": int(summary["steps_done"]),
            "best_loss": float(summary["best_loss"]), "seconds": float(summary["seconds"]),
            "n_records": int(summary["n_train_trajectories"])}
