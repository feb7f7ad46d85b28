"""Packings, surrogate ensembles and sweeps, design studies and the DEM's ensembles at design
points: where a config, a trained surrogate and the DEM meet the core's design study
(:mod:`sgn_jax.design`) and rollout (:mod:`sgn_jax.surrogate.rollout`).

The public names are re-exported by :mod:`sgn_jax.api` (docs/api.md): :func:`make_packings`,
:func:`seed_packings`, :class:`Packings`, :func:`design_study`, :class:`DesignStudy`,
:func:`rollout_ensemble`, :func:`rollout_sweep`, :func:`shard_packings`, :func:`sensitivity`,
:class:`DEMEnsemble`, :func:`design_config`, :func:`parameter_values_of`, :func:`ensemble_mean`
and :func:`at_surrogate_step`.

A surrogate whose kind reads the charge (``ModelFactory.takes_charge``: ``contact_charge``)
rolls out any charge: the windows of its rollouts carry the case config's charge (a
:class:`sgn_jax.surrogate.graph.BallCharge` with the leading packing axis of the windows), its
graph spec keeps the trained config's ``[balls]`` (the skins and ``phi_sb`` are set against that
reference radius) with the case's ball count, as :func:`sgn_jax.api.run_rollout` does. Every
other kind rolls out the charge it was trained on.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from sgn_jax.analysis.collisions import (
    DEFAULT_THRESHOLD_J,
    EVENT_FIELDS,
    PREFIX,
    EventTable,
    collision_statistics,
    mean_and_se,
)
from sgn_jax.config import Config, replace_section
from sgn_jax.dem.engine import DISSIPATION_KINDS, make_sampler, reset_ledger_totals
from sgn_jax.dem.placement import placement_candidates
from sgn_jax.design import (
    DesignError,
    EnsemblePower,
    PackingStart,
    anchored_window,
    apply_parameters,
    check_batching,
    check_parameter_names,
    check_parameters,
    default_step,
    is_charge_parameter,
    make_dem_start,
    make_ensemble_power,
    make_settled_start,
    parameter_unit,
    parameter_values,
    summarize_estimate,
)
from sgn_jax.geometry import JarParams
from sgn_jax.motion import Motion, frequency_hz, motion_kind, offset
from sgn_jax.pipelines.charge_points import charge_parameter_value, with_charge_parameter
from sgn_jax.pipelines.configure import (
    graph_spec_from_config,
    jar_params_from_config,
    model_takes_charge,
    motion_from_config,
)
from sgn_jax.pipelines.dem_run import (
    initial_state,
    load_settled,
    run_dem,
    save_settled,
    settle_sample_count,
    setup_from_config,
)
from sgn_jax.pipelines.rollout_run import (
    _effective_config,
    config_at_model_step,
    initial_window,
    window_charge,
)
from sgn_jax.pipelines.validation import check_dem_config, check_duration, warn_outside_envelope
from sgn_jax.records.checkpoint import TrainedModel
from sgn_jax.records.shipped_models import load_surrogate
from sgn_jax.scene import analytic_jar_query
from sgn_jax.surrogate.collisions import DEFAULT_CAPACITY, check_capacity
from sgn_jax.surrogate.graph import BallCharge, GraphSpec, Window
from sgn_jax.surrogate.rollout import (
    RolloutResult,
    make_rollout,
    model_predictor,
    single_rollout_model,
)


def at_surrogate_step(cfg: Config, surrogate: TrainedModel) -> Config:
    """``cfg`` sampled at the surrogate's own step: a model trained at a coarser step than
    ``cfg``'s ``[dem] dt`` by an integer factor (the 2e-4 s contact model on a 1e-4 s case)
    rolls out at its step, and its packings' windows are sampled at it (``[dem] dt`` is the
    sampling and surrogate step; the DEM's own step is ``dt_dem_max``). Any other mismatch is
    left for :func:`design_study` to refuse with its message."""
    return config_at_model_step(cfg, float(surrogate.config.dem.dt))


def reads_charge(surrogate: TrainedModel) -> bool:
    """Whether ``surrogate``'s kind reads each ball's radius, mass and material from its
    windows' charge (``ModelFactory.takes_charge``), and so rolls out any charge."""
    return model_takes_charge(surrogate.config)


def surrogate_graph_spec(surrogate: TrainedModel, cfg: Config) -> GraphSpec:
    """The graph spec of ``surrogate``'s rollouts of ``cfg``'s balls: the trained config's graph
    rules at ``cfg``'s ``[dem] dt`` for ``cfg``'s ball count. A kind that reads the charge keeps
    the trained config's ``[balls]``, whose radius its skins and ``phi_sb`` are set against (each
    ball's own radius is applied to them: docs/contact_charge.md); every other kind takes
    ``cfg``'s (its trained balls, checked by the callers)."""
    model_cfg = surrogate.config
    balls = model_cfg.balls if reads_charge(surrogate) else cfg.balls
    return graph_spec_from_config(dataclasses.replace(model_cfg, balls=balls, dem=cfg.dem),
                                  n_particles=cfg.balls.n_balls)


def case_charge(surrogate: TrainedModel, cfg: Config) -> BallCharge | None:
    """The :class:`BallCharge` of ``cfg``'s charge (``[balls]``, its mixture and materials) that
    the windows of ``surrogate``'s rollouts carry, or None for a kind that does not read the
    charge. The charge sections are taken from ``cfg`` as :func:`sgn_jax.api.run_rollout` takes
    a case config's (``_effective_config``, ``window_charge``)."""
    if not reads_charge(surrogate):
        return None
    effective = _effective_config(surrogate.config, cfg)
    return window_charge(effective, SimpleNamespace(meta={}), int(cfg.balls.n_balls))


def _batched(charge: BallCharge | None, k: int) -> BallCharge | None:
    """``charge`` with a leading axis of ``k`` packings (the same charge for each)."""
    if charge is None:
        return None
    return jax.tree_util.tree_map(
        lambda a: np.broadcast_to(np.asarray(a), (k, *np.shape(a))).copy(), charge)


@dataclasses.dataclass(frozen=True)
class Packings:
    """K initial states of the surrogate, one per DEM packing.

    Attributes:
        windows: :class:`sgn_jax.surrogate.graph.Window` with a leading axis K (positions
            (K, W+1, N, 3)); None for :func:`seed_packings` (seeds only: a study with
            ``start="dem"`` or ``"settle"`` makes them itself). The DEM's states only: the
            rollouts of a surrogate that reads the charge give them the charge of their config
            (:func:`case_charge`).
        t0: time (s since the start of motion) of the windows' newest sample.
        seeds: the K DEM placement seeds.
        config: the config they were made with (jar, balls, motion at which they were sampled).
    """

    windows: Window | None
    t0: float
    seeds: tuple[int, ...]
    config: Config

    def __len__(self) -> int:
        return len(self.seeds)


def make_packings(cfg: Config, seeds: Iterable[int], *, window: int | None = None,
                  progress: bool = False, log: Callable[[str], None] = lambda m: None
                  ) -> Packings:
    """Settle one DEM packing per seed and take the surrogate's first full window of motion.

    Each packing: the DEM places the balls from the seed, settles them with the jar at rest
    (``[dem] settle_time``), then runs ``W`` samples of the config's motion; the window ends at
    ``t0 = W dt``. ``log`` is called after each packing. Any charge the DEM runs
    (``[balls]``, ``[[balls.mix]]``, materials: docs/charge.md); N is its ball count.
    """
    seeds = _placement_seeds(seeds, "make_packings")
    w = int(cfg.graph.window if window is None else window)
    dt = float(cfg.dem.dt)
    freq = float(frequency_hz(motion_from_config(cfg.motion)))
    windows = []
    check_dem_config(cfg)  # once for all seeds (it may warn)
    for i, seed in enumerate(seeds):
        run = run_dem(cfg, duration=w * dt, seed=seed, progress=progress, check=False)
        traj = SimpleNamespace(pos=run.arrays["pos"], offset=run.arrays["offset"],
                               offset_vel=run.arrays["offset_vel"])
        windows.append(initial_window(traj, w, w, freq=freq))
        log(f"packing {i + 1}/{len(seeds)} (seed {seed})")
    stacked = jax.tree_util.tree_map(lambda *a: np.stack(a), *windows)
    return Packings(windows=stacked, t0=w * dt, seeds=seeds, config=cfg)


