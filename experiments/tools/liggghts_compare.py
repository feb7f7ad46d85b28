"""Our DEM beside LIGGGHTS-PUBLIC 3.8 on one charge, over an ensemble of packings.

For a config (a TOML path; jar kind "emax" without a post, motion kind "circle" or
"harmonic", one ball size) and a list of placement seeds, per seed:

1. our DEM settles the packing and runs DURATION s of motion (``sgn_jax.pipelines.dem_run.
   run_dem``, the same run as ``sgn-jax dem``); its record is kept in OUT/ours_seedS.npz;
2. LIGGGHTS starts from sample 0 of that record (the settled packing at t = 0: positions,
   velocities and spins; contact histories start empty) and runs the same motion for the same
   duration with the same contact law family (``pair_style gran model hertz tangential history
   rolling_friction cdt``), material, step, gravity and jar (``jar_mesh``'s side wall and
   planar floor and lid, :func:`jar_stl_mesh`), the jar moved by ``fix move/mesh viblin``
   terms, one per harmonic and axis (a circle is two: x = A sin, z = A cos);
3. both are measured over the same window [WARMUP, DURATION]:

   - ``wall_power_W``: the mean power the moving wall puts into the balls. Ours: the record's
     ``work_wall`` difference over the window. LIGGGHTS: the per-step ``-F_mesh . v_wall``
     (``fix mesh/surface/stress`` total force on the mesh, ``v_wall`` the analytic jar
     velocity, which is what ``viblin`` sets), averaged per sample interval by
     ``fix ave/time`` and then over the window;
   - ``dissipation_W``: ``(wall work - change of KE_trans + KE_rot + PE_grav) / window``, the
     same formula for both codes from the ball states at the window's ends (the elastic energy
     in the contacts, at most ~4e-4 J, is left out of both); in steady state it is the dissipated
     power. Ours also has the ledger's exact dissipation, ``ledger_W`` (the sum of all kinds
     over the window);
   - ``speed_m_s``: mean ball speed in the jar frame, |v - v_jar|, over balls and the states
     every DUMP_EVERY samples in the window;
   - ``pp_contacts``: mean number of ball-ball contacts at those states (ours: the record's
     ``n_pp_contacts``; LIGGGHTS: half the sum of ``compute contact/atom``).

Ensemble statistics: mean and standard error (std with ddof 1 / sqrt(n)) over the seeds; the
difference LIGGGHTS - ours in units of sqrt(SE_l^2 + SE_o^2) and in % of ours. Written to
OUT/NAME.json and OUT/NAME.md. Both codes' CPU times (user + sys) are recorded per seed.

    nice -n 10 taskset -c 1 python experiments/tools/liggghts_compare.py \\
        --config sgn_jax/configs/emax_300rpm.toml --seeds 0 1 2 --duration 1.0 --warmup 0.5 \\
        --out runs/liggghts/standard --name standard

Resumable: a seed whose record (ours) or LIGGGHTS output (OUT/lig_seedS/) is complete is not
run again. Needs the ``liggghts`` binary (Debian package ``liggghts``, LIGGGHTS-PUBLIC 3.8.0).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np

import sgn_jax.api as sj
from sgn_jax.experiment_tools import (
    CircleMotion,
    HarmonicMotion,
    dem_setup_from_config,
    jar_mesh,
    motion_offset,
)

# Degrees: faces meeting at less than this count as one surface for LIGGGHTS (contacts with
# two such neighbours are not double-counted, histories move across them). The side facets
# of a 256-segment jar meet at 1.4 deg; the floor/side and lid/side edges (90 deg) stay edges.
CURVATURE_DEG = 2.0
DUMP_EVERY = 10  # samples between LIGGGHTS state dumps (and ours: the same states)


# --------------------------------------------------------------------------------------------
# Jar STL


def jar_stl_mesh(jar_cfg, segments: int = 256, cap_margin: float = 0.005):
    """The jar for LIGGGHTS: ``jar_mesh``'s side wall and two planar caps (m, jar frame).

    The side wall is ``jar_mesh``'s own triangles (one quad per outline edge, vertices on the
    arcs). Floor and lid are each one rectangle (two triangles) that covers the outline with
    ``cap_margin`` to spare: balls never reach beyond the side wall, and LIGGGHTS does not need
    a closed mesh. ``jar_mesh``'s caps (manifold3d's triangulation of the outline) have slivers
    with angles down to 0.01 deg, below LIGGGHTS' hard limit of 0.018 deg, and fans of 258
    triangles made the mesh twice as slow to move and to search as these caps.
    """
    import trimesh

    params = sj.jar_params_from_config(jar_cfg)
    if params.has_post:
        raise SystemExit("liggghts_compare: a jar with a post is not supported")
    ref = jar_mesh(params, segments=segments)
    is_side = np.abs(ref.face_normals[:, 1]) < 1e-9
    if np.any(np.abs(np.abs(ref.face_normals[~is_side, 1]) - 1) > 1e-9):
        raise SystemExit("internal: jar_mesh has faces that are neither side nor cap")
    side = ref.faces[is_side]
    (x0, _, z0), (x1, height, z1) = ref.bounds
    x0, z0, x1, z1 = x0 - cap_margin, z0 - cap_margin, x1 + cap_margin, z1 + cap_margin
    n = len(ref.vertices)
    caps = np.array([[x0, 0, z0], [x1, 0, z0], [x1, 0, z1], [x0, 0, z1],
                     [x0, height, z0], [x1, height, z0], [x1, height, z1], [x0, height, z1]])
    cap_faces = n + np.array([[0, 1, 2], [0, 2, 3], [4, 6, 5], [4, 7, 6]])  # normals out
    return trimesh.Trimesh(np.concatenate([ref.vertices, caps]),
                           np.concatenate([side, cap_faces]), process=True)


# --------------------------------------------------------------------------------------------
# Motion


def viblin_terms(motion) -> dict[int, list[tuple[float, float, float]]]:
    """Per axis (0, 1, 2) the ``fix move/mesh viblin`` terms (amplitude m, phase rad, period s)
    with ``offset(t) - offset(0) = sum C (cos(w t + p) - cos p)``, w = 2 pi / period (viblin's
    displacement from its start, LIGGGHTS src/mesh_mover_linear.cpp)."""
    terms: dict[int, list[tuple[float, float, float]]] = {0: [], 1: [], 2: []}
    if isinstance(motion, CircleMotion):
        a, phase = float(motion.amplitude), float(motion.phase)
        period = 60.0 / float(motion.rpm)
        terms[0].append((a, phase - math.pi / 2, period))  # A sin(wt + p)
        terms[2].append((a, phase, period))  # A cos(wt + p)
    elif isinstance(motion, HarmonicMotion):
        f0 = float(motion.base_frequency_hz)
        sin_c, cos_c = np.asarray(motion.sin_coeffs), np.asarray(motion.cos_coeffs)
        for k in range(sin_c.shape[0]):
            period = 1.0 / (f0 * (k + 1))
            for axis in range(3):
                if sin_c[k, axis] != 0:
                    terms[axis].append((float(sin_c[k, axis]), -math.pi / 2, period))
                if cos_c[k, axis] != 0:
                    terms[axis].append((float(cos_c[k, axis]), 0.0, period))
    else:
        raise SystemExit(f"liggghts_compare: motion {type(motion).__name__} is not supported "
                         "(circle and harmonic are)")
    return terms


def wall_velocity_expr(terms: dict[int, list[tuple[float, float, float]]], dt: float) -> list[str]:
    """LIGGGHTS equal-style expressions of the jar velocity per axis at the current step."""
    out = []
    for axis in range(3):
        parts = [f"-({c!r})*({2 * math.pi / per!r})*sin({2 * math.pi / per!r}*step*{dt!r}+({p!r}))"
                 for c, p, per in terms[axis]]
        out.append("+".join(parts) if parts else "0.0")
    return out


def wall_velocity(terms, t: np.ndarray) -> np.ndarray:
    """(T, 3) jar velocity (m/s) at times ``t`` from the viblin terms."""
    v = np.zeros((len(t), 3))
    for axis in range(3):
        for c, p, per in terms[axis]:
            w = 2 * math.pi / per
            v[:, axis] -= c * w * np.sin(w * t + p)
    return v


# --------------------------------------------------------------------------------------------
# LIGGGHTS input


def write_data(path: Path, pos, vel, omega, radius: float, density: float, box,
               n_types: int = 1) -> None:
    lines = ["LIGGGHTS data file: settled packing of our DEM (sample 0)", "",
             f"{len(pos)} atoms", f"{n_types} atom types", "",
             f"{box[0][0]!r} {box[0][1]!r} xlo xhi", f"{box[1][0]!r} {box[1][1]!r} ylo yhi",
             f"{box[2][0]!r} {box[2][1]!r} zlo zhi", "", "Atoms", ""]
    pos, vel, omega = (np.asarray(a, dtype=float).tolist() for a in (pos, vel, omega))
    lines += [f"{i + 1} 1 {2 * radius!r} {density!r} {x!r} {y!r} {z!r}"
              for i, (x, y, z) in enumerate(pos)]
    lines += ["", "Velocities", ""]
    lines += [f"{i + 1} {v[0]!r} {v[1]!r} {v[2]!r} {w[0]!r} {w[1]!r} {w[2]!r}"
              for i, (v, w) in enumerate(zip(vel, omega, strict=True))]
    path.write_text("\n".join(lines) + "\n")


def material_lines(mat, pp_rolling_scale: float = 1.0) -> str:
    """``fix property/global`` lines of the one material. With ``pp_rolling_scale`` != 1 the
    jar is atom type 2 (same material) and the ball-ball (1-1) rolling coefficient is
    multiplied by it (a diagnostic: 2 makes LIGGGHTS' ball-ball rolling torque mu_r F R/2 the
    size of ours, mu_r F R_c)."""
    if pp_rolling_scale == 1.0:
        return f"""# Balls and jar are atom type 1: one material.
