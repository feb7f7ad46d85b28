#!/usr/bin/env python
"""Generate DEM ensembles: every (case, seed) of an ensembles file (docs/conventions.md section 7).

    python experiments/tools/generate_data.py [--ensembles experiments/ensembles.toml]
        [--cases standard,motion1,...] [--split all|train|eval] [--out data/] [--jobs 1]
        [--prefix SECONDS] [--dry-run] [--no-pin] [--no-progress]

For every (case, seed) of the ensembles file (experiments/ensembles.toml: config, seconds of
motion, seeds and which of them are training packings) this runs

    taskset -c CORE sgn-jax dem --config CONFIG --duration D --seed S --out OUT/{case}_seed{S}.npz

unless that file is already complete. A file counts as complete when
``sgn_jax.records.trajectory.load_trajectory`` accepts it *and* it is the run asked for: its seed,
its number of samples (D / dt + 1) and the DEM-relevant part of its config ([jar], [motion],
[balls], [material], [dem] except seed/duration/chunk_samples, [sdf] for mesh jars) match the
case. A corrupt or stale file is deleted and redone. An interrupted run left ``OUT.partial/``
behind; ``sgn-jax dem`` resumes from there, so rerunning this script continues where it stopped.

Runs go to ``--jobs`` parallel processes, process k pinned to the k-th core this process may
use (``taskset -c``), because one DEM process per core is the fastest way to run an ensemble
on a CPU: vmapping packings inside one process gives fewer system-steps per second per core
(docs/benchmarks.md, DEM throughput). Each run's output (its JSON summary line, errors) goes to
``OUT/logs/{case}_seed{S}.log``.

After every finished run ``OUT/manifest.json`` is rewritten atomically: one entry per file
(case, seed, split, file, sha256, duration, wall time, total dissipation, mean dissipation
power, mean ball-ball contacts, regime label, ...) and a per-case summary (states of the
training and evaluation packings, mean power and spread).

The regime label is the state (docs/conventions.md section 7) from the DEM's mean ball-ball contact count
(``sgn_jax.regime.regime_of``: "bed" when the mean number of ball-ball contacts per ball is >=
``sgn_jax.regime.REGIME_PP_CONTACTS_PER_BALL``, 14 contacts for 24 balls, else "agitated"); it
is also given per ``sgn_jax.regime.REGIME_WINDOW_S`` = 1-s window (``regime_windows``) because a
run can switch. The rule, its threshold and their provenance are documented in
``sgn_jax.regime``. The old rule of ``sgn-jax evaluate`` (ball pairs within ``2 R + [graph]
pp_skin`` per ball >= ``sgn_jax.regime.BED_PAIRS_PER_BALL``) does not separate the states; its
label is recorded too (``regime_evaluate_rule``) with the value it thresholds.

**Prefixes** (``--prefix SECONDS``, e.g. 0.002): only the first milliseconds of every
evaluation run (the seeds that are not training seeds), ``sgn-jax dem ... --duration SECONDS``
to ``OUT/{case}_seed{S}.npz``, no manifest. A prefix has the same settled packing and the same
DEM steps as the full run, so its samples are the full record's first ones, bit for bit. It is
what ``evaluate_contact.py --dem-reference`` needs: the model's rollouts start from the
record's first window, and the DEM's statistics come from an earlier evaluation's JSON. The
prefix must cover the first window at the model's step (7 windows of 2e-4 s: 1.4 ms). A file
already there is kept.

Exit status: 0 when every selected run is complete, 1 if a run failed (the others still run),
2 for a bad ensembles file or argument, 130 when interrupted.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import datetime
import json
import math
import os
import shlex
import shutil
import subprocess
import sys
import time
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

from sgn_jax.experiment_tools import (
    Case,
    EnsembleError,
    last_json_line,
    load_ensembles,
    select_cases,
    sgn_jax_command,
    usable_cores,
)

HERE = Path(__file__).resolve().parent
DEFAULT_ENSEMBLES = HERE.parent / "ensembles.toml"
MANIFEST_NAME = "manifest.json"
MANIFEST_FORMAT = 1
# Wall time per simulated second of one DEM process (settling included), for estimates before
# any run has finished: 11 s uncontended (95k steps/s), ~30 s with a busy second core
# (docs/dem.md: 308 s for 0.5 s of settling + 10 s of motion).
WALL_PER_SIM_SECOND_RANGE = (11.0, 30.0)
POLL_S = 1.0

# Config sections that determine the DEM trajectory of a seed (the rest configure the SGN).
_DEM_SECTIONS = ("jar", "motion", "balls", "material", "dem")
_DEM_KEYS_NOT_COMPARED = ("seed", "duration", "chunk_samples")


# --------------------------------------------------------------------------------------------
# Runs and their files


@dataclasses.dataclass(frozen=True)
class Run:
    """One (case, seed): the DEM run that writes ``out_dir/{case}_seed{seed}.npz``."""

    case: Case
    seed: int
    out_dir: Path

    @property
    def key(self) -> str:
        return f"{self.case.name}_seed{self.seed}"

    @property
    def file_name(self) -> str:
        return f"{self.key}.npz"

    @property
    def out_path(self) -> Path:
        return self.out_dir / self.file_name

    @property
    def log_path(self) -> Path:
        return self.out_dir / "logs" / f"{self.key}.log"

    @property
    def split(self) -> str:
        return self.case.split_of(self.seed)


def plan_runs(cases: Iterable[Case], out_dir: str | Path, split: str = "all") -> list[Run]:
    """Every (case, seed) of ``cases`` in ``split`` ("all", "train" or "eval")."""
    if split not in ("all", "train", "eval"):
        raise EnsembleError(f"--split must be all, train or eval, got {split!r}")
    runs = []
    for case in cases:
        for seed in case.seeds:
            if split in ("all", case.split_of(seed)):
                runs.append(Run(case=case, seed=seed, out_dir=Path(out_dir)))
    return runs


def dem_relevant_config(cfg: Any) -> dict[str, Any]:
    """The parts of a config that determine a seed's DEM trajectory, as plain data."""
    from sgn_jax.experiment_tools import config_to_dict

    full = config_to_dict(cfg)
    out = {section: full[section] for section in _DEM_SECTIONS}
    out["dem"] = {k: v for k, v in out["dem"].items() if k not in _DEM_KEYS_NOT_COMPARED}
    if full["jar"].get("kind") != "emax":  # only mesh jars read the DEM's walls from [sdf]
        out["sdf"] = full["sdf"]
    return out