def seed_packings(cfg: Config, seeds: Iterable[int]) -> Packings:
    """Packings that are only their seeds (no DEM run): for a design study that makes each
    packing itself in every jar it evaluates (``start="dem"`` or ``"settle"``), from the
    seed's placement as the DEM places it."""
    return Packings(windows=None, t0=0.0, seeds=_placement_seeds(seeds, "seed_packings"),
                    config=cfg)


def _placement_seeds(seeds: Iterable[int], who: str) -> tuple[int, ...]:
    """``seeds`` as a tuple of ints, refused unless there is one or more and all are >= 0."""
    seeds = tuple(int(s) for s in seeds)
    if not seeds:
        raise DesignError(f"{who} needs at least one seed")
    if any(s < 0 for s in seeds):
        raise DesignError(f"seeds must be >= 0, got {list(seeds)}")
    return seeds


STARTS = ("packing", "dem", "settle")
"""Where a design study's rollouts start (:func:`design_study`'s ``start``)."""


def resolve_start(start: str, names: Sequence[str]) -> str:
    """A design study's start (:data:`STARTS`) for ``start``: ``"auto"`` is ``"dem"`` when a
    jar-shape parameter is among ``names`` (a packing settled in one jar is not the DEM's start
    in another: docs/design.md), else ``"packing"``."""
    if start == "auto":
        return "dem" if any(str(n).startswith("jar.") for n in names) else "packing"
    if start not in STARTS:
        raise DesignError(f"start must be 'auto' or one of {STARTS}, got {start!r}")
    return start


def check_study_sizes(duration: float, burn_in: float, packings: int | None = None) -> None:
    """Refuse a study before any work: duration > burn_in >= 0 s, and >= 2 packings (a
    standard error needs two)."""
    check_duration(duration, "duration")
    if not (math.isfinite(burn_in) and 0 <= burn_in < duration):
        raise DesignError(f"need duration > burn_in >= 0 s, got duration {duration:g}, burn_in "
                          f"{burn_in:g}")
    if packings is not None and packings < 2:
        raise DesignError(f"packings must be >= 2 (a standard error needs two), got {packings}")


@dataclasses.dataclass(frozen=True)
class _SurrogateFrame:
    """What a surrogate needs to roll ``packings`` out under ``cfg``: its graph spec, the motion
    and jar pytrees, the windows anchored to that motion (K leading; with the case's charge,
    K leading, for a kind that reads it), the motion the packings' windows are anchored from
    (``made_under``: theirs, or ``motion`` for another motion kind), and the case's charge
    (:func:`case_charge`, one packing's; None for a kind that does not read it)."""

    spec: GraphSpec
    motion: Motion
    jar: JarParams
    windows: Window | None
    made_under: Motion
    charge: BallCharge | None = None


def _surrogate_frame(surrogate: TrainedModel, cfg: Config, packings: Packings
                     ) -> _SurrogateFrame:
    """Check that ``surrogate`` can roll ``packings`` out under ``cfg`` (dt as trained, and the
    balls as trained for a kind that does not read the charge; an envelope warning otherwise)
    and build the pieces of that rollout."""
    model_cfg = surrogate.config
    charged = reads_charge(surrogate)
    trained = (("dem", "dt"),) if charged else (("balls", "count"), ("balls", "radius"),
                                                 ("dem", "dt"))
    for section, field in trained:
        a = getattr(getattr(model_cfg, section), field)
        b = getattr(getattr(cfg, section), field)
        if not math.isclose(float(a), float(b), rel_tol=1e-12):
            hint = ("; sj.at_surrogate_step(cfg, model) samples the case at the model's step "
                    "(make the packings with that config)"
                    if section == "dem" and config_at_model_step(cfg, float(a)) is not cfg
                    else "")
            raise DesignError(f"the surrogate was trained with [{section}] {field} = {a}, the "
                              f"design config has {b}{hint}")
    if charged and packings.config.balls != cfg.balls:
        raise DesignError("the packings were made with another charge ([balls]) than the design "
                          "config's; make them with this config (sj.make_packings(cfg, seeds))")
    warn_outside_envelope(cfg, model_cfg, surrogate.meta)
    if (packings.windows is not None
            and packings.windows.positions.shape[-2] != cfg.balls.n_balls):
        raise DesignError("the packings have a different number of balls from the config")
    # Window-level features come from the model's graph rules; the jar and motion from cfg.
    spec = surrogate_graph_spec(surrogate, cfg)
    charge = case_charge(surrogate, cfg)
    motion = motion_from_config(cfg.motion)
    base_motion = motion_from_config(packings.config.motion)
    if type(base_motion) is not type(motion):
        # Packings made under another motion kind are re-anchored to this motion at t0.
        base_motion = motion
    windows = (None if packings.windows is None
               else _reanchor(packings, base_motion, motion, float(cfg.dem.dt), charge))
    return _SurrogateFrame(spec=spec, motion=motion, jar=jar_params_from_config(cfg.jar),
                           windows=windows, made_under=base_motion, charge=charge)