fix m1 all property/global youngsModulus peratomtype {mat.young!r}
fix m2 all property/global poissonsRatio peratomtype {mat.poisson!r}
fix m3 all property/global coefficientRestitution peratomtypepair 1 {mat.restitution!r}
fix m4 all property/global coefficientFriction peratomtypepair 1 {mat.friction!r}
fix m5 all property/global coefficientRollingFriction peratomtypepair 1 {mat.rolling_friction!r}"""
    e, mu, mur = mat.restitution, mat.friction, mat.rolling_friction
    return f"""# Balls are atom type 1, the jar type 2, one material; ball-ball rolling x {pp_rolling_scale!r}.
fix m1 all property/global youngsModulus peratomtype {mat.young!r} {mat.young!r}
fix m2 all property/global poissonsRatio peratomtype {mat.poisson!r} {mat.poisson!r}
fix m3 all property/global coefficientRestitution peratomtypepair 2 {e!r} {e!r} {e!r} {e!r}
fix m4 all property/global coefficientFriction peratomtypepair 2 {mu!r} {mu!r} {mu!r} {mu!r}
fix m5 all property/global coefficientRollingFriction peratomtypepair 2 {mur * pp_rolling_scale!r} {mur!r} {mur!r} {mur!r}"""


def write_input(path: Path, *, cfg, dt_dem: float, n_steps: int, block: int, dump_every: int,
                offset0, terms, pp_rolling_scale: float = 1.0) -> None:
    mat, dem = cfg.material, cfg.dem
    jar_type = 1 if pp_rolling_scale == 1.0 else 2
    g = np.asarray(dem.gravity, dtype=float)
    gmag = float(np.linalg.norm(g))
    gdir = [float(c) for c in (g / gmag if gmag > 0 else (0.0, -1.0, 0.0))]
    offset0 = [float(c) for c in offset0]
    moves = []
    for axis, name in enumerate("xyz"):
        if not terms[axis]:
            continue
        axis_vec = " ".join("1" if a == axis else "0" for a in range(3))
        amps = " ".join(repr(c) for c, _, _ in terms[axis])
        phases = " ".join(repr(p) for _, p, _ in terms[axis])
        periods = " ".join(repr(per) for _, _, per in terms[axis])
        moves.append(f"fix move_{name} all move/mesh mesh jar viblin axis {axis_vec} "
                     f"order {len(terms[axis])} amplitude {amps} phase {phases} period {periods}")
    vx, vy, vz = wall_velocity_expr(terms, dt_dem)
    text = f"""# Generated by experiments/tools/liggghts_compare.py from {cfg.case.name}
