"""Tests of sgn_jax.config: shipped configs, strict keys, round trip, motion keys per kind."""

import dataclasses
import tomllib
from pathlib import Path

import pytest
import tomli_w

from sgn_jax.config import (
    Config,
    ConfigError,
    MotionConfig,
    builtin_config_path,
    config_from_dict,
    config_to_dict,
    load_config,
    replace_section,
    save_config,
)

SHIPPED = ("emax_300rpm", "emax_post_motion1", "motion1", "motion2")
CONFIG_DIR = Path(__file__).resolve().parents[1] / "experiments" / "configs"


def _shipped_dict(name: str) -> dict:
    with open(builtin_config_path(name), "rb") as fh:
        return tomllib.load(fh)


def _write(tmp_path: Path, data: dict, name: str = "cfg.toml") -> Path:
    path = tmp_path / name
    path.write_text(tomli_w.dumps(data))
    return path


@pytest.mark.parametrize("name", SHIPPED)
def test_shipped_configs_load_with_spec_values(name):
    cfg = load_config(builtin_config_path(name))
    assert cfg == load_config(CONFIG_DIR / f"{name}.toml")  # experiments/configs is the same
    assert cfg.case.name == name
    # docs/conventions.md section 2: the standard balls, material and sampling
    assert (cfg.balls.count, cfg.balls.radius, cfg.balls.density) == (24, 0.005, 7700.0)
    assert (cfg.material.young, cfg.material.poisson, cfg.material.restitution,
            cfg.material.friction, cfg.material.rolling_friction) == (2.05e9, 0.235, 0.3, 0.3, 0.045)
    assert cfg.dem.dt == 1e-4
    assert cfg.dem.substeps == 106
    assert cfg.dem.dt_dem == pytest.approx(9.434e-7, rel=1e-4)
    assert cfg.dem.dt_dem <= 9.5e-7 and 1e-4 / 105 > 9.5e-7  # 106 is the smallest k
    assert cfg.jar.kind == "emax"
    assert (cfg.jar.radius, cfg.jar.straight_length, cfg.jar.height) == (0.020, 0.035, 0.047)
    assert cfg.jar.post_radius == (0.006 if name == "emax_post_motion1" else 0.0)
    expected_kind = "circle" if name == "emax_300rpm" else "harmonic"
    assert cfg.motion.kind == expected_kind


def test_standard_motion_and_harmonic_coefficients():
    circle = load_config(builtin_config_path("emax_300rpm")).motion
    assert (circle.rpm, circle.amplitude, circle.phase) == (300.0, 0.017, 0.0)
    m1 = load_config(builtin_config_path("motion1")).motion
    assert (m1.x_sin, m1.x_cos, m1.z_sin, m1.z_cos) == ((0.017, 0.0), (0.0, -0.0085),
                                                        (0.0, -0.0085), (0.017, 0.0))
    m2 = load_config(builtin_config_path("motion2")).motion
    assert (m2.x_sin, m2.z_cos, m2.x_cos, m2.z_sin) == ((0.017, 0.0), (0.0, 0.017), (), ())


def test_unknown_builtin_name_lists_available():
    with pytest.raises(ConfigError, match=r"no built-in config 'nope'.*emax_300rpm"):
        builtin_config_path("nope")


@pytest.mark.parametrize(
    "section, key",
    [("balls", "colour"), ("dem", "dtt"), ("motion", "rpmm"), ("jar", "radius_mm")],
)
def test_unknown_key_is_named(tmp_path, section, key):
    data = _shipped_dict("emax_300rpm")
    data[section][key] = 1.0
    path = _write(tmp_path, data)
    with pytest.raises(ConfigError) as info:
        load_config(path)
    message = str(info.value)
    assert f"config.{section}.{key}" in message
    assert str(path) in message
    if section != "motion":  # motion keys of the wrong kind are reported by the kind check
        assert "allowed keys" in message


def test_unknown_section_is_named(tmp_path):
    data = _shipped_dict("emax_300rpm")
    data["solver"] = {"dt": 1e-4}
    with pytest.raises(ConfigError, match=r"unknown key\(s\) config\.solver"):
        load_config(_write(tmp_path, data))


@pytest.mark.parametrize(
    "section, key",
    [("balls", "density"), ("material", "young"), ("case", "name"), ("motion", "kind"),
     ("jar", "kind")],
)
def test_missing_required_key_is_named(tmp_path, section, key):
    data = _shipped_dict("emax_300rpm")
    del data[section][key]
    with pytest.raises(ConfigError, match=rf"missing required key config\.{section}\.{key}"):
        load_config(_write(tmp_path, data))


def test_missing_required_section_is_named(tmp_path):
    data = _shipped_dict("emax_300rpm")
    del data["material"]
    with pytest.raises(ConfigError, match=r"missing required key config\.material"):
        load_config(_write(tmp_path, data))
    # optional sections fall back to their defaults
    del data["dem"], data["sdf"]
    data["material"] = _shipped_dict("emax_300rpm")["material"]
    cfg = load_config(_write(tmp_path, data, "defaults.toml"))
    assert cfg.dem == load_config(builtin_config_path("emax_300rpm")).dem