def _differences(a: Any, b: Any, prefix: str = "") -> list[str]:
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for key in sorted(set(a) | set(b)):
            out += _differences(a.get(key), b.get(key), f"{prefix}{key}.")
        return out
    return [] if a == b else [f"{prefix[:-1]}: file {b!r}, case {a!r}"]


@dataclasses.dataclass
class FileStatus:
    """What is at a run's output path: kind in missing / partial / valid / corrupt / stale."""

    kind: str
    reason: str = ""
    trajectory: Any = None
    partial_sim_s: float = 0.0  # simulated seconds (settling + motion) done in OUT.partial/


def partial_progress(run: Run, cfg: Any) -> float:
    """Simulated seconds (settling + motion) a run has in its ``OUT.partial/`` checkpoint.

    The DEM driver writes chunk 0 (the settled state) after settling, then one chunk file per
    ``[dem] chunk_samples`` samples of motion.
    """
    from sgn_jax.experiment_tools import partial_dir

    folder = partial_dir(run.out_path)
    if not folder.is_dir():
        return 0.0
    n_chunks = len(list(folder.glob("chunk_*.npz")))
    if n_chunks == 0:
        return 0.0
    motion = min(run.case.duration, (n_chunks - 1) * cfg.dem.chunk_samples * cfg.dem.dt)
    return cfg.dem.settle_time + motion


