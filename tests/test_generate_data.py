"""experiments/tools/generate_data.py: the ensembles files, the plan, and an end-to-end run of a
tiny ensemble (2 seeds, 5 ms of motion, 2 ms of settling): files, manifest, skip, redo."""

from __future__ import annotations

import importlib.util
import json
import re
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

import sgn_jax.regime
from sgn_jax.analysis.metrics import BED_PAIRS_PER_BALL, pairs_within
from sgn_jax.config import builtin_config_path, load_config, replace_section, save_config
from sgn_jax.records.io_utils import sha256_file
from sgn_jax.records.trajectory import Trajectory, load_trajectory

ROOT = Path(__file__).resolve().parents[1]
DURATION = 0.005  # s of motion: 51 samples


def _load_generator():
    spec = importlib.util.spec_from_file_location(
        "generate_data", ROOT / "experiments" / "tools" / "generate_data.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["generate_data"] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


gd = _load_generator()


# --------------------------------------------------------------------------------------------
# The shipped ensembles file


def test_the_contact_models_training_ensembles_write_the_files_its_config_reads(tmp_path):
    """The training records of the shipped contact model: experiments/contact/training_runs.toml
    (55 envelope runs), experiments/contact/kicks.toml (12 kicked beds) and
    experiments/envelope/corners.toml (12 corner runs) write, with ``--split train``, exactly the
    files that sgn_jax/configs/contact_train.toml's record globs name."""
    import fnmatch

    globs = {"training_runs": ("contact", "envelope", "train_*.npz", 55),
             "kicks": ("contact", "kicks", "kick_still_*_seed3[012]0[0-3].npz", 12),
             "corners": ("envelope", "corners", "corner_*.npz", 12)}
    for name, (folder, out, pattern, count) in globs.items():
        cases = gd.load_ensembles(ROOT / "experiments" / folder / f"{name}.toml")
        runs = gd.plan_runs(cases.values(), tmp_path / out, "train")
        assert len(runs) == count, name
        assert all(fnmatch.fnmatch(run.file_name, pattern) for run in runs), name
        assert all(run.case.config_path.is_file() for run in runs), name


def test_the_paper_ensembles_hold_the_cases_and_splits_of_the_protocol():
    cases = gd.load_ensembles(ROOT / "experiments" / "ensembles.toml")
    assert list(cases) == ["standard", "motion1", "motion2", "post_motion1"]
    standard = cases["standard"]
    assert standard.duration == 10.0
    assert len(standard.eval_seeds) >= 8 and len(standard.train_seeds) >= 2
    assert set(standard.train_seeds).isdisjoint(standard.eval_seeds)
    for name in ("motion1", "motion2", "post_motion1"):
        case = cases[name]
        assert case.duration == 5.0 and case.train_seeds == ()
        assert len(case.eval_seeds) >= 8
        # evaluation packings are never the standard case's training packings
        assert set(case.eval_seeds).isdisjoint(standard.train_seeds)
    configs = {name: load_config(case.config_path) for name, case in cases.items()}
    assert configs["standard"].motion.kind == "circle" and configs["standard"].motion.rpm == 300
    assert configs["standard"].jar.post_radius == 0.0
    assert configs["motion1"].motion.x_cos == (0.0, -0.0085)
    assert configs["motion2"].motion.z_cos == (0.0, 0.017)
    assert configs["post_motion1"].jar.post_radius == 0.006
    assert configs["post_motion1"].motion == configs["motion1"].motion


def _write_ensembles(folder: Path, body: str) -> Path:
    path = folder / "ensembles.toml"
    path.write_text(body)
    return path


@pytest.mark.parametrize("body, message", [
    ('[cases.a]\nconfig = "emax_300rpm"\nduration = 1.0\nseeds = [0, 1]\ntrain_seeds = [2]\n',
     "train_seeds [2] are not in seeds"),
    ('[cases.a]\nconfig = "emax_300rpm"\nduration = 1.0\nseeds = [0, 1, 1]\n',
     "more than once"),
    ('[cases.a]\nconfig = "emax_300rpm"\nduration = 0\nseeds = [0]\n', "duration must be"),
    ('[cases.a]\nconfig = "emax_300rpm"\nduraton = 1.0\nseeds = [0]\n', "unknown key"),
    ('[cases.a]\nconfig = "nope.toml"\nduration = 1.0\nseeds = [0]\n', "does not exist"),
    ('[cases.a]\nconfig = "no_such_config"\nduration = 1.0\nseeds = [0]\n',
     "no built-in config"),
    ('[cases."a b"]\nconfig = "emax_300rpm"\nduration = 1.0\nseeds = [0]\n', "case name"),
    ('[cases.a]\nconfig = "emax_300rpm"\nduration = 1.0\nseeds = [-1]\n', "integers >= 0"),
    ('title = "x"\n', "unknown top-level"),
])
def test_bad_ensembles_files_are_refused(tmp_path, body, message):
    with pytest.raises(gd.EnsembleError, match=re.escape(message)):
        gd.load_ensembles(_write_ensembles(tmp_path, body))


def test_unknown_case_and_bad_jobs_exit_2(tmp_path, capsys):
    ensembles = str(ROOT / "experiments" / "ensembles.toml")
    assert gd.main(["--ensembles", ensembles, "--cases", "standard,nope", "--dry-run"]) == 2
    assert "unknown case(s) ['nope']" in capsys.readouterr().err
    assert gd.main(["--ensembles", ensembles, "--jobs", "0", "--dry-run"]) == 2


def test_plan_selects_splits():
    cases = gd.load_ensembles(ROOT / "experiments" / "ensembles.toml")
    train = gd.plan_runs(cases.values(), "data", "train")
    assert [(r.case.name, r.seed) for r in train] == [("standard", s)
                                                       for s in cases["standard"].train_seeds]
    evaluation = gd.plan_runs(cases.values(), "data", "eval")
    assert all(r.split == "eval" for r in evaluation)
    assert len(train) + len(evaluation) == len(gd.plan_runs(cases.values(), "data"))
    assert str(evaluation[0].out_path) == f"data/standard_seed{cases['standard'].eval_seeds[0]}.npz"


# --------------------------------------------------------------------------------------------
# A tiny ensemble, end to end


@pytest.fixture
def tiny(tmp_path):
    """A 2-seed ensemble of the standard case with 2 ms of settling and 5 ms of motion, chunks
    of 10 samples (one compilation per run)."""
    cfg = load_config(builtin_config_path("emax_300rpm"))
    cfg = replace_section(cfg, "dem", settle_time=0.002, chunk_samples=10)
    save_config(cfg, tmp_path / "tiny.toml")
    ensembles = _write_ensembles(tmp_path, (
        '[cases.tiny]\nconfig = "tiny.toml"\n'
        f"duration = {DURATION}\nseeds = [0, 1]\ntrain_seeds = [0]\n"))
    return {"cfg": cfg, "ensembles": ensembles, "out": tmp_path / "data"}


def _args(tiny, *extra):
    return ["--ensembles", str(tiny["ensembles"]), "--out", str(tiny["out"]), "--jobs", "2",
            "--no-progress", *extra]


def _launches(log: Path) -> int:
    """Processes started for a run: one '# time command' header line each."""
    return sum(line.startswith("# ") for line in log.read_text().splitlines())


def test_dry_run_prints_the_commands_and_runs_nothing(tiny, capsys):
    assert gd.main(_args(tiny, "--dry-run")) == 0
    out = capsys.readouterr().out
    commands = [line for line in out.splitlines() if " dem --config " in line]
    assert len(commands) == 2
    for seed, command in enumerate(commands):
        assert f"--seed {seed} " in command and f"tiny_seed{seed}.npz" in command
        assert f"--duration {DURATION!r}" in command
        if shutil.which("taskset"):
            cores = gd.usable_cores()   # two jobs, one per usable core (one core: both on it)
            assert command.startswith(f"taskset -c {cores[seed % len(cores)]} ")
    assert not tiny["out"].exists()


# The slow tier (`pytest -m slow`; the default run's time): three DEM runs in subprocesses; the ensembles file's validation stays in the default run.
@pytest.mark.slow
def test_generates_records_skips_and_redoes(tiny, capsys, monkeypatch):
    out, cfg = tiny["out"], tiny["cfg"]
    assert gd.main(_args(tiny)) == 0
    files = [out / f"tiny_seed{seed}.npz" for seed in (0, 1)]
    logs = [out / "logs" / f"tiny_seed{seed}.log" for seed in (0, 1)]
    manifest = json.loads((out / "manifest.json").read_text())
    entries = {entry["seed"]: entry for entry in manifest["runs"]}
    assert sorted(entries) == [0, 1]
    for seed, (path, log) in enumerate(zip(files, logs, strict=True)):
        traj = load_trajectory(path)
        entry = entries[seed]
        assert traj.meta["seed"] == seed and traj.n_samples == 51
        assert entry["file"] == path.name and entry["case"] == "tiny"
        assert entry["split"] == ("train" if seed == 0 else "eval")
        assert entry["sha256"] == sha256_file(path)
        assert entry["duration_s"] == pytest.approx(DURATION, rel=1e-12)
        assert entry["wall_time_s"] > 0 and not entry["resumed"]
        # the DEM's own summary line (in the log) and the file agree with the manifest
        summary = json.loads(log.read_text().splitlines()[-1])
        assert entry["total_dissipation_J"] == pytest.approx(summary["total_dissipation_J"],
                                                             rel=1e-9)
        assert entry["total_dissipation_J"] > 0
        assert entry["mean_pp_contacts"] == pytest.approx(summary["mean_pp_contacts"],
                                                          rel=1e-12)
        assert entry["balls_outside"] == 0
        contacts = summary["mean_pp_contacts"] / 24
        assert entry["regime"] == ("bed" if contacts >= 14 / 24 else "agitated")
        assert len(entry["regime_windows"]) == 1  # 5 ms: one window
        pairs = pairs_within(traj.pos, 2 * 0.005 + cfg.graph.pp_skin).mean() / 24
        assert entry["pp_pairs_within_skin_per_ball"] == pytest.approx(pairs, rel=1e-12)
        assert entry["regime_evaluate_rule"] == ("bed" if pairs >= BED_PAIRS_PER_BALL
                                                 else "agitated")
        assert _launches(log) == 1
    summary = manifest["cases"]["tiny"]
    assert summary["train"]["complete"] == 1 and summary["eval"]["complete"] == 1
    assert summary["train"]["seeds"] == [0] and summary["eval"]["seeds"] == [1]
    assert not any(p.name.endswith(".partial") for p in out.iterdir())

    # A second invocation validates both files and runs nothing.
    mtimes = [p.stat().st_mtime_ns for p in files]
    capsys.readouterr()
    assert gd.main(_args(tiny)) == 0
    printed = capsys.readouterr().out
    assert printed.count("skip  tiny_seed") == 2 and "nothing to do" in printed
    assert [p.stat().st_mtime_ns for p in files] == mtimes
    assert [_launches(log) for log in logs] == [1, 1]
    again = {e["seed"]: e for e in json.loads((out / "manifest.json").read_text())["runs"]}
    assert again == entries  # kept as recorded, wall times included

    # A corrupted file is redone; the good one is left alone.
    data = files[1].read_bytes()
    files[1].write_bytes(data[: len(data) // 2])
    assert gd.main(_args(tiny)) == 0
    printed = capsys.readouterr().out
    assert "redo  tiny_seed1: corrupt" in printed
    assert [_launches(log) for log in logs] == [1, 2]
    assert files[0].stat().st_mtime_ns == mtimes[0]
    redone = {e["seed"]: e for e in json.loads((out / "manifest.json").read_text())["runs"]}
    load_trajectory(files[1])
    assert redone[1]["sha256"] == sha256_file(files[1])
    assert redone[0] == entries[0]
    # the DEM is deterministic: the redone run has the same physics
    assert redone[1]["total_dissipation_J"] == pytest.approx(entries[1]["total_dissipation_J"],
                                                             rel=1e-12)

    # Stale files: a different duration or DEM config is not the run asked for; a change in
    # the SGN sections ([graph], [train]) does not touch the DEM data.
    case = gd.load_ensembles(tiny["ensembles"])["tiny"]
    run = gd.Run(case=case, seed=0, out_dir=out)
    assert gd.inspect_output(run, cfg).kind == "valid"
    longer = gd.Run(case=gd.dataclasses.replace(case, duration=0.004), seed=0, out_dir=out)
    status = gd.inspect_output(longer, cfg)
    assert status.kind == "stale" and "41" in status.reason
    other = replace_section(cfg, "material", restitution=0.5)
    status = gd.inspect_output(run, other)
    assert status.kind == "stale" and "material.restitution" in status.reason
    retrained = replace_section(replace_section(cfg, "train", epochs=99), "graph", pp_skin=0.002)
    assert gd.inspect_output(run, retrained).kind == "valid"

    # The regime per window follows the DEM contact count: a run that switches shows it.
    traj = load_trajectory(files[0])
    pairs = np.full_like(np.asarray(traj.pp_pairs), -1)
    switch = 26  # samples 1-25: 20 contacts (bed), 26-50: 5 (agitated)
    pairs[1:switch, :20] = (0, 1)
    pairs[switch:, :5] = (0, 1)
    switched = Trajectory(arrays={**traj.arrays, "pp_pairs": pairs}, meta=traj.meta)
    monkeypatch.setattr(sgn_jax.regime, "REGIME_WINDOW_S", DURATION / 2)  # moved there
    entry = gd.file_record(run, switched, cfg, "0" * 64)
    assert entry["regime_windows"] == ["bed", "agitated"]
    assert entry["mean_pp_contacts"] == pytest.approx((25 * 20 + 25 * 5) / 51)
    assert entry["regime"] == "agitated"  # 12.3 contacts < 14


def test_partial_checkpoints_count_as_progress(tiny):
    cfg = tiny["cfg"]
    case = gd.load_ensembles(tiny["ensembles"])["tiny"]
    run = gd.Run(case=case, seed=0, out_dir=tiny["out"])
    assert gd.inspect_output(run, cfg).kind == "missing"
    folder = tiny["out"] / "tiny_seed0.npz.partial"
    folder.mkdir(parents=True)
    (folder / "state.npz").write_bytes(b"")
    assert gd.inspect_output(run, cfg).kind == "missing"  # still settling: nothing saved yet
    for chunk in range(3):  # the settled state, then two chunks of 10 samples
        (folder / f"chunk_{chunk:05d}.npz").write_bytes(b"")
    status = gd.inspect_output(run, cfg)
    assert status.kind == "partial"
    assert status.partial_sim_s == pytest.approx(0.002 + 2 * 10 * 1e-4)