@dataclasses.dataclass(frozen=True)
class DesignStudy:
    """A design study: the ensemble-mean power as a function of named design parameters.

    Attributes:
        names: the D parameter names (``motion.rpm``, ``jar.straight_length``, ...).
        theta0: (D,) their values at the config's design point (SI units; rpm for rpm).
        power: ``power(theta) -> () W`` (compiled); ``jax.value_and_grad(power)(theta)`` gives the
            power and its estimated gradient (W per unit).
        ensemble: the underlying :class:`sgn_jax.design.EnsemblePower`.
        duration, burn_in: seconds of rollout and of the burn-in at its start; the power is
            averaged over the remaining ``duration - burn_in`` seconds.
    """

    names: tuple[str, ...]
    theta0: np.ndarray
    power: Callable[[Any], jax.Array]
    ensemble: EnsemblePower
    duration: float
    burn_in: float
    _args: tuple = dataclasses.field(repr=False)
    _source: Any = dataclasses.field(default=None, repr=False)

    def estimate(self, theta: Any = None) -> dict[str, Any]:
        """Power and gradient with standard errors at ``theta`` (default ``theta0``)."""
        theta = self.theta0 if theta is None else theta
        est = jax.device_get(self.ensemble.estimate(jnp.asarray(theta, jnp.float64),
                                                    *self._args))
        return summarize_estimate(est, self.names)

    def collision_tables(self, theta: Any = None, *,
                         collision_capacity: int = DEFAULT_CAPACITY) -> list[EventTable]:
        """The collision events of every packing at ``theta`` (default ``theta0``) over the
        measurement interval (after the burn-in), one :class:`EventTable` per packing
        (docs/collisions.md): forward rollouts of the contact model with its collision ledger,
        from the packings' windows moved to the motion at ``theta``. Motion parameters and a
        study started from the packings only (a jar parameter would need each packing refitted
        into the changed jar)."""
        if self._source is None:
            raise DesignError("this study holds no packings to roll out (build it with "
                              "sj.design_study)")
        surrogate, cfg, packings, start, frame = self._source
        jar_names = [n for n in self.names if not n.startswith("motion.")]
        if jar_names or start != "packing":
            raise DesignError(f"collision statistics of a design study take motion parameters "
                              f"from the packings (start='packing'); this study has "
                              f"{jar_names or self.names} with start={start!r}")
        theta = self.theta0 if theta is None else np.asarray(theta, np.float64)
        if np.shape(theta) != np.shape(self.theta0):
            raise DesignError(f"theta has shape {np.shape(theta)}, the study's parameters "
                              f"{list(self.names)} need {np.shape(self.theta0)}")
        capacity = check_capacity(collision_capacity)
        motion, jar = apply_parameters(self.names, jnp.asarray(theta), frame.motion, frame.jar)
        windows = _reanchor(packings, frame.made_under, motion, float(cfg.dem.dt), frame.charge)
        run = _ensemble_runner(surrogate, cfg, self.duration, None, "map", False, capacity)
        result = jax.device_get(run(windows, (surrogate.params, surrogate.norm_stats, motion,
                                              jar, jnp.asarray(packings.t0))))
        t0 = float(packings.t0)
        mass = float(cfg.balls.density) * 4.0 / 3.0 * math.pi * float(cfg.balls.radius) ** 3
        total_mass = (mass * int(cfg.balls.count) if cfg.balls.single_class
                      else float(cfg.balls.mass))
        tables = []
        for k in range(len(packings)):
            arrays = result.collision_arrays(packing=k)
            table = EventTable(**{name: arrays[PREFIX + name] for name in EVENT_FIELDS},
                               record_duration_s=self.duration, record_start_s=t0,
                               n_balls=int(cfg.balls.n_balls),
                               total_mass_kg=total_mass, source="surrogate")
            tables.append(table.window(t0 + self.burn_in, t0 + self.duration))
        return tables

    def collision_estimate(self, statistic: str = "power_above_W", theta: Any = None, *,
                           steps: dict[str, float] | None = None,
                           threshold: float = DEFAULT_THRESHOLD_J,
                           threshold_by: str = "dissipated") -> dict[str, Any]:
        """A collision statistic (a scalar of
        :func:`sgn_jax.analysis.collisions.collision_statistics`: ``power_above_W``,
        ``share_above``, ``frequency_per_ball_hz[all]``, ``mean_stress_energy_J[all]``, ...)
        at ``theta`` with its standard error over the packings, and its gradient by central
        differences with common packings (step ``steps[name]``, default
        :func:`default_step`), each with the standard error of the per-packing differences.
        Events are discrete, so the statistic is not differentiated through the rollout.
        Costs 1 + 2 D ensembles of rollouts with the collision ledger."""
        theta = self.theta0 if theta is None else np.asarray(theta, np.float64)

        def per_packing(at: np.ndarray) -> np.ndarray:
            values = []
            for table in self.collision_tables(at):
                stats = collision_statistics(table, threshold=threshold,
                                             threshold_by=threshold_by)
                if statistic not in stats or np.ndim(stats[statistic]) != 0:
                    scalars = sorted(k for k, v in stats.items() if np.ndim(v) == 0)
                    raise DesignError(f"unknown scalar collision statistic {statistic!r}; "
                                      f"choose one of {scalars}")
                values.append(float(stats[statistic]))
            return np.asarray(values)

        unknown = sorted(set(steps or {}) - set(self.names))
        if unknown:
            raise DesignError(f"steps given for {unknown}, not parameters of this study "
                              f"({list(self.names)})")
        value, se = (float(x) for x in mean_and_se(per_packing(theta)))
        out: dict[str, Any] = {"statistic": statistic, "theta": theta.tolist(),
                               "names": list(self.names), "value": value, "se": se,
                               "threshold_J": threshold, "threshold_by": threshold_by,
                               "gradient": {}}
        for i, name in enumerate(self.names):
            h = float((steps or {}).get(name, default_step(name, float(theta[i]))))
            plus, minus = theta.copy(), theta.copy()
            plus[i] += h
            minus[i] -= h
            g, g_se = (float(x) for x in mean_and_se((per_packing(plus) - per_packing(minus))
                                                      / (2 * h)))
            out["gradient"][name] = {"value": g, "se": g_se, "step": h}
        return out

    def powers(self, theta: Any = None) -> np.ndarray:
        """(K,) per-packing powers (W) at ``theta`` without any gradient work."""
        theta = self.theta0 if theta is None else theta
        powers = np.asarray(self.ensemble.forward(jnp.asarray(theta, jnp.float64), *self._args))
        if not np.all(np.isfinite(powers)):
            raise DesignError(f"a rollout diverged at theta = {np.asarray(theta).tolist()} "
                              f"({int(np.sum(~np.isfinite(powers)))} of {powers.size} packings "
                              "non-finite)")
        return powers


def _steps(seconds: float, dt: float, what: str) -> int:
    n = int(round(seconds / dt))
    if not math.isclose(n * dt, seconds, rel_tol=1e-9, abs_tol=1e-12):
        raise DesignError(f"{what} = {seconds:g} s is not a whole number of dt = {dt:g} s steps")
    return n


def design_study(surrogate: TrainedModel, cfg: Config, names: Sequence[str], packings: Packings,
                 *, duration: float = 1.5, burn_in: float = 0.5, horizon: int = 10,
                 n_segments: int = 8, separation: bool | None = None,
                 estimator: str = "difference", steps: dict[str, float] | None = None,
                 shard: bool = False, start: str = "auto") -> DesignStudy:
    """Build a :class:`DesignStudy` of ``cfg``'s jar and motion over ``packings``.

    Args:
        surrogate: :func:`load_surrogate`'s model (its balls and dt must be ``cfg``'s).
        cfg: the design point (jar, motion, rollout settings).
        names: design parameters (:data:`sgn_jax.design.PARAMETER_UNITS`).
        packings: :func:`make_packings` of the same balls (any motion: the packings are
            anchored in the jar frame).
        duration: seconds of surrogate rollout per packing (> burn_in).
        burn_in: seconds before the measurement starts.
        horizon: steps of each gradient horizon (``estimator="horizon"``; docs/design.md).
        n_segments: gradient horizons per packing, spread over the measurement interval
            (``"horizon"``; with ``"difference"`` only the measurement must split into them).
        separation: the ball-ball separation (default: ``cfg``'s ``[rollout] pp_separation``).
        estimator: ``"difference"`` (default): ``jax.grad`` of ``study.power`` is the ensemble
            central difference with common packings, step ``steps[name]`` (default
            :func:`default_step`, 10 % of the value); ``"horizon"``: the truncated-horizon
            autodiff estimator. docs/design.md measures both against the DEM.
        steps: difference step per parameter name (SI units), for the names it lists.
        shard: split the packings over all devices (:func:`shard_packings`); the powers and
            gradients equal the unsharded ones to float tolerance.
        start: where each packing's rollout starts (:func:`resolve_start`). ``"packing"``:
            from its DEM window, fitted into a changed jar
            (:func:`sgn_jax.design.fit_packing_to_jar`). ``"dem"``: the DEM makes it in every
            jar the study evaluates, as :func:`make_packings` makes one (the seed's placement,
            ``[dem] settle_time`` with the jar at rest, a window of motion;
            :func:`sgn_jax.design.make_dem_start`): the start the DEM's own runs in that jar
            have, at the price of a DEM settle per packing and jar (docs/design.md gives the
            cost); a motion parameter's sides share the design point's packings. ``"settle"``:
            the same placement settled by the surrogate instead (cheap; docs/design.md compares
            its jar-length gradients with the DEM's). ``"auto"`` (default): ``"dem"`` when a jar-shape
            parameter is studied, else ``"packing"``. With ``"dem"`` and ``"settle"`` only the
            packings' seeds are used (:func:`seed_packings` skips the DEM's packings).

    With the difference estimator and no sharding, a model with a single-rollout form (the
    contact kind) runs its packings one after another in it (``make_ensemble_power``'s
    ``batching="map"``, the faster form on CPU cores: docs/benchmarks.md); the SGN, the horizon
    estimator and sharded studies run the plain model vmapped.
    """
    check_study_sizes(duration, burn_in)
    start = resolve_start(start, names)
    if start == "packing" and packings.windows is None:
        raise DesignError("these packings are seeds only (seed_packings): a study from the "
                          "packings needs make_packings, or start='dem' or 'settle'")
    frame = _surrogate_frame(surrogate, cfg, packings)
    motion, jar = frame.motion, frame.jar
    dt = float(cfg.dem.dt)
    n_burn = _steps(burn_in, dt, "burn_in")
    n_measure = _steps(duration - burn_in, dt, "duration - burn_in")
    if n_measure % n_segments:
        raise DesignError(f"the measurement interval ({n_measure} steps) must split into "
                          f"n_segments = {n_segments} equal parts")
    names = check_parameters(names, motion, jar)
    rollout = cfg.rollout
    use_sep = rollout.pp_separation if separation is None else bool(separation)
    theta0 = parameter_values(names, motion, jar)
    unknown = sorted(set(steps or {}) - set(names))
    if unknown:
        raise DesignError(f"steps given for {unknown}, which are not design parameters here "
                          f"({list(names)})")
    fd_steps = [float((steps or {}).get(n, default_step(n, v))) for n, v in zip(names, theta0,
                                                                                  strict=True)]
    # The difference estimator only runs rollouts forward: a model with a single-rollout form
    # (the contact kind) runs its packings one after another in it, the faster form per
    # packing on CPU cores; under sharding, or to differentiate (the horizon estimator), the
    # plain model vmapped.
    single = (estimator == "difference" and not shard
              and getattr(surrogate.model, "for_single_rollout", None) is not None)
    module = single_rollout_model(surrogate.model)[0] if single else surrogate.model
    ensemble = make_ensemble_power(
        frame.spec, model_predictor(module), names, motion, jar, packings.t0,
        batching="map" if single else "vmap",
        estimator=estimator, steps=fd_steps if estimator == "difference" else None,
        n_burn=n_burn, n_measure=n_measure, horizon=horizon, n_segments=n_segments,
        snap_back=rollout.snap_back, phi_sb=surrogate.config.graph.phi_sb,
        snap_velocity=rollout.snap_velocity,
        pp_max_overlap=rollout.pp_max_overlap if use_sep else None,
        start=_packing_start(start, surrogate, cfg, frame.spec, module, use_sep, frame.charge))
    starts = (frame.windows if start == "packing" else
              np.stack([placement_candidates(seed) for seed in packings.seeds]))
    args = (jax.device_put(surrogate.params), jax.device_put(surrogate.norm_stats),
            shard_packings(starts) if shard else jax.device_put(starts))
    power = ensemble.power

    def power_of_theta(theta: Any) -> jax.Array:
        return power(jnp.asarray(theta, jnp.float64), *args)

    return DesignStudy(names=names, theta0=theta0,
                       power=power_of_theta, ensemble=ensemble, duration=float(duration),
                       burn_in=float(burn_in), _args=args,
                       _source=(surrogate, cfg, packings, start, frame))


