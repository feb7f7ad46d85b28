"""Config -> core: every ``*_from_config`` adapter of the package, in one place.

The core modules take plain values, specs and pytrees; this module reads the typed config
(:mod:`sgn_jax.config`) and builds them. It also holds the two file-reading parts of the jar
geometry (STL loading, the on-disk cache of mesh SDF grids), so the core geometry stays pure.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path
from typing import Any

import jax.numpy as jnp
import numpy as np

from sgn_jax.config import ConfigError, MotionConfig
from sgn_jax.dem.charge import BallClass, Charge, ChargeError, Material, PairRule, charge_params
from sgn_jax.dem.engine import DEMParams
from sgn_jax.dem.laws import ContactLawError, contact_law
from sgn_jax.geometry import GeometryError, JarParams, SDFGrid, check_closed_mesh
from sgn_jax.geometry.jar import jar_mesh, jar_volume
from sgn_jax.geometry.mesh_distance import signed_distance_grid
from sgn_jax.geometry.sdf_grid import grid_layout, sdf_grid_from_jar
from sgn_jax.geometry.stl import UNIT_SCALES
from sgn_jax.motion import Motion, motion_kind_named
from sgn_jax.records.io_utils import atomic_write
from sgn_jax.scene import (
    JarGeometry,
    analytic_jar_query,
    grid_jar,
    grid_query,
    parametric_jar,
)
from sgn_jax.surrogate.graph import GraphSpec
from sgn_jax.surrogate.model import model_factory, model_kind


def motion_from_config(cfg: MotionConfig, dtype: jnp.dtype = jnp.float64) -> Motion:
    """Build the motion pytree described by a ``[motion]`` config section, leaves of ``dtype``.

    Built through the motion-kind registry: the kind named ``cfg.kind``
    (:func:`sgn_jax.motion.motion_kind_named`) gets the plain values of its ``config_keys``
    and constructs the motion (:attr:`sgn_jax.motion.MotionKind.from_config`). Harmonic
    coefficient lists that are empty mean zero; all lists of one config have the same length K
    (checked by MotionConfig).
    """
    if not isinstance(cfg, MotionConfig):
        raise TypeError(
            f"motion_from_config expects a sgn_jax.config.MotionConfig (cfg.motion), "
            f"got {type(cfg).__name__}"
        )
    try:
        kind = motion_kind_named(cfg.kind)
    except ValueError:
        raise ConfigError(f"[motion] unknown kind {cfg.kind!r}") from None
    if kind.from_config is None:
        raise ConfigError(f"[motion] kind {cfg.kind!r} cannot be built from a config (its "
                          "MotionKind has no from_config)")
    values = {key: getattr(cfg, key) for key in kind.config_keys}
    return kind.from_config(values, dtype)


def graph_spec_from_config(cfg: Any, n_particles: int | None = None) -> GraphSpec:
    """The GraphSpec of a :class:`sgn_jax.config.Config` (balls, dem.dt and the [graph] section).

    The ball-ball capacity is ``graph.pp_edges_per_particle * N`` directed edges.
    ``node_walls`` follows the ``[model] kind`` (``ModelFactory.node_walls``; a config without
    a ``[model]`` section gets the paper's True).
    """
    check_surrogate_charge(cfg)
    n = cfg.balls.count if n_particles is None else int(n_particles)
    return GraphSpec(
        n_particles=n,
        window=cfg.graph.window,
        ball_radius=cfg.balls.radius,
        dt=cfg.dem.dt,
        pp_skin=cfg.graph.pp_skin,
        phi_pw=cfg.graph.phi_pw,
        pp_pair_capacity=max(1, (cfg.graph.pp_edges_per_particle * n) // 2),
        contact_features=cfg.graph.contact_features,
        wall_patches=cfg.graph.wall_patches,
        node_walls=_kind_reads_node_walls(cfg),
    )


def model_takes_charge(cfg: Any) -> bool:
    """Whether the config's ``[model] kind`` reads each ball's radius, mass and material from
    the window's charge (``ModelFactory.takes_charge``: the charge-conditioned contact kind);
    False for a config without a ``[model]`` section."""
    model_cfg = getattr(cfg, "model", None)
    return model_cfg is not None and model_factory(model_kind(model_cfg)).takes_charge


def check_surrogate_charge(cfg: Any) -> None:
    """ConfigError unless the config's charge is one its surrogate takes: any charge for a
    kind that reads the charge (:func:`model_takes_charge`), otherwise one ball class of the
    jar's material (``[balls]`` without ``[[balls.mix]]`` and without a ``material`` of its
    own). The DEM runs every charge (docs/charge.md)."""
    balls = getattr(cfg, "balls", None)
    if balls is None or not hasattr(balls, "single_class") or model_takes_charge(cfg):
        return
    if not balls.single_class:
        raise ConfigError(
            f"the surrogates model one ball class, and this charge has {len(balls.classes)} "
            "([[balls.mix]]); run the DEM for mixed charges (`sgn-jax dem`), or remove "
            "[[balls.mix]]")
    if balls.material and balls.material != cfg.material.name:
        raise ConfigError(
            f"the surrogates model balls of the jar's material ([material] "
            f"{cfg.material.name!r}), and [balls] material = {balls.material!r}; run the DEM "
            "for this charge (`sgn-jax dem`), or give the balls the jar's material")


def _kind_reads_node_walls(cfg: Any) -> bool:
    """Whether the config's ``[model] kind`` reads the node features' wall columns."""
    model_cfg = getattr(cfg, "model", None)
    if model_cfg is None:
        return True
    return model_factory(model_kind(model_cfg)).node_walls


def jar_params_from_config(jar_cfg: Any) -> JarParams:
    """``JarParams`` of a ``[jar]`` config section of kind "emax" (``has_post = post_radius > 0``)."""
    if jar_cfg.kind != "emax":
        raise GeometryError(
            f"jar_params_from_config needs a [jar] section of kind 'emax', got {jar_cfg.kind!r}; "
            "an STL jar has no parameters: use jar_mesh_from_config / load_stl instead"
        )
    return JarParams(
        radius=float(jar_cfg.radius),
        straight_length=float(jar_cfg.straight_length),
        height=float(jar_cfg.height),
        post_radius=float(jar_cfg.post_radius),
        has_post=float(jar_cfg.post_radius) > 0,
    )


def jar_mesh_from_config(jar_cfg: Any) -> Any:
    """The jar of a ``[jar]`` config section as a trimesh: kind "emax" -> :func:`jar_mesh`,
    kind "stl" -> :func:`sgn_jax.pipelines.configure.load_stl` of ``stl_path`` in ``stl_units``."""
    if jar_cfg.kind == "emax":
        return jar_mesh(jar_params_from_config(jar_cfg))
    if jar_cfg.kind == "stl":
        return load_stl(jar_cfg.stl_path, jar_cfg.stl_units)
    raise GeometryError(f"[jar] kind must be 'emax' or 'stl', got {jar_cfg.kind!r}")


def load_stl(path: str | Path, units: str = "m") -> Any:
    """Load a cavity STL in ``units`` ("m" or "mm"), return a validated trimesh in m.

    Vertices are merged (an STL is a triangle soup); the mesh must be watertight and
    consistently wound (see :func:`check_closed_mesh`). Raises GeometryError on a missing or
    unreadable file, unknown units or a bad mesh.
    """
    if units not in UNIT_SCALES:
        raise GeometryError(f"STL units must be one of {sorted(UNIT_SCALES)}, got {units!r}")
    path = Path(path)
    if not path.is_file():
        raise GeometryError(f"STL file not found: {path} (check [jar] stl_path)")
    import trimesh  # here, not at the top: 0.35 s of every process's start, for STL jars only

    try:
        mesh = trimesh.load(str(path), file_type="stl", force="mesh", process=True)
    except Exception as exc:  # trimesh raises a variety of parse errors
        raise GeometryError(f"{path}: cannot read as STL: {exc}") from exc
    if not isinstance(mesh, trimesh.Trimesh):
        raise GeometryError(f"{path}: expected a single triangle mesh, got {type(mesh).__name__}")
    if UNIT_SCALES[units] != 1.0:
        mesh.apply_scale(UNIT_SCALES[units])
    return check_closed_mesh(mesh, name=str(path))


MESH_GRID_CACHE_VERSION = 1


def default_cache_dir() -> Path:
    """``$SGN_JAX_CACHE`` if set, else ``~/.cache/sgn_jax``."""
    env = os.environ.get("SGN_JAX_CACHE")
    return Path(env) if env else Path.home() / ".cache" / "sgn_jax"


def mesh_grid_cache_key(mesh: Any, spacing: float, margin: float) -> str:
    """sha256 of the mesh's vertices and faces, the spacing, the margin and the cache version."""
    digest = hashlib.sha256()
    digest.update(np.ascontiguousarray(mesh.vertices, dtype=np.float64).tobytes())
    digest.update(np.ascontiguousarray(mesh.faces, dtype=np.int64).tobytes())
    digest.update(f"|spacing={float(spacing)!r}|margin={float(margin)!r}|".encode())
    digest.update(f"v{MESH_GRID_CACHE_VERSION}".encode())
    return digest.hexdigest()