def inspect_output(run: Run, cfg: Any) -> FileStatus:
    """Classify the run's output file; a valid one comes with its loaded Trajectory."""
    from sgn_jax.api import DatasetError, load_trajectory
    from sgn_jax.experiment_tools import config_from_dict

    path = run.out_path
    if not path.exists():
        done = partial_progress(run, cfg)
        return FileStatus("partial" if done > 0 else "missing", partial_sim_s=done)
    try:
        traj = load_trajectory(path)
    except DatasetError as exc:
        return FileStatus("corrupt", str(exc))
    meta = traj.meta
    if meta["seed"] != run.seed:
        return FileStatus("stale", f"{path} holds seed {meta['seed']}, not {run.seed}")
    expected = int(round(run.case.duration / cfg.dem.dt)) + 1
    if traj.n_samples != expected or not math.isclose(meta["dt"], cfg.dem.dt, rel_tol=1e-9):
        return FileStatus("stale", f"{path} holds {traj.n_samples} samples of dt = "
                          f"{meta['dt']:g} s, the case asks for {expected} (duration "
                          f"{run.case.duration:g} s, dt = {cfg.dem.dt:g} s)")
    try:
        file_cfg = config_from_dict(meta["config"])
    except ValueError as exc:
        return FileStatus("corrupt", f"{path}: its meta config does not load: {exc}")
    differences = _differences(dem_relevant_config(cfg), dem_relevant_config(file_cfg))
    if differences:
        shown = "; ".join(differences[:4]) + (" ..." if len(differences) > 4 else "")
        return FileStatus("stale", f"{path} was made with a different config ({shown})")
    return FileStatus("valid", trajectory=traj)


def file_record(run: Run, traj: Any, cfg: Any, sha256: str) -> dict[str, Any]:
    """The manifest entry of a valid file, from the file itself (wall times added by caller)."""
    import numpy as np

    from sgn_jax.experiment_tools import (
        BED_PAIRS_PER_BALL,
        REGIME_PP_CONTACTS_PER_BALL,
        classify_state,
        pairs_within,
        pp_contact_counts,
        regime_of,
        regime_windows,
    )

    arrays = traj.arrays
    diss = {name: float(np.sum(value)) for name, value in arrays.items()
            if name.startswith("diss_")}
    total = sum(diss.values())
    duration = float(traj.t[-1] - traj.t[0])
    n_balls = traj.n_balls
    cutoff = 2.0 * float(traj.meta["ball_radius"]) + float(cfg.graph.pp_skin)
    mean_pairs = float(np.mean(pairs_within(traj.pos, cutoff))) / n_balls
    contacts = pp_contact_counts(traj.pp_pairs)
    windows, window_s = regime_windows(contacts, n_balls, duration)
    return {
        "case": run.case.name,
        "seed": run.seed,
        "split": run.split,
        "config": str(run.case.config),
        "file": run.file_name,
        "sha256": sha256,
        "size_bytes": run.out_path.stat().st_size,
        "duration_s": duration,
        "n_samples": traj.n_samples,
        "settle_time_s": traj.meta.get("settle_time"),
        "total_dissipation_J": total,
        "surrogate_target_J": float(traj.cumulative_dissipation()[-1]),
        "dissipation_J": diss,
        "mean_dissipation_power_W": total / duration if duration > 0 else None,
        "mean_pp_contacts": float(np.mean(contacts)),
        "mean_pw_contacts": float(np.mean(np.sum(traj.pw_contact, axis=1))),
        "mean_ke_trans_J": float(np.mean(traj.ke_trans)),
        "regime": regime_of(float(np.mean(contacts)) / n_balls),
        "regime_threshold_pp_contacts_per_ball": REGIME_PP_CONTACTS_PER_BALL,
        "regime_windows": windows,
        "regime_window_s": window_s,
        "pp_pairs_within_skin_per_ball": mean_pairs,
        "pp_cutoff_m": cutoff,
        "regime_evaluate_rule": classify_state(mean_pairs, BED_PAIRS_PER_BALL, "contacts"),
        "ledger_residual_J": traj.meta.get("ledger_residual_J"),
        "code_version": traj.meta.get("code_version"),
        "created": traj.meta.get("created"),
    }