def _packing_start(start: str, surrogate: TrainedModel, cfg: Config, spec: GraphSpec,
                   module: Any, separation: bool, charge: BallCharge | None = None
                   ) -> PackingStart | None:
    """The :class:`sgn_jax.design.PackingStart` of a study's ``start`` (None: the packings);
    ``charge``: the case's, which the started windows carry (a kind that reads the charge)."""
    if start == "packing":
        return None
    if start == "settle":
        r = cfg.rollout
        return make_settled_start(
            spec, model_predictor(module),
            _steps(float(cfg.dem.settle_time), float(cfg.dem.dt), "[dem] settle_time"),
            snap_back=r.snap_back, phi_sb=surrogate.config.graph.phi_sb,
            snap_velocity=r.snap_velocity, query=analytic_jar_query,
            pp_max_overlap=r.pp_max_overlap if separation else None, jit=False,
            charge=charge)
    if not cfg.balls.single_class:   # before the DEM's setup, which a mixture makes per ball
        raise DesignError("the DEM's start in every jar (start='dem') places balls of one size, "
                          "and this charge has several ([[balls.mix]]); a study of a mixture "
                          "starts from its packings (start='packing')")
    setup = setup_from_config(cfg)
    return make_dem_start(setup.spec, setup.jar.wall_fn, setup.params, float(cfg.dem.dt),
                          setup.substeps, settle_sample_count(setup), setup.pp_capacity,
                          spec.window, charge=charge)


def _ensemble_rollout(surrogate: TrainedModel, cfg: Config, duration: float,
                      save_every: int | None, single: bool = False,
                      collision_capacity: int = 0) -> Callable:
    """The unjitted rollout of ``cfg``'s ``[rollout]`` settings for ``duration`` s (shared by
    :func:`rollout_ensemble` and :func:`rollout_sweep`). ``single``: the model kind's
    single-rollout form (:func:`sgn_jax.surrogate.rollout.single_rollout_model`), for
    rollouts run one after another, never vmapped. ``collision_capacity`` > 0: with the
    collision ledger, that many events per rollout."""
    check_duration(duration, "duration")
    n_steps = _steps(duration, float(cfg.dem.dt), "duration")
    every = int(cfg.rollout.save_every if save_every is None else save_every)
    if every < 1 or n_steps % every:
        raise DesignError(f"duration ({n_steps} steps) must be a multiple of save_every = "
                          f"{every} steps")
    spec = surrogate_graph_spec(surrogate, cfg)
    r = cfg.rollout
    module = single_rollout_model(surrogate.model)[0] if single else surrogate.model
    collisions = collision_capacity > 0
    return make_rollout(spec, model_predictor(module, collisions), n_steps, every,
                        snap_back=r.snap_back, phi_sb=surrogate.config.graph.phi_sb,
                        snap_velocity=r.snap_velocity, query=analytic_jar_query,
                        pp_max_overlap=r.pp_max_overlap if r.pp_separation else None,
                        collisions=collisions,
                        collision_capacity=collision_capacity or DEFAULT_CAPACITY, jit=False)


def over_packings(fn: Callable[[Any, Any], Any], batching: str = "vmap", shard: bool = False
                  ) -> Callable[[Any, Any], Any]:
    """``fn(one packing's pytree, shared) -> pytree`` as a jitted ``run(batch, shared)`` over
    the batch's leading axis K (``shared``: the same for every packing, e.g. the parameters).

    ``batching`` "vmap": all K in one batched program (what a gradient or a design study
    needs); "map": one after another in one compiled program (``lax.map``), each as a single
    rollout runs, so the model's single-rollout form and its ``cond`` branches stay cheap: on
    a CPU core the faster per packing (docs/benchmarks.md). ``shard``: each device takes a
    slice of the packings (``shard_packings`` places them); with "map" each device maps over
    its own slice (``jax.shard_map``; K a multiple of the device count).
    """
    check_batching(batching)
    if batching == "vmap":
        return jax.jit(jax.vmap(fn, in_axes=(0, None)))

    def mapped(batch: Any, shared: Any) -> Any:
        return jax.lax.map(lambda one: fn(one, shared), batch)

    if not shard:
        return jax.jit(mapped)
    from jax.sharding import Mesh, PartitionSpec

    mesh = Mesh(np.asarray(jax.devices()), ("packings",))
    return jax.jit(jax.shard_map(mapped, mesh=mesh,
                                 in_specs=(PartitionSpec("packings"), PartitionSpec()),
                                 out_specs=PartitionSpec("packings"),
                                 # the rollout's scans start from per-packing zeros: no
                                 # cross-device values, so no varying-axis bookkeeping
                                 check_vma=False))


def rollout_ensemble(surrogate: TrainedModel, cfg: Config, packings: Packings,
                     duration: float, *, save_every: int | None = None,
                     shard: bool = False, batching: str = "vmap", collisions: bool = False,
                     collision_capacity: int = DEFAULT_CAPACITY) -> RolloutResult:
    """Roll the surrogate out from every packing under ``cfg``'s jar and motion.

    The rollout uses ``cfg``'s ``[rollout]`` settings (snap-back, its velocity rule, the
    ball-ball separation), so a script gets the physics of the shipped config and of
    ``sgn-jax rollout`` (``make_rollout``'s own defaults are the paper's: no separation). The
    jar is queried through its analytic SDF, as in design studies; packings made under another
    motion are anchored to this one in the jar frame. ``shard``: split the packings over all
    devices (:func:`shard_packings`). ``batching``: "vmap" (default) runs them as one batch,
    "map" one after another in the model's single-rollout form (:func:`over_packings`; the
    faster on CPU cores for a model that has one, the contact kind); the same numbers to
    float rounding. ``collisions``: record each rollout's collision ledger (a contact model;
    ``collision_capacity`` events per rollout), read packing k's events with
    ``result.collision_arrays(packing=k)``.

    Returns:
        a :class:`sgn_jax.surrogate.rollout.RolloutResult` with a leading axis K (packings):
        ``positions`` (K, P, N, 3) m at the times ``t_pos`` (every ``save_every`` steps, default
        ``[rollout] save_every``), ``steps.energy_cum`` (K, S) J, ``steps.n_outside`` /
        ``n_snapped`` (K, S).
    """
    check_batching(batching)   # before any work (the rollout's form depends on it)
    capacity = check_capacity(collision_capacity) if collisions else 0
    frame = _surrogate_frame(surrogate, cfg, packings)
    run = _ensemble_runner(surrogate, cfg, duration, save_every, batching, shard, capacity)
    windows = shard_packings(frame.windows) if shard else frame.windows
    return jax.device_get(run(windows, (surrogate.params, surrogate.norm_stats, frame.motion,
                                        frame.jar, jnp.asarray(packings.t0))))


