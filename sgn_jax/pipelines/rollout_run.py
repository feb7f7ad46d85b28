"""Host driver of the surrogate rollout: a trained model and a dataset window -> prediction file.

The pure, jittable rollout is :mod:`sgn_jax.surrogate.rollout` (``make_rollout`` /
``make_rollout_advance``); this module meets it with a config (the trained model's, optionally with
another jar, motion, SDF and rollout section), a dataset trajectory for the initial window, timing
and the prediction file (``sgn-jax rollout``).
"""

from __future__ import annotations

import dataclasses
import datetime
import math
import time
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

import sgn_jax
from sgn_jax.config import ConfigError, config_from_dict, config_to_dict, replace_section
from sgn_jax.pipelines.configure import (
    charge_from_config,
    graph_spec_from_config,
    model_takes_charge,
    motion_from_config,
    surrogate_walls_from_config,
)
from sgn_jax.records.io_utils import git_commit
from sgn_jax.records.prediction import save_prediction
from sgn_jax.records.trajectory import DatasetError
from sgn_jax.surrogate.collisions import (
    DEFAULT_CAPACITY,
    EVENT_FORCE_FRACTION,
    STANDARD_GRAVITY,
    check_capacity,
    collision_arrays,
    concat_tables,
    pending_energy,
)
from sgn_jax.surrogate.contact_charge import ball_charge
from sgn_jax.surrogate.graph import Window, windows_from_arrays
from sgn_jax.surrogate.rollout import (
    RolloutError,
    RolloutResult,
    check_neighbours,
    empty_neighbour_list,
    init_state,
    jar_state_window,
    make_rollout_advance,
    model_predictor,
    single_rollout_model,
)

# A single rollout of this many balls or more tests its ball-ball candidates from a neighbour
# list (sgn_jax.surrogate.rollout.NeighbourList) instead of all N (N - 1) / 2 pairs: the same
# graphs, a step whose cost grows linearly with N (docs/rollout.md). Below it all pairs cost
# less than keeping the list.
NEIGHBOUR_LIST_MIN_BALLS = 48
# The list's margin over the graph's reach (m): a ball moves ~0.1 mm per 1e-4 s step at 1 m/s,
# so a list lasts several steps; and its capacity in pairs per ball: in a random close packing
# of 6 mm balls ~14 centres lie within 6 + 1.5 + 1 mm of a ball's (7 pairs per ball); a list
# that finds more refuses the run (check_neighbours).
NEIGHBOUR_SKIN_M = 1.0e-3
NEIGHBOUR_PAIRS_PER_BALL = 10


def coarser_step_factor(model_dt: float, case_dt: float) -> int:
    """The integer factor k > 1 with ``model_dt = k case_dt`` (a case sampled finer than the
    model's step, e.g. a 1e-4 s case and the 2e-4 s contact model), or 1 when there is none
    (the same step, or steps that are not whole multiples)."""
    factor = round(model_dt / case_dt) if case_dt > 0 else 1
    if factor > 1 and math.isclose(model_dt, factor * case_dt, rel_tol=1e-9):
        return int(factor)
    return 1


def config_at_model_step(cfg: Any, model_dt: float) -> Any:
    """``cfg`` sampled at a model's step ``model_dt`` (s) when that step is a whole multiple
    of ``cfg``'s ``[dem] dt`` (:func:`coarser_step_factor`: the 2e-4 s contact model on a
    1e-4 s case): ``[dem] dt`` is the sampling and surrogate step, so the DEM of the returned
    config records at the model's step (its own step is ``dt_dem_max``). Otherwise ``cfg``."""
    if coarser_step_factor(float(model_dt), float(cfg.dem.dt)) > 1:
        return replace_section(cfg, "dem", dt=float(model_dt))
    return cfg


# The sections that make the charge: a kind that reads the charge (``model_takes_charge``)
# takes them from the case, every other kind keeps the trained model's.
CHARGE_SECTIONS = ("balls", "material", "materials", "interactions")