def dem_command(run: Run, base: Sequence[str] | None = None) -> list[str]:
    """The ``sgn-jax dem`` command of a run (without the taskset prefix)."""
    base = list(base) if base is not None else sgn_jax_command()
    return [*base, "dem", "--config", str(run.case.config_path), "--duration",
            repr(run.case.duration), "--seed", str(run.seed), "--out", str(run.out_path),
            "--no-progress"]


# --------------------------------------------------------------------------------------------
# The manifest


def _now() -> str:
    return datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")


def read_manifest(out_dir: Path) -> dict[str, dict[str, Any]]:
    """The entries of an existing manifest by file name ({} if none or unreadable)."""
    path = out_dir / MANIFEST_NAME
    if not path.is_file():
        return {}
    try:
        data = json.loads(path.read_text())
        return {entry["file"]: entry for entry in data["runs"]}
    except (ValueError, KeyError, TypeError) as exc:
        print(f"generate_data: warning: {path} is unreadable ({exc}); rebuilding it from the "
              "files", file=sys.stderr)
        return {}


def _spread(values: list[float]) -> dict[str, Any]:
    import numpy as np

    if not values:
        return {"n": 0, "mean": None, "std": None, "min": None, "max": None}
    array = np.asarray(values, dtype=np.float64)
    return {"n": int(array.size), "mean": float(array.mean()),
            "std": float(array.std(ddof=1)) if array.size > 1 else None,
            "min": float(array.min()), "max": float(array.max())}


def case_summaries(cases: Iterable[Case], entries: dict[str, dict[str, Any]]
                   ) -> tuple[dict[str, Any], list[str]]:
    """Per case: completeness, states and power of its training and evaluation packings; plus
    warnings (a complete training set in one state only: it should hold both, docs/conventions.md section 7)."""
    summaries, warnings = {}, []
    for case in cases:
        per_split: dict[str, Any] = {}
        for split, seeds in (("train", case.train_seeds), ("eval", case.eval_seeds)):
            done = [entries[f"{case.name}_seed{s}.npz"] for s in seeds
                    if f"{case.name}_seed{s}.npz" in entries]
            states: dict[str, list[int]] = collections.defaultdict(list)
            for entry in done:
                states[entry["regime"]].append(entry["seed"])
            per_split[split] = {
                "seeds": list(seeds), "complete": len(done), "states": dict(states),
                "power_W": _spread([e["mean_dissipation_power_W"] for e in done
                                    if e["mean_dissipation_power_W"] is not None]),
                "mean_pp_contacts": _spread([e["mean_pp_contacts"] for e in done]),
            }
        train = per_split["train"]
        if case.train_seeds and train["complete"] == len(case.train_seeds) \
                and len(train["states"]) == 1 and len(case.train_seeds) > 1:
            (state,) = train["states"]
            warnings.append(f"{case.name}: every training packing {list(case.train_seeds)} is "
                            f"'{state}'; training data should hold both states: move a "
                            "packing of the other state into train_seeds (or add seeds)")
        summaries[case.name] = {"config": case.config, "duration_s": case.duration,
                                "description": case.description, **per_split}
    return summaries, warnings


def write_manifest(out_dir: Path, ensembles_path: Path, cases: Sequence[Case],
                   entries: dict[str, dict[str, Any]]) -> list[str]:
    """Rewrite ``out_dir/manifest.json`` atomically; returns the case warnings."""
    from sgn_jax.experiment_tools import git_commit, sha256_file, write_json

    summaries, warnings = case_summaries(cases, entries)
    write_json(out_dir / MANIFEST_NAME, {
        "format": MANIFEST_FORMAT,
        "updated": _now(),
        "generator": "experiments/tools/generate_data.py",
        "generator_commit": git_commit(),
        "ensembles": str(ensembles_path),
        "ensembles_sha256": sha256_file(ensembles_path),
        "runs": sorted(entries.values(), key=lambda entry: (entry["case"], entry["seed"])),
        "cases": summaries,
        "warnings": warnings,
    })
    return warnings


