"""Replays of a contact model's own free rollouts, and contact models derived from a trained one.

- :func:`floor_activity_run`: how often the rigid limit of the contact law (``[model]
  overlap_limit``, docs/contact.md "One step", item 7) sets a contact model's impulses in a free
  rollout. The rollout is run as ``run_rollout`` runs it; then every ``every``-th step is
  REPLAYED from the model's own frames (frames k-W..k, the motion's jar state, the spins
  ``omega_model`` of frame k) through ``ContactNet.step_terms``, and per contact kind it counts
  the acting contacts (gate), those at the floor (``at_floor``) and the share of the normal
  impulse the floor added, sum(du_n - learned) / sum(du_n) (m* cancels within a kind);
  ``learned`` is du_n where the floor did not set it, else du_n of the model with the limit off
  on the same graph (the model's own logits with one impulse pass, as all models so far).

  Replay check, every replayed step: x_k + (v_k + a dt) dt, a = dv / dt in float32 as the
  rollout integrates it, must be frame k + 1 (float32 ulps of max(|a|, 1)); w_k + (dw / dt) dt
  the next spin (ulps of the ball's contact moments R sum|J| / I: dw = R n x J / I cancels where
  J is nearly normal). A snap-back moves a ball's whole window unseen by the frames: each
  snapping step is replayed first and its shift recomputed as the rollout does. Without the
  shifts the check fails by 1e7 ulps; with them, a spin model with a 0.1-mm overlap limit on 24
  runs (1.5 s, 1665 snapped ball-steps): positions within 0.003 ulp, spins within 1.3. Graph
  and model run fused per window (``lax.map``): vmapped, XLA rounded the float32 centre
  distance by an ulp (1 nm), which the fine gap input tanh(gap / 5 um) turned into du_n
  differences of up to 0.2 %.
- :func:`derive_contact_model`: a trained model's parameters under a changed ``[model]``
  section (e.g. the overlap limit switched on without retraining), saved as a new checkpoint
  whose meta says where it came from.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from sgn_jax.config import config_to_dict, replace_section, save_config
from sgn_jax.motion import frequency_hz, offset, velocity
from sgn_jax.pipelines import configure
from sgn_jax.pipelines.rollout_run import _effective_config, run_rollout
from sgn_jax.pipelines.train_run import envelope_meta
from sgn_jax.records.checkpoint import TrainedModel, load_trained_model, save_checkpoint
from sgn_jax.surrogate.contact import ContactNet, edge_geometry
from sgn_jax.surrogate.contact_train import share_logits
from sgn_jax.surrogate.graph import build_graph, windows_from_arrays
from sgn_jax.surrogate.rollout import single_rollout_model, snap_back_shift

CHUNK = 250                    # replayed windows per jitted call (fixed: one compilation)
EPS32 = float(np.finfo(np.float32).eps)
KINDS = ("pp", "pw")


def make_replay(model, spec, query):
    """Jitted ``replay(params, windows, sdf)``: per window the tallies of both contact kinds
    and the accelerations the rollout integrates (``lax.map``: see the module docstring)."""
    free = model.clone(physics=dataclasses.replace(model.physics, overlap_limit=0.0,
                                                   overlap_law_factor=0.0))

    def one(params, sdf, window):
        graph = build_graph(window, sdf, spec, query)[0]
        terms = model.apply({"params": params}, graph, method=ContactNet.step_terms)
        learned = free.apply({"params": params}, graph, method=ContactNet.step_terms)["du_n"]
        geo = edge_geometry(graph, model.physics, primary_only=True, spin=model.spin)
        # only the floored rows take the clone's value (its float32 noise stays out elsewhere)
        added = terms["at_floor"] * (terms["du_n"] - jnp.minimum(learned, terms["du_n"]))
        out = {"accel": terms["dv"][:spec.n_particles] / model.physics.dt}  # as the rollout
        if model.spin:   # with each ball's sum of contact impulse sizes, the check's scale
            out["spin_accel"] = terms["dw"][:spec.n_particles] / model.physics.dt
            size = (jnp.where(geo["is_pw"], 1.0, 0.5) * model.physics.ball_mass
                    * jnp.hypot(terms["du_n"], terms["du_t"]))
            n_node = graph.nodes["features"].shape[0]
            out["impulse_sum"] = (jax.ops.segment_sum(size, geo["receivers"], n_node)
                                  + jax.ops.segment_sum(size * geo["is_pp"], geo["senders"],
                                                        n_node))[:spec.n_particles]
        for kind in KINDS:
            is_k = geo[f"is_{kind}"].astype(jnp.float32)
            for name, value in (("acting", terms["gate"]), ("at_floor", terms["at_floor"]),
                                ("du", terms["du_n"]), ("du_floor", added)):
                out[f"{kind}_{name}"] = jnp.sum(value * is_k)
        return out

    return jax.jit(lambda params, wins, sdf: jax.lax.map(lambda w: one(params, sdf, w), wins))


def carried_windows(pos, jar, ends, window, spins, shifts):
    """The windows ending at pos indices ``ends`` as the rollout carried them: the snap-back
    of frame s moved the window's older positions by its shift, so a slot is its frame plus
    the shifts of the later snaps within the window, added in their order (as the rollout)."""
    wins = windows_from_arrays(pos, *jar, ends, window, omega=spins)
    positions = np.array(wins.positions)
    slot = ends[:, None] + np.arange(-window, 1)[None]
    for s, shift in shifts.items():                      # chronological
        positions[(slot < s) & (ends[:, None] >= s)] += shift
    return wins.replace(positions=positions)


def replay_run(trained, model, replay, cfg, spec, sdf, query, traj, n_steps, every):
    """Roll out, replay every ``every``-th step, tally and check; returns the run's row."""
    window, dt, phys = spec.window, spec.dt, model.physics
    t_start = time.perf_counter()
    a = run_rollout(trained, traj, window, n_steps * dt, None, cfg, save_every=1,
                    progress=False)["arrays"]
    t_rollout = time.perf_counter() - t_start
    # pos index i = frame i - W: the DEM's samples before the start window, then the frames
    pos = np.concatenate([np.asarray(traj.pos[:window], np.float64), a["pos"]])
    times = float(traj.t[window]) + np.arange(-window, n_steps + 1) * dt   # t0 + step dt
    motion = configure.motion_from_config(cfg.motion)
    jar = [np.asarray(f(motion, jnp.asarray(times))) for f in (offset, velocity)]
    jar.append(float(frequency_hz(motion)))
    spins = (np.concatenate([np.zeros((window,) + a["omega_model"].shape[1:]),
                             a["omega_model"]]) if model.spin else None)

    def replay_at(ends):   # the carried windows ending at ``ends``: outputs and x_{k+1}
        win = carried_windows(pos, jar, ends, window, spins, shifts)
        out = jax.device_get(replay(trained.params, win, sdf))
        x_n, x_prev = win.positions[:, -1], win.positions[:, -2]   # the rollout's step:
        return out, x_n + ((x_n - x_prev) / dt + np.asarray(out["accel"], np.float64) * dt) * dt

    shifts = {}   # pos index -> (N, 3) m; step k made pos index k + W + 1
    for k in np.flatnonzero(a["n_snapped"]):
        x = replay_at(np.array([k + window]))[1][0]
        phi, n = (jnp.asarray(q, jnp.float64) for q in query(sdf, x, jar[0][k + window + 1]))
        shifts[k + window + 1] = np.asarray(snap_back_shift(phi, n, cfg.graph.phi_sb)[0])

    steps = np.arange(0, n_steps, every)
    ends = np.concatenate([steps, np.full(-len(steps) % CHUNK, steps[-1])]) + window
    outs, x_err = [], []
    for i in range(0, len(ends), CHUNK):
        chunk = ends[i:i + CHUNK]
        out, x = replay_at(chunk)
        outs.append(out)
        x += np.stack([shifts.get(e + 1, np.zeros(x.shape[1:])) for e in chunk])
        scale = EPS32 * np.maximum(np.linalg.norm(out["accel"], axis=-1), 1.0)
        x_err.append(np.linalg.norm(x - pos[chunk + 1], axis=-1) / dt ** 2 / scale)
    out = {k: np.concatenate([o[k] for o in outs])[:len(steps)] for k in outs[0]}
    row = {"seed": int(traj.meta.get("seed", -1)), "steps": n_steps, "replayed": len(steps),
           "snapped_ball_steps": int(np.sum(a["n_snapped"])),
           "check_max_ulp": float(np.max(np.concatenate(x_err))), "rollout_s": t_rollout,
           "replay_s": time.perf_counter() - t_start - t_rollout}
    if model.spin:
        dw = out["spin_accel"].astype(np.float64)
        moment = phys.ball_radius * out["impulse_sum"] / phys.inertia / dt   # rad/s^2
        scale = EPS32 * np.maximum(np.maximum(np.linalg.norm(dw, axis=-1), 1.0), moment)
        w_err = a["omega_model"][steps] + dw * dt - a["omega_model"][steps + 1]
        row["check_spin_max_ulp"] = float(np.max(np.linalg.norm(w_err, axis=-1) / dt / scale))
    for kind in KINDS:
        acting, du = out[f"{kind}_acting"].sum(), out[f"{kind}_du"].sum()
        row[f"{kind}_acting_per_step"] = float(acting / len(steps))
        row[f"{kind}_at_floor_share"] = float(out[f"{kind}_at_floor"].sum() / max(acting, 1))
        row[f"{kind}_floor_impulse_share"] = float(out[f"{kind}_du_floor"].sum() / max(du, 1e-30))
    return row