atom_style granular
atom_modify map array
boundary f f f
newton off
communicate single vel yes
units si
processors 1 1 1
hard_particles yes  # Y > 1e9 Pa is refused in SI units without it
read_data data.lig
neighbor {dem.neighbour_skin!r} bin
neigh_modify delay 0

# Hertz-Mindlin, damping from the restitution, tangential history, EDEM type A rolling
# (constant directional torque).
pair_style gran model hertz tangential history rolling_friction cdt
pair_coeff * *
timestep {dt_dem!r}
{material_lines(mat, pp_rolling_scale)}
fix grav all gravity {gmag!r} vector {gdir[0]!r} {gdir[1]!r} {gdir[2]!r}

# The jar at offset(0), moved by viblin terms (offset(t) - offset(0)); mesh velocity = offset'(t).
fix jar all mesh/surface/stress file jar.stl type {jar_type} move {offset0[0]!r} {offset0[1]!r} {offset0[2]!r} curvature {CURVATURE_DEG!r} curvature_tolerant yes
fix walls all wall/gran model hertz tangential history rolling_friction cdt mesh n_meshes 1 meshes jar
{chr(10).join(moves)}
fix integr all nve/sphere

# Power of the wall on the balls, -F_on_mesh . v_wall, per step, averaged per sample interval.
variable vwx equal {vx}
variable vwy equal {vy}
variable vwz equal {vz}
variable pwall equal -(f_jar[1]*v_vwx+f_jar[2]*v_vwy+f_jar[3]*v_vwz)
fix power all ave/time 1 {block} {block} v_pwall f_jar[1] f_jar[2] f_jar[3] file power.txt
compute cc all contact/atom
dump states all custom {dump_every} dump.txt id x y z vx vy vz omegax omegay omegaz c_cc
dump_modify states sort id format "%d %.17g %.17g %.17g %.17g %.17g %.17g %.17g %.17g %.17g %g"
thermo_style custom step atoms f_jar[1] f_jar[2] f_jar[3] v_pwall
thermo {block * 1000}
run {n_steps}
"""
    path.write_text(text)


def liggghts_binary(name: str) -> str:
    for candidate in (name, "liggghts", "lmp_auto"):
        found = shutil.which(candidate)
        if found:
            return found
    raise SystemExit("liggghts_compare: no LIGGGHTS binary (apt-get install liggghts)")


def run_liggghts(binary: str, workdir: Path) -> float:
    """Run ``in.lig`` in ``workdir``; returns the child's CPU time (user + sys, s)."""
    env = dict(os.environ, OMPI_MCA_btl="self", OMPI_MCA_mtl="^ofi,psm",
               OMPI_MCA_btl_base_warn_component_unused="0")
    with open(workdir / "screen.txt", "w") as screen:
        proc = subprocess.Popen([binary, "-in", "in.lig", "-log", "log.lig", "-nocite"],
                                cwd=workdir, stdout=screen, stderr=subprocess.STDOUT, env=env)
        _, status, usage = os.wait4(proc.pid, 0)
    if os.waitstatus_to_exitcode(status) != 0:
        tail = (workdir / "screen.txt").read_text()[-2000:]
        raise SystemExit(f"liggghts_compare: LIGGGHTS failed in {workdir}:\n{tail}")
    return usage.ru_utime + usage.ru_stime


