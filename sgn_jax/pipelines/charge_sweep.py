"""Sweeps over the charge: power against ball diameter or against filling, from DEM ensembles
and from a surrogate that reads the charge.

``charge_sweep(cfg, "diameter", values)`` runs, for every ball diameter, the config's jar and
motion with a charge of one size at the config's filling (``hold="fill"``: the count follows
the diameter) or with the config's ball count (``hold="count"``); ``charge_sweep(cfg, "fill",
values)`` holds the diameter and sets the count from each filling (the balls' solid volume over
the jar's; :func:`sgn_jax.pipelines.charge_points.charge_point`). Each point is an ensemble of
DEM packings (seeds ``first_seed ..``), each run for ``duration`` s of motion, the power
averaged over ``(burn_in, duration]``: the mean power (normal + tangential damping, the
surrogates' target, and the total of every dissipation kind), the specific power per kg of
balls, and their standard errors over the packings.

With ``surrogate=`` (a model whose kind reads the charge, ``contact_charge``) the same DEM
packings of every point (the same seeds, settled once with the settled-packing cache on) are
also rolled out by the surrogate for the same duration and burn-in, giving its power and
specific power with their standard errors beside the DEM's; ``dem=False`` runs the surrogate
only (the DEM settles the packings and takes their first window, nothing more). The DEM's
cost is about a minute of one core per packing and simulated second for 60 balls of 6 mm.
Every point's config is checked before any work (fill, grid resolution, contact resolution,
whole steps).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from sgn_jax.config import Config, ConfigError
from sgn_jax.design import DesignError
from sgn_jax.pipelines.charge_points import HOLDS, SWEEP_PARAMETERS, ball_fill, charge_point
from sgn_jax.pipelines.studies import (
    DEMEnsemble,
    at_surrogate_step,
    check_ensemble_steps,
    check_study_sizes,
    ensemble_mean,
    ensemble_powers,
    make_packings,
    reads_charge,
)
from sgn_jax.pipelines.validation import check_dem_config
from sgn_jax.records.checkpoint import TrainedModel
from sgn_jax.records.shipped_models import load_surrogate


def charge_sweep(cfg: Config, parameter: str, values: Sequence[float], *, hold: str = "fill",
                 packings: int = 4, first_seed: int = 100, duration: float = 1.5,
                 burn_in: float = 0.5, surrogate: TrainedModel | str | Path | None = None,
                 dem: bool = True,
                 progress: Callable[[str], None] = lambda stage: None) -> dict[str, Any]:
    """Mean power, specific power and their standard errors at each charge of a sweep (DEM
    ensembles, and a surrogate's with ``surrogate``; see the module docstring).
    ``progress(stage)`` is called after every DEM run and every packing the surrogate rolls out
    from (its settle and first window).

    Args:
        surrogate: a :class:`TrainedModel`, or what :func:`load_surrogate` loads (a training
            run or checkpoint directory, a shipped model's name), of a kind that reads the
            charge; None: the DEM only. Each point runs at the model's step
            (:func:`sgn_jax.api.at_surrogate_step`), its DEM runs too.
        dem: run the DEM's ensembles (False: the surrogate's only; needs ``surrogate``).

    Returns a JSON-ready dict: ``parameter``, ``hold``, ``points`` (one per value: ``value``,
    ``diameter_m``, ``n_balls``, ``fill``, ``mass_kg``; with ``dem``: ``power_W``,
    ``power_se_W``, ``power_total_W``, ``power_total_se_W``, ``specific_W_per_kg`` and
    ``specific_se_W_per_kg`` (every kind per kg), ``specific_damping_W_per_kg`` and
    ``specific_damping_se_W_per_kg`` (normal + tangential damping per kg), ``powers_W`` and
    ``powers_total_W`` per packing; with ``surrogate``: ``surrogate_power_W``,
    ``surrogate_power_se_W``, ``surrogate_specific_W_per_kg``,
    ``surrogate_specific_se_W_per_kg`` (normal + tangential damping, the surrogate's
    dissipation) and ``surrogate_powers_W`` per packing), ``seeds``, ``duration_s``,
    ``burn_in_s``, ``simulator`` ("dem", "surrogate" or "dem+surrogate"), ``surrogate``
    (the model's kind and meta checkpoint, or None), ``timing_s``.
    """
    check_study_sizes(duration, burn_in, packings)
    if len(values) < 1:
        raise ConfigError("a charge sweep needs at least one value")
    if not dem and surrogate is None:
        raise ConfigError("a charge sweep with dem=False needs a surrogate (surrogate=<checkpoint "
                          "directory>, `sgn-jax charge-sweep --surrogate DIR --no-dem`)")
    points_cfg = [charge_point(cfg, parameter, float(v), hold) for v in values]
    model = None
    if surrogate is not None:
        model = surrogate if isinstance(surrogate, TrainedModel) else load_surrogate(surrogate)
        if not reads_charge(model):
            kind = getattr(model.config.model, "kind", "?")
            raise DesignError(f"a charge sweep's surrogate must read the charge (model kind "
                              f"'contact_charge'); this one's kind is {kind!r}, which rolls out "
                              "the one charge it was trained on")
        # the DEM's runs at the model's step too: the same settled packings for both
        points_cfg = [at_surrogate_step(point, model) for point in points_cfg]
    for point in points_cfg:  # every point is a valid DEM run, before any work
        check_dem_config(point, warn=False)
        if model is not None:
            check_ensemble_steps(point, duration, burn_in)
    seeds = list(range(first_seed, first_seed + packings))
    ensemble = DEMEnsemble()
    t0 = time.perf_counter()
    points = []
    for value, point in zip(values, points_cfg, strict=True):
        mass = point.balls.mass
        entry: dict[str, Any] = {"value": float(value), "diameter_m": 2 * point.balls.radius,
                                 "n_balls": point.balls.n_balls, "fill": ball_fill(point),
                                 "mass_kg": mass}
        if dem:
            runs = []
            for seed in seeds:
                runs.append(ensemble.power(point, seed, duration, burn_in))
                progress(f"{parameter} = {float(value):g}, seed {seed}")
            target = [r["power_W"] for r in runs]
            total = [r["power_total_W"] for r in runs]
            mean, se = ensemble_mean(target)
            mean_total, se_total = ensemble_mean(total)
            entry.update({"power_W": mean, "power_se_W": se,
                          "power_total_W": mean_total, "power_total_se_W": se_total,
                          "specific_W_per_kg": mean_total / mass,
                          "specific_se_W_per_kg": se_total / mass,
                          "specific_damping_W_per_kg": mean / mass,
                          "specific_damping_se_W_per_kg": se / mass,
                          "powers_W": target, "powers_total_W": total})
        if model is not None:
            packed = make_packings(point, seeds, log=lambda message, v=value: progress(
                f"{parameter} = {float(v):g}, surrogate {message}"))
            powers = ensemble_powers(model, point, packed, duration, burn_in)
            mean, se = ensemble_mean(powers)
            entry.update({"surrogate_power_W": mean, "surrogate_power_se_W": se,
                          "surrogate_specific_W_per_kg": mean / mass,
                          "surrogate_specific_se_W_per_kg": se / mass,
                          "surrogate_powers_W": powers.tolist()})
        points.append(entry)
    simulator = "+".join(name for name, on in (("dem", dem), ("surrogate", model is not None))
                         if on)
    return {"parameter": parameter, "hold": hold if parameter == "diameter" else "diameter",
            "points": points, "seeds": seeds, "duration_s": duration, "burn_in_s": burn_in,
            "simulator": simulator,
            "surrogate": None if model is None else {
                "kind": getattr(model.config.model, "kind", None),
                "checkpoint": (None if isinstance(surrogate, TrainedModel) else str(surrogate))},
            "timing_s": time.perf_counter() - t0}


def plot_charge_sweep(result: dict[str, Any], path: Any) -> Any:
    """Mean power and specific power against the swept parameter, with +- 1 SE bars; a PNG at
    ``path``. The DEM's normal + tangential damping and every kind, and the surrogate's power
    (normal + tangential damping, its dissipation) where the sweep has them, overlaid."""
    # deferred: plots imports matplotlib, which the sweep itself (and the API) does not need
    from sgn_jax.analysis.plots import new_figure, save_figure

    pts = result["points"]
    x = np.array([p["value"] for p in pts])
    scale, unit = (1e3, "ball diameter (mm)") if result["parameter"] == "diameter" else (
        100.0, "balls' volume fraction of the jar (%)")
    fig = new_figure(9.0, 3.6, layout="constrained")
    ax1, ax2 = fig.subplots(1, 2)
    # (power key, its SE key, specific key, its SE key, label), each drawn where the sweep has it
    series = (("power_total_W", "power_total_se_W", "specific_W_per_kg",
               "specific_se_W_per_kg", "DEM, all dissipation"),
              ("power_W", "power_se_W", "specific_damping_W_per_kg",
               "specific_damping_se_W_per_kg", "DEM, normal + tangential damping"),
              ("surrogate_power_W", "surrogate_power_se_W", "surrogate_specific_W_per_kg",
               "surrogate_specific_se_W_per_kg", "surrogate, normal + tangential damping"))
    for power, power_se, specific, specific_se, label in series:
        if power not in pts[0]:
            continue
        marker = "s" if power.startswith("surrogate") else "o"
        ax1.errorbar(x * scale, [p[power] for p in pts], yerr=[p[power_se] for p in pts],
                     marker=marker, capsize=3, label=label)
        if specific in pts[0]:
            ax2.errorbar(x * scale, [p[specific] for p in pts],
                         yerr=[p[specific_se] for p in pts], marker=marker, capsize=3,
                         label=label)
    for ax, ylabel in ((ax1, "mean power (W)"), (ax2, "specific power (W per kg of balls)")):
        ax.set_xlabel(unit)
        ax.set_ylabel(ylabel)
        ax.legend(fontsize=7)
        ax.grid(alpha=0.3)
    held = ("at fixed filling" if result["hold"] == "fill" else
            "at fixed ball count" if result["hold"] == "count" else "at fixed diameter")
    who = {"dem": "DEM", "surrogate": "surrogate"}.get(result.get("simulator", "dem"),
                                                        "DEM and surrogate")
    fig.suptitle(f"{who}, {len(result['seeds'])} packings per point, {held}; mean +- SE",
                 fontsize=10)
    return save_figure(fig, path)


__all__ = ["HOLDS", "SWEEP_PARAMETERS", "ball_fill", "charge_point", "charge_sweep",
           "plot_charge_sweep"]
