"""Staged training of the contact model (``[[train.stages]]``, ``sgn-jax train --config``):
the stages run in order, each warm-started from the one before, their record globs are
checked before any work, and a killed run goes on where it stopped."""

import json

import numpy as np
import pytest

import sgn_jax.api as sj
from sgn_jax.config import ConfigError, TrainStage, resolve_config
from sgn_jax.pipelines.contact_train_run import stage_records, stage_start, train_stages
from sgn_jax.surrogate.train import TrainingError
from sgn_jax.testing import synthetic_trajectory


def staged_config(*stages: TrainStage):
    cfg = sj.load_config("emax_300rpm")
    cfg = sj.replace_section(cfg, "balls", count=6)
    cfg = sj.replace_section(cfg, "graph", window=3, wall_patches=4, pp_edges_per_particle=4)
    cfg = sj.replace_section(cfg, "model", kind="contact", hidden=8, mlp_layers=2)
    return sj.replace_section(cfg, "train", envelope="default", stages=tuple(stages))


def stage(name, records, **kw):
    args = dict(steps=2, unroll=2, lr_init=1e-3, lr_final=1e-4, batch_size=2,
                checkpoint_every=1)
    return TrainStage(name=name, records=tuple(records), **{**args, **kw})


@pytest.fixture
def data_dir(tmp_path):
    """Three record files; their contents come from ``load`` (synthetic trajectories)."""
    root = tmp_path / "data"
    for sub, name in (("a", "r1.npz"), ("a", "r2.npz"), ("b", "r3.npz")):
        (root / sub).mkdir(parents=True, exist_ok=True)
        (root / sub / name).write_bytes(b"")
    return root


def load_synthetic(path):
    return synthetic_trajectory(40, 6, seed=int(path.stem[1:]))


# The slow tier (`pytest -m slow`; the default run's time): three training stages; the stage config's validation stays in the default run.
@pytest.mark.slow
def test_stages_run_in_order_each_from_the_last(tmp_path, data_dir):
    cfg = staged_config(stage("first", ["a/*.npz"]),
                        stage("second", ["a/*.npz", "b/*.npz"], unroll=3, pushforward=True))
    out = tmp_path / "run"
    summary = train_stages(cfg, data_dir, out, progress=False, load=load_synthetic,
                           log=lambda _: None)
    assert [s["name"] for s in summary["stages"]] == ["first", "second"]
    assert [s["n_records"] for s in summary["stages"]] == [2, 3]
    assert summary["model"] == str(out / "second" / "checkpoints" / "best")
    first = json.loads((out / "first" / "run_info.json").read_text())
    second = json.loads((out / "second" / "run_info.json").read_text())
    assert first["init_from"] is None
    assert second["init_from"] == str(out / "first" / "checkpoints" / "best")
    assert (second["unroll"], second["pushforward"]) == (3, True)
    model = sj.load_surrogate(summary["model"])
    assert model.config.model.kind == "contact"
    assert json.loads((out / "summary.json").read_text())["model"] == summary["model"]

    # a second run into the same folder needs --resume; with it, finished stages are skipped
    with pytest.raises(TrainingError, match="resume"):
        train_stages(cfg, data_dir, out, progress=False, load=load_synthetic, log=lambda _: None)
    lines = []
    again = train_stages(cfg, data_dir, out, resume=True, progress=False, load=load_synthetic,
                         log=lines.append)
    assert sum("done, skipped" in line for line in lines) == 2
    assert again["model"] == summary["model"]