def read_dump(path: Path, n_balls: int) -> tuple[np.ndarray, np.ndarray]:
    """Steps (S,) and states (S, N, 10): x y z vx vy vz wx wy wz contacts, sorted by id."""
    steps, states = [], []
    with open(path) as f:
        lines = f.read().splitlines()
    k = 0
    while k < len(lines):
        if lines[k].startswith("ITEM: TIMESTEP"):
            steps.append(int(lines[k + 1]))
            n = int(lines[k + 3])
            rows = np.array([line.split() for line in lines[k + 9:k + 9 + n]], dtype=float)
            if n != n_balls:
                raise SystemExit(f"liggghts_compare: {path} step {steps[-1]} has {n} balls, "
                                 f"not {n_balls} (a ball left the jar)")
            states.append(rows[np.argsort(rows[:, 0]), 1:])
            k += 9 + n
        else:
            k += 1
    return np.array(steps), np.array(states)


# --------------------------------------------------------------------------------------------
# Measurements


def mechanical_energy(pos, vel, omega, mass: float, radius: float, gravity) -> np.ndarray:
    """KE_trans + KE_rot + PE_grav (J) of states (S, N, 3) each, (S,)."""
    inertia = 0.4 * mass * radius**2
    return (0.5 * mass * np.sum(vel**2, axis=(1, 2)) + 0.5 * inertia * np.sum(omega**2, axis=(1, 2))
            - mass * np.einsum("snk,k->s", pos, np.asarray(gravity)))