def make_floor_replay(trained: TrainedModel, case_cfg: Any,
                      compiled: dict[Any, Any] | None = None) -> dict[str, Any]:
    """Everything :func:`floor_activity_run` needs for the rollouts of one case config: the
    effective config (the model's physics, the case's scene and motion), its graph spec and
    walls, and the jitted replay. Pass the same ``compiled`` dict for every case: cases of one
    graph spec and walls then share the jitted replay (one compilation), each with its own
    config and motion."""
    model = single_rollout_model(trained.model)[0]   # the form run_rollout steps with
    if not isinstance(model, ContactNet):
        raise TypeError(f"floor activity needs a contact model, got {type(model).__name__}")
    cfg = _effective_config(trained.config, case_cfg)  # what run_rollout steps under
    spec = configure.graph_spec_from_config(cfg, n_particles=int(cfg.balls.count))
    sdf, query = configure.surrogate_walls_from_config(cfg)
    compiled = {} if compiled is None else compiled
    if (spec, query) not in compiled:
        compiled[(spec, query)] = make_replay(model, spec, query)
    return {"model": model, "cfg": cfg, "spec": spec, "sdf": sdf, "query": query,
            "replay": compiled[(spec, query)]}


def floor_activity_run(trained: TrainedModel, replay: dict[str, Any], traj: Any,
                       duration: float, every: int = 5) -> dict[str, Any]:
    """One free rollout of ``duration`` s from ``traj``'s first window under ``replay``'s
    config (:func:`make_floor_replay`), every ``every``-th step replayed: the row of the run
    (per kind: ``{kind}_acting_per_step``, ``{kind}_at_floor_share``,
    ``{kind}_floor_impulse_share``; the replay check's ``check_max_ulp``)."""
    spec = replay["spec"]
    return replay_run(trained, replay["model"], replay["replay"], replay["cfg"], spec,
                      replay["sdf"], replay["query"], traj, round(duration / spec.dt), every)