@pytest.mark.slow
def test_a_killed_staged_run_resumes_in_its_stage(tmp_path, data_dir):
    cfg = staged_config(stage("first", ["a/*.npz"]), stage("second", ["a/r1.npz"]))

    class Killed(Exception):
        pass

    def kill_in_second_stage(line):
        if line.startswith("stage 2/2"):
            seen.append(line)
        if seen and '"step": 1' in line:
            raise Killed

    seen: list[str] = []
    with pytest.raises(Killed):
        train_stages(cfg, data_dir, tmp_path / "run", progress=False, load=load_synthetic,
                     log=kill_in_second_stage)
    lines: list[str] = []
    summary = train_stages(cfg, data_dir, tmp_path / "run", resume=True, progress=False,
                           load=load_synthetic, log=lines.append)
    assert any("first: done, skipped" in line for line in lines)
    assert any("resuming" in line for line in lines)
    assert [s["steps"] for s in summary["stages"]] == [2, 2]
    metrics = (tmp_path / "run" / "second" / "metrics.csv").read_text().splitlines()
    assert [r.split(",")[0] for r in metrics[1:]] == ["1", "2"]
    assert all(np.isfinite(float(r.split(",")[1])) for r in metrics[1:])


def test_a_pattern_without_records_is_refused_before_any_work(tmp_path, data_dir):
    cfg = staged_config(stage("first", ["a/*.npz"]), stage("second", ["missing/*.npz"]))
    with pytest.raises(TrainingError, match="missing/\\*.npz"):
        train_stages(cfg, data_dir, tmp_path / "run", progress=False, load=load_synthetic,
                     log=lambda _: None)
    assert not (tmp_path / "run").exists()
    assert [p.name for p in stage_records(data_dir, ["b/*.npz", "a/*.npz", "a/r1.npz"])] == [
        "r3.npz", "r1.npz", "r2.npz"]


@pytest.mark.slow
def test_a_stage_starts_from_the_checkpoint_it_names(tmp_path, data_dir):
    """``init_from``: a fine-tuning stage starts from a training run's best checkpoint (or a
    shipped model's)."""
    base = tmp_path / "base"
    train_stages(staged_config(stage("first", ["a/*.npz"])), data_dir, base, progress=False,
                 load=load_synthetic, log=lambda _: None)
    out = tmp_path / "tuned"
    train_stages(staged_config(stage("tune", ["b/*.npz"], init_from=str(base / "first"))),
                 data_dir, out, progress=False, load=load_synthetic, log=lambda _: None)
    info = json.loads((out / "tune" / "run_info.json").read_text())
    assert info["init_from"] == str(base / "first" / "checkpoints" / "best")


def test_a_stage_that_starts_from_nothing_is_refused_before_any_work(tmp_path, data_dir):
    missing = staged_config(stage("tune", ["b/*.npz"], init_from=str(tmp_path / "nothing")))
    with pytest.raises(TrainingError, match="init_from"):
        train_stages(missing, data_dir, tmp_path / "never", progress=False,
                     load=load_synthetic, log=lambda _: None)
    assert not (tmp_path / "never").exists()
    assert stage_start("contact").is_dir()          # a shipped model's name


def test_stage_settings_are_checked():
    with pytest.raises(ConfigError, match="schedule_steps"):
        stage("s", ["a/*.npz"], steps=10, schedule_steps=5)
    with pytest.raises(ConfigError, match="lr_final"):
        stage("s", ["a/*.npz"], lr_init=1e-4, lr_final=1e-3)
    with pytest.raises(ConfigError, match="name"):
        stage("a b", ["a/*.npz"])
    with pytest.raises(ConfigError, match="records"):
        stage("s", [])
    with pytest.raises(ConfigError, match="names must differ"):
        staged_config(stage("s", ["a"]), stage("s", ["b"]))
    sgn = sj.load_config("emax_300rpm")
    with pytest.raises(ConfigError, match="kind = 'contact'"):
        sj.replace_section(sgn, "train", stages=(stage("s", ["a"]),))


def test_the_shipped_models_recipe_is_a_builtin_staged_config():
    cfg = resolve_config("contact_train")
    assert cfg.model.kind == "contact" and cfg.model.spin
    names = [s.name for s in cfg.train.stages]
    assert names == ["unroll6", "unroll24", "unroll12", "corners"]
    first, last = cfg.train.stages[0], cfg.train.stages[-1]
    assert first.schedule_steps > first.steps           # stops part-way down its schedule
    assert set(first.records) < set(last.records)       # the corners join in the last stage
    assert cfg.dem.dt == 2e-4