def measure_ours(path: Path, warmup: float, duration: float, mass: float, radius: float,
                 gravity, bin_s: float) -> dict:
    with np.load(path) as data:
        a = {name: data[name] for name in data.files if name != "meta"}
    t = np.asarray(a["t"])
    dt = float(t[1] - t[0])
    i0 = int(round(warmup / dt))
    i1 = int(round(duration / dt))
    span = t[i1] - t[i0]
    diss = sum(np.asarray(a[name]) for name in a.keys()
               if name.startswith("diss_"))  # per-interval, all kinds incl. stiffness
    ledger = float(np.sum(diss[i0 + 1:i1 + 1])) / span
    work = float(a["work_wall"][i1] - a["work_wall"][i0]) / span
    pos, vel, omega = (np.asarray(a[k]) for k in ("pos", "vel", "omega"))
    e = mechanical_energy(pos[[i0, i1]], vel[[i0, i1]], omega[[i0, i1]], mass, radius, gravity)
    idx = np.arange(i0, i1 + 1, DUMP_EVERY)
    rel = vel[idx] - np.asarray(a["offset_vel"])[idx][:, None, :]
    edges = np.arange(0, i1 + 1, int(round(bin_s / dt)))
    e_edges = mechanical_energy(pos[edges], vel[edges], omega[edges], mass, radius, gravity)
    w_edges = np.asarray(a["work_wall"])[edges]
    contacts = np.asarray(a["n_pp_contacts"])
    return {
        "wall_power_W": work,
        "dissipation_W": work - float(e[1] - e[0]) / span,
        "ledger_W": ledger,
        "speed_m_s": float(np.mean(np.linalg.norm(rel, axis=-1))),
        "pp_contacts": float(np.mean(contacts[idx])),
        "profile_dissipation_W": list((np.diff(w_edges) - np.diff(e_edges)) / bin_s),
        "profile_pp_contacts": [float(np.mean(contacts[e0:e1:DUMP_EVERY]))
                                for e0, e1 in zip(edges[:-1], edges[1:], strict=True)],
    }


def measure_liggghts(workdir: Path, *, warmup: float, dt: float, block: int, dt_dem: float,
                     n_balls: int, mass: float, radius: float, gravity, terms,
                     bin_s: float) -> dict:
    power = np.loadtxt(workdir / "power.txt", comments="#")
    block_end = power[:, 0].astype(np.int64)  # the block of steps (end - block, end]
    t_end = block_end * dt_dem
    i0 = int(round(warmup / dt))
    keep = block_end > i0 * block
    span = (block_end[-1] - i0 * block) * dt_dem
    work = float(np.sum(power[keep, 1]) * block * dt_dem) / span
    steps, states = read_dump(workdir / "dump.txt", n_balls)
    s0 = int(np.searchsorted(steps, i0 * block))
    if steps[s0] != i0 * block or steps[-1] != block_end[-1]:
        raise SystemExit(f"liggghts_compare: {workdir}: dumps do not cover the window")
    pos, vel, omega, cc = states[..., 0:3], states[..., 3:6], states[..., 6:9], states[..., 9]
    e = mechanical_energy(pos[[s0, -1]], vel[[s0, -1]], omega[[s0, -1]], mass, radius, gravity)
    t_states = steps[s0:] * dt_dem
    rel = vel[s0:] - wall_velocity(terms, t_states)[:, None, :]
    # Per bin: the work from the per-block powers (block k ends at sample k + 1), the energies
    # from the dumped states at the bin edges.
    cum_work = np.concatenate([[0.0], np.cumsum(power[:, 1]) * block * dt_dem])
    nb = int(round(bin_s / dt))
    edges = np.arange(0, len(cum_work), nb)
    at = np.searchsorted(steps, edges * block)
    if np.any(steps[at] != edges * block):
        raise SystemExit(f"liggghts_compare: {workdir}: no dump at a bin edge")
    e_edges = mechanical_energy(pos[at], vel[at], omega[at], mass, radius, gravity)
    pp = np.sum(cc, axis=1) / 2.0
    return {
        "wall_power_W": work,
        "dissipation_W": work - float(e[1] - e[0]) / span,
        "speed_m_s": float(np.mean(np.linalg.norm(rel, axis=-1))),
        "pp_contacts": float(np.mean(pp[s0:])),
        "t_end_s": float(t_end[-1]),
        "profile_dissipation_W": list((np.diff(cum_work[edges]) - np.diff(e_edges)) / bin_s),
        "profile_pp_contacts": [float(np.mean(pp[a0:a1])) for a0, a1 in zip(at[:-1], at[1:],
                                                                            strict=True)],
    }


