"""The tools of experiments/tools/ (run_experiments.py, results_table.py, evaluate_contact.py,
generate_data.py's prefixes) and the reproduce folders: the rollout length a DEM file covers, an
end-to-end run of the shipped model on a tiny two-packing ensemble (DEM -> rollouts -> evaluation
-> results.json -> markdown table), the contact evaluation's bars, and that every reproduce
folder states its command, its expected numbers and its time."""

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
TOOLS = ROOT / "experiments" / "tools"
REPRODUCE = ROOT / "experiments" / "reproduce"


def _load(name: str):
    spec = importlib.util.spec_from_file_location(name, TOOLS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


gd = _load("generate_data")
rx = _load("run_experiments")
rt = _load("results_table")
ec = _load("evaluate_contact")


def test_rollout_duration_is_whole_blocks_the_reference_covers(tmp_path):
    path = tmp_path / "ref.npz"
    np.savez(path, t=np.arange(0, 1001) * 1e-4)  # 0 .. 0.1 s
    # from sample 7 (0.7 ms) there are 99.3 ms: 9 blocks of 10 steps of 0.1 ms
    assert rx.rollout_duration(path, 7, 1e-4, 10) == pytest.approx(0.099)
    assert rx.rollout_duration(path, 0, 1e-4, 10) == pytest.approx(0.1)
    np.savez(path, t=np.arange(0, 12) * 1e-4)
    with pytest.raises(rx.ExperimentError, match="covers only"):
        rx.rollout_duration(path, 7, 1e-4, 10)


def test_prefix_commands_cover_only_the_missing_evaluation_runs(tmp_path):
    """``generate_data.py --prefix``: one ``sgn-jax dem`` of the prefix's duration per evaluation
    seed (training seeds are never evaluated), none for a file already there."""
    ensembles = tmp_path / "ensembles.toml"
    ensembles.write_text('[cases.tiny]\nconfig = "tiny.toml"\nduration = 1.0\n'
                         "seeds = [0, 5, 6]\ntrain_seeds = [0]\n")
    save_config(load_config(builtin_config_path("emax_300rpm")), tmp_path / "tiny.toml")
    cases = gd.load_ensembles(ensembles)
    out = tmp_path / "prefix"
    out.mkdir()
    (out / "tiny_seed6.npz").write_bytes(b"")
    commands = gd.prefix_commands(cases.values(), out, 0.002)
    assert len(commands) == 1
    cmd = commands[0]
    assert cmd[cmd.index("--seed") + 1] == "5"
    assert cmd[cmd.index("--duration") + 1] == "0.002"
    assert cmd[cmd.index("--out") + 1] == str(out / "tiny_seed5.npz")
    with pytest.raises(gd.EnsembleError, match="prefix"):
        gd.run_prefixes(list(cases.values()), out, 1.0, 1)


def _summary(case, **changes):
    base = {"case": case, "power_error": 0.0, "power_bar": 0.10, "speed_error": 0.0,
            "pp_touching_error": 0.0, "pw_touching_error": 0.0, "deepest_pp_overlap_m": 1e-4,
            "snapped_fraction": 0.0, "outside_ball_steps": 0, "non_finite_runs": 0}
    return base | changes


def test_contact_bars_name_each_miss():
    """The bars of ``evaluate_contact.py``: the case's power bar (15 % Motion 1 and 2, 20 % the
    post jar, max(5 %, 2 SE) the standard case, the summary's max(10 %, 2 SE) elsewhere), speed
    15 %, contacts 25 %, overlap 0.5 mm, snapped 1 %, nothing outside."""
    assert ec.power_bar("motion2", 0.3) == 0.15
    assert ec.power_bar("post_motion1", 0.1) == 0.20
    assert ec.power_bar("standard", 0.03) == 0.05 and ec.power_bar("standard", 0.2) == 0.2
    assert ec.power_bar("heldout_c00", 0.13) == 0.13
    assert ec.misses(_summary("heldout_c00")) == []
    assert ec.misses(_summary("motion1", power_error=0.14)) == []
    assert ec.misses(_summary("motion1", power_error=-0.16)) == ["power -16.0% (bar 15%)"]
    missed = ec.misses(_summary("heldout_h01", speed_error=0.2, pw_touching_error=-0.3,
                                deepest_pp_overlap_m=6e-4, outside_ball_steps=3))
    assert missed == ["speed +20.0%", "pw contacts -30.0%", "overlap 0.60 mm",
                      "outside or non-finite"]
    table = ec.bars_table([_summary("fresh_h46", power_error=0.2)])
    assert "| fresh_h46 | +20.0% (10%) |" in table and "power +20.0% (bar 10%)" in table


def test_the_shipped_contact_models_expected_numbers_meet_its_bars():
    """The committed held-out results of the shipped contact model (the expected numbers of
    experiments/reproduce/contact_heldout) meet every bar, as docs/results.md states."""
    expected = REPRODUCE / "contact_heldout" / "expected"
    for part in ("heldout", "unseen", "standard", "fresh", "heldout_sepon", "unseen_sepon"):
        summaries = json.loads((expected / f"{part}.json").read_text())["summaries"]
        assert summaries, part
        for summary in summaries:
            assert ec.misses(summary) == [], (part, summary["case"])


def test_every_reproduce_folder_states_command_expected_numbers_and_time():
    """Each folder of experiments/reproduce has a README.md with one command (a fenced block),
    the expected numbers and the time it takes; the scripts and files it names exist."""
    folders = sorted(p for p in REPRODUCE.iterdir() if p.is_dir())
    assert len(folders) >= 5
    for folder in folders:
        readme = (folder / "README.md").read_text()
        assert "```" in readme and "## Expected" in readme and "## Time" in readme, folder.name
        for token in readme.replace("`", " ").split():
            if token.startswith("experiments/") and token.endswith((".py", ".sh", ".toml")):
                assert (ROOT / token).is_file(), (folder.name, token)
        run = folder / "run.sh"
        if run.exists():
            for token in run.read_text().split():
                if token.startswith("experiments/") and token.endswith((".py", ".toml", ".jsonl")):
                    assert (ROOT / token.strip("\"'")).is_file(), (folder.name, token)


# The slow tier (32-34 s of subprocesses, too long for the default run). The default run keeps generate_data's records, skips and redos (tests/test_generate_data.py) and
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
    # One job at a time: the second DEM and the second rollout load the first one's
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


def test_with_model_keys_changes_a_built_in_setting_and_keeps_the_weights():
    """An evaluation's ``--model-set friction_sweeps=12``: the same weights, the module rebuilt
    with the new [model] key; a malformed assignment is a clear error."""
    import sgn_jax.experiment_tools as tools

    trained = tools.load_trained_model(tools.resolve_checkpoint("contact_charge"))
    varied = tools.with_model_keys(trained, ["friction_sweeps=12", "overlap_sweeps = 4"])
    assert varied.model.physics.friction_sweeps == 12
    assert varied.model.physics.overlap_sweeps == 4
    assert trained.model.physics.friction_sweeps == 6          # the original is untouched
    assert varied.params is trained.params
    assert tools.with_model_keys(trained, []) is trained
    with pytest.raises(SystemExit, match="KEY=VALUE"):
        tools.with_model_keys(trained, ["friction_sweeps"])
    with pytest.raises(SystemExit, match="TOML value"):
        tools.with_model_keys(trained, ["law_rebound_exact=wall"])