# --------------------------------------------------------------------------------------------
# Running


@dataclasses.dataclass
class Active:
    run: Run
    process: subprocess.Popen
    log: Any
    log_offset: int
    core: int | None
    started: float
    partial_at_start: float  # simulated s already in OUT.partial/ when it started

    @property
    def resumed(self) -> bool:
        return self.partial_at_start > 0


def _format_duration(seconds: float | None) -> str:
    if seconds is None or not math.isfinite(seconds):
        return "?"
    seconds = int(round(seconds))
    return f"{seconds // 3600:d}:{seconds // 60 % 60:02d}:{seconds % 60:02d}"


def _log_tail(path: Path, offset: int, lines: int = 6) -> str:
    with open(path, "rb") as fh:
        fh.seek(offset)
        text = fh.read().decode("utf-8", "replace")
    return "\n".join("    " + line for line in text.splitlines()[-lines:])


class Generator:
    """Plans, runs and records one invocation (see the module docstring)."""

    def __init__(self, ensembles_path: Path, cases: dict[str, Case], selected: list[Case],
                 out_dir: Path, split: str, jobs: int, pin: bool, progress: bool,
                 echo=print) -> None:
        from sgn_jax.api import load_config

        self.ensembles_path = ensembles_path
        self.all_cases = list(cases.values())
        self.selected = selected
        self.out_dir = out_dir
        self.jobs = jobs
        self.progress = progress
        self.echo = echo
        self.runs = plan_runs(selected, out_dir, split)
        self.configs = {case.name: load_config(case.config_path) for case in selected}
        self.pin = pin and shutil.which("taskset") is not None
        self.pin_note = "" if self.pin or not pin else " (taskset not found: not pinned)"
        self.cores = usable_cores()
        self.base = sgn_jax_command()

    def work_of(self, run: Run) -> float:
        """Simulated seconds of a run: settling + motion."""
        return self.configs[run.case.name].dem.settle_time + run.case.duration

    def command(self, run: Run, slot: int) -> tuple[list[str], int | None]:
        cmd = dem_command(run, self.base)
        if not self.pin:
            return cmd, None
        core = self.cores[slot % len(self.cores)]
        return ["taskset", "-c", str(core), *cmd], core

    # ---- scan
    def scan(self, dry_run: bool) -> tuple[list[tuple[Run, FileStatus]], dict[str, Any]]:
        """Check every planned run's file; returns (runs to do with their status, entries)."""
        from sgn_jax.experiment_tools import sha256_file

        entries = read_manifest(self.out_dir)
        todo = []
        for run in self.runs:
            cfg = self.configs[run.case.name]
            status = inspect_output(run, cfg)
            if status.kind == "valid":
                if dry_run:  # no manifest is written: skip hashing and statistics
                    self.echo(f"skip  {run.key}: valid ({run.out_path})")
                    continue
                sha = sha256_file(run.out_path)
                old = entries.get(run.file_name)
                if old is None or old.get("sha256") != sha:
                    entry = file_record(run, status.trajectory, cfg, sha)
                    entry.update(wall_time_s=None, note="recorded from an existing file")
                    entries[run.file_name] = entry
                else:
                    old["split"] = run.split  # the split may have been edited since
                self.echo(f"skip  {run.key}: valid ({run.out_path})")
                continue
            entries.pop(run.file_name, None)
            if status.kind in ("corrupt", "stale"):
                action = "would redo" if dry_run else "redo"
                self.echo(f"{action}  {run.key}: {status.kind}: {status.reason}")
                if not dry_run:
                    run.out_path.unlink()
                status.partial_sim_s = partial_progress(run, cfg)
            elif status.kind == "partial":
                self.echo(f"resume {run.key}: {status.partial_sim_s:g} of "
                          f"{self.work_of(run):g} simulated s done in "
                          f"{run.out_path.name}.partial/")
            todo.append((run, status))
        return todo, entries

    # ---- run
    def execute(self, todo: list[tuple[Run, FileStatus]], entries: dict[str, Any]) -> int:
        from tqdm import tqdm

        write_manifest(self.out_dir, self.ensembles_path, self.all_cases, entries)
        n_total = len(self.runs)
        n_done = n_total - len(todo)
        total_work = sum(self.work_of(run) for run, _ in todo)
        done_work = sum(status.partial_sim_s for _, status in todo)
        queue = collections.deque(todo)
        active: dict[int, Active] = {}
        failures: list[str] = []
        t_start = time.perf_counter()
        run_start_work = done_work
        completed_work = done_work  # work of finished runs + partial work found at start
        bar = tqdm(total=round(total_work, 3), initial=round(done_work, 3), unit="sim s",
                   disable=not self.progress, dynamic_ncols=True,
                   bar_format="{l_bar}{bar}| {n:.4g}/{total:.4g} sim s "
                   "[{elapsed}<{remaining}{postfix}]")
        bar.set_postfix_str(f"runs {n_done}/{n_total}")
        write = bar.write if self.progress else self.echo

        def progress_of(item: Active) -> float:
            cfg = self.configs[item.run.case.name]
            return max(0.0, partial_progress(item.run, cfg) - item.partial_at_start)

        def current_work() -> float:
            return completed_work + sum(progress_of(item) for item in active.values())

        def eta() -> float | None:
            elapsed = time.perf_counter() - t_start
            gained = current_work() - run_start_work
            if gained <= 0:
                return None
            return elapsed / gained * (total_work - current_work())

        try:
            while queue or active:
                for slot in range(self.jobs):
                    if slot in active or not queue:
                        continue
                    run, status = queue.popleft()
                    cmd, core = self.command(run, slot)
                    run.log_path.parent.mkdir(parents=True, exist_ok=True)
                    log = open(run.log_path, "ab")  # closed when the process ends
                    offset = log.tell()
                    log.write(f"# {_now()} {shlex.join(cmd)}\n".encode())
                    log.flush()
                    env = dict(os.environ, PYTHONUNBUFFERED="1")
                    process = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT,
                                               env=env)
                    active[slot] = Active(run, process, log, offset, core,
                                          time.perf_counter(), status.partial_sim_s)
                    where = f" on core {core}" if core is not None else ""
                    write(f"start {run.key}{where}: {shlex.join(cmd)}")
                time.sleep(POLL_S)
                for slot in list(active):
                    item = active[slot]
                    if item.process.poll() is None:
                        continue
                    item.log.close()
                    ok = self.finish(item, entries, write)
                    if ok:
                        n_done += 1
                        completed_work += self.work_of(item.run) - item.partial_at_start
                    else:  # what it did stays in OUT.partial/; the rest is not done now
                        failures.append(item.run.key)
                        gained = progress_of(item)
                        completed_work += gained
                        total_work -= self.work_of(item.run) - item.partial_at_start - gained
                        bar.total = round(total_work, 3)
                    del active[slot]
                    write_manifest(self.out_dir, self.ensembles_path, self.all_cases, entries)
                    write(f"[{n_done}/{n_total} runs done, {len(failures)} failed] "
                          f"ETA {_format_duration(eta() if (queue or active) else 0.0)}")
                    bar.set_postfix_str(f"runs {n_done}/{n_total}")
                shown = round(min(current_work(), total_work), 3)
                if shown != bar.n:  # a new checkpoint chunk: redraw (and no more often)
                    bar.n = shown
                    bar.refresh()
        except KeyboardInterrupt:
            for item in active.values():
                item.process.terminate()
            for item in active.values():
                try:
                    item.process.wait(timeout=15)
                except subprocess.TimeoutExpired:
                    item.process.kill()
                item.log.close()
            bar.close()
            write_manifest(self.out_dir, self.ensembles_path, self.all_cases, entries)
            self.echo("generate_data: interrupted; rerun the same command to resume (the "
                      "runs continue from their .partial/ checkpoints)")
            return 130
        bar.close()
        for warning in write_manifest(self.out_dir, self.ensembles_path, self.all_cases,
                                      entries):
            self.echo(f"generate_data: warning: {warning}")
        self.echo(f"generate_data: {n_done}/{n_total} runs complete in "
                  f"{_format_duration(time.perf_counter() - t_start)}; manifest "
                  f"{self.out_dir / MANIFEST_NAME}")
        if failures:
            self.echo(f"generate_data: {len(failures)} run(s) failed: {failures}; see their "
                      f"logs in {self.out_dir / 'logs'}; rerun to retry (they resume)")
            return 1
        return 0

    def finish(self, item: Active, entries: dict[str, Any], write) -> bool:
        """Validate and record a finished process's file; False (with the log's tail) if not."""
        from sgn_jax.experiment_tools import sha256_file

        run = item.run
        wall = time.perf_counter() - item.started
        rc = item.process.returncode
        status = inspect_output(run, self.configs[run.case.name]) if rc == 0 else None
        if status is None or status.kind != "valid":
            why = f"exit status {rc}" if rc != 0 else f"its file is {status.kind}: {status.reason}"
            write(f"FAILED {run.key} after {wall:.0f} s ({why}); log {run.log_path}:\n"
                  f"{_log_tail(run.log_path, item.log_offset)}")
            return False
        entry = file_record(run, status.trajectory, self.configs[run.case.name],
                            sha256_file(run.out_path))
        summary = last_json_line(run.log_path, item.log_offset) or {}
        entry.update({
            "wall_time_s": wall,
            "dem_wall_time_s": summary.get("wall_time_s"),
            "compile_time_s": summary.get("compile_time_s"),
            "steps_per_s": summary.get("steps_per_s"),
            "balls_outside": summary.get("balls_outside"),
            "resumed": item.resumed,
            "core": item.core,
            "log": str(run.log_path),
        })
        entries[run.file_name] = entry
        power = entry["mean_dissipation_power_W"]
        write(f"done  {run.key} in {wall:.0f} s: {entry['total_dissipation_J']:.4g} J "
              f"({power:.4g} W), {entry['mean_pp_contacts']:.1f} ball-ball contacts, "
              f"{entry['regime']}")
        return True