def mean_se(values) -> tuple[float, float]:
    x = np.asarray([v for v in values if v is not None and np.isfinite(v)], dtype=float)
    if len(x) == 0:
        return math.nan, math.nan
    se = float(np.std(x, ddof=1) / math.sqrt(len(x))) if len(x) > 1 else math.nan
    return float(np.mean(x)), se


# --------------------------------------------------------------------------------------------
# Main


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", required=True, help="experiment config (TOML path)")
    ap.add_argument("--seeds", type=int, nargs="+", required=True, help="placement seeds")
    ap.add_argument("--duration", type=float, required=True, help="s of motion")
    ap.add_argument("--warmup", type=float, default=0.5, help="s discarded at the start")
    ap.add_argument("--out", required=True, help="output directory")
    ap.add_argument("--name", default="compare", help="basename of the JSON and markdown")
    ap.add_argument("--liggghts", default="liggghts", help="LIGGGHTS binary")
    ap.add_argument("--only", choices=("ours", "liggghts"), default=None,
                    help="run only one code (the other's finished results are still read)")
    ap.add_argument("--dt-dem", type=float, default=None,
                    help="the DEM step of both codes (default: the charge's, sgn-jax dem's)")
    ap.add_argument("--bin", type=float, default=0.25,
                    help="s per bin of the time profile of the dissipated power (whole run)")
    ap.add_argument("--pp-rolling-scale", type=float, default=1.0,
                    help="diagnostic: multiply LIGGGHTS' ball-ball rolling coefficient (2: its "
                    "torque mu_r F R/2 becomes the size of ours); runs go to OUT/lig_pprX_seedS")
    args = ap.parse_args(argv)

    cfg = sj.load_config(args.config)
    setup = dem_setup_from_config(cfg, dt_dem=args.dt_dem)
    dt, dt_dem, block = setup.dt, setup.dt_dem, setup.substeps
    radius, density = float(cfg.balls.radius), float(cfg.balls.density)
    mass = 4.0 / 3.0 * math.pi * radius**3 * density
    gravity = np.asarray(cfg.dem.gravity, dtype=float)
    motion = sj.motion_from_config(cfg.motion)
    terms = viblin_terms(motion)
    n_motion = int(round(args.duration / dt))
    n_bin = int(round(args.bin / dt))
    if int(round(args.warmup / dt)) % DUMP_EVERY or n_motion % DUMP_EVERY or n_bin % DUMP_EVERY:
        raise SystemExit(f"--warmup, --duration and --bin must be multiples of "
                         f"{DUMP_EVERY * dt:g} s")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    binary = liggghts_binary(args.liggghts) if args.only != "ours" else None

    stl = jar_stl_mesh(cfg.jar)
    lo, hi = stl.bounds
    offset0 = motion_offset0(motion)
    # The jar's travel from offset(0) on each axis is at most 2 sum |C|; 5 mm to spare.
    reach = [2 * sum(abs(c) for c, _, _ in terms[k]) + 0.005 for k in range(3)]
    box = [(float(lo[k] + offset0[k] - reach[k]), float(hi[k] + offset0[k] + reach[k]))
           for k in range(3)]

    results = {}
    for seed in args.seeds:
        rec = out / f"ours_seed{seed}.npz"
        row = results.setdefault(seed, {})
        if args.only != "liggghts":
            if not rec.is_file():
                r0 = resource.getrusage(resource.RUSAGE_SELF)
                w0 = time.perf_counter()
                run = sj.run_dem(cfg, duration=args.duration, out_path=rec, seed=seed,
                                 dt_dem=args.dt_dem, progress=False)
                r1 = resource.getrusage(resource.RUSAGE_SELF)
                timing = {"cpu_s": (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime),
                          "wall_s": time.perf_counter() - w0,
                          "settle_wall_s": run.summary["settle_wall_s"],
                          "motion_wall_s": run.summary["motion_wall_s"],
                          "settle_cached": run.summary["settle_cached"]}
                (out / f"ours_seed{seed}.timing.json").write_text(json.dumps(timing))
                print(f"seed {seed}: our DEM {timing['wall_s']:.0f} s", flush=True)
        if rec.is_file():
            row["ours"] = measure_ours(rec, args.warmup, args.duration, mass, radius, gravity,
                                       args.bin)
            tfile = out / f"ours_seed{seed}.timing.json"
            row["ours"]["timing"] = json.loads(tfile.read_text()) if tfile.is_file() else None

        work = out / (f"lig_seed{seed}" if args.pp_rolling_scale == 1.0
                      else f"lig_ppr{args.pp_rolling_scale:g}_seed{seed}")
        done = work / "done.json"
        if args.only != "ours" and not done.is_file() and rec.is_file():
            work.mkdir(exist_ok=True)
            with np.load(rec) as data:
                pos0, vel0, om0 = data["pos"][0], data["vel"][0], data["omega"][0]
                off0 = data["offset"][0]
            if not np.allclose(off0, offset0, atol=1e-12):
                raise SystemExit(f"internal: record offset(0) {off0} != motion's {offset0}")
            stl.export(work / "jar.stl", file_type="stl_ascii")
            write_data(work / "data.lig", pos0, vel0, om0, radius, density, box,
                       n_types=1 if args.pp_rolling_scale == 1.0 else 2)
            write_input(work / "in.lig", cfg=cfg, dt_dem=dt_dem, n_steps=n_motion * block,
                        block=block, dump_every=DUMP_EVERY * block, offset0=offset0, terms=terms,
                        pp_rolling_scale=args.pp_rolling_scale)
            w0 = time.perf_counter()
            cpu = run_liggghts(binary, work)
            done.write_text(json.dumps({"cpu_s": cpu, "wall_s": time.perf_counter() - w0}))
            print(f"seed {seed}: LIGGGHTS {cpu:.0f} s CPU", flush=True)
        if done.is_file():
            row["liggghts"] = measure_liggghts(work, warmup=args.warmup, dt=dt, block=block,
                                               dt_dem=dt_dem, n_balls=cfg.balls.count,
                                               mass=mass, radius=radius, gravity=gravity,
                                               terms=terms, bin_s=args.bin)
            row["liggghts"]["timing"] = json.loads(done.read_text())

    report = summarize(cfg, args, results, dt_dem)
    (out / f"{args.name}.json").write_text(json.dumps(report, indent=1))
    (out / f"{args.name}.md").write_text(markdown(report))
    print(markdown(report))


