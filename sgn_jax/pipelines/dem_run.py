"""DEM driver: placement, settling, chunked sampling with checkpoints, the trajectory record
(docs/conventions.md section 4).

``run_dem(cfg, duration, out_path)``:

1. place the charge's balls (``cfg.balls`` and its ``[[balls.mix]]``, largest first) at rest
   in the jar from ``seed`` (random sequential insertion);
2. settle for ``cfg.dem.settle_time`` with the jar at rest at ``offset(0)`` (DEM steps
   -settle_steps .. 0), then zero the dissipation and wall-work totals: t = 0;
3. run ``duration`` of motion in chunks of ``cfg.dem.chunk_samples`` samples (one jitted nested
   ``lax.scan`` per chunk, no host sync inside), a sample every ``dt = substeps * dt_dem``;
4. after settling and after each chunk, write the chunk's samples and the state atomically into
   ``OUT.partial/`` next to the output, so an interrupted run resumes from its last chunk;
5. write the dataset with :func:`sgn_jax.records.trajectory.save_trajectory` and remove
   ``OUT.partial/``.

Sample 0 is the settled state at t = 0. The per-interval dissipation arrays are differences of
the engine's cumulative ledger (first sample 0). Besides the required arrays the file holds
``diss_pp_stiffness`` / ``diss_pw_stiffness`` (the tangential-stiffness ledger term, see
docs/dem.md) and ``n_pp_contacts`` (the regime indicator of docs/conventions.md section 7).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import shutil
import time
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from sgn_jax.config import Config, config_to_dict, replace_section
from sgn_jax.dem import collisions as coll
from sgn_jax.dem.cells import CellGrid, cell_grid_for
from sgn_jax.dem.charge import pair_params
from sgn_jax.dem.contact import MIN_CONTACT_STEPS
from sgn_jax.dem.engine import (
    DISSIPATION_KINDS,
    DEMError,
    DEMParams,
    DEMSpec,
    DEMState,
    init_state,
    make_sampler,
    observe,
    reset_ledger_totals,
)
from sgn_jax.dem.placement import PLACEMENT_GAP, place_balls
from sgn_jax.motion import offset
from sgn_jax.pipelines.configure import (
    contact_law_from_config,
    geometry_from_config,
    params_from_config,
)
from sgn_jax.pipelines.validation import check_dem_config, check_duration, with_charge_step
from sgn_jax.records.cache import settled_dir
from sgn_jax.records.io_utils import atomic_write
from sgn_jax.records.trajectory import DatasetError, build_meta, save_trajectory
from sgn_jax.scene import JarGeometry

PARTIAL_FORMAT = 1


class DEMRunError(DEMError):
    """A run that stopped because its state became invalid (a ball left the jar, a non-finite
    value, a contact the time step cannot resolve).

    Attributes:
        time_s: time of motion (s) of the first invalid sample (negative while settling).
        ball: index of the ball it concerns.
        cause: ``"outside"``, ``"non-finite"`` or ``"unresolved-contact"``.
        valid: :class:`DEMRun` of the samples before it (None if there were none), also
            written to ``valid_path`` when the run had an output file.
        valid_path: where the valid part was written, or None.
    """

    def __init__(self, message: str, *, time_s: float, ball: int, cause: str,
                 valid: Any = None, valid_path: Path | None = None) -> None:
        super().__init__(message)
        self.time_s, self.ball, self.cause = time_s, ball, cause
        self.valid, self.valid_path = valid, valid_path


@dataclasses.dataclass(frozen=True)
class DEMSetup:
    """Everything a run of a config needs, built once by :func:`setup_from_config`."""

    cfg: Any
    spec: DEMSpec
    params: DEMParams
    jar: JarGeometry
    substeps: int
    pp_capacity: int

    @property
    def dt(self) -> float:
        return float(self.cfg.dem.dt)

    @property
    def dt_dem(self) -> float:
        return self.spec.dt_dem


def setup_from_config(cfg: Any, dt_dem: float | None = None, dtype: str | None = None,
                      pair_mode: str = "auto") -> DEMSetup:
    """Build spec, params and jar of a config.

    The step used is dt / k with the smallest integer k such that dt / k is at most the bound,
    so every sample falls on a step (docs/conventions.md section 2). The bound is ``[dem]
    dt_dem_max``, lowered for a charge of small or light balls to the step that resolves its
    shortest contact as finely as the standard case's
    (:func:`sgn_jax.pipelines.validation.with_charge_step`); ``dt_dem`` (optional) replaces
    both (a step chosen on purpose, e.g. a dt against dt/2 study).
    """
    if dt_dem is not None:
        if not dt_dem > 0:
            raise DEMError(f"dt_dem must be > 0, got {dt_dem}")
        cfg = replace_section(cfg, "dem", dt_dem_max=float(dt_dem))
    else:
        cfg = with_charge_step(cfg)
    if dtype is not None:
        cfg = replace_section(cfg, "dem", dtype=dtype)
    jar = geometry_from_config(cfg)
    params = params_from_config(cfg, geometry=jar.geometry)
    n = cfg.balls.n_balls
    grid = (cell_grid_of(cfg, jar)
            if pair_mode in ("auto", "neighbour") and uses_cell_list(cfg) else None)
    spec = DEMSpec(n_balls=n, n_patches=len(jar.patch_names), dt_dem=cfg.dem.dt_dem,
                   dtype=cfg.dem.dtype, clip_attractive=cfg.dem.clip_attractive,
                   pair_mode=pair_mode, neighbour_capacity=cfg.dem.neighbour_capacity,
                   neighbour_skin=cfg.dem.neighbour_skin,
                   contact_law=contact_law_from_config(cfg),
                   collision_capacity=collision_capacity(cfg) if pair_mode != "nxn" else 0,
                   cell_grid=grid, cell_lower=tuple(np.asarray(jar.lower, float)))
    capacity = cfg.dem.pp_capacity if cfg.dem.pp_capacity > 0 else 3 * n
    return DEMSetup(cfg=cfg, spec=spec, params=params, jar=jar, substeps=cfg.dem.substeps,
                    pp_capacity=capacity)


CELL_LIST_FROM_BALLS = 500
"""``[dem] neighbour_search = "auto"`` rebuilds the Verlet list from a cell list from this many
balls on: below it testing all pairs is faster on a CPU core (docs/benchmarks.md, "Neighbour
search"), above it the cell list (6.4x at 1,000 balls)."""


def uses_cell_list(cfg: Any) -> bool:
    """Whether the DEM of ``cfg`` rebuilds its Verlet list from a cell list."""
    search = cfg.dem.neighbour_search
    return search == "cells" or (search == "auto" and cfg.balls.n_balls >= CELL_LIST_FROM_BALLS)


def cell_grid_of(cfg: Any, jar: JarGeometry) -> CellGrid:
    """The cell grid of a config's charge over its jar's cavity box (jar frame): cells as wide
    as the largest pair cutoff, capacity from the densest packing of the smallest balls."""
    radii = [c.radius for c in cfg.balls.classes]
    return cell_grid_for(jar.lower, jar.upper, 2 * max(radii) + cfg.dem.neighbour_skin,
                         min(radii), cfg.balls.n_balls)


COLLISION_RATE_BOUND = 1000.0
"""Events per ball per second the collision buffer is sized for when ``[dem]
collision_capacity`` is 0 (the standard case closes ~280 per ball per second, most of them
brief touches in the bed)."""


def collision_capacity(cfg: Any) -> int:
    """Events the DEM's collision buffer holds per chunk: ``[dem] collision_capacity``, or when
    that is 0 sized from the chunk's duration (:data:`COLLISION_RATE_BOUND`, at least 4,096);
    0 when ``[dem] collisions`` is false."""
    if not cfg.dem.collisions:
        return 0
    if cfg.dem.collision_capacity:
        return int(cfg.dem.collision_capacity)
    chunk_s = cfg.dem.chunk_samples * cfg.dem.dt
    return max(4096, math.ceil(COLLISION_RATE_BOUND * cfg.balls.n_balls * chunk_s))


def collision_table(setup: DEMSetup, ints: np.ndarray, floats: np.ndarray) -> dict[str, np.ndarray]:
    """The record's ``collision_*`` arrays (docs/collisions.md) from ledger rows (E, N_INTS),
    (E, N_FLOATS) (:mod:`sgn_jax.dem.collisions`); steps become seconds of motion (a contact
    that began before t = 0 gets a negative start and the began-before flag)."""
    dt_dem = setup.dt_dem
    wall = ints[:, coll.WALL].astype(bool)
    start = ints[:, coll.START_STEP]
    flags = ints[:, coll.FLAGS] | np.where(start < 0, coll.FLAG_BEGAN_BEFORE, 0)
    mass_eff = event_mass_eff(setup.params, ints[:, coll.BALL], ints[:, coll.PARTNER], wall)
    columns = {
        "ball": ints[:, coll.BALL], "partner": ints[:, coll.PARTNER], "wall": wall,
        "start_s": start * dt_dem, "duration_s": (ints[:, coll.END_STEP] - start) * dt_dem,
        "impact_normal": floats[:, coll.IMPACT_NORMAL],
        "impact_tangential": np.sqrt(np.maximum(floats[:, coll.IMPACT_TANGENTIAL_SQ], 0.0)),
        "max_overlap": floats[:, coll.MAX_OVERLAP], "peak_force": floats[:, coll.PEAK_FORCE],
        "mass_eff": mass_eff, "energy": floats[:, coll.ENERGY0:], "flags": flags,
    }
    return {coll.COLLISION_PREFIX + key: np.array(columns[key], dtype=dtype)
            for key, (dtype, _) in coll.COLLISION_FIELDS.items()}


def event_mass_eff(params: Any, ball: np.ndarray, partner: np.ndarray, wall: np.ndarray
                   ) -> np.ndarray:
    """(E,) kg, the effective mass m* of each event's contact: the pair's (ball-ball) or the
    ball's (ball-wall, where ``partner`` is a wall patch)."""
    pp_m = np.asarray(params.pp.mass_eff, np.float64)
    pw_m = np.asarray(params.pw.mass_eff, np.float64)
    if not params.polydisperse:
        return np.where(wall, float(pw_m), float(pp_m))
    cls = np.asarray(params.ball_class)
    partner_cls = cls[np.where(wall, 0, partner)]
    return np.where(wall, pw_m[cls[ball]], pp_m[cls[ball], partner_cls])


COLLISION_ARRAYS = tuple(coll.COLLISION_PREFIX + name for name in coll.COLLISION_FIELDS)
"""The names of the collision table's arrays in a trajectory record."""


# The jar's offset as one program (op by op its formulas are ~10 small compilations).
_offset_jit = jax.jit(offset)


def initial_state(setup: DEMSetup, seed: int, gap: float = PLACEMENT_GAP) -> DEMState:
    """Balls placed at rest from ``seed``, at DEM step -settle_steps (jar at rest)."""
    jar = setup.jar
    x_jar = place_balls(lambda x: jar.sdf_fn(jar.geometry, x), jar.lower, jar.upper,
                        setup.spec.n_balls, np.asarray(setup.params.radius, np.float64), seed,
                        gap=gap)
    x_lab = x_jar + np.asarray(_offset_jit(setup.params.motion, 0.0))
    settle_samples = settle_sample_count(setup)
    return init_state(setup.spec, setup.params, x_lab, step=-settle_samples * setup.substeps)


def kick_balls(state: DEMState, kick_speed: float, seed: int) -> DEMState:
    """``state`` with every ball given a random velocity (``[dem] kick_speed``): direction
    uniform on the sphere, magnitude uniform in [0, kick_speed] m/s, from ``seed`` (numpy);
    spins unchanged. ``kick_speed`` 0 returns ``state`` itself."""
    if not kick_speed:
        return state
    rng = np.random.default_rng([int(seed), 0x6B1C])
    n = state.vel.shape[0]
    direction = rng.normal(size=(n, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    speed = rng.uniform(0.0, kick_speed, size=(n, 1))
    vel = jnp.asarray(np.asarray(state.vel) + speed * direction, state.vel.dtype)
    return state.replace(vel=vel)


def settle_sample_count(setup: DEMSetup) -> int:
    return int(round(setup.cfg.dem.settle_time / setup.dt))


# --------------------------------------------------------------------------------------------
# Checkpoints


def _tree_to_npz(tree: Any) -> dict[str, np.ndarray]:
    leaves, _ = jax.tree_util.tree_flatten_with_path(tree)
    out = {f"leaf_{k:03d}": np.asarray(v) for k, (_, v) in enumerate(leaves)}
    out["leaf_names"] = np.array(json.dumps([jax.tree_util.keystr(p) for p, _ in leaves]))
    return out


def _tree_from_npz(template: Any, data: Any, where: str) -> Any:
    leaves, treedef = jax.tree_util.tree_flatten_with_path(template)
    names = json.loads(str(data["leaf_names"]))
    if names != [jax.tree_util.keystr(p) for p, _ in leaves]:
        raise DEMError(f"{where}: the saved state does not match this version's DEMState; "
                       "delete the .partial directory to start over")
    new = []
    for k, (_, ref) in enumerate(leaves):
        value = np.asarray(data[f"leaf_{k:03d}"])
        if value.shape != np.shape(ref):
            raise DEMError(f"{where}: saved state leaf {names[k]} has shape {value.shape}, "
                           f"expected {np.shape(ref)}; delete the .partial directory")
        new.append(jnp.asarray(value, dtype=jnp.asarray(ref).dtype))
    return jax.tree_util.tree_unflatten(treedef, new)


def _fingerprint(setup: DEMSetup, seed: int) -> str:
    cfg = config_to_dict(setup.cfg)
    cfg["dem"].pop("duration", None)
    cfg["dem"].pop("chunk_samples", None)
    if cfg["dem"].get("contact_law") == "hertz_mindlin":
        cfg["dem"].pop("contact_law")  # the default: partial runs of older versions resume
    if not cfg["dem"].get("kick_speed"):
        cfg["dem"].pop("kick_speed", None)  # likewise
    return json.dumps({"config": cfg, "seed": seed, "dt_dem": setup.dt_dem,
                       "pp_capacity": setup.pp_capacity, "format": PARTIAL_FORMAT},
                      sort_keys=True)


def partial_dir(out_path: str | Path) -> Path:
    out_path = Path(out_path)
    return out_path.with_name(out_path.name + ".partial")


def _save_npz(path: Path, arrays: dict[str, Any]) -> None:
    with atomic_write(path, "wb") as fh:
        np.savez(fh, **arrays)


# --------------------------------------------------------------------------------------------
# Settled packings, cached across runs and processes

_DEM_DIR = Path(__file__).resolve().parent.parent / "dem"
_DEM_SOURCES = (_DEM_DIR / "engine.py", _DEM_DIR / "contact.py", _DEM_DIR / "laws.py",
                _DEM_DIR / "charge.py",
                _DEM_DIR / "placement.py", _DEM_DIR / "walls.py", _DEM_DIR / "collisions.py",
                Path(__file__).resolve())


def _dem_source_digest() -> str:
    """SHA-256 of the DEM's source files: a cached state is reused only by the same code."""
    h = hashlib.sha256()
    for name in _DEM_SOURCES:  # a Path each
        h.update(name.read_bytes())
    return h.hexdigest()


def settle_key(setup: DEMSetup, seed: int) -> str:
    """Digest of what a settled state depends on, bit for bit: jar, balls, material, DEM
    settings (not the duration or chunking), seed, the DEM's code, and where the jar rests,
    ``offset(0)``. The rest of the motion (rpm, frequency) does not enter settling, so circles of
    one amplitude and phase share their packings. A packing settled at another rest position
    is the same packing translated physically, but not bit for bit (settling is chaotic and
    its rounding depends on the absolute positions): it gets its own entry."""
    cfg = config_to_dict(setup.cfg)
    dem = {k: v for k, v in cfg["dem"].items()
           if k not in ("duration", "chunk_samples", "seed", "kick_speed")}  # not in settling
    rest = [float(v).hex() for v in np.asarray(_offset_jit(setup.params.motion, 0.0))]
    key = {"jar": cfg["jar"], "balls": cfg["balls"], "material": cfg["material"], "dem": dem,
           "materials": cfg["materials"], "interactions": cfg["interactions"],
           "seed": int(seed), "dt_dem": setup.dt_dem, "pp_capacity": setup.pp_capacity,
           "collision_capacity": setup.spec.collision_capacity,
           "pair_mode": setup.spec.resolved_pair_mode, "format": PARTIAL_FORMAT,
           "code": _dem_source_digest(), "rest_offset": rest}
    return hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:32]


def load_settled(setup: DEMSetup, seed: int) -> DEMState | None:
    """The cached settled state at t = 0 of this jar, balls, DEM and rest position, or None."""
    directory = settled_dir()
    if directory is None:
        return None
    path = directory / f"{settle_key(setup, seed)}.npz"
    if not path.is_file():
        return None
    template = init_state(setup.spec, setup.params, np.zeros((setup.spec.n_balls, 3)))
    try:
        with np.load(path) as data:
            state = _tree_from_npz(template, data, str(path))
    except (OSError, ValueError, KeyError, DEMError):
        return None  # a damaged or stale entry is settled again (and overwritten)
    return state


def save_settled(setup: DEMSetup, seed: int, state: DEMState) -> Path | None:
    """Store a settled state (atomically); None when the cache is off or not writable."""
    directory = settled_dir()
    if directory is None:
        return None
    path = directory / f"{settle_key(setup, seed)}.npz"
    try:
        directory.mkdir(parents=True, exist_ok=True)
        _save_npz(path, _tree_to_npz(jax.device_get(state)))
    except OSError:
        return None
    return path


# --------------------------------------------------------------------------------------------
# Run


class DEMRun(NamedTuple):
    """Result of :func:`run_dem`: the dataset arrays, its meta and a summary dict."""

    arrays: dict[str, np.ndarray]
    meta: dict[str, Any]
    summary: dict[str, Any]


def _progress(total: float, desc: str, enabled: bool) -> Any:
    from tqdm import tqdm

    return tqdm(total=round(total, 6), desc=desc, unit="s", disable=not enabled,
                bar_format="{l_bar}{bar}| {n:.3f}/{total:.3f} s sim [{elapsed}<{remaining}, "
                "{postfix}]", dynamic_ncols=True)


def run_dem(
    cfg: Any,
    duration: float | None = None,
    out_path: str | Path | None = None,
    seed: int | None = None,
    dt_dem: float | None = None,
    resume: bool = True,
    progress: bool = True,
    chunk_samples: int | None = None,
    dtype: str | None = None,
    check: bool = True,
    settle_cache: bool = True,
) -> DEMRun:
    """Settle and run the DEM of ``cfg``; write the trajectory record to ``out_path`` if given.

    Args:
        cfg: a ``sgn_jax.config.Config``.
        duration: seconds of motion (default ``cfg.dem.duration``); T = duration / dt + 1.
        out_path: ``.npz`` destination; checkpoints go to ``out_path + '.partial/'``.
        seed: placement seed (default ``cfg.dem.seed``).
        dt_dem: override ``[dem] dt_dem_max`` (see :func:`setup_from_config`).
        resume: continue from ``OUT.partial/`` if it exists and matches this run.
        progress: show tqdm bars (simulated time, rate, ETA).
        chunk_samples: samples per jitted chunk (default ``cfg.dem.chunk_samples``).
        dtype: override ``[dem] dtype``.
        check: refuse a config the DEM cannot represent before any work
            (:func:`sgn_jax.pipelines.validation.check_dem_config`; an envelope warning otherwise).
        settle_cache: reuse (and store) the settled packing of this jar, balls, material, DEM
            settings, seed and rest position in the user cache (:mod:`sgn_jax.records.cache`;
            off with ``SGN_JAX_NO_CACHE=1``); a cached run is bit-identical to a fresh one.

    Raises:
        DEMRunError: a ball left the jar, a value went non-finite, or a contact became too fast
            for the time step; it names the time, the ball and the cause, and keeps the valid
            samples before it (written to ``OUT.valid_part.npz`` when ``out_path`` is given).
    """
    seed = cfg.dem.seed if seed is None else int(seed)
    duration = cfg.dem.duration if duration is None else float(duration)
    check_duration(duration, "duration", dt=cfg.dem.dt)
    if check:
        check_dem_config(cfg if dt_dem is None
                         else replace_section(cfg, "dem", dt_dem_max=float(dt_dem)),
                         step_given=dt_dem is not None)
    chunk = int(chunk_samples or cfg.dem.chunk_samples)
    if chunk < 1:
        raise DEMError(f"chunk_samples must be >= 1, got {chunk}")
    if out_path is not None and Path(out_path).suffix != ".npz":
        raise DatasetError(f"output path {str(out_path)!r} must end in '.npz'")
    if chunk != cfg.dem.chunk_samples:  # the collision buffer is sized per chunk
        cfg = replace_section(cfg, "dem", chunk_samples=chunk)
    setup = setup_from_config(cfg, dt_dem=dt_dem, dtype=dtype)
    spec, params, k = setup.spec, setup.params, setup.substeps
    n_motion = int(round(duration / setup.dt))
    n_settle = settle_sample_count(setup)
    t_wall0 = time.perf_counter()

    run = make_sampler(spec, setup.jar.wall_fn, k, setup.pp_capacity)
    compiled: dict[int, Any] = {}
    compile_time = 0.0

    def ensure_compiled(state: DEMState, n: int) -> None:
        nonlocal compile_time
        if n not in compiled:
            t0 = time.perf_counter()
            compiled[n] = run.lower(params, state, n).compile()
            compile_time += time.perf_counter() - t0

    def run_chunk(state: DEMState, n: int) -> tuple[DEMState, dict[str, np.ndarray]]:
        ensure_compiled(state, n)
        state, samples = compiled[n](params, state)
        return state, jax.tree_util.tree_map(np.asarray, samples)

    def drain_events(state: DEMState, t_end: float) -> tuple[DEMState, dict[str, np.ndarray]]:
        """The events the chunk closed (as ``events_ints`` / ``events_floats`` rows) and the
        state with an empty buffer; an overflowed buffer stops the run."""
        if state.collisions is None:
            return state, {}
        count = int(state.collisions.buffer.count)
        if count > spec.collision_capacity:
            raise DEMError(
                f"{count} contacts closed in the chunk ending at t = {t_end:g} s, more than the "
                f"collision ledger's {spec.collision_capacity} slots: raise [dem] "
                "collision_capacity (or lower [dem] chunk_samples) and rerun")
        ints, floats = coll.buffer_rows(state.collisions)
        state = state.replace(collisions=coll.empty_buffer(state.collisions))
        return state, {"events_ints": ints, "events_floats": floats}

    observe_jit = jax.jit(lambda p, s: observe(spec, setup.jar.wall_fn, p, s, setup.pp_capacity))
    jar = setup.jar
    sdf = jax.jit(jax.vmap(jax.vmap(lambda x: jar.sdf_fn(jar.geometry, x))))

    pdir = partial_dir(out_path) if out_path is not None else None
    fingerprint = _fingerprint(setup, seed)
    chunks: list[dict[str, np.ndarray]] = []
    event_chunks: list[dict[str, np.ndarray]] = []  # the collision events closed in each chunk
    state = None
    done = 0  # motion samples done after sample 0
    if pdir is not None and pdir.is_dir():
        state_file = pdir / "state.npz"
        ok = resume and state_file.is_file()
        if ok:
            with np.load(state_file) as data:
                ok = str(data["fingerprint"]) == fingerprint
                if ok:
                    template = init_state(spec, params, np.zeros((spec.n_balls, 3)))
                    state = _tree_from_npz(template, data, str(state_file))
                    n_chunks = int(data["n_chunks"])
                    done = int(data["samples_done"])
        if ok:
            for c in range(n_chunks):
                with np.load(pdir / f"chunk_{c:05d}.npz") as data:
                    chunks.append({name: data[name] for name in data.files
                                   if not name.startswith("events_")})
                    event_chunks.append({name: data[name] for name in data.files
                                         if name.startswith("events_")})
            if done > n_motion:
                raise DEMError(f"{pdir} holds {done * setup.dt:g} s of motion, more than the "
                               f"requested {duration:g} s; delete it or ask for more")
        else:
            shutil.rmtree(pdir)
            state = None

    def checkpoint(state: DEMState) -> None:
        if pdir is None:
            return
        pdir.mkdir(parents=True, exist_ok=True)
        _save_npz(pdir / f"chunk_{len(chunks) - 1:05d}.npz",
                  {**chunks[-1], **event_chunks[-1]})
        _save_npz(pdir / "state.npz", {**_tree_to_npz(state), "fingerprint": np.array(fingerprint),
                                       "n_chunks": np.array(len(chunks)),
                                       "samples_done": np.array(done)})

    steps_run = 0
    settle_wall = 0.0
    settle_cached = False
    if state is None and settle_cache:
        state = load_settled(setup, seed)
        settle_cached = state is not None
        if settle_cached:
            state = reset_ledger_totals(kick_balls(state, cfg.dem.kick_speed, seed))
            chunks.append(jax.tree_util.tree_map(lambda a: np.asarray(a)[None],
                                                 observe_jit(params, state)))
            event_chunks.append({})
            checkpoint(state)
    if state is None:
        state = initial_state(setup, seed)
        bar = _progress(n_settle * setup.dt, "settling", progress)
        t0 = time.perf_counter()
        left = n_settle
        while left > 0:
            n = min(chunk, left)
            state, samples = run_chunk(state, n)
            if state.collisions is not None:  # settling is not recorded: drop its events
                state = state.replace(collisions=coll.empty_buffer(state.collisions))
            bad = check_samples(setup, samples, sdf)
            if bad:
                first = -(left - 1)  # sample index (negative: before t = 0) of the chunk's first
                raise _stop_invalid(setup, [], samples, bad, first, None, seed)
            left -= n
            steps_run += n * k
            bar.update(round(n * setup.dt, 6))
        bar.close()
        settle_wall = time.perf_counter() - t0
        if int(state.step) != 0:
            raise DEMError(f"internal: settling ended at step {int(state.step)}, not 0")
        if settle_cache:
            save_settled(setup, seed, state)
        state = reset_ledger_totals(kick_balls(state, cfg.dem.kick_speed, seed))
        chunks.append(jax.tree_util.tree_map(lambda a: np.asarray(a)[None],
                                             observe_jit(params, state)))
        event_chunks.append({})
        checkpoint(state)

    bar = _progress(n_motion * setup.dt, "DEM", progress)
    bar.update(round(done * setup.dt, 6))
    motion_steps = 0
    motion_wall = 0.0
    while done < n_motion:
        n = min(chunk, n_motion - done)
        ensure_compiled(state, n)
        t0 = time.perf_counter()
        state, samples = run_chunk(state, n)
        if np.any(samples["pp_overflow"]):
            first = int(np.argmax(samples["pp_overflow"]))
            t_bad = (done + first + 1) * setup.dt
            if (bool(state.pairs.overflow) and spec.cell_grid is not None
                    and int(state.pairs.max_candidates) <= spec.n_pair_slots):
                raise DEMError(
                    f"a cell of the DEM's cell list held more than "
                    f"{spec.cell_grid.cell_capacity} balls by t = {t_bad:g} s (balls far "
                    "outside the jar crowd its edge cells, or overlaps far deeper than the "
                    "grid allows); check the run, or use [dem] neighbour_search = 'all_pairs'")
            if bool(state.pairs.overflow):
                raise DEMError(
                    f"the DEM's Verlet list overflowed (more than {spec.n_pair_slots} pairs "
                    f"within the {spec.neighbour_skin:g} m skin) by t = {t_bad:g} s: raise "
                    "[dem] neighbour_capacity (pairs per ball) and rerun")
            raise DEMError(
                f"{int(samples['n_pp_contacts'][first])} ball-ball contacts at t = {t_bad:g} s, "
                f"more than the {setup.pp_capacity} slots of pp_pairs: raise [dem] pp_capacity "
                "and rerun")
        chunk_wall = time.perf_counter() - t0
        bad = check_samples(setup, samples, sdf)
        if bad:
            bar.close()
            raise _stop_invalid(setup, chunks, samples, bad, done + 1, out_path, seed)
        state, events = drain_events(state, (done + n) * setup.dt)
        motion_wall += chunk_wall
        chunks.append(samples)
        event_chunks.append(events)
        done += n
        steps_run += n * k
        motion_steps += n * k
        checkpoint(state)
        bar.set_postfix_str(f"{n * k / chunk_wall:,.0f} steps/s")
        bar.update(round(n * setup.dt, 6))
    bar.close()

    arrays = assemble_arrays(setup, chunks)
    if state.collisions is not None:
        rows = [(e["events_ints"], e["events_floats"]) for e in event_chunks if e]
        rows.append(coll.open_rows(state.collisions, state.pairs.i, state.pairs.j,
                                   int(state.step)))
        arrays.update(collision_table(setup, np.concatenate([r[0] for r in rows]),
                                      np.concatenate([r[1] for r in rows])))
    summary = summarize(setup, arrays)
    summary.update({
        "seed": seed, "duration_s": n_motion * setup.dt, "dt_dem": setup.dt_dem,
        "substeps": k, "wall_time_s": time.perf_counter() - t_wall0,
        "compile_time_s": compile_time, "settle_wall_s": settle_wall,
        "settle_cached": settle_cached,
        "motion_wall_s": motion_wall, "dem_steps": steps_run,
        "steps_per_s": motion_steps / motion_wall if motion_wall > 0 and motion_steps else None,
        "pair_mode": spec.resolved_pair_mode, "dtype": spec.dtype,
    })
    meta = build_meta(setup.cfg, seed=seed, extra={
        "dt_dem": setup.dt_dem, "substeps": k, "settle_time": n_settle * setup.dt,
        "pp_capacity": setup.pp_capacity, "pair_mode": spec.resolved_pair_mode,
        "dtype": spec.dtype, "ledger_residual_J": summary["ledger_residual_J"],
        "extra_arrays": ["diss_pp_stiffness", "diss_pw_stiffness", "n_pp_contacts",
                         *(name for name in COLLISION_ARRAYS if name in arrays)],
    })
    if out_path is not None:
        save_trajectory(out_path, arrays, meta)
        if pdir is not None and pdir.is_dir():
            shutil.rmtree(pdir)
        summary["out"] = str(out_path)
    return DEMRun(arrays=arrays, meta=meta, summary=summary)


def _first(mask: np.ndarray) -> tuple[int, int] | None:
    """(sample, ball) of the first True in a (S, N) mask, or None."""
    rows = np.flatnonzero(np.any(mask, axis=1))
    if rows.size == 0:
        return None
    return int(rows[0]), int(np.argmax(mask[rows[0]]))


def check_samples(setup: DEMSetup, samples: dict[str, np.ndarray], sdf: Any
                  ) -> tuple[int, int, str, str] | None:
    """The first invalid sample of a chunk: ``(sample, ball, cause, detail)`` or None.

    Causes, in the order checked per sample: a non-finite position or velocity; a ball whose
    centre is outside the cavity (phi > 0 in the jar frame); a contact that the DEM step cannot
    resolve: the contact law's duration (Hertz by default) at the largest relative speed (any
    ball pair, or any ball against the wall) below :data:`MIN_CONTACT_STEPS` steps.
    """
    pos, vel = samples["pos"], samples["vel"]
    found: list[tuple[int, int, str, str]] = []
    bad = ~(np.all(np.isfinite(pos), axis=-1) & np.all(np.isfinite(vel), axis=-1))
    hit = _first(bad)
    if hit:
        found.append((*hit, "non-finite", "its position or velocity is not finite"))
    ok_rows = ~np.any(bad, axis=1)
    x_jar = np.where(ok_rows[:, None, None], pos - samples["offset"][:, None, :], 0.0)
    phi = np.asarray(sdf(jnp.asarray(x_jar)))
    hit = _first(phi > 0)
    if hit:
        found.append((*hit, "outside", f"its centre is {phi[hit] * 1e3:.3g} mm outside the jar "
                      "wall"))
    v = np.where(ok_rows[:, None, None], vel, 0.0)
    v_wall = np.linalg.norm(v - samples["offset_vel"][:, None, :], axis=-1)      # (S, N)
    law = setup.spec.contact_law
    # t_c(v) < k dt_dem  <=>  v > v_limit (Hertz: t_c decreases as v^(-1/5)); with several
    # ball classes each contact kind has its own limit.
    limit_wall, limit_pair = resolved_speed_limits(setup)
    # Per ball: the partner whose relative speed most exceeds its limit, in blocks of samples
    # ((S, N, N, 3) at once is a gigabyte for 200 balls).
    excess, partner, v_pair = (np.empty(v_wall.shape), np.empty(v_wall.shape, int),
                               np.empty(v_wall.shape))
    for a in range(0, v.shape[0], 64):
        block = v[a:a + 64]
        speeds = np.linalg.norm(block[:, :, None, :] - block[:, None, :, :], axis=-1)
        over = speeds - limit_pair
        partner[a:a + 64] = np.argmax(over, axis=2)
        excess[a:a + 64] = np.take_along_axis(over, partner[a:a + 64, :, None], 2)[..., 0]
        v_pair[a:a + 64] = np.take_along_axis(speeds, partner[a:a + 64, :, None], 2)[..., 0]
    laws = {"ball-wall": (v_wall, limit_wall, None), "ball-ball": (v_pair, excess, partner)}
    for name, (speed, limit, partner_of) in laws.items():
        over = (speed > limit) if partner_of is None else (limit > 0)
        hit = _first(over)
        if hit:
            other = None if partner_of is None else int(partner_of[hit])
            law_params = contact_kind_params(setup.params, hit[1], other)
            t_c = float(law.contact_time(law_params, float(speed[hit])))
            found.append((*hit, "unresolved-contact",
                          f"a {name} relative speed of {speed[hit]:.4g} m/s, where a "
                          f"{law.title} contact lasts {t_c / setup.dt_dem:.1f} DEM steps (need >= "
                          f"{MIN_CONTACT_STEPS}): reduce [dem] dt_dem_max or the motion"))
    return min(found) if found else None


def _stop_invalid(setup: DEMSetup, chunks: list[dict[str, np.ndarray]], samples: dict,
                  bad: tuple[int, int, str, str], first_sample: int, out_path: Any,
                  seed: int) -> DEMRunError:
    """The error for an invalid sample; keeps (and writes) the valid samples before it."""
    index, ball, cause, detail = bad
    t_bad = (first_sample + index) * setup.dt
    head = {k: v[:index] for k, v in samples.items()}
    kept = [*chunks, head] if index > 0 else list(chunks)
    if t_bad < 0:
        kept = []  # stopped while settling: there is no motion to keep
    valid, valid_path = None, None
    if kept:
        arrays = assemble_arrays(setup, kept)
        meta = build_meta(setup.cfg, seed=seed, extra={
            "dt_dem": setup.dt_dem, "substeps": setup.substeps,
            "stopped": {"time_s": t_bad, "ball": ball, "cause": cause}})
        valid = DEMRun(arrays=arrays, meta=meta, summary={})
        if out_path is not None and arrays["t"].size >= 2:
            valid_path = Path(out_path).with_name(Path(out_path).stem + ".valid_part.npz")
            save_trajectory(valid_path, arrays, meta)
    where = f"while settling (t = {t_bad:.4g} s)" if t_bad < 0 else f"at t = {t_bad:.6g} s"
    kept_text = (f"; the {t_bad:.4g} s before it are in {valid_path}" if valid_path else "")
    return DEMRunError(f"the DEM run stopped {where}: ball {ball}: {detail} [{cause}]{kept_text}",
                       time_s=t_bad, ball=ball, cause=cause, valid=valid, valid_path=valid_path)


def contact_kind_params(params: Any, ball: int, partner: int | None) -> Any:
    """The scalar contact-law parameters of ball ``ball`` against ball ``partner`` (None: the
    wall)."""
    if not params.polydisperse:
        return params.pw if partner is None else params.pp
    cls = np.asarray(params.ball_class)
    return pair_params(params.pw if partner is None else params.pp, int(cls[ball]),
                       None if partner is None else int(cls[partner]))


def resolved_speed_limits(setup: DEMSetup) -> tuple[np.ndarray, np.ndarray]:
    """The largest relative speeds (m/s) whose contacts last at least
    :data:`MIN_CONTACT_STEPS` DEM steps: per ball against the wall (N,) and per ball pair
    (N, N) (the diagonal inf)."""
    law, params, n = setup.spec.contact_law, setup.params, setup.spec.n_balls
    span = MIN_CONTACT_STEPS * setup.dt_dem
    if params.polydisperse:
        cls = np.asarray(params.ball_class)
        n_cls = int(cls.max()) + 1
        wall = np.array([law.max_speed_for_duration(pair_params(params.pw, a), span)
                         for a in range(n_cls)])[cls]
        table = np.array([[law.max_speed_for_duration(pair_params(params.pp, a, b), span)
                           for b in range(n_cls)] for a in range(n_cls)])
        pair = table[cls[:, None], cls[None, :]]
    else:
        wall = np.full(n, law.max_speed_for_duration(params.pw, span))
        pair = np.full((n, n), law.max_speed_for_duration(params.pp, span))
    np.fill_diagonal(pair, np.inf)
    return wall, pair


def assemble_arrays(setup: DEMSetup, chunks: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """The trajectory record's arrays from the cumulative per-sample observations."""
    cat = {name: np.concatenate([c[name] for c in chunks]) for name in chunks[0]}
    n_samples = cat["pos"].shape[0]
    arrays: dict[str, np.ndarray] = {
        "t": np.arange(n_samples, dtype=np.float64) * setup.dt,
        "pos": cat["pos"], "vel": cat["vel"], "omega": cat["omega"],
        "offset": cat["offset"], "offset_vel": cat["offset_vel"],
    }
    for which in ("pp", "pw"):
        cumulative = cat[f"diss_{which}"]
        interval = np.diff(cumulative, axis=0, prepend=cumulative[:1])
        for kind_index, kind in enumerate(DISSIPATION_KINDS):
            arrays[f"diss_{which}_{kind}"] = interval[:, kind_index]
    for name in ("ke_trans", "ke_rot", "pe_grav", "e_elastic", "work_wall"):
        arrays[name] = cat[name]
    pairs = cat["pp_pairs"]
    small = setup.spec.n_balls < np.iinfo(np.int16).max
    arrays["pp_pairs"] = pairs.astype(np.int16 if small else np.int32)
    arrays["pw_contact"] = cat["pw_contact"].astype(bool)
    arrays["n_pp_contacts"] = cat["n_pp_contacts"].astype(np.int32)
    return arrays


def total_dissipation(arrays: dict[str, np.ndarray]) -> np.ndarray:
    """(T,) cumulative dissipation of all kinds (J), including the stiffness term."""
    parts = [arrays[f"diss_{w}_{k}"] for w in ("pp", "pw") for k in DISSIPATION_KINDS]
    return np.cumsum(np.sum(parts, axis=0))


def summarize(setup: DEMSetup, arrays: dict[str, np.ndarray]) -> dict[str, Any]:
    """Totals by kind, ledger residual, balls outside the jar, contact statistics."""
    diss = {f"{w}_{k}": float(np.sum(arrays[f"diss_{w}_{k}"]))
            for w in ("pp", "pw") for k in DISSIPATION_KINDS}
    total = total_dissipation(arrays)
    balance = (arrays["ke_trans"] + arrays["ke_rot"] + arrays["pe_grav"] + arrays["e_elastic"]
               + total - arrays["work_wall"])
    residual = float(balance[-1] - balance[0])
    jar = setup.jar
    sdf = jax.jit(jax.vmap(lambda x: jar.sdf_fn(jar.geometry, x)))
    x_jar = arrays["pos"] - arrays["offset"][:, None, :]
    phi = np.asarray(sdf(jnp.asarray(x_jar)))
    outside = np.any(phi > 0, axis=0)
    duration = float(arrays["t"][-1]) if arrays["t"].size else 0.0
    target = sum(diss[f"{w}_{k}"] for w in ("pp", "pw") for k in ("normal", "tangential"))
    summary_collisions = collision_closure(arrays) if "collision_energy" in arrays else None
    return {
        "dissipation_J": diss,
        "total_dissipation_J": float(total[-1]),
        "surrogate_target_J": target,
        "mean_dissipation_power_W": float(total[-1]) / duration if duration > 0 else None,
        "work_wall_J": float(arrays["work_wall"][-1]),
        "ledger_residual_J": residual,
        "ledger_residual_rel": residual / float(total[-1]) if total[-1] > 0 else None,
        "balls_outside": int(np.sum(outside)),
        "max_phi_m": float(np.max(phi)),
        "mean_pp_contacts": float(np.mean(arrays["n_pp_contacts"])),
        "mean_pw_contacts": float(np.mean(np.sum(arrays["pw_contact"], axis=1))),
        "collisions": summary_collisions,
    }


def collision_closure(arrays: dict[str, np.ndarray]) -> dict[str, Any]:
    """How the collision events add up against the energy ledger: the event count, and per
    contact type and kind the events' energy, the ledger's, and their difference relative to
    the ledger's total dissipation (J, -)."""
    energy = arrays["collision_energy"]
    wall = arrays["collision_wall"]
    total = float(sum(np.sum(arrays[f"diss_{w}_{k}"]) for w in ("pp", "pw")
                      for k in DISSIPATION_KINDS))
    out: dict[str, Any] = {"events": int(energy.shape[0]),
                           "ball_ball": int(np.sum(~wall)), "ball_wall": int(np.sum(wall))}
    worst = 0.0
    for which, mask in (("pp", ~wall), ("pw", wall)):
        for index, kind in enumerate(DISSIPATION_KINDS):
            events = float(np.sum(energy[mask, index]))
            ledger = float(np.sum(arrays[f"diss_{which}_{kind}"]))
            rel = (events - ledger) / total if total > 0 else 0.0
            out[f"{which}_{kind}"] = {"events_J": events, "ledger_J": ledger, "rel": rel}
            worst = max(worst, abs(rel))
    out["worst_rel"] = worst
    return out


def simulate_dem(cfg: Config, duration: float, *, seed: int = 0, progress: bool = False
                 ) -> dict[str, np.ndarray]:
    """The DEM in memory: settle the balls of ``cfg`` (placement ``seed``) and run ``duration``
    s of its motion; returns the dataset arrays (``pos`` (T, N, 3) m, ``vel``, ``offset``, the
    cumulative dissipation per kind, ...; docs/dem.md). :func:`run_dem` is the same run with its
    metadata and summary, and with ``out_path=`` it writes the dataset file (resumable)."""
    return run_dem(cfg, duration=duration, seed=seed, progress=progress).arrays