# --------------------------------------------------------------------------------------------
# Command line


def prefix_commands(cases: Iterable[Case], out_dir: Path, seconds: float) -> list[list[str]]:
    """``sgn-jax dem`` commands for the first ``seconds`` of every evaluation run of ``cases``
    whose file ``out_dir/{case}_seed{S}.npz`` does not exist yet."""
    commands = []
    for case in cases:
        for seed in (s for s in case.seeds if s not in case.train_seeds):
            path = out_dir / f"{case.name}_seed{seed}.npz"
            if not path.exists():
                commands.append([
                    *sgn_jax_command(), "dem", "--config", str(case.config_path), "--duration",
                    f"{seconds:g}", "--seed", str(seed), "--out", str(path), "--no-progress"])
    return commands


def run_prefixes(cases: Sequence[Case], out_dir: Path, seconds: float, jobs: int,
                 dry_run: bool = False) -> int:
    """Run :func:`prefix_commands` in ``jobs`` threads; 1 when a run failed, else 0."""
    if not 0 < seconds <= 0.05:
        raise EnsembleError(f"--prefix {seconds}: a prefix of a few ms (0 < SECONDS <= 0.05)")
    out_dir.mkdir(parents=True, exist_ok=True)
    commands = prefix_commands(cases, out_dir, seconds)
    print(f"generate_data: {len(commands)} prefix runs of {seconds:g} s to {out_dir}", flush=True)
    if dry_run:
        for cmd in commands:
            print(shlex.join(cmd))
        return 0

    def run(cmd: list[str]) -> int:
        proc = subprocess.run(cmd, capture_output=True, text=True)
        print(("ok   " if proc.returncode == 0 else "FAIL ") + cmd[-2], flush=True)
        if proc.returncode:
            print(proc.stderr[-2000:], file=sys.stderr)
        return proc.returncode

    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max_workers=max(1, jobs)) as pool:
        codes = list(pool.map(run, commands))
    return 1 if any(codes) else 0