# rollout_ensemble's compiled programs, by what fixes the program: the motion's and the jar's
# values, the start time and the parameters are arguments, so a second ensemble of the same
# model, sizes and [rollout] settings under another motion (a sweep of rpm, the two sides of a
# difference) runs the program already compiled instead of tracing and compiling it again.
_ENSEMBLE_RUNNERS: dict[tuple, Callable] = {}
_ENSEMBLE_RUNNERS_MAX = 8


def _ensemble_runner(surrogate: TrainedModel, cfg: Config, duration: float,
                     save_every: int | None, batching: str, shard: bool,
                     collision_capacity: int = 0) -> Callable:
    """The jitted ``run(windows, (params, norm_stats, motion, jar, t0))`` of
    :func:`rollout_ensemble`, made once per model, [balls], [dem], [rollout], duration,
    ``save_every``, batching and devices (for ``shard``), and kept (the last few)."""
    key = (surrogate.model, surrogate.config, cfg.balls, cfg.dem, cfg.rollout, float(duration),
           save_every, batching, shard, tuple(jax.devices()) if shard else None,
           collision_capacity)
    run = _ENSEMBLE_RUNNERS.get(key)
    if run is None:
        rollout = _ensemble_rollout(surrogate, cfg, duration, save_every,
                                    single=batching == "map",
                                    collision_capacity=collision_capacity)

        def one(window, shared):
            params, norm_stats, motion, jar, t0 = shared
            return rollout(params, norm_stats, window, motion, jar, t0)

        run = over_packings(one, batching, shard)
        if len(_ENSEMBLE_RUNNERS) >= _ENSEMBLE_RUNNERS_MAX:
            _ENSEMBLE_RUNNERS.pop(next(iter(_ENSEMBLE_RUNNERS)))   # the oldest
        _ENSEMBLE_RUNNERS[key] = run
    return run


def rollout_sweep(surrogate: TrainedModel, cfgs: Sequence[Config], packings: Packings,
                  duration: float, *, save_every: int | None = None,
                  shard: bool = False) -> RolloutResult:
    """Roll the surrogate out from every packing under each of ``cfgs`` (a sweep of motions),
    all M x K rollouts vmapped in one compiled program.

    The configs may differ in their ``[motion]`` parameters only: one motion kind (one pytree
    structure), and the jar, balls, dt and ``[rollout]`` settings of ``cfgs[0]`` (else a
    :class:`DesignError` that names the section). Each rollout is the one
    :func:`rollout_ensemble` gives for its config (the packings anchored to that motion).
    ``shard``: split the M x K rollouts over all devices (:func:`shard_packings`; M x K must be
    a multiple of the device count). A new M x K compiles once; the same sizes reuse it.

    Returns:
        a :class:`sgn_jax.surrogate.rollout.RolloutResult` with leading axes (M, K): ``positions``
        (M, K, P, N, 3) m, ``steps.energy_cum`` (M, K, S) J, ...
    """
    cfgs = list(cfgs)
    if not cfgs:
        raise DesignError("rollout_sweep needs at least one config")
    base = cfgs[0]
    for i, c in enumerate(cfgs[1:], start=1):
        for section in ("jar", "balls", "dem", "rollout"):
            if getattr(c, section) != getattr(base, section):
                raise DesignError(f"rollout_sweep: config {i} has another [{section}] section "
                                  f"than config 0; a sweep varies the [motion] only")
    rollout = _ensemble_rollout(surrogate, base, duration, save_every)
    frames = [_surrogate_frame(surrogate, c, packings) for c in cfgs]
    kinds = {type(f.motion).__name__ for f in frames}
    if len(kinds) != 1:
        raise DesignError(f"rollout_sweep: the configs' motions are of kinds {sorted(kinds)}; "
                          "a sweep vmaps one kind (run one sweep per kind)")
    k = packings.windows.positions.shape[0]
    windows = jax.tree_util.tree_map(lambda *a: np.concatenate(a),
                                     *[f.windows for f in frames])
    motions = jax.tree_util.tree_map(
        lambda *leaves: np.repeat(np.stack([np.asarray(x) for x in leaves]), k, axis=0),
        *[f.motion for f in frames])
    if shard:
        windows, motions = shard_packings(windows), shard_packings(motions)
    run = jax.jit(jax.vmap(rollout, in_axes=(None, None, 0, 0, None, None)))
    flat = jax.device_get(run(surrogate.params, surrogate.norm_stats, windows, motions,
                              frames[0].jar, packings.t0))
    return jax.tree_util.tree_map(
        lambda a: a.reshape((len(cfgs), k) + a.shape[1:]) if np.ndim(a) and a.shape[0] == len(
            cfgs) * k else a, flat)


def check_ensemble_steps(cfg: Config, duration: float, burn_in: float) -> tuple[int, int]:
    """``(steps, burn-in steps)`` of an ensemble of ``duration`` s whose power is averaged after
    ``burn_in`` s, at ``cfg``'s ``[dem] dt``; DesignError unless both are whole numbers of
    steps and duration > burn_in >= 0."""
    check_study_sizes(duration, burn_in)
    dt = float(cfg.dem.dt)
    return _steps(duration, dt, "duration"), _steps(burn_in, dt, "burn_in")


def ensemble_powers(surrogate: TrainedModel, cfg: Config, packings: Packings, duration: float,
                    burn_in: float, *, shard: bool = False) -> np.ndarray:
    """(K,) W: each packing's mean dissipation power (the surrogate's: normal + tangential
    damping, ball-ball + ball-wall) over ``(burn_in, duration]`` s of its rollout under
    ``cfg`` (:func:`rollout_ensemble`, any charge for a kind that reads it). A model with a
    single-rollout form runs the packings one after another in it (``batching="map"``), as a
    design study does, unless ``shard``. DesignError for a rollout that diverged."""
    n_total, n_burn = check_ensemble_steps(cfg, duration, burn_in)
    single = not shard and getattr(surrogate.model, "for_single_rollout", None) is not None
    result = rollout_ensemble(surrogate, cfg, packings, duration, save_every=n_total,
                              shard=shard, batching="map" if single else "vmap")
    energy = np.asarray(result.steps.energy_cum, np.float64)           # (K, S) J
    start = energy[:, n_burn - 1] if n_burn else 0.0
    powers = (energy[:, -1] - start) / ((n_total - n_burn) * float(cfg.dem.dt))
    if not np.all(np.isfinite(powers)):
        bad = int(np.flatnonzero(~np.isfinite(powers))[0])
        raise DesignError(f"the rollout of packing {bad} (seed {packings.seeds[bad]}) gave a "
                          "non-finite power (the surrogate diverged); check the model's envelope "
                          "and the outside/overflow counts with `sgn-jax rollout`")
    return powers