def _effective_config(trained_cfg: Any, override: Any) -> Any:
    """The trained model's config with [jar], [motion], [sdf] and [rollout] of ``override``,
    and for a kind that reads the charge also its charge (:data:`CHARGE_SECTIONS`).
    A case sampled at a finer step than the model's by an integer factor (a 1e-4 s case and the
    2e-4 s contact model) runs at the model's step, as ``sgn_jax.api.at_surrogate_step`` does
    for design studies (the initial record is coarsened to it)."""
    if override is None:
        return trained_cfg
    takes_charge = model_takes_charge(trained_cfg)
    for section, fields in (("balls", () if takes_charge else ("count", "radius")),
                            ("dem", ("dt",))):
        for name in fields:
            a, b = getattr(getattr(trained_cfg, section), name), getattr(getattr(override,
                                                                                 section), name)
            if section == "dem" and coarser_step_factor(a, b) > 1:
                continue
            if a != b:
                raise RolloutError(
                    f"the override config has [{section}] {name} = {b} but the model was trained "
                    f"with {a}; a config override may change only [jar], [motion], [sdf] and "
                    "[rollout]")
    charge = {name: getattr(override, name) for name in CHARGE_SECTIONS} if takes_charge else {}
    return dataclasses.replace(trained_cfg, jar=override.jar, motion=override.motion,
                               sdf=override.sdf, rollout=override.rollout, **charge)


def record_charge_config(cfg: Any, traj: Any, override_given: bool) -> Any:
    """The config whose charge a charge-reading kind rolls out: ``cfg`` (the effective one)
    when a case config was given, otherwise the charge of the record the rollout starts from
    (its meta ``config``: the DEM run that made it), so that a DEM record of any charge is
    rolled out with its own balls."""
    meta_cfg = getattr(traj, "meta", {}).get("config")
    if override_given or meta_cfg is None:
        return cfg
    try:
        record_cfg = config_from_dict(meta_cfg)
    except ConfigError as exc:
        raise RolloutError(f"the initial record's config cannot be read for its charge: {exc}; "
                           "give the case config") from None
    return dataclasses.replace(cfg, **{name: getattr(record_cfg, name)
                                       for name in CHARGE_SECTIONS})


def window_charge(cfg: Any, traj: Any, n_balls: int) -> Any:
    """The :class:`sgn_jax.surrogate.graph.BallCharge` of a rollout of ``n_balls`` balls from
    ``traj``: the charge of ``cfg`` with the record's own ball radii and masses where its meta
    has them (a DEM record of a mixture). RolloutError when the counts or radii disagree."""
    charge = charge_from_config(cfg)
    if charge.n_balls != n_balls:
        raise RolloutError(f"the charge has {charge.n_balls} balls ([balls] and [[balls.mix]]) "
                           f"but the initial record has {n_balls}; roll out the record with "
                           "the config of the DEM run that made it")
    meta = getattr(traj, "meta", {})
    radii, masses = meta.get("ball_radii"), meta.get("ball_masses")
    if radii is not None and not np.allclose(np.asarray(radii, np.float64), charge.radii,
                                             rtol=1e-9, atol=0.0):
        raise RolloutError("the initial record's ball radii (meta ball_radii) are not the "
                           "charge's, ball by ball; roll out the record with the config of the "
                           "DEM run that made it")
    return ball_charge(charge, n_balls=n_balls, radii=radii, masses=masses)


def initial_window(traj: Any, start_index: int, window: int, freq: float = 0.0) -> Window:
    """The :class:`Window` of a trajectory ending at sample ``start_index`` (float64 numpy),
    with the balls' spins there where the trajectory records them (``omega``; a model with
    spin state starts from them, every other kind ignores them)."""
    n_samples = int(np.shape(traj.pos)[0])
    if not window <= start_index < n_samples:
        raise RolloutError(
            f"start index {start_index} is out of range: a window of {window} slots needs "
            f"{window} earlier samples, so use {window} <= start index <= {n_samples - 1}")
    wins = windows_from_arrays(traj.pos, traj.offset, traj.offset_vel, freq,
                               np.array([start_index]), window,
                               omega=getattr(traj, "omega", None))
    return jax.tree_util.tree_map(lambda a: np.asarray(a)[0], wins)


# Pair-capacity tiers trade compile time for run time: the step is compiled once per tier
# (a lax.switch of three graphs instead of one), which for the standard SGN (hidden 256) added
# 1.4 s of compile and saved 0.27 ms per step on one core (docs/benchmarks.md, realistic
# states: 1.6 -> 3.0 s, 1.145 -> 0.880 ms). They pay back after ~5,000 steps; shorter rollouts
# (a quick look, a test) run faster without them, and the numbers are the same either way.
TIERS_MIN_STEPS = 5000


