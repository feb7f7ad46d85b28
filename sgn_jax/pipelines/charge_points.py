"""Charges at a point of a sweep or a study: a config's charge with one ball size set by its
diameter or its filling (:func:`charge_point`, the charge sweep's points), and the charge
parameters of a sensitivity (:data:`sgn_jax.design.CHARGE_PARAMETER_UNITS`: their values in a
config, :func:`charge_parameter_value`, and a config with one set, :func:`with_charge_parameter`).

Config-level only (no DEM, no surrogate): :mod:`sgn_jax.pipelines.charge_sweep` and
:mod:`sgn_jax.pipelines.studies` build on it.
"""

from __future__ import annotations

import dataclasses
import math

from sgn_jax.config import Config, ConfigError, replace_section
from sgn_jax.design import CHARGE_PARAMETER_UNITS
from sgn_jax.geometry import jar_volume
from sgn_jax.pipelines.configure import jar_params_from_config

SWEEP_PARAMETERS = ("diameter", "fill")
HOLDS = ("fill", "count")


def ball_fill(cfg: Config) -> float:
    """The balls' solid volume over the jar's (parametric jars)."""
    if cfg.jar.kind != "emax":
        raise ConfigError("a charge sweep needs the parametric jar ([jar] kind = 'emax'), whose "
                          f"volume is known; got kind = {cfg.jar.kind!r}")
    return cfg.balls.solid_volume / float(jar_volume(jar_params_from_config(cfg.jar)))


def _one_class(cfg: Config, what: str) -> None:
    if not cfg.balls.single_class:
        raise ConfigError(f"{what} starts from a charge of one ball class; remove "
                          "[[balls.mix]] from the config")


def charge_point(cfg: Config, parameter: str, value: float, hold: str = "fill") -> Config:
    """``cfg`` with one ball size: ``parameter`` "diameter" (m) at the config's filling
    (``hold="fill"``) or ball count (``hold="count"``), or "fill" (the balls' volume fraction)
    at the config's diameter. The charge must be of one class (its density and material are
    kept). At a fixed filling the count is the nearest whole number of balls of that volume."""
    if parameter not in SWEEP_PARAMETERS:
        raise ConfigError(f"charge sweep parameter {parameter!r}: use one of "
                          f"{list(SWEEP_PARAMETERS)}")
    if hold not in HOLDS:
        raise ConfigError(f"hold={hold!r}: use one of {list(HOLDS)}")
    _one_class(cfg, "a charge sweep")
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


def _check_charge_name(name: str) -> None:
    if name not in CHARGE_PARAMETER_UNITS:
        raise ConfigError(f"unknown charge parameter {name!r}; known: "
                          f"{sorted(CHARGE_PARAMETER_UNITS)}")


def charge_parameter_value(cfg: Config, name: str) -> float:
    """The value of charge parameter ``name`` in ``cfg`` (a charge of one ball class): the
    ball radius (m) for ``balls.radius_fill`` and ``balls.radius_count``, the density
    (kg/m^3), or the restitution / sliding friction of the balls' material."""
    _check_charge_name(name)
    _one_class(cfg, f"the charge parameter {name}")
    if name in ("balls.radius_fill", "balls.radius_count"):
        return float(cfg.balls.radius)
    if name == "balls.density":
        return float(cfg.balls.density)
    return float(getattr(cfg.material_named(cfg.balls.material), name.split(".", 1)[1]))


def with_charge_parameter(cfg: Config, name: str, value: float) -> Config:
    """``cfg`` with charge parameter ``name`` set to ``value`` (a charge of one ball class):

    - ``balls.radius_fill``: the radius at the config's filling, the count the nearest whole
      number of balls of that volume (:func:`charge_point` with ``hold="fill"``);
    - ``balls.radius_count``: the radius at the config's ball count;
    - ``balls.density``: the balls' density (kg/m^3);
    - ``balls.restitution``, ``balls.friction``: of the balls' material, that is the
      ``[material]`` section when ``[balls]`` names none (the jar's lining too, so the ball-wall
      contacts change with the ball-ball ones), else its ``[[materials]]`` entry; a pair with
      an ``[[interactions]]`` rule keeps the rule's value.

    ConfigError for a value the config refuses (a radius the jar cannot hold, restitution
    outside (0, 1], ...)."""
    _check_charge_name(name)
    _one_class(cfg, f"the charge parameter {name}")
    value = float(value)
    if not math.isfinite(value):
        raise ConfigError(f"{name} = {value!r}: must be finite")
    if name in ("balls.radius_fill", "balls.radius_count"):
        if not value > 0:
            raise ConfigError(f"{name} = {value:g} m: a ball radius must be > 0")
        return charge_point(cfg, "diameter", 2.0 * value,
                            hold="fill" if name == "balls.radius_fill" else "count")
    if name == "balls.density":
        return replace_section(cfg, "balls", density=value)
    field = name.split(".", 1)[1]
    material = cfg.material_named(cfg.balls.material)
    if material is cfg.material:
        return replace_section(cfg, "material", **{field: value})
    materials = tuple(dataclasses.replace(m, **{field: value}) if m.name == material.name else m
                      for m in cfg.materials)
    return dataclasses.replace(cfg, materials=materials)


__all__ = ["HOLDS", "SWEEP_PARAMETERS", "ball_fill", "charge_parameter_value", "charge_point",
           "with_charge_parameter"]