def _short(path: Path) -> Path:
    """``path`` relative to the working directory when it lies below it (shorter commands)."""
    try:
        return path.resolve().relative_to(Path.cwd().resolve())
    except ValueError:
        return path


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="generate_data.py",
        description="Run `sgn-jax dem` for every (case, seed) of the ensembles file that has no "
        "complete file yet (valid files are skipped, corrupt or stale ones redone, interrupted "
        "ones resumed), in --jobs processes pinned to one core each, and keep OUT/manifest.json "
        "up to date.")
    p.add_argument("--ensembles", default=str(_short(DEFAULT_ENSEMBLES)),
                   help="ensembles file (default: experiments/ensembles.toml)")
    p.add_argument("--cases", default=None,
                   help="comma-separated case names (default: all cases of the file)")
    p.add_argument("--split", choices=("all", "train", "eval"), default="all",
                   help="only the training or only the evaluation packings (default: all)")
    p.add_argument("--out", default="data", help="output folder (default: data/)")
    p.add_argument("--jobs", type=int, default=1,
                   help="parallel DEM processes, one per core (default 1)")
    p.add_argument("--prefix", type=float, default=None, metavar="SECONDS",
                   help="only the first SECONDS (0 < SECONDS <= 0.05) of every evaluation run, "
                   "the start records of evaluate_contact.py --dem-reference; no manifest")
    p.add_argument("--dry-run", action="store_true",
                   help="check the existing files and print the commands; run nothing")
    p.add_argument("--no-pin", action="store_true", help="do not pin processes with taskset")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from sgn_jax.api import ConfigError

    try:
        if args.jobs < 1:
            raise EnsembleError(f"--jobs must be >= 1, got {args.jobs}")
        ensembles_path = Path(args.ensembles)
        cases = load_ensembles(ensembles_path)
        selected = select_cases(cases, args.cases)
        if args.prefix is not None:
            return run_prefixes(selected, Path(args.out), args.prefix, args.jobs, args.dry_run)
        generator = Generator(ensembles_path, cases, selected, Path(args.out), args.split,
                              args.jobs, pin=not args.no_pin,
                              progress=not args.no_progress and not args.dry_run)
    except (EnsembleError, ConfigError) as exc:
        print(f"generate_data: error: {exc}", file=sys.stderr)
        return 2
    if args.jobs > len(generator.cores):
        print(f"generate_data: warning: {args.jobs} jobs on {len(generator.cores)} core(s): "
              "processes will share cores", file=sys.stderr)
    todo, entries = generator.scan(dry_run=args.dry_run)
    work = sum(generator.work_of(run) - status.partial_sim_s for run, status in todo)
    low, high = (work * rate / 60.0 for rate in WALL_PER_SIM_SECOND_RANGE)
    print(f"generate_data: {len(generator.runs)} runs selected, {len(todo)} to do "
          f"({work:g} simulated s incl. settling: ~{low:.0f}-{high:.0f} core-minutes, "
          f"~{low / args.jobs:.0f}-{high / args.jobs:.0f} min with {args.jobs} job(s))"
          f"{generator.pin_note}")
    if args.dry_run:
        for slot, (run, _) in enumerate(todo):
            cmd, _core = generator.command(run, slot % args.jobs)
            print(shlex.join(cmd))
        return 0
    if not todo:
        for warning in write_manifest(generator.out_dir, ensembles_path, generator.all_cases,
                                      entries):
            print(f"generate_data: warning: {warning}")
        print(f"generate_data: nothing to do; manifest {generator.out_dir / MANIFEST_NAME}")
        return 0
    return generator.execute(todo, entries)


if __name__ == "__main__":
    sys.exit(main())