def motion_offset0(motion) -> np.ndarray:
    return np.asarray(motion_offset(motion, 0.0), dtype=float)


METRICS = (("dissipation_W", "dissipated power (W)"), ("wall_power_W", "wall power (W)"),
           ("speed_m_s", "mean speed in the jar frame (m/s)"),
           ("pp_contacts", "ball-ball contacts"))


def summarize(cfg, args, results: dict, dt_dem: float) -> dict:
    seeds = sorted(results)
    table = {}
    for key, _ in METRICS + (("ledger_W", ""),):
        ours = [results[s].get("ours", {}).get(key) for s in seeds]
        lig = [results[s].get("liggghts", {}).get(key) for s in seeds]
        mo, so = mean_se(ours)
        ml, sl = mean_se(lig)
        se = math.hypot(so, sl)
        table[key] = {"ours": [mo, so], "liggghts": [ml, sl],
                      "diff": ml - mo, "diff_se_units": (ml - mo) / se if se > 0 else math.nan,
                      "diff_pct": 100 * (ml - mo) / mo if mo else math.nan}

    profile = {}
    for code in ("ours", "liggghts"):
        rows = [results[s][code]["profile_dissipation_W"] for s in seeds if code in results[s]]
        cont = [results[s][code]["profile_pp_contacts"] for s in seeds if code in results[s]]
        if rows:
            n = min(len(r) for r in rows)
            profile[code] = {"dissipation_W": [mean_se([r[k] for r in rows]) for k in range(n)],
                             "pp_contacts": [mean_se([r[k] for r in cont]) for k in range(n)]}

    def total(code: str, field: str) -> float:
        return float(sum((results[s].get(code, {}).get("timing") or {}).get(field, 0.0)
                         for s in seeds))

    return {
        "config": str(args.config), "case": cfg.case.name, "balls": cfg.balls.count,
        "radius_m": cfg.balls.radius, "seeds": seeds, "duration_s": args.duration,
        "warmup_s": args.warmup, "dt_dem_s": dt_dem,
        "liggghts_pp_rolling_scale": args.pp_rolling_scale, "per_seed": {str(s): results[s] for s in seeds},
        "table": table, "bin_s": args.bin, "profile": profile,
        "cpu_s": {"ours": total("ours", "cpu_s"), "liggghts": total("liggghts", "cpu_s")},
    }