def _load_cached_grid(path: Path) -> tuple[np.ndarray, np.ndarray, float] | None:
    try:
        with np.load(path) as data:
            values = np.asarray(data["values"], dtype=np.float64)
            origin = np.asarray(data["origin"], dtype=np.float64)
            spacing = float(data["spacing"])
    except (OSError, KeyError, ValueError):
        return None  # unreadable or stale cache file: recompute and overwrite it
    if values.ndim != 3 or origin.shape != (3,) or not np.all(np.isfinite(values)):
        return None
    return values, origin, spacing


def sdf_grid_from_mesh(
    mesh: Any,
    spacing: float = 5e-4,
    margin: float = 3e-3,
    dtype: Any = jnp.float32,
    cache_dir: str | Path | None = None,
) -> SDFGrid:
    """Grid of the signed distance to a closed cavity mesh (negative inside; docs/conventions.md
    section 1).

    The mesh's bounding box grown by ``margin`` is sampled with
    :func:`sgn_jax.geometry.mesh_distance.signed_distance_grid` (exact distances by
    branch-and-bound over blocks of nodes, sign from angle-weighted pseudonormals). The float64 result is cached as
    ``sdf_grid_<sha256>.npz`` in ``cache_dir`` (default :func:`default_cache_dir`), keyed by
    :func:`mesh_grid_cache_key`, and written atomically.
    """
    lower = np.asarray(mesh.bounds[0], dtype=np.float64) - margin
    upper = np.asarray(mesh.bounds[1], dtype=np.float64) + margin
    origin, shape = grid_layout(lower, upper, spacing)
    cache_path = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    cache_path = cache_path / f"sdf_grid_{mesh_grid_cache_key(mesh, spacing, margin)}.npz"

    cached = _load_cached_grid(cache_path) if cache_path.is_file() else None
    if cached is not None and cached[0].shape == shape and cached[2] == float(spacing):
        values, origin = cached[0], cached[1]
    else:
        values = signed_distance_grid(
            mesh, origin, shape, spacing, progress=int(np.prod(shape)) > 200_000
        )
        with atomic_write(cache_path, "wb") as fh:
            np.savez(fh, values=values, origin=origin, spacing=np.float64(spacing))
    return SDFGrid(
        values=jnp.asarray(values, dtype=dtype),
        origin=jnp.asarray(origin, dtype=dtype),
        spacing=float(spacing),
    )