def pair_capacity_tiers(capacity: int, n_steps: int, tiers_help: bool = True) -> tuple[int, ...]:
    """The ball-pair capacity tiers of a single rollout of ``n_steps`` steps: 1/4 and 1/2 of the
    graph's ``capacity`` (those in (0, capacity)) when the model kind is sped up by tiers
    (``tiers_help``) and the rollout is long enough to repay their compile
    (``n_steps >= TIERS_MIN_STEPS``); otherwise none."""
    if not tiers_help or n_steps < TIERS_MIN_STEPS:
        return ()
    return tuple(t for t in sorted({capacity // 4, capacity // 2}) if 0 < t < capacity)


def run_rollout(trained_model: Any, init_traj: Any, start_index: int | None, duration: float,
                out_path: str | Path | None = None, cfg_override: Any = None, *,
                save_every: int | None = None, progress: bool = True,
                checkpoint_path: str | None = None, collisions: bool = False,
                collision_capacity: int = DEFAULT_CAPACITY,
                collision_force_fraction: float = EVENT_FORCE_FRACTION) -> dict[str, Any]:
    """Roll a trained SGN out from a dataset's window and save a prediction file.

    Runs in jitted chunks of ``[rollout] chunk_steps`` with a progress bar, with ball-pair
    capacity tiers of 1/4 and 1/2 of the graph's capacity (:func:`make_rollout`; speed only)
    for a model kind they speed up (its ``capacity_tiers_help``, default True; the contact
    kind runs faster without them) when the rollout has at least ``TIERS_MIN_STEPS`` steps
    (:func:`pair_capacity_tiers`), and the model's single-rollout form where it has one
    (``for_single_rollout``).

    Args:
        trained_model: :class:`sgn_jax.records.checkpoint.TrainedModel` (model, params, stats,
            config).
        init_traj: a :class:`sgn_jax.records.trajectory.Trajectory`; the initial window ends at
            sample ``start_index`` (W <= start_index < T), time ``t0 = traj.t[start_index]``;
            None: the first sample with a full window at the model's step (W, times the step
            ratio for a record sampled finer than the model).
        duration: seconds of rollout; S = round(duration / dt) steps, a multiple of save_every.
        out_path: prediction ``.npz`` (:func:`sgn_jax.records.prediction.save_prediction`), or None.
        cfg_override: a config whose [jar], [motion], [sdf] and [rollout] replace the trained
            model's (balls and dt must agree).
        save_every: steps between saved frames (default ``[rollout] save_every``).
        progress: tqdm bar (steps, rate, ETA).
        checkpoint_path: recorded in the meta.
        collisions: record the collision ledger (a contact model only;
            :mod:`sgn_jax.surrogate.collisions`): the prediction gains the ``collision_*``
            event arrays, the events still open at the end flushed (flags bit 1), and the
            summary ``collision_events``.
        collision_capacity: events the ledger holds per chunk of ``[rollout] chunk_steps``
            steps; a chunk that closes more raises
            :class:`sgn_jax.surrogate.collisions.CollisionCapacityError` saying so.
        collision_force_fraction: a contact touches in a step when its normal force is at
            least this fraction of its reduced mass's weight (default
            :data:`sgn_jax.surrogate.collisions.EVENT_FORCE_FRACTION`, docs/collisions.md).

    Returns:
        a summary dict (steps, energy, counts, wall and compile time, ms per step); the arrays
        and meta under "arrays" and "meta".
    """
    from tqdm.auto import tqdm

    cfg = _effective_config(trained_model.config, cfg_override)
    takes_charge = model_takes_charge(cfg)
    rcfg = cfg.rollout
    k = int(save_every or rcfg.save_every)
    dt = float(cfg.dem.dt)
    if not duration > 0:
        raise RolloutError(f"duration must be > 0 s, got {duration}")
    capacity = check_capacity(collision_capacity) if collisions else 0
    n_steps = int(round(duration / dt))
    if n_steps < k or n_steps % k:
        raise RolloutError(f"duration {duration:g} s = {n_steps} steps of dt = {dt:g} s must be a "
                           f"positive multiple of save_every = {k} steps")
    traj_dt = float(init_traj.meta["dt"]) if "dt" in init_traj.meta else dt
    if start_index is None:
        start_index = int(cfg.graph.window) * max(1, round(dt / traj_dt))
    record_index = int(start_index)   # the sample index in the given record (meta init_index)
    if not math.isclose(traj_dt, dt, rel_tol=1e-9):
        # A record sampled finer than the model's step by an integer factor gives its window
        # coarsened (start_index counts the record's own samples).
        factor = max(1, round(dt / traj_dt))
        if not hasattr(init_traj, "at_step") or record_index % factor:
            raise RolloutError(f"the initial dataset has dt = {traj_dt:g} s but the model uses "
                               f"dt = {dt:g} s, and its window at sample {start_index} cannot "
                               "be coarsened to it (dt must be an integer multiple of the "
                               "record's step, and the start sample a multiple of that factor)")
        try:
            coarse = init_traj.at_step(dt)
        except DatasetError as exc:
            raise RolloutError(str(exc)) from exc
        start_index = record_index // factor
        init_traj = coarse
    n_balls = int(np.shape(init_traj.pos)[1])
    charge = None
    if takes_charge:   # any charge: the case's or the record's own (record_charge_config)
        cfg = record_charge_config(cfg, init_traj, cfg_override is not None)
        charge = window_charge(cfg, init_traj, n_balls)
    else:
        radius = init_traj.meta.get("ball_radius", cfg.balls.radius)
        if not math.isclose(float(radius), cfg.balls.radius, rel_tol=1e-9):
            raise RolloutError(f"the initial dataset's balls have radius {radius} m, the "
                               f"model's {cfg.balls.radius} m")
    # A charge-reading kind's graph keeps the trained config's [balls] radius: its skins
    # (pw_skin = -phi_pw - ball_radius) and the snap-back's phi_sb are set against it and
    # applied to each ball's own radius (docs/contact_charge.md).
    spec_cfg = dataclasses.replace(cfg, balls=trained_model.config.balls) if takes_charge else cfg
    spec = graph_spec_from_config(spec_cfg, n_particles=n_balls)
    window0 = initial_window(init_traj, int(start_index), spec.window)
    if charge is not None:
        window0 = window0.replace(charge=charge)
    t0 = float(init_traj.t[start_index])
    motion = motion_from_config(cfg.motion)
    sdf, query = surrogate_walls_from_config(cfg)
    chunk = min(int(rcfg.chunk_steps) // k * k or k, n_steps)
    cap = spec.pp_pair_capacity
    model, tiers = single_rollout_model(trained_model.model)   # one rollout, not vmapped
    options = dict(query=query, checkpoint_steps=min(rcfg.checkpoint_steps, chunk) // k * k or k,
                   snap_back=rcfg.snap_back, phi_sb=cfg.graph.phi_sb,
                   snap_velocity=rcfg.snap_velocity,
                   pp_max_overlap=(rcfg.pp_max_overlap if rcfg.pp_separation else None),
                   pp_capacity_tiers=pair_capacity_tiers(cap, n_steps, tiers))
    predictor = model_predictor(model, collisions=bool(collisions))
    options["collisions"] = bool(collisions)
    if collisions:
        options["collision_capacity"] = capacity
    params = jax.device_put(trained_model.params)
    stats = jax.device_put(trained_model.norm_stats)

    state = jax.jit(init_state, static_argnums=(3, 4))(window0, motion, t0, spec.dt, capacity)
    if n_balls >= NEIGHBOUR_LIST_MIN_BALLS:   # one rollout of many balls: a step linear in N
        state = state.replace(neighbours=empty_neighbour_list(
            state.window, NEIGHBOUR_PAIRS_PER_BALL * n_balls, NEIGHBOUR_SKIN_M))
    if collisions:   # the force floor of a touching contact (docs/collisions.md)
        if not collision_force_fraction >= 0:
            raise RolloutError(f"collision_force_fraction must be >= 0, got "
                               f"{collision_force_fraction!r}")
        state = state.replace(collisions=state.collisions.replace(
            min_force_per_kg=jnp.asarray(collision_force_fraction * STANDARD_GRAVITY,
                                         jnp.float64)))
    tables: list[dict[str, np.ndarray]] = []
    compiled: dict[int, Any] = {}
    compile_time = 0.0
    parts: list[RolloutResult] = []
    t_wall = time.perf_counter()
    run_time = 0.0
    with tqdm(total=n_steps, desc="rollout", unit="step", disable=not progress,
              dynamic_ncols=True) as bar:
        done = 0
        while done < n_steps:
            n = min(chunk, n_steps - done)
            if n not in compiled:
                t_c = time.perf_counter()
                advance = make_rollout_advance(spec, predictor, n, k, **options)
                compiled[n] = advance.lower(params, stats, state, motion, sdf, t0).compile()
                compile_time += time.perf_counter() - t_c
            t_r = time.perf_counter()
            result = jax.device_get(compiled[n](params, stats, state, motion, sdf, t0))
            run_time += time.perf_counter() - t_r
            state = result.final
            check_neighbours(state)
            if collisions:   # drain the chunk's events (and at the end flush the open ones)
                tables.append(collision_arrays(
                    state.collisions, int(state.step) if done + n == n_steps else None,
                    f", or shorten the chunks ([rollout] chunk_steps = {chunk})"))
                state = state.replace(collisions=state.collisions.replace(count=np.int32(0)))
            if not np.all(np.isfinite(result.positions)):
                bad = int(np.flatnonzero(~np.isfinite(result.positions).all(axis=(1, 2)))[0])
                raise RolloutError(
                    f"the rollout diverged: non-finite positions by t = "
                    f"{float(result.t_pos[bad]):.6g} s (step {done + (bad + 1) * k}); check the "
                    "model and the overflow/outside counts")
            parts.append(result)
            done += n
            bar.set_postfix_str(f"{1e3 * run_time / done:.3f} ms/step, "
                                f"E={float(state.energy):.4g} J")
            bar.update(n)
    wall_time = time.perf_counter() - t_wall

    arrays = {name: np.concatenate([p.prediction_arrays()[name] for p in parts])
              for name in parts[0].prediction_arrays()}
    w0 = jax.device_get(jar_state_window(window0, motion, t0, spec.dt))
    arrays["t_pos"] = np.concatenate([[t0], arrays["t_pos"]])
    arrays["pos"] = np.concatenate([np.asarray(w0.positions[-1])[None], arrays["pos"]])
    arrays["offset"] = np.concatenate([np.asarray(w0.offsets[-1])[None], arrays["offset"]])
    if "omega_model" in arrays:   # the spins of the frames, the initial one first as for pos
        arrays["omega_model"] = np.concatenate([np.asarray(w0.spins)[None],
                                                arrays["omega_model"]])
    if collisions:
        arrays.update(concat_tables(tables))
    summary = {
        "steps": n_steps,
        "duration_s": n_steps * dt,
        "t_start": t0,
        "energy_J": float(arrays["energy_cum"][-1]),
        "overflow_total": int(arrays["overflow"].sum()),
        "outside_ball_steps": int(arrays["n_outside"].sum()),
        "snapped_ball_steps": int(arrays["n_snapped"].sum()),
        "mean_pp_pairs": float(arrays["n_pp_edges"].mean() / 2),
        "wall_time_s": wall_time,
        "compile_time_s": compile_time,
        "ms_per_step": 1e3 * run_time / n_steps,
    }
    if collisions:
        summary["collision_events"] = int(arrays["collision_ball"].size)
        summary["collision_pending_J"] = pending_energy(state.collisions).tolist()
    meta = {
        "dt": dt, "save_every": k, "init_index": record_index,
        "config": config_to_dict(cfg),
        "checkpoint": checkpoint_path,
        "init_dataset": getattr(init_traj, "path", None),
        "code_version": f"sgn_jax {sgn_jax.__version__} ({git_commit()})",
        "created": datetime.datetime.now(datetime.UTC).isoformat(),
        "surrogate": "SGN",
        "snap_back": bool(rcfg.snap_back), "snap_velocity": rcfg.snap_velocity,
        "pp_max_overlap": rcfg.pp_max_overlap if rcfg.pp_separation else None,
        "phi_sb": float(cfg.graph.phi_sb),
        **({"ball_radii": np.asarray(charge.radius).tolist(),
            "ball_masses": np.asarray(charge.mass).tolist()} if charge is not None else {}),
        **{key: summary[key] for key in ("wall_time_s", "compile_time_s", "ms_per_step")},
    }
    if collisions:
        meta["collisions"] = {"capacity": capacity, "energy": "model ledger diss_pp + diss_pw",
                              "force_fraction": float(collision_force_fraction),
                              "pending_J": summary["collision_pending_J"]}
        share = getattr(trained_model.params, "get", lambda _k: None)("share_logit")
        if share is not None:   # dE: share_pp diss_pp + share_pw diss_pw, or per contact
            share_pp, share_pw = (float(x) for x in 1.0 / (1.0 + np.exp(-np.asarray(share))))
            meta["collisions"].update(
                share_pp=share_pp, share_pw=share_pw,
                damping_target=str(getattr(trained_model.config.model, "damping_target", "kind")))
    if out_path is not None:
        save_prediction(out_path, arrays, meta)
        summary["out"] = str(out_path)
    summary["arrays"], summary["meta"] = arrays, meta
    return summary