@pytest.mark.parametrize(
    "kind, foreign",
    [("circle", {"x_sin": [0.01]}), ("circle", {"period": 0.2}),
     ("harmonic", {"rpm": 300.0}), ("spline", {"amplitude": 0.01})],
)
def test_motion_keys_of_another_kind_rejected(tmp_path, kind, foreign):
    data = _shipped_dict("emax_300rpm")
    motion = {
        "circle": {"kind": "circle", "rpm": 300.0, "amplitude": 0.017},
        "harmonic": {"kind": "harmonic", "base_frequency_hz": 5.0, "x_sin": [0.017]},
        "spline": {"kind": "spline", "period": 0.2,
                   "points": [[0, 0, 0.01], [0.01, 0, 0], [0, 0, -0.01], [-0.01, 0, 0]]},
    }[kind]
    data["motion"] = dict(motion)
    load_config(_write(tmp_path, data, "ok.toml"))  # valid without the foreign key
    data["motion"].update(foreign)
    (key,) = foreign
    with pytest.raises(ConfigError, match=rf"\['{key}'\] are not used by motion kind '{kind}'"):
        load_config(_write(tmp_path, data))


def test_unknown_motion_kind_says_which_kinds_exist(tmp_path):
    data = _shipped_dict("emax_300rpm")
    data["motion"]["kind"] = "ellipse"
    with pytest.raises(ConfigError, match=r"kind must be one of \('circle', 'harmonic', 'spline'\)"):
        load_config(_write(tmp_path, data))


@pytest.mark.parametrize(
    "section, key, value, message",
    [("motion", "rpm", "fast", r"config\.motion\.rpm must be a number"),
     ("balls", "count", 24.5, r"config\.balls\.count must be an integer"),
     ("balls", "radius", True, r"config\.balls\.radius must be a number"),
     ("dem", "gravity", [0.0, -9.81], r"config\.dem\.gravity must have 3 elements"),
     ("material", "restitution", 1.5, r"restitution must be in \(0, 1\]"),
     ("jar", "post_radius", 0.03, r"post_radius must be in \[0, radius\)")],
)
def test_wrong_type_or_value_is_named(tmp_path, section, key, value, message):
    data = _shipped_dict("emax_300rpm")
    data[section][key] = value
    with pytest.raises(ConfigError, match=message):
        load_config(_write(tmp_path, data))


def test_motion_validation():
    with pytest.raises(ConfigError, match="same length"):
        MotionConfig(kind="harmonic", x_sin=(0.01, 0.0), z_cos=(0.01,))
    with pytest.raises(ConfigError, match="needs at least one"):
        MotionConfig(kind="harmonic")
    with pytest.raises(ConfigError, match="at least 4 points"):
        MotionConfig(kind="spline", points=((0.0, 0.0, 0.0),) * 3)
    with pytest.raises(ConfigError, match="period must be > 0"):
        MotionConfig(kind="spline", period=0.0, points=((0.0, 0.0, 0.0),) * 4)


def test_bad_files(tmp_path):
    with pytest.raises(ConfigError, match="config file not found"):
        load_config(tmp_path / "missing.toml")
    broken = tmp_path / "broken.toml"
    broken.write_text("[case\nname = 1\n")
    with pytest.raises(ConfigError, match=r"broken\.toml: not valid TOML"):
        load_config(broken)


def _spline_config() -> Config:
    cfg = load_config(builtin_config_path("emax_300rpm"))
    points = ((0.0, 0.0, 0.01), (0.01, 0.0, 0.0), (0.0, 0.0, -0.01), (-0.01, 0.001, 0.0))
    return replace_section(
        dataclasses.replace(cfg, motion=MotionConfig(kind="spline", period=0.25, points=points)),
        "dem", seed=17, duration=2.5,
    )


@pytest.mark.parametrize("name", [*SHIPPED, "spline"])
def test_save_load_round_trip(tmp_path, name):
    cfg = _spline_config() if name == "spline" else load_config(builtin_config_path(name))
    path = tmp_path / "sub" / "resolved.toml"
    save_config(cfg, path)
    assert [p.name for p in path.parent.iterdir()] == ["resolved.toml"]  # atomic, no temp left
    assert load_config(path) == cfg
    assert config_from_dict(config_to_dict(cfg)) == cfg
    # only the keys of the motion's own kind are written (the others would be rejected)
    written = tomllib.loads(path.read_text())
    assert set(written["motion"]) == MotionConfig._KEYS_BY_KIND[cfg.motion.kind] | {"kind"}
    # defaults are written out explicitly
    assert {"dem", "sdf", "graph", "model", "train"} <= set(written)


def test_replace_section_validates_again():
    cfg = load_config(builtin_config_path("emax_300rpm"))
    assert replace_section(cfg, "balls", count=8).balls.count == 8
    with pytest.raises(ConfigError, match="count must be >= 1"):
        replace_section(cfg, "balls", count=0)