def shard_packings(tree: Any, devices: Sequence[Any] | None = None) -> Any:
    """Place a pytree batched over packings (leading axis K) across ``devices`` (default: all),
    one slice of packings per device, with a 1-D ``jax.sharding.Mesh`` over the batch axis.

    A jitted, vmapped rollout of a sharded batch runs each device's packings on that device
    (the packings are independent: no communication until the ensemble mean). K must be a
    multiple of the number of devices. On one CPU, ``XLA_FLAGS=
    --xla_force_host_platform_device_count=2`` makes two host devices (tests/test_sharding.py).
    """
    from jax.sharding import Mesh, NamedSharding, PartitionSpec

    devices = list(jax.devices() if devices is None else devices)
    k = int(jax.tree_util.tree_leaves(tree)[0].shape[0])
    if k % len(devices):
        raise DesignError(f"{k} packings do not split over {len(devices)} devices; use a "
                          f"multiple of {len(devices)} packings")
    mesh = Mesh(np.asarray(devices), ("packings",))
    sharding = NamedSharding(mesh, PartitionSpec("packings"))
    return jax.device_put(tree, sharding)


def _reanchor(packings: Packings, made_under: Motion, motion: Motion, dt: float,
              charge: BallCharge | None = None) -> Window:
    """The packings' windows moved to ``motion`` (jar-frame positions kept; host side), with
    ``charge`` (one packing's) given to each of them when it is not None."""
    windows = jax.device_get(_anchored_windows(packings.windows,
                                               jnp.asarray(packings.t0, jnp.float64),
                                               made_under, motion, float(dt)))
    if charge is not None:
        windows = windows.replace(charge=_batched(charge, len(packings)))
    return windows


@functools.partial(jax.jit, static_argnums=4)
def _anchored_windows(windows: Window, t0: jax.Array, made_under: Motion, motion: Motion,
                      dt: float) -> Window:
    # (one compiled program per motion kind and sizes: the motions' values are arguments)
    return jax.vmap(lambda w: anchored_window(w, t0, made_under, motion, dt)[0])(windows)


def split_parameters(names: Sequence[str]) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """``names`` split into the design parameters of a rollout (motion, jar) and the charge
    parameters (:data:`sgn_jax.design.CHARGE_PARAMETER_UNITS`), each in the given order;
    DesignError for none, a repeat or an unknown name."""
    names = check_parameter_names(names)
    return (tuple(n for n in names if not is_charge_parameter(n)),
            tuple(n for n in names if is_charge_parameter(n)))


def parameter_values_of(cfg: Config, names: Sequence[str]) -> np.ndarray:
    """The values (D,) of design parameters ``names`` in ``cfg`` (``motion.scale`` is 1),
    charge parameters included (:func:`sgn_jax.pipelines.charge_points.charge_parameter_value`:
    a charge of one ball class)."""
    design, charge = split_parameters(names)
    values = {name: charge_parameter_value(cfg, name) for name in charge}
    if design:
        motion = motion_from_config(cfg.motion)
        jar = jar_params_from_config(cfg.jar)
        values.update(zip(design, parameter_values(check_parameters(design, motion, jar),
                                                   motion, jar), strict=True))
    return np.asarray([values[name] for name in names], dtype=np.float64)


def design_config(cfg: Config, names: Sequence[str], theta: Any) -> Config:
    """``cfg`` with the design parameters set to ``theta`` (for DEM runs at a design point).

    ``motion.scale`` multiplies the amplitude / every harmonic coefficient. The changed motion
    is written back by its kind's ``to_config`` (:class:`sgn_jax.motion.MotionKind`). Charge
    parameters are set first, in the config's own jar (``balls.radius_fill`` keeps the
    filling of that jar; :func:`sgn_jax.pipelines.charge_points.with_charge_parameter`).
    """
    design, charge = split_parameters(names)
    theta = np.asarray(theta, np.float64).reshape(-1)
    if theta.shape != (len(tuple(names)),):
        raise DesignError(f"theta has {theta.size} values for the {len(tuple(names))} "
                          f"parameters {list(names)}")
    value = dict(zip(tuple(names), theta.tolist(), strict=True))
    for name in charge:
        cfg = with_charge_parameter(cfg, name, value[name])
    if not design:
        return cfg
    motion = motion_from_config(cfg.motion)
    jar = jar_params_from_config(cfg.jar)
    names = check_parameters(design, motion, jar)
    motion, jar = apply_parameters(names, jnp.asarray([value[n] for n in names], jnp.float64),
                                   motion, jar)
    kind = motion_kind(motion)
    if any(n.startswith("motion.") for n in names) and kind.to_config is not None:
        old = {key: getattr(cfg.motion, key) for key in kind.config_keys}
        cfg = replace_section(cfg, "motion", **kind.to_config(motion, old))
    if any(n.startswith("jar.") for n in names):
        cfg = replace_section(cfg, "jar", radius=float(jar.radius),
                              straight_length=float(jar.straight_length),
                              height=float(jar.height), post_radius=float(jar.post_radius))
    return cfg


def _parameter_step(name: str, value: float, steps: dict[str, float] | None) -> float:
    """The difference / curve step of ``name`` at ``value``: ``steps[name]`` or
    :func:`default_step`; DesignError unless finite and > 0."""
    h = float((steps or {}).get(name, default_step(name, value)))
    if not (math.isfinite(h) and h > 0):
        raise DesignError(f"the step of {name} must be finite and > 0, got {h!r}")
    return h


def _charge_sides(cfg: Config, name: str, value: float, h: float) -> dict[int, Config]:
    """The configs at ``value -+ h`` of charge parameter ``name`` (keys -1, +1), each checked as
    a DEM run before any work."""
    sides = {}
    for side in (-1, 1):
        point = with_charge_parameter(cfg, name, value + side * h)
        check_dem_config(point, warn=False)
        sides[side] = point
    return sides


def check_charge_study(surrogate: TrainedModel, names: Sequence[str], estimator: str,
                       start: str) -> None:
    """Refuse a study of charge parameters (``names`` holds one) that cannot be made, before any
    work: the horizon estimator (it differentiates a rollout of fixed balls), the surrogate's
    settle (a charge parameter's sides start from the DEM's packings of their own charge), and a
    surrogate that does not read the charge (it rolls out its training charge only)."""
    charge = [n for n in names if is_charge_parameter(n)]
    if not charge:
        return
    if estimator != "difference":
        raise DesignError(
            f"{charge[0]} is a charge parameter: the balls change (with balls.radius_fill "
            f"their count too), and estimator={estimator!r} differentiates a rollout of fixed "
            "balls; use estimator='difference' (central differences of ensembles, each side "
            "with DEM packings of its own charge), or study the charge parameters apart from "
            "the horizon estimator's")
    if start == "settle":
        raise DesignError(
            f"{charge[0]} is a charge parameter, whose sides start from the DEM's packings of "
            "their own charge; start='settle' (the surrogate's settle) applies to motion and "
            "jar parameters: use start='auto' or study the charge parameters apart")
    if not reads_charge(surrogate):
        kind = getattr(surrogate.config.model, "kind", "?")
        raise DesignError(
            f"{charge[0]} changes the charge, and this surrogate (model kind {kind!r}) rolls "
            "out the one charge it was trained on; use a model whose kind reads the charge "
            "(model kind 'contact_charge', docs/contact_charge.md)")