def markdown(report: dict) -> str:
    n = len(report["seeds"])
    lines = [f"{report['case']}: {report['balls']} balls of radius {report['radius_m'] * 1e3:g} mm, "
             f"{n} packings (seeds {', '.join(map(str, report['seeds']))}), "
             f"{report['duration_s']:g} s of motion, window {report['warmup_s']:g}-"
             f"{report['duration_s']:g} s, dt = {report['dt_dem_s']:.4g} s", "",
             "| quantity | ours (mean +- SE) | LIGGGHTS (mean +- SE) | difference | in SE | % |",
             "|---|---|---|---|---|---|"]
    for key, label in METRICS:
        row = report["table"][key]
        (mo, so), (ml, sl) = row["ours"], row["liggghts"]
        lines.append(f"| {label} | {mo:.4g} +- {so:.2g} | {ml:.4g} +- {sl:.2g} | "
                     f"{row['diff']:+.3g} | {row['diff_se_units']:+.2f} | {row['diff_pct']:+.1f} |")
    mo, so = report["table"]["ledger_W"]["ours"]
    lines += ["", f"Our ledger's dissipation over the window: {mo:.4g} +- {so:.2g} W.", "",
              "| seed | ours: dissipated (W) | ours: ledger (W) | ours: pp contacts | "
              "LIGGGHTS: dissipated (W) | LIGGGHTS: pp contacts |", "|---|---|---|---|---|---|"]
    for s, row in report["per_seed"].items():
        o, li = row.get("ours", {}), row.get("liggghts", {})
        lines.append(f"| {s} | {o.get('dissipation_W', math.nan):.4f} | "
                     f"{o.get('ledger_W', math.nan):.4f} | {o.get('pp_contacts', math.nan):.1f} | "
                     f"{li.get('dissipation_W', math.nan):.4f} | "
                     f"{li.get('pp_contacts', math.nan):.1f} |")
    prof = report.get("profile", {})
    if "ours" in prof and "liggghts" in prof:
        b = report["bin_s"]
        lines += ["", f"Time profile (ensemble mean +- SE per {b:g} s bin, from t = 0):", "",
                  "| t (s) | ours: dissipated (W) | LIGGGHTS: dissipated (W) | ours: pp contacts "
                  "| LIGGGHTS: pp contacts |", "|---|---|---|---|---|"]
        po, pl = prof["ours"], prof["liggghts"]
        for k in range(min(len(po["dissipation_W"]), len(pl["dissipation_W"]))):
            (do, so), (dl, sl) = po["dissipation_W"][k], pl["dissipation_W"][k]
            (co, sco), (cl, scl) = po["pp_contacts"][k], pl["pp_contacts"][k]
            lines.append(f"| {k * b:g}-{(k + 1) * b:g} | {do:.3f} +- {so:.3f} | {dl:.3f} +- "
                         f"{sl:.3f} | {co:.1f} +- {sco:.1f} | {cl:.1f} +- {scl:.1f} |")
    cpu = report["cpu_s"]
    lines += ["", f"CPU time (user + sys, all seeds): ours {cpu['ours']:.0f} s, "
              f"LIGGGHTS {cpu['liggghts']:.0f} s."]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
