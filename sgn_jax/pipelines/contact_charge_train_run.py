"""Training driver of the charge-conditioned contact model (kind "contact_charge") on DEM
records of many charges (``data/charges/<name>/seed_K.npz``).

Each record brings its own charge: its config (the record's metadata) gives the classes and
materials (:func:`sgn_jax.pipelines.configure.charge_from_config`), its ``ball_radii`` and
``ball_masses`` the per-ball values; every record is padded to the largest ball count of the
set (:mod:`sgn_jax.surrogate.contact_charge_train`). The training config (e.g.
``sgn_jax/configs/contact_charge_train.toml``) gives the jar (every record must have it), the
step, the graph and the model; its ``[balls]`` is only the reference ball of the graph's skins.
The checkpoint states the envelope the model covers (:func:`stated_envelope`, meta key
``envelope``; docs/contact_charge.md, "What it covers").

    python -m sgn_jax.pipelines.contact_charge_train_run --config contact_charge_train \\
        --data data/charges --out runs/contact_charge --steps 200
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax

from sgn_jax.config import config_from_dict, config_to_dict, resolve_config, save_config
from sgn_jax.pipelines.configure import (
    charge_from_config,
    graph_spec_from_config,
    surrogate_walls_from_config,
)
from sgn_jax.pipelines.contact_train_run import identity_stats
from sgn_jax.pipelines.train_run import at_model_step, named_envelope
from sgn_jax.records.charge_envelope import (
    charge_circle_notes,
    charge_model_envelope,
    load_charge_envelope,
)
from sgn_jax.records.checkpoint import latest_step, restore_checkpoint, save_checkpoint
from sgn_jax.records.io_utils import write_json
from sgn_jax.records.trajectory import load_trajectory
from sgn_jax.surrogate.contact_charge import ball_charge, make_contact_charge_net
from sgn_jax.surrogate.contact_charge_train import (
    ChargeStretchSource,
    make_charge_unroll_loss,
    pad_balls,
    parked,
)
from sgn_jax.surrogate.contact_train import (
    ContactTrainState,
    UnrollSpec,
    init_on_first_stretch,
    make_optimizer,
    make_train_step,
    share_logits,
    tangential_damping_shares,
    velocity_change_scale,
)
from sgn_jax.surrogate.train import TrainingError


def charge_source(cfg: Any, trajectories: Sequence[Any], n_max: int, classes: int,
                  unroll: int, spin: bool) -> ChargeStretchSource:
    """The padded stretch source of records (each with its config in ``meta["config"]``)."""
    dt = float(cfg.dem.dt)
    positions, offsets, offset_vel, charges, scales, spins = [], [], [], [], [], []
    for t in trajectories:
        meta = t.meta
        record_cfg = config_from_dict(meta["config"])
        if config_to_dict(record_cfg)["jar"] != config_to_dict(cfg)["jar"]:
            raise TrainingError(f"{getattr(t, 'path', '?')}: its jar is not the config's")
        charge = charge_from_config(record_cfg)
        radii = meta.get("ball_radii")
        masses = meta.get("ball_masses")
        charges.append(ball_charge(charge, n_balls=n_max, classes=classes, radii=radii,
                                   masses=masses))
        t = at_model_step(t, dt)
        pos = np.asarray(t.pos, np.float64)
        n = pos.shape[1]
        positions.append(pad_balls(pos, n_max, parked(n_max - n)))
        offsets.append(np.asarray(t.offset, np.float64))
        offset_vel.append(np.asarray(t.offset_vel, np.float64))
        scales.append(velocity_change_scale(pos, dt))
        if spin:
            spins.append(pad_balls(np.asarray(t.omega, np.float64), n_max))
    return ChargeStretchSource(positions=positions, offsets=offsets,
                               offset_velocities=offset_vel, charges=charges,
                               scales=np.asarray(scales), window=int(cfg.graph.window),
                               unroll=unroll, spins=spins if spin else None)


def stated_envelope(cfg: Any, record_configs: Sequence[Any]) -> dict[str, Any]:
    """The ``envelope`` meta of a charge model trained on records of ``record_configs``: the
    charge envelope (sgn_jax/data/charge_envelope.toml: its charges on its circles) and, when
    a record's motion is not one of those circles (the standard charge's training motions of
    the recipe's later stages), the motion envelope ``[train] envelope`` names (the default
    one when it names none): :func:`sgn_jax.records.charge_envelope.charge_model_envelope`."""
    charges = load_charge_envelope()
    off_circle = any(charge_circle_notes(c.motion, charges) for c in record_configs)
    motion = named_envelope(cfg.train.envelope or "default") if off_circle else None
    return charge_model_envelope(motion, charges)


def train_contact_charge(cfg: Any, record_paths: Sequence[str | Path], out_dir: str | Path, *,
                         steps: int = 1000, batch_size: int = 8,
                         unroll: UnrollSpec | None = None, lr_init: float = 1e-3,
                         lr_final: float = 3e-5, seed: int = 0, classes: int = 3,
                         log_every: int = 10, checkpoint_every: int = 200,
                         resume: bool = False, init_from: str | Path | None = None
                         ) -> dict[str, Any]:
    """Train kind "contact_charge" on the records; writes ``checkpoints/latest`` (every
    ``checkpoint_every`` steps and at the end, with the optimiser state), ``run_info.json`` and
    ``summary.json`` to ``out_dir``. A killed run goes on from its latest checkpoint with
    ``resume=True`` (the batches are drawn from ``(seed, step)``, so a resumed run draws what
    an unbroken one would); without it a run directory that holds a checkpoint is an error.
    ``init_from``: a checkpoint directory (e.g. an earlier stage's ``checkpoints/latest``)
    whose parameters start the run instead of a fresh initialisation (a later stage: longer
    unrolls, pushforward, a lower learning rate). Returns the summary."""
    if cfg.model.kind != "contact_charge":
        raise TrainingError(f"train_contact_charge trains kind 'contact_charge', got "
                            f"{cfg.model.kind!r}")
    unroll = UnrollSpec() if unroll is None else unroll
    trajectories = [load_trajectory(p) for p in record_paths]
    if not trajectories:
        raise TrainingError("no training records")
    n_max = max(np.asarray(t.pos).shape[1] for t in trajectories)
    spec = dataclasses.replace(graph_spec_from_config(cfg, n_particles=n_max),
                               pp_pair_capacity=max(1, cfg.graph.pp_edges_per_particle * n_max
                                                    // 2))
    net = make_contact_charge_net(cfg)
    source = charge_source(cfg, trajectories, n_max, classes, unroll.unroll, net.spin)
    sdf, query = surrogate_walls_from_config(cfg)
    shares = tangential_damping_shares(trajectories)
    envelope = stated_envelope(cfg, [config_from_dict(t.meta["config"]) for t in trajectories])

    example = source.draw(np.random.default_rng(0), 1)
    params = init_on_first_stretch(net, spec, sdf, query, example, jax.random.PRNGKey(seed))
    params = {**params, "share_logit": share_logits(shares)}
    if init_from is not None:   # a later stage: the earlier stage's weights, the same shapes
        warm = restore_checkpoint(init_from).params
        if jax.tree_util.tree_structure(warm) != jax.tree_util.tree_structure(params):
            raise TrainingError(f"{init_from}: its parameters are not this config's model's")
        params = {**warm, "share_logit": params["share_logit"]}
    schedule = optax.cosine_decay_schedule(lr_init, steps, alpha=lr_final / lr_init)
    tx = make_optimizer(schedule)
    opt_state = tx.init(params)
    out_dir = Path(out_dir)
    ckpt_latest = out_dir / "checkpoints" / "latest"
    done = latest_step(ckpt_latest)
    if done is not None and not resume:
        raise TrainingError(f"{out_dir} already holds a training run (step {done}); pass "
                            "--resume to continue it or choose another --out")
    losses: list[float] = []
    if done is not None:
        full = restore_checkpoint(ckpt_latest, opt_state_like=opt_state)
        params, opt_state = full.params, full.opt_state
        previous = out_dir / "losses.json"
        losses = json.loads(previous.read_text())[:done] if previous.is_file() else []
    state = ContactTrainState(jax.tree_util.tree_map(jnp.asarray, params),
                              jax.tree_util.tree_map(jnp.asarray, opt_state),
                              jnp.asarray(done or 0, jnp.int32))
    train_step = make_train_step(make_charge_unroll_loss(net, spec, sdf, query, unroll), tx)

    out_dir.mkdir(parents=True, exist_ok=True)
    save_config(cfg, out_dir / "config.toml")
    info = {"model_kind": "contact_charge", "records": [str(p) for p in record_paths],
            "n_max": n_max, "classes": classes, "steps": steps, "batch_size": batch_size,
            "unroll": unroll.unroll, "pushforward": unroll.pushforward,
            "init_from": None if init_from is None else str(init_from),
            "relative_floor": unroll.relative_floor, "touch_weight": unroll.touch_weight,
            "lr_init": lr_init, "lr_final": lr_final,
            "tangential_damping_shares": {"pp": shares[0], "pw": shares[1]},
            "n_params": int(sum(p.size for p in jax.tree_util.tree_leaves(params)))}
    write_json(out_dir / "run_info.json", info)
    t0 = time.perf_counter()
    first = done or 0

    def checkpoint(step: int) -> None:
        save_checkpoint(ckpt_latest, step, params=state.params,
                        norm_stats=identity_stats(spec.window), opt_state=state.opt_state,
                        meta={"config": config_to_dict(cfg), "info": info,
                              "envelope": envelope, "global_step": step}, keep=1)
        write_json(out_dir / "losses.json", losses)

    for step_no in range(first, steps):
        batch = source.draw(np.random.default_rng([seed, step_no]), batch_size)
        state, value, _ = train_step(state, batch, jax.random.PRNGKey(step_no))
        losses.append(float(value))
        if not np.isfinite(losses[-1]):
            raise TrainingError(f"non-finite training loss at step {step_no}")
        if (step_no + 1) % log_every == 0 or step_no == first:
            elapsed = time.perf_counter() - t0
            rate = (step_no + 1 - first) / max(elapsed, 1e-9)
            print(json.dumps({"step": step_no + 1, "loss": round(losses[-1], 5),
                              "seconds": round(elapsed, 1), "steps_per_s": round(rate, 3),
                              "eta_min": round((steps - step_no - 1) / rate / 60, 1)}),
                  flush=True)
        if (step_no + 1) % checkpoint_every == 0 and step_no + 1 < steps:
            checkpoint(step_no + 1)
    checkpoint(steps)
    summary = {**info, "losses": losses, "seconds": time.perf_counter() - t0}
    write_json(out_dir / "summary.json", summary)
    return summary


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--config", default="contact_charge_train")
    ap.add_argument("--data", required=True, help="folder of <charge>/seed_K.npz records")
    ap.add_argument("--out", required=True)
    ap.add_argument("--charges", nargs="*", default=None, help="charge folder names (all)")
    ap.add_argument("--records", nargs="*", default=[],
                    help="further records (e.g. the standard charge's training motions, "
                    "data/envelope/train_*.npz)")
    ap.add_argument("--resume", action="store_true",
                    help="go on from the run's latest checkpoint (a killed run)")
    ap.add_argument("--checkpoint-every", type=int, default=200)
    ap.add_argument("--init-from", default=None,
                    help="start from this checkpoint's parameters (a later stage)")
    ap.add_argument("--pushforward", action="store_true",
                    help="cut the gradient between unrolled steps (GNS pushforward)")
    ap.add_argument("--touch-weight", type=float, default=0.0,
                    help="weight of the contact-state term (docs/contact_charge.md; 0: off)")
    ap.add_argument("--lr-init", type=float, default=1e-3)
    ap.add_argument("--lr-final", type=float, default=3e-5)
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--batch-size", type=int, default=8)
    ap.add_argument("--unroll", type=int, default=6)
    args = ap.parse_args(argv)
    cfg = resolve_config(args.config)  # a built-in name or a TOML path
    data = Path(args.data)
    names = args.charges or sorted(p.name for p in data.iterdir() if p.is_dir())
    paths = [p for name in names for p in sorted((data / name).glob("seed_*.npz"))]
    paths += [Path(p) for p in args.records]
    unroll = UnrollSpec(unroll=args.unroll, relative_floor=3e-4, pushforward=args.pushforward,
                        touch_weight=args.touch_weight)
    summary = train_contact_charge(cfg, paths, args.out, steps=args.steps,
                                   batch_size=args.batch_size, unroll=unroll,
                                   checkpoint_every=args.checkpoint_every, resume=args.resume,
                                   init_from=args.init_from, lr_init=args.lr_init,
                                   lr_final=args.lr_final)
    print(json.dumps({k: summary[k] for k in ("n_max", "steps", "seconds")}))


if __name__ == "__main__":
    main()