def derive_contact_model(checkpoint: str, out: str, shares: Any = None,
                         **model_changes: Any) -> str:
    """Save ``checkpoint``'s model (a run or checkpoint directory) with its ``[model]`` section
    changed by ``model_changes`` (e.g. ``overlap_limit=1e-4``) as a new run directory ``out``
    (``out/checkpoints/best``), the same parameters; its meta's ``derived_from`` names the
    source and the change, and a source without the envelope its ``[train]`` section names
    (older contact runs did not record it) gets it. ``shares`` (ball-ball, ball-wall) replace
    the fitted damping shares (``share_logit``): a change of ``damping_target`` changes what
    they mean and needs them (``tangential_damping_shares`` or ``dissipation_shares`` of the
    model's training records, sgn_jax.surrogate.contact_train). Refuses an existing ``out``,
    a model that is not a contact model and a ``damping_target`` change without ``shares``.
    ``out`` also gets the changed config as ``config.toml`` and the source run's own records
    (``run_info.json``, ``summary.json``, ``loss.png``, ``metrics.csv``, where the source lies in a
    run directory), so that it ships as a run (``experiments/tools/ship_model.py --run out``).
    Returns ``out``."""
    if os.path.exists(out):
        raise FileExistsError(f"{out} exists: choose a new directory")
    trained = load_trained_model(checkpoint)
    if getattr(trained.config.model, "kind", "sgn") not in ("contact", "contact_charge"):
        raise ValueError(f"{checkpoint} is not a contact model (kind 'contact' or "
                         "'contact_charge')")
    cfg = replace_section(trained.config, "model", **model_changes)
    params = trained.params
    if shares is not None:
        params = {**params, "share_logit": share_logits(tuple(float(x) for x in shares))}
        model_changes = {**model_changes, "shares": [float(x) for x in shares]}
    elif cfg.model.damping_target != trained.config.model.damping_target:
        raise ValueError(f"damping_target {trained.config.model.damping_target!r} -> "
                         f"{cfg.model.damping_target!r} changes what the fitted shares mean: "
                         "pass shares= (tangential_damping_shares of the training records)")
    meta = {k: v for k, v in dict(trained.meta).items()
            if not k.endswith("_digest") and k not in ("format_version", "has_opt_state")}
    if "envelope" not in meta:   # models trained before the contact trainer recorded it
        meta.update(envelope_meta(cfg.train))
    meta.update(config=config_to_dict(cfg),
                derived_from={"model": os.path.abspath(checkpoint),
                              "change": {k: model_changes[k] for k in sorted(model_changes)}})
    save_checkpoint(os.path.join(out, "checkpoints", "best"), int(meta.get("step", 0)),
                    params=params, norm_stats=trained.norm_stats, meta=meta, keep=1)
    save_config(cfg, os.path.join(out, "config.toml"))
    source_run = _run_directory(checkpoint)
    if source_run is not None:
        for name in RUN_RECORDS:
            if os.path.isfile(os.path.join(source_run, name)):
                shutil.copy2(os.path.join(source_run, name), os.path.join(out, name))
    return out


RUN_RECORDS: tuple[str, ...] = ("run_info.json", "summary.json", "loss.png", "metrics.csv")
"""A training run's own records that a model derived from it carries (its settings, its
wall time and losses), for ``experiments/tools/ship_model.py``."""


def _run_directory(checkpoint: str) -> str | None:
    """The training run directory that holds ``checkpoint`` (RUN, RUN/checkpoints/NAME or
    RUN/checkpoints/NAME/STEP: the nearest of it and its three parents with a
    ``summary.json``), or None (a shipped model's folder, a bare checkpoint)."""
    path = os.path.abspath(checkpoint)
    for _ in range(4):
        if os.path.isfile(os.path.join(path, "summary.json")):
            return path
        path = os.path.dirname(path)
    return None