def sensitivity(cfg: Config, names: Sequence[str], *, duration: float = 1.5,
                burn_in: float = 0.5, packings: int = 8, first_seed: int = 100,
                checkpoint: str | Path | TrainedModel | None = None,
                estimator: str = "difference", horizon: int = 10, n_segments: int = 8,
                curve: bool = True, steps: dict[str, float] | None = None,
                separation: bool | None = None, start: str = "auto", dem: bool = False,
                progress: Callable[[str], None] = lambda stage: None) -> dict[str, Any]:
    """The design sensitivity of ``cfg``: ensemble-mean power, its gradient, standard errors.

    Packings come from DEM seeds ``first_seed .. first_seed + packings - 1`` (never used for
    training): settled by the DEM in the config's jar (``start="packing"``), or made by the
    DEM in every evaluated jar (``"dem"``; the default ``"auto"`` picks it when a jar-shape
    parameter is studied, :func:`resolve_start`), or settled there by the surrogate
    (``"settle"``).
    The gradient is :func:`design_study`'s ``estimator``. ``curve`` adds the
    surrogate's ensemble power at ``theta +- h`` per parameter (``steps`` or
    :func:`default_step`): free with the difference estimator (its own evaluations), extra
    rollouts with the horizon estimator.

    Charge parameters (:data:`sgn_jax.design.CHARGE_PARAMETER_UNITS`: ``balls.radius_fill``,
    ``balls.radius_count``, ``balls.density``, ``balls.restitution``, ``balls.friction``; a
    surrogate that reads the charge, a charge of one ball class) change the balls, and two of
    them their count, so their derivative is the central difference of surrogate ensembles at
    ``theta -+ h``, each side with DEM packings of its own charge from the same placement
    seeds: ``mean_k (P_k(theta + h) - P_k(theta - h)) / 2h`` with the standard error of the
    per-seed differences (docs/design.md). They take the difference estimator only
    (:func:`check_charge_study`); motion and jar parameters beside them are
    :func:`design_study`'s at the config's charge.

    ``dem``: also the DEM's ensemble central difference of every parameter at the same two
    points, seeds, duration and burn-in (:meth:`DEMEnsemble.central_difference`), under
    ``"dem"``, for a comparison of the surrogate's differences with the DEM's. ``progress(stage)``
    is called after every packing, DEM run and evaluation. ``checkpoint``: what
    :func:`load_surrogate` loads, or a :class:`TrainedModel`. Returns a JSON-ready dict (SI
    units; the gradient in W per unit of each parameter).
    """
    check_study_sizes(duration, burn_in, packings)
    if first_seed < 0:
        raise DesignError(f"first_seed must be >= 0, got {first_seed}")
    names = tuple(names)
    design_names, charge_names = split_parameters(names)
    unknown = sorted(set(steps or {}) - set(names))
    if unknown:
        raise DesignError(f"steps given for {unknown}, which are not design parameters here "
                          f"({list(names)})")
    t_start = time.perf_counter()
    model = checkpoint if isinstance(checkpoint, TrainedModel) else load_surrogate(checkpoint)
    check_charge_study(model, names, estimator, start)
    cfg = at_surrogate_step(cfg, model)
    seeds = range(first_seed, first_seed + packings)
    theta0 = parameter_values_of(cfg, names)
    step_of = {name: _parameter_step(name, float(v), steps) for name, v in zip(names, theta0,
                                                                                strict=True)}
    # every charge side is a valid DEM run, and the durations whole steps, before any work
    charge_sides = {name: _charge_sides(cfg, name, float(theta0[names.index(name)]),
                                        step_of[name]) for name in charge_names}
    if charge_names:
        check_ensemble_steps(cfg, duration, burn_in)
    start = resolve_start(start, design_names)
    if not design_names:   # the design point's packings are the DEM's in the config's jar
        start = "packing"
    pk = (make_packings(cfg, seeds, log=progress) if start == "packing"
          else seed_packings(cfg, seeds))
    t_packings = time.perf_counter() - t_start
    t0 = time.perf_counter()
    curves = {}
    if design_names:
        study = design_study(model, cfg, design_names, pk, duration=duration, burn_in=burn_in,
                             horizon=horizon, n_segments=n_segments, separation=separation,
                             estimator=estimator,
                             steps={n: step_of[n] for n in design_names}, start=start)
        result = study.estimate()
        progress("estimate")
        t_estimate = time.perf_counter() - t0
        t0 = time.perf_counter()
        d = len(design_names)
        sides = np.asarray(result.pop("side_powers_W", []), np.float64)
        for i, name in enumerate(design_names if curve else ()):
            h = step_of[name]
            if estimator == "difference":
                points = {1: sides[i], -1: sides[d + i]}
            else:
                points = {}
                for side in (-1, 1):
                    theta = study.theta0.copy()
                    theta[i] += side * h
                    points[side] = study.powers(theta)
                    progress(f"curve {name} {side:+d}h")
            curves[name] = _curve(name, float(study.theta0[i]), h, points,
                                  (result["power_W"], result["power_se_W"]))
    else:   # charge parameters only: the design point's ensemble, the curves' middle
        powers = ensemble_powers(model, cfg, pk, duration, burn_in)
        progress("ensemble")
        t_estimate = time.perf_counter() - t0
        t0 = time.perf_counter()
        mean, se = ensemble_mean(powers)
        result = {"power_W": mean, "power_se_W": se, "power_per_packing_W": powers.tolist(),
                  "gradient": {}, "gradient_se": {}, "gradient_per_packing": {}}
    for name in charge_names:
        points = {}
        for side, point in charge_sides[name].items():
            side_packings = make_packings(point, seeds, log=progress)
            points[side] = ensemble_powers(model, point, side_packings, duration, burn_in)
            progress(f"{name} {side:+d}h")
        i = names.index(name)
        curves[name] = _curve(name, float(theta0[i]), step_of[name], points,
                              (result["power_W"], result["power_se_W"]))
        curves[name]["n_balls"] = [charge_sides[name][-1].balls.n_balls, cfg.balls.n_balls,
                                   charge_sides[name][1].balls.n_balls]
        diff = (points[1] - points[-1]) / (2 * step_of[name])
        result["gradient"][name] = curves[name]["central_difference"]
        result["gradient_se"][name] = curves[name]["central_difference_se"]
        result["gradient_per_packing"][name] = diff.tolist()
    for key in ("gradient", "gradient_se", "gradient_per_packing"):
        result[key] = {name: result[key][name] for name in names}
    result.update(names=list(names), theta0=theta0.tolist(),
                  units={n: parameter_unit(n) for n in names}, seeds=list(seeds),
                  charge_parameters=list(charge_names),
                  steps={n: step_of[n] for n in names},
                  duration_s=duration, burn_in_s=burn_in, estimator=estimator, start=start,
                  horizon_steps=horizon, n_segments=n_segments,
                  separation=bool(cfg.rollout.pp_separation if separation is None
                                  else separation))
    result["curves"] = {name: curves[name] for name in names if name in curves}
    t_curves = time.perf_counter() - t0
    timing = {"packings": t_packings, "estimate": t_estimate, "curves": t_curves}
    if dem:
        t0 = time.perf_counter()
        ensemble = DEMEnsemble()
        result["dem"] = {name: ensemble.central_difference(cfg, name, seeds, duration, burn_in,
                                                           step=step_of[name],
                                                           progress=progress)
                         for name in names}
        timing["dem"] = time.perf_counter() - t0
    timing["total"] = time.perf_counter() - t_start
    result["timing_s"] = timing
    return result


def _curve(name: str, value: float, h: float, points: dict[int, np.ndarray],
           middle: tuple[float, float]) -> dict[str, Any]:
    """A parameter's curve: the ensemble powers at ``value -+ h`` (``points``, per packing),
    the design point's (``middle``: mean, SE) between them, and their central difference with
    the standard error of its per-packing values."""
    diff = (points[1] - points[-1]) / (2 * h)
    return {
        "h": h, "theta": [value - h, value, value + h],
        "power_W": [float(points[-1].mean()), middle[0], float(points[1].mean())],
        "power_se_W": [ensemble_mean(points[-1])[1], middle[1], ensemble_mean(points[1])[1]],
        "central_difference": ensemble_mean(diff)[0],
        "central_difference_se": ensemble_mean(diff)[1],
    }


def sensitivity_tasks(names: Sequence[str], packings: int, start: str, estimator: str,
                      curve: bool, dem: bool) -> int:
    """How many times :func:`sensitivity` calls ``progress`` (for a progress bar)."""
    design, charge = split_parameters(names)
    start = resolve_start(start, design) if design else "packing"
    total = packings if start == "packing" else 0
    total += 1 + (2 * len(design) if estimator == "horizon" and curve else 0)
    total += len(charge) * 2 * (packings + 1)
    return total + (2 * packings * len(names) if dem else 0)


# --------------------------------------------------------------------------------------------
# DEM ensembles at design points (the ground truth of a design study)

_SURROGATE_KINDS = tuple(DISSIPATION_KINDS.index(k) for k in ("normal", "tangential"))


def _jar_key(cfg: Config) -> tuple:
    j = cfg.jar
    return (j.kind, j.radius, j.straight_length, j.height, j.post_radius, j.stl_path)