def sdf_grid_from_config(cfg: Any, dtype: Any = jnp.float32, per_patch: bool = True) -> SDFGrid:
    """The SDF grid of a whole config: ``[jar]`` kind "emax" -> :func:`sdf_grid_from_jar`
    (patch-stacked unless ``per_patch=False``), kind "stl" -> the mesh of ``stl_path`` (a single
    patch); spacing and margin from ``[sdf]``."""
    if cfg.jar.kind == "emax":
        return sdf_grid_from_jar(
            jar_params_from_config(cfg.jar), cfg.sdf.spacing, cfg.sdf.margin, dtype, per_patch
        )

    return sdf_grid_from_mesh(jar_mesh_from_config(cfg.jar), cfg.sdf.spacing, cfg.sdf.margin, dtype)


def surrogate_walls_from_config(cfg: Any) -> tuple[Any, Any]:
    """``(geometry, query)`` through which a surrogate sees the jar's walls: the patch-stacked
    SDF grid and ``grid_query`` (the paper's featurizer); for a model with one ball-wall edge
    per wall patch (``[graph] wall_patches``) in a parametric ("emax") jar, the jar's exact
    analytic patches (``JarParams`` and ``analytic_jar_query``), as the DEM has them: a
    grid's trilinear side wall is off by up to 2 um, as much as a resting ball's overlap."""
    if cfg.graph.wall_patches and cfg.jar.kind == "emax":
        return jar_params_from_config(cfg.jar), analytic_jar_query
    return sdf_grid_from_config(cfg), grid_query


