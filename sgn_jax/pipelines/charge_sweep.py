"""Sweeps over the charge: power against ball diameter or against filling, from DEM ensembles.

``charge_sweep(cfg, "diameter", values)`` runs, for every ball diameter, the config's jar and
motion with a charge of one size at the config's filling (``hold="fill"``: the count follows
the diameter) or with the config's ball count (``hold="count"``); ``charge_sweep(cfg, "fill",
values)`` holds the diameter and sets the count from each filling (the balls' solid volume over
the jar's). Each point is an ensemble of DEM packings (seeds ``first_seed ..``), each run for
``duration`` s of motion, the power averaged over ``(burn_in, duration]``: the mean power
(normal + tangential damping, the surrogates' target, and the total of every dissipation
kind), the specific power per kg of balls, and their standard errors over the packings.

The surrogates model one charge today (docs/charge.md), so the sweep is the DEM's: its cost is
the DEM's, about a minute of one core per packing and simulated second for 60 balls of 6 mm.
Every point's config is checked before any work (fill, grid resolution, contact resolution).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from sgn_jax.config import Config, ConfigError, replace_section
from sgn_jax.geometry import jar_volume
from sgn_jax.pipelines.configure import jar_params_from_config
from sgn_jax.pipelines.studies import DEMEnsemble, check_study_sizes, ensemble_mean
from sgn_jax.pipelines.validation import check_dem_config

SWEEP_PARAMETERS = ("diameter", "fill")
HOLDS = ("fill", "count")


def ball_fill(cfg: Config) -> float:
    """The balls' solid volume over the jar's (parametric jars)."""
    if cfg.jar.kind != "emax":
        raise ConfigError("a charge sweep needs the parametric jar ([jar] kind = 'emax'), whose "
                          f"volume is known; got kind = {cfg.jar.kind!r}")
    return cfg.balls.solid_volume / float(jar_volume(jar_params_from_config(cfg.jar)))


def charge_point(cfg: Config, parameter: str, value: float, hold: str = "fill") -> Config:
    """``cfg`` with one ball size: ``parameter`` "diameter" (m) at the config's filling
    (``hold="fill"``) or ball count (``hold="count"``), or "fill" (the balls' volume fraction)
    at the config's diameter. The charge must be of one class (its density and material are
    kept)."""
    if parameter not in SWEEP_PARAMETERS:
        raise ConfigError(f"charge sweep parameter {parameter!r}: use one of "
                          f"{list(SWEEP_PARAMETERS)}")
    if hold not in HOLDS:
        raise ConfigError(f"hold={hold!r}: use one of {list(HOLDS)}")
    if not cfg.balls.single_class:
        raise ConfigError("a charge sweep starts from a charge of one ball class; remove "
                          "[[balls.mix]] from the config")
    if not (math.isfinite(value) and value > 0):
        raise ConfigError(f"charge sweep value {value!r} for {parameter}: must be > 0 "
                          "(diameter in m, fill as a fraction, e.g. 0.15)")
    volume = float(jar_volume(jar_params_from_config(cfg.jar)))
    if parameter == "diameter":
        radius = value / 2
        if hold == "count":
            count = cfg.balls.count
        else:
            count = max(1, round(ball_fill(cfg) * volume / (4.0 / 3.0 * math.pi * radius**3)))
    else:
        if value >= 1:
            raise ConfigError(f"fill = {value:g}: the balls' volume fraction of the jar must be "
                              "below 1 (e.g. 0.15 for 15 %)")
        radius = cfg.balls.radius
        count = max(1, round(value * volume / (4.0 / 3.0 * math.pi * radius**3)))
    return replace_section(cfg, "balls", count=int(count), radius=float(radius))


def charge_sweep(cfg: Config, parameter: str, values: Sequence[float], *, hold: str = "fill",
                 packings: int = 4, first_seed: int = 100, duration: float = 1.5,
                 burn_in: float = 0.5,
                 progress: Callable[[str], None] = lambda stage: None) -> dict[str, Any]:
    """Mean power, specific power and their standard errors at each charge of a sweep (DEM
    ensembles; see the module docstring). ``progress(stage)`` is called after every packing.

    Returns a JSON-ready dict: ``parameter``, ``hold``, ``points`` (one per value: ``value``,
    ``diameter_m``, ``n_balls``, ``fill``, ``mass_kg``, ``power_W``, ``power_se_W``,
    ``power_total_W``, ``power_total_se_W``, ``specific_W_per_kg``, ``specific_se_W_per_kg``,
    ``powers_W`` per packing), ``seeds``, ``duration_s``, ``burn_in_s``, ``timing_s``.
    """
    check_study_sizes(duration, burn_in, packings)
    if len(values) < 1:
        raise ConfigError("a charge sweep needs at least one value")
    points_cfg = [charge_point(cfg, parameter, float(v), hold) for v in values]
    for point in points_cfg:  # every point is a valid DEM run, before any work
        check_dem_config(point, warn=False)
    seeds = list(range(first_seed, first_seed + packings))
    ensemble = DEMEnsemble()
    t0 = time.perf_counter()
    points = []
    for value, point in zip(values, points_cfg, strict=True):
        runs = []
        for seed in seeds:
            runs.append(ensemble.power(point, seed, duration, burn_in))
            progress(f"{parameter} = {float(value):g}, seed {seed}")
        target = [r["power_W"] for r in runs]
        total = [r["power_total_W"] for r in runs]
        mass = point.balls.mass
        mean, se = ensemble_mean(target)
        mean_total, se_total = ensemble_mean(total)
        points.append({"value": float(value), "diameter_m": 2 * point.balls.radius,
                       "n_balls": point.balls.n_balls, "fill": ball_fill(point),
                       "mass_kg": mass, "power_W": mean, "power_se_W": se,
                       "power_total_W": mean_total, "power_total_se_W": se_total,
                       "specific_W_per_kg": mean_total / mass,
                       "specific_se_W_per_kg": se_total / mass,
                       "powers_W": target, "powers_total_W": total})
    return {"parameter": parameter, "hold": hold if parameter == "diameter" else "diameter",
            "points": points, "seeds": seeds, "duration_s": duration, "burn_in_s": burn_in,
            "simulator": "dem", "timing_s": time.perf_counter() - t0}


def plot_charge_sweep(result: dict[str, Any], path: Any) -> Any:
    """Mean power (normal + tangential damping, and every kind) and specific power against the
    swept parameter, with +- 1 SE bars; a PNG at ``path``."""
    # deferred: plots imports matplotlib, which the sweep itself (and the API) does not need
    from sgn_jax.analysis.plots import new_figure, save_figure

    pts = result["points"]
    x = np.array([p["value"] for p in pts])
    scale, unit = (1e3, "ball diameter (mm)") if result["parameter"] == "diameter" else (
        100.0, "balls' volume fraction of the jar (%)")
    fig = new_figure(9.0, 3.6)
    ax1, ax2 = fig.subplots(1, 2)
    for key, label in (("power_total_W", "all dissipation"),
                       ("power_W", "normal + tangential damping")):
        ax1.errorbar(x * scale, [p[key] for p in pts],
                     yerr=[p[key.replace("_W", "_se_W")] for p in pts], marker="o", capsize=3,
                     label=label)
    ax1.set_xlabel(unit)
    ax1.set_ylabel("mean power (W)")
    ax1.legend(fontsize=8)
    ax2.errorbar(x * scale, [p["specific_W_per_kg"] for p in pts],
                 yerr=[p["specific_se_W_per_kg"] for p in pts], marker="o", capsize=3)
    ax2.set_xlabel(unit)
    ax2.set_ylabel("specific power (W per kg of balls)")
    held = ("at fixed filling" if result["hold"] == "fill" else
            "at fixed ball count" if result["hold"] == "count" else "at fixed diameter")
    fig.suptitle(f"DEM, {len(result['seeds'])} packings per point, {held}; mean +- SE",
                 fontsize=10)
    for ax in (ax1, ax2):
        ax.grid(alpha=0.3)
    return save_figure(fig, path)


__all__ = ["HOLDS", "SWEEP_PARAMETERS", "ball_fill", "charge_point", "charge_sweep",
           "plot_charge_sweep"]