@dataclasses.dataclass
class DEMEnsemble:
    """Runs the DEM of many design points over the same packings, settling each packing once.

    The settled packing depends on the jar, the balls and the seed, not on the motion (the jar
    rests during settling); a motion whose start offset differs is given the packing translated
    with the jar. ``power(cfg, seed, duration, burn_in)`` returns one seed's mean power of
    normal + tangential damping (ball-ball + ball-wall; the surrogate's target) over
    ``(burn_in, duration]`` seconds of motion, in W, and as ``power_total_W`` that of every
    dissipation kind. One process; run one per core for speed.
    """

    chunk_samples: int = 1000
    _settled: dict = dataclasses.field(default_factory=dict)
    _samplers: dict = dataclasses.field(default_factory=dict)

    def _sampler(self, setup: Any) -> Any:
        key = (setup.spec, setup.substeps, setup.pp_capacity, _jar_key(setup.cfg))
        if key not in self._samplers:
            self._samplers[key] = make_sampler(setup.spec, setup.jar.wall_fn, setup.substeps,
                                               setup.pp_capacity)
        return self._samplers[key]

    def _run(self, setup: Any, state: Any, n_samples: int) -> tuple[Any, list[dict]]:
        run = self._sampler(setup)
        out = []
        while n_samples > 0:
            n = min(self.chunk_samples, n_samples)
            state, samples = run(setup.params, state, n)
            out.append(jax.device_get(samples))
            n_samples -= n
        return state, out

    def settled(self, cfg: Config, seed: int) -> Any:
        """The settled DEM state of ``cfg``'s jar and balls for ``seed`` (cached in memory and
        in the user cache, :mod:`sgn_jax.records.cache`), in the lab frame of ``cfg``'s motion at
        t = 0."""
        setup = setup_from_config(cfg)
        key = (_jar_key(cfg), cfg.balls, cfg.material, cfg.materials, cfg.interactions,
               cfg.dem.settle_time, cfg.dem.dt, setup.dt_dem, int(seed))
        if key not in self._settled:
            state = load_settled(setup, int(seed))
            if state is None:
                state = initial_state(setup, int(seed))
                state, _ = self._run(setup, state, settle_sample_count(setup))
                save_settled(setup, int(seed), state)
            state = reset_ledger_totals(state)
            self._settled[key] = (jax.device_get(state),
                                  np.asarray(offset(setup.params.motion, 0.0)))
        state, offset0 = self._settled[key]
        shift = np.asarray(offset(setup.params.motion, 0.0)) - offset0
        return state.replace(pos=state.pos + shift, offset=state.offset + shift)

    def power(self, cfg: Config, seed: int, duration: float, burn_in: float) -> dict[str, Any]:
        """One packing's mean power (W) over ``(burn_in, duration]`` s and its run checks."""
        setup = setup_from_config(cfg)
        dt = float(cfg.dem.dt)
        n_total = _steps(duration, dt, "duration")
        n_burn = _steps(burn_in, dt, "burn_in")
        state = self.settled(cfg, seed)
        _, chunks = self._run(setup, state, n_total)
        diss_pp = np.concatenate([c["diss_pp"] for c in chunks])
        diss_pw = np.concatenate([c["diss_pw"] for c in chunks])
        cumulative = (diss_pp[:, list(_SURROGATE_KINDS)].sum(axis=1)
                      + diss_pw[:, list(_SURROGATE_KINDS)].sum(axis=1))
        every_kind = diss_pp.sum(axis=1) + diss_pw.sum(axis=1)
        start = cumulative[n_burn - 1] if n_burn > 0 else 0.0
        energy = float(cumulative[-1] - start)
        energy_total = float(every_kind[-1] - (every_kind[n_burn - 1] if n_burn > 0 else 0.0))
        pos = np.concatenate([c["pos"] for c in chunks])
        off = np.concatenate([c["offset"] for c in chunks])
        phi = np.asarray(jax.vmap(jax.vmap(lambda x: setup.jar.sdf_fn(setup.jar.geometry, x)))(
            jnp.asarray(pos - off[:, None, :])))
        if not np.all(np.isfinite(pos)) or np.any(phi > 0):
            raise DesignError(f"the DEM run of seed {seed} left the jar or went non-finite "
                              f"(max phi {float(np.nanmax(phi)):.3g} m)")
        return {"seed": int(seed), "power_W": energy / ((n_total - n_burn) * dt),
                "power_total_W": energy_total / ((n_total - n_burn) * dt),
                "energy_J": energy, "max_phi_m": float(phi.max()),
                "mean_pp_contacts": float(np.mean(np.concatenate(
                    [c["n_pp_contacts"] for c in chunks])))}


    def central_difference(self, cfg: Config, name: str, seeds: Iterable[int], duration: float,
                           burn_in: float, *, step: float | None = None,
                           progress: Callable[[str], None] = lambda stage: None
                           ) -> dict[str, Any]:
        """The DEM's ensemble central difference of the power in one parameter ``name`` (a
        design or a charge parameter) at ``cfg``: ``mean_k (P_k(theta + h) - P_k(theta - h)) /
        2h`` over the packings of ``seeds`` (common placement seeds; a charge parameter's sides
        settle packings of their own charge), with the standard error of the per-seed
        differences: the DEM's side of a :func:`sensitivity`. ``h`` is ``step`` (default
        :func:`default_step`); the powers are :meth:`power`'s over ``(burn_in, duration]``.
        ``progress(stage)`` is called after every run.

        Returns a JSON-ready dict: ``name``, ``h``, ``theta`` (theta - h, theta + h),
        ``n_balls`` at each side, ``power_W`` and ``power_se_W`` at each side, ``powers_W``
        (per seed, each side), ``central_difference``, ``central_difference_se``,
        ``differences`` (per seed), ``seeds``.
        """
        seeds = _placement_seeds(seeds, "central_difference")
        value = float(parameter_values_of(cfg, [name])[0])
        h = _parameter_step(name, value, None if step is None else {name: step})
        sides = {side: design_config(cfg, [name], [value + side * h]) for side in (-1, 1)}
        for point in sides.values():   # both sides are valid DEM runs before any work
            check_dem_config(point, warn=False)
        powers = {}
        for side, point in sides.items():
            runs = []
            for seed in seeds:
                runs.append(self.power(point, seed, duration, burn_in)["power_W"])
                progress(f"DEM {name} {side:+d}h, seed {seed}")
            powers[side] = np.asarray(runs, np.float64)
        diff = (powers[1] - powers[-1]) / (2 * h)
        mean, se = ensemble_mean(diff)
        return {"name": name, "h": h, "theta": [value - h, value + h],
                "n_balls": [sides[-1].balls.n_balls, sides[1].balls.n_balls],
                "power_W": [float(powers[s].mean()) for s in (-1, 1)],
                "power_se_W": [ensemble_mean(powers[s])[1] for s in (-1, 1)],
                "powers_W": [powers[s].tolist() for s in (-1, 1)],
                "central_difference": mean, "central_difference_se": se,
                "differences": diff.tolist(), "seeds": list(seeds)}


def ensemble_mean(values: Sequence[float]) -> tuple[float, float]:
    """Mean and its standard error (ddof 1) of a list of per-packing values."""
    arr = np.asarray(values, np.float64)
    se = float(arr.std(ddof=1) / np.sqrt(arr.size)) if arr.size > 1 else float("nan")
    return float(arr.mean()), se


__all__ = [
    "STARTS",
    "DEMEnsemble",
    "DesignStudy",
    "Packings",
    "at_surrogate_step",
    "case_charge",
    "check_charge_study",
    "check_ensemble_steps",
    "check_study_sizes",
    "design_config",
    "design_study",
    "ensemble_mean",
    "ensemble_powers",
    "make_packings",
    "over_packings",
    "parameter_values_of",
    "reads_charge",
    "resolve_start",
    "rollout_ensemble",
    "rollout_sweep",
    "seed_packings",
    "sensitivity",
    "sensitivity_tasks",
    "shard_packings",
    "split_parameters",
    "surrogate_graph_spec",
]