def contact_law_from_config(cfg: Any) -> Any:
    """The contact law named by ``[dem] contact_law`` (sgn_jax.dem.laws registry)."""
    try:
        return contact_law(cfg.dem.contact_law)
    except ContactLawError as exc:
        raise ConfigError(f"[dem] contact_law: {exc}") from None


def material_from_config(material_cfg: Any) -> Material:
    """The core :class:`sgn_jax.dem.charge.Material` of a ``[material]`` / ``[[materials]]``
    table."""
    m = material_cfg
    try:
        return Material(name=m.name, young=m.young, poisson=m.poisson,
                        restitution=m.restitution, friction=m.friction,
                        rolling_friction=m.rolling_friction)
    except ChargeError as exc:
        raise ConfigError(str(exc)) from None


def charge_from_config(cfg: Any) -> Charge:
    """The charge of a config (docs/charge.md): ``[balls]`` and its ``[[balls.mix]]`` classes,
    each of its named material (``[material]`` when it names none), in a jar of ``[material]``,
    with the ``[[interactions]]`` pair rules."""
    try:
        classes = tuple(BallClass(count=c.count, radius=c.radius, density=c.density,
                                  material=material_from_config(cfg.material_named(c.material)))
                        for c in cfg.balls.classes)
        rules = tuple(((r.materials[0], r.materials[1]),
                       PairRule(r.restitution, r.friction, r.rolling_friction))
                      for r in cfg.interactions)
        # A rule may name a defined material that no ball uses: it has nothing to act on.
        used = {c.material.name for c in classes} | {cfg.material.name}
        rules = tuple(r for r in rules if set(r[0]) <= used)
        return Charge(classes=classes, wall=material_from_config(cfg.material), pair_rules=rules)
    except ChargeError as exc:
        raise ConfigError(str(exc)) from None


def params_from_config(cfg: Any, geometry: Any = None, motion: Any = None) -> DEMParams:
    """DEMParams of an experiment config (the charge, gravity, jar patches, motion)."""
    if geometry is None:
        geometry = geometry_from_config(cfg).geometry
    if motion is None:
        motion = motion_from_config(cfg.motion)
    return charge_params(charge_from_config(cfg), gravity=tuple(cfg.dem.gravity),
                         geometry=geometry, motion=motion,
                         contact_law=contact_law_from_config(cfg))


def geometry_from_config(cfg: Any) -> JarGeometry:
    """The jar of a config for the DEM.

    The parametric jar gives one contact per wall patch (floor, lid, side[, post]), each its own
    analytic SDF. An STL jar is a single patch read from an SDF grid (float64, ``[sdf]``
    spacing): a ball in a concave edge of an STL jar then feels only the nearer wall, and the
    wall is only as smooth as the trilinear grid (documented limitation,
    docs/conventions.md section 3).
    """
    if cfg.jar.kind == "emax":
        return parametric_jar(jar_params_from_config(cfg.jar))
    return grid_jar(sdf_grid_from_config(cfg, dtype=jnp.float64), float(cfg.sdf.margin))


def mesh_report(mesh: Any, jar_cfg: Any) -> dict[str, Any]:
    """JSON-able summary of a jar mesh: volume_ml, watertight, winding_consistent, n_faces,
    bounds (m, [[xmin, ymin, zmin], [xmax, ymax, zmax]]) and, for an "emax" jar,
    analytic_volume_ml and volume_error_percent (mesh vs analytic)."""
    report: dict[str, Any] = {
        "volume_ml": float(mesh.volume) * 1e6,
        "watertight": bool(mesh.is_watertight),
        "winding_consistent": bool(mesh.is_winding_consistent),
        "n_faces": int(len(mesh.faces)),
        "bounds": np.asarray(mesh.bounds, dtype=float).tolist(),
    }
    if jar_cfg.kind == "emax":
        analytic_ml = float(jar_volume(jar_params_from_config(jar_cfg))) * 1e6
        report["analytic_volume_ml"] = analytic_ml
        report["volume_error_percent"] = 100 * (report["volume_ml"] - analytic_ml) / analytic_ml
    return report
