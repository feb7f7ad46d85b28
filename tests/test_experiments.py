"""experiments/run_experiments.py, results_table.py and sensitivity.py: the rollout length a
DEM file covers, the sensitivity configs, and an end-to-end run of the shipped model on a tiny
two-packing ensemble (DEM -> rollouts -> evaluation -> results.json -> markdown table)."""

from __future__ import annotations

import importlib.util
import json
import shlex
import sys
from pathlib import Path

import numpy as np
import pytest

import sgn_jax  # noqa: F401  (x64)
from sgn_jax.config import builtin_config_path, load_config, replace_section, save_config
from sgn_jax.records.shipped_models import shipped_model_dir

ROOT = Path(__file__).resolve().parents[1]


def _load(name: str):
    spec = importlib.util.spec_from_file_location(name, ROOT / "experiments" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


gd = _load("generate_data")
rx = _load("run_experiments")
rt = _load("results_table")
sens = _load("sensitivity")


def test_rollout_duration_is_whole_blocks_the_reference_covers(tmp_path):
    path = tmp_path / "ref.npz"
    np.savez(path, t=np.arange(0, 1001) * 1e-4)  # 0 .. 0.1 s
    # from sample 7 (0.7 ms) there are 99.3 ms: 9 blocks of 10 steps of 0.1 ms
    assert rx.rollout_duration(path, 7, 1e-4, 10) == pytest.approx(0.099)
    assert rx.rollout_duration(path, 0, 1e-4, 10) == pytest.approx(0.1)
    np.savez(path, t=np.arange(0, 12) * 1e-4)
    with pytest.raises(rx.ExperimentError, match="covers only"):
        rx.rollout_duration(path, 7, 1e-4, 10)


def test_sensitivity_variants_change_only_what_they_declare(tmp_path):
    base = ROOT / "experiments" / "configs" / "emax_300rpm.toml"
    reference = load_config(sens.variant_config("baseline", base, tmp_path, 3))
    assert reference.train.epochs == 3
    for name, changes in sens.VARIANTS.items():
        cfg = load_config(sens.variant_config(name, base, tmp_path, 3))
        for section in ("graph", "model", "train", "rollout", "jar", "motion"):
            got, want = getattr(cfg, section), getattr(reference, section)
            declared = changes.get(section, {})
            for field, value in declared.items():
                assert getattr(got, field) == value, (name, section, field)
            for field in type(want).__dataclass_fields__:
                if field not in declared:
                    assert getattr(got, field) == getattr(want, field), (name, section, field)
        assert name in sens.PAPER
    # the phi_pw variants keep phi_sb 0.3 mm above phi_pw, as the paper did
    for name in ("phi_pw_-0.0049", "phi_pw_-0.0055"):
        g = sens.VARIANTS[name]["graph"]
        assert g["phi_sb"] - g["phi_pw"] == pytest.approx(0.0003)


# The slow tier (session 7, the default run's 6 minutes: 32-34 s of subprocesses). The default
# run keeps generate_data's records, skips and redos (tests/test_generate_data.py) and
# run_experiments' scheduler with its logs and exit statuses (below); the rollouts, results
# and report of a whole run are checked here only.
@pytest.mark.slow
@pytest.mark.skipif(not (shipped_model_dir("emax_300rpm") / "PROVENANCE.json").is_file(),
                    reason="no shipped model")
def test_experiments_end_to_end_on_a_tiny_ensemble(tmp_path, capsys):
    cfg = load_config(builtin_config_path("emax_300rpm"))
    cfg = replace_section(cfg, "dem", settle_time=0.002, chunk_samples=10)
    save_config(cfg, tmp_path / "tiny.toml")
    ensembles = tmp_path / "ensembles.toml"
    ensembles.write_text('[cases.tiny]\nconfig = "tiny.toml"\nduration = 0.005\n'
                         "seeds = [0, 5, 6]\ntrain_seeds = [0]\n")
    data = tmp_path / "data"
    # One job at a time (issue 20): the second DEM and the second rollout load the first one's
    # compiled programs from the session's cache instead of compiling the same programs at the
    # same time. Two parallel jobs are checked by tests/test_generate_data.py (generate_data)
    # and by test_run_pinned_runs_jobs_side_by_side_each_with_its_log below (run_experiments).
    assert gd.main(["--ensembles", str(ensembles), "--out", str(data), "--split", "eval",
                    "--jobs", "1", "--no-progress", "--no-pin"]) == 0
    args = ["--model", str(shipped_model_dir("emax_300rpm")), "--name", "tiny_run", "--ensembles",
            str(ensembles), "--data", str(data), "--out-root", str(tmp_path / "runs"),
            "--jobs", "1", "--skip-runtime", "--no-pin"]
    assert rx.main(args) == 0
    out = tmp_path / "runs" / "tiny_run"
    results = json.loads((out / "results.json").read_text())
    assert results["failed"] == []
    case = results["cases"]["tiny"]
    assert [r["seed"] for r in case["runs"]] == [5, 6]  # held-out seeds only
    for run in case["runs"]:
        # 5 ms of DEM from the first window (sample 7): 4 blocks of 10 steps
        pred = np.load(out / "rollouts" / f"tiny_seed{run['seed']}.npz")
        assert pred["t_step"].shape == (40,)
        assert run["mse_plateau_m2"] is not None and run["mse_plateau_m2"] >= 0
        assert run["energy_ref_J"] >= 0 and run["ms_per_step"] > 0
        if run["energy_ref_J"] > 0:  # a packing at rest in these 5 ms dissipates nothing
            expected = abs(run["energy_pred_J"] - run["energy_ref_J"]) / run["energy_ref_J"]
            assert run["energy_relative_error_final"] == pytest.approx(expected, rel=1e-9)
    assert case["ensemble"]["n_runs"] == 2
    assert case["ensemble"]["states"]["classify_by"] == "speed"
    assert Path(case["curves_plot"]).stat().st_size > 10_000
    markdown = rt.table(results)
    row = next(line for line in markdown.splitlines() if line.startswith("| tiny |"))
    signed = np.mean([(r["energy_pred_J"] - r["energy_ref_J"]) / r["energy_ref_J"]
                      for r in case["runs"] if r["energy_ref_J"] > 0])
    assert f"{100 * signed:+.1f} %" in row

    # a rerun skips the finished rollouts and rebuilds the summary
    capsys.readouterr()
    assert rx.main(args) == 0
    printed = capsys.readouterr().out
    assert printed.count("skip  tiny_seed") == 2 and "start tiny_seed" not in printed


def test_run_pinned_runs_jobs_side_by_side_each_with_its_log(tmp_path, monkeypatch, capsys):
    """run_experiments' scheduler with two slots: two jobs run at the same time (the first
    waits for a file only the second writes), a third starts when a slot frees, each job's
    output goes to its own log after its command line, and exit statuses come back by name."""
    monkeypatch.setattr(rx, "usable_cores", lambda: [0, 1])   # two slots on any machine
    monkeypatch.setattr(rx, "POLL_S", 0.05)
    flag = tmp_path / "second_started"
    waits = ("import pathlib, sys, time\n"
             f"flag = pathlib.Path({str(flag)!r})\n"
             "deadline = time.time() + 60\n"
             "while not flag.exists() and time.time() < deadline:\n"
             "    time.sleep(0.02)\n"
             "print('first saw the second:', flag.exists())\n"
             "sys.exit(0 if flag.exists() else 4)\n")
    writes = f"import pathlib; pathlib.Path({str(flag)!r}).write_text('x'); print('second')"
    jobs = [("first", [sys.executable, "-c", waits], tmp_path / "logs" / "first.log"),
            ("second", [sys.executable, "-c", writes], tmp_path / "logs" / "second.log"),
            ("third", [sys.executable, "-c", "import sys; print('third'); sys.exit(3)"],
             tmp_path / "logs" / "third.log")]
    status = rx.run_pinned(jobs, 2, pin=False)
    assert status == {"first": 0, "second": 0, "third": 3}
    for name, argv, log in jobs:
        header = "$ " + shlex.join(argv) + "\n"
        expected = {"first": "first saw the second: True", "second": "second",
                    "third": "third"}[name]
        assert log.read_text() == header + expected + "\n"
    printed = capsys.readouterr().out
    assert "start first on core 0" in printed and "start second on core 1" in printed
    assert "FAILED third (exit 3" in printed
