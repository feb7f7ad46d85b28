"""Training of the contact model: the unrolled loss learns, and a killed run resumes exactly."""

import dataclasses

import numpy as np
import pytest

import sgn_jax.api as sj
from sgn_jax.config import load_config
from sgn_jax.pipelines.contact_replay import derive_contact_model
from sgn_jax.pipelines.contact_train_run import train_contact
from sgn_jax.records.checkpoint import load_trained_model
from sgn_jax.surrogate.contact_train import UnrollSpec, dissipation_shares
from sgn_jax.testing import synthetic_trajectory


def small_config():
    cfg = sj.load_config("emax_300rpm")
    cfg = sj.replace_section(cfg, "balls", count=6)
    cfg = sj.replace_section(cfg, "graph", window=3, wall_patches=4, pp_edges_per_particle=4)
    cfg = sj.replace_section(cfg, "train", envelope="default")   # trained over the envelope
    return sj.replace_section(cfg, "model", kind="contact", hidden=8, mlp_layers=2)


TRAIN_KWARGS = dict(batch_size=2, unroll=UnrollSpec(unroll=2, relative_floor=1e-3),
                    checkpoint_every=1, progress=False, steps=2)


@pytest.fixture(scope="module")
def unbroken_run(tmp_path_factory):
    """A 2-step run of a small spinless contact model on synthetic data."""
    out = tmp_path_factory.mktemp("contact_train") / "whole"
    trajs = [synthetic_trajectory(40, 6, seed=s) for s in (1, 2)]
    return train_contact(small_config(), trajs, out, log=lambda _: None, **TRAIN_KWARGS), out


@pytest.mark.slow
def test_a_resumed_run_equals_an_unbroken_one(tmp_path, unbroken_run):
    cfg = small_config()
    trajs = [synthetic_trajectory(40, 6, seed=s) for s in (1, 2)]
    kwargs = TRAIN_KWARGS
    whole, whole_dir = unbroken_run

    class Killed(Exception):
        pass

    def kill_after_step_1(line):
        if '"step": 1' in line:
            raise Killed  # the process dies right after step 1's checkpoint

    with pytest.raises(Killed):
        train_contact(cfg, trajs, tmp_path / "broken", log=kill_after_step_1, **kwargs)
    resumed = train_contact(cfg, trajs, tmp_path / "broken", resume=True, log=lambda _: None,
                            **kwargs)
    assert resumed["steps_done"] == whole["steps_done"] == 2
    a = load_trained_model(tmp_path / "broken", which="latest")
    b = load_trained_model(whole_dir, which="latest")
    for x, y in zip(np.concatenate([np.ravel(v) for v in _leaves(a.params)]),
                    np.concatenate([np.ravel(v) for v in _leaves(b.params)]), strict=True):
        assert x == y
    rows = (tmp_path / "broken" / "metrics.csv").read_text().splitlines()
    assert [r.split(",")[0] for r in rows[1:]] == ["1", "2"]
    assert all(np.isfinite(float(r.split(",")[1])) for r in rows[1:])
    # the loaded model is the contact kind with its fitted damping shares
    assert a.model.__class__.__name__ == "ContactNet"


# The slow tier: warm-starting a spin model from a spinless one (docs/contact.md); the shipped
# model trains with spin from its first step. The default run keeps a spin model's training (the resume
# test's model) and its rollout (tests/test_contact.py, the spins integrated).
@pytest.mark.slow
def test_a_spin_model_trains_warm_started_from_a_spinless_one(tmp_path, unbroken_run):
    """``[model] spin = true`` trains on the records' spins (``omega``): warm-started from a
    spinless model, its first layers take the donor's rows and zeros for the new inputs (the
    contact-point slip), the loss is finite, and the saved model carries spin. Records
    without spins are refused before any work."""
    import jax.numpy as jnp

    from sgn_jax.surrogate.train import TrainingError

    _, donor_dir = unbroken_run
    cfg = sj.replace_section(small_config(), "model", spin=True)
    trajs = [synthetic_trajectory(40, 6, seed=s) for s in (1, 2)]
    lines = []
    summary = train_contact(cfg, trajs, tmp_path / "spin", init_from=donor_dir / "checkpoints"
                            / "latest", log=lines.append, **{**TRAIN_KWARGS, "steps": 1})
    assert any("warm start" in line and "pp_net" in line and "pw_net" in line for line in lines)
    assert summary["spin"] is True and np.isfinite(summary["best_loss"])
    spin_model = load_trained_model(tmp_path / "spin", which="latest")
    donor = load_trained_model(donor_dir, which="latest")
    assert spin_model.model.spin
    k_spin = spin_model.params["pp_net"]["dense_0"]["kernel"]
    k_donor = donor.params["pp_net"]["dense_0"]["kernel"]
    assert k_spin.shape[0] == k_donor.shape[0] + 2        # |v_t| at the contact point, twice
    assert float(jnp.abs(k_spin[: k_donor.shape[0]] - k_donor).max()) < 0.05   # one small step
    # its rollout from a record starts from the record's spins and saves them per frame
    res = sj.run_rollout(spin_model, trajs[0], 3, 4 * cfg.dem.dt, None, save_every=1,
                         progress=False)
    omega = res["arrays"]["omega_model"]
    assert omega.shape == res["arrays"]["pos"].shape
    np.testing.assert_allclose(omega[0], trajs[0].omega[3])
    assert np.abs(omega[-1] - omega[0]).max() > 0
    bare = [dataclasses.replace(t, omega=None) for t in trajs]
    with pytest.raises(TrainingError, match="omega"):
        train_contact(cfg, bare, tmp_path / "bare", log=lambda _: None, **TRAIN_KWARGS)


def _leaves(tree):
    import jax
    return jax.tree_util.tree_leaves(tree)


def test_dissipation_shares_are_the_dem_damping_fractions():
    class Rec:
        diss_pp_normal = np.array([0.0, 2.0])
        diss_pp_tangential = np.array([0.0, 1.0])
        diss_pp_slip = np.array([0.0, 1.0])
        diss_pp_rolling = np.array([0.0, 0.0])
        diss_pw_normal = np.array([0.0, 1.0])
        diss_pw_tangential = np.array([0.0, 0.0])
        diss_pw_slip = np.array([0.0, 0.5])
        diss_pw_rolling = np.array([0.0, 0.5])

    assert dissipation_shares([Rec()]) == (0.75, 0.5)


def test_impact_stretches_answer_with_the_configs_restitution():
    """The isolated impacts of the impact loss are the DEM law's: rebound / approach = the
    config's restitution (0.3) for ball-floor and ball-ball, ballistic before the contact, no
    overlap before the onset, and the floor ball's bystander never near it."""
    import math

    from sgn_jax.pipelines.configure import params_from_config
    from sgn_jax.surrogate.contact_train import impact_stretches

    cfg = sj.load_config("emax_300rpm")
    laws = params_from_config(cfg)
    r, dt, w, k = cfg.balls.radius, 1e-4, 7, 12
    batch = impact_stretches(laws.pw, laws.pp, r, dt, w, k, 16, seed=0)
    pos = np.asarray(batch.positions)
    assert pos.shape == (16, w + 1 + k, 2, 3)
    v = np.diff(pos, axis=1) / dt
    g_dt = 9.81 * dt
    checked = 0
    for i in range(16):
        if i % 2 == 0:  # ball 0 on the floor: normal velocity along +y
            vn = v[i, :, 0, 1]
            gap = pos[i, :, 0, 1] - r
            assert np.linalg.norm(pos[i, :, 1] - pos[i, :, 0], axis=-1).min() > 0.02
        else:           # ball on ball along x
            vn = v[i, :, 1, 0] - v[i, :, 0, 0]
            gap = pos[i, :, 1, 0] - pos[i, :, 0, 0] - 2 * r
        first, last = np.flatnonzero(gap < 0)[[0, -1]]
        assert 1 < first and last + 2 < len(vn)
        # the last step wholly before the contact and the last one wholly after it
        approach, rebound = -vn[first - 2], vn[-1]
        if i % 2 == 0:
            if approach < 0.1:
                continue  # gravity's change within a step (1 mm/s) is too large a share
            approach += 1.5 * g_dt   # gravity's change up to the contact and after it,
            rebound += g_dt * (len(vn) - last - 1.5)  # to within half a step each
        checked += 1
        assert rebound / approach == pytest.approx(cfg.material.restitution, abs=0.02), i
    assert checked >= 10 and math.isfinite(float(pos.sum()))


def test_warm_start_takes_the_matching_submodules_and_refuses_a_foreign_checkpoint():
    """``train_contact(init_from=...)``: a model takes the submodules of a trained one that
    have the same names and shapes; the others (one the donor lacks, one of another width) and
    the data's dissipation shares start fresh; a checkpoint with nothing in common is an
    error, not a silent fresh start."""
    from sgn_jax.pipelines.contact_train_run import _warm_start
    from sgn_jax.surrogate.train import TrainingError

    fresh = {"pp_net": {"dense_0": {"kernel": np.zeros((4, 8))}},
             "pw_net": {"dense_0": {"kernel": np.zeros((4, 8))}},
             "extra_net": {"dense_0": {"kernel": np.zeros((8, 8))}},
             "share_logit": np.zeros(2)}
    donor = {"pp_net": {"dense_0": {"kernel": np.ones((4, 8))}},
             "pw_net": {"dense_0": {"kernel": np.ones((4, 16))}},   # another width: not taken
             "share_logit": np.ones(2)}
    params, names = _warm_start(fresh, donor, "donor")
    assert names == ["pp_net"]
    assert float(params["pp_net"]["dense_0"]["kernel"].sum()) == 32.0
    assert float(np.sum(params["pw_net"]["dense_0"]["kernel"])) == 0.0
    assert float(np.sum(params["share_logit"])) == 0.0
    with pytest.raises(TrainingError, match="no parameter of this model"):
        _warm_start(fresh, {"encoder": {"w": np.ones(3)}}, "sgn checkpoint")
    # A first layer with inputs appended (a spin model from a spinless donor): the donor's rows
    # and zeros for the new ones; a donor with MORE rows is not taken.
    wider = {**fresh, "pp_net": {"dense_0": {"kernel": np.full((6, 8), 7.0)}}}
    params, names = _warm_start(wider, donor, "donor")
    kernel = np.asarray(params["pp_net"]["dense_0"]["kernel"])
    assert names == ["pp_net"] and kernel.shape == (6, 8)
    assert (kernel[:4] == 1.0).all() and (kernel[4:] == 0.0).all()
    with pytest.raises(TrainingError, match="no parameter of this model"):
        _warm_start(fresh, {"pp_net": {"dense_0": {"kernel": np.ones((5, 8))}}}, "donor")


def test_the_checkpoint_states_its_envelope_and_a_derived_model_keeps_it(tmp_path, unbroken_run):
    """A contact run whose [train] names the envelope records it in the checkpoint meta (so the
    API's envelope checks use it, not the training motion alone); ``derive_contact_model``
    saves the same parameters under a changed [model] section, with where they came from (and
    new damping shares where the damping target changes)."""
    from sgn_jax.pipelines.validation import model_envelope

    _, whole_dir = unbroken_run
    source = load_trained_model(whole_dir)
    assert model_envelope(source.config, source.meta).source == "the model's stated envelope"
    out = derive_contact_model(str(whole_dir / "checkpoints" / "latest"),
                               str(tmp_path / "limited"), overlap_limit=1e-4)
    derived = load_trained_model(out)
    assert derived.model.physics.overlap_limit == 1e-4
    # it ships as a run: the changed config and the source run's own records beside it
    assert load_config(tmp_path / "limited" / "config.toml").model.overlap_limit == 1e-4
    for name in ("run_info.json", "summary.json"):
        assert (tmp_path / "limited" / name).read_bytes() == (whole_dir / name).read_bytes()
    assert derived.meta["derived_from"]["change"] == {"overlap_limit": 1e-4}
    assert derived.meta["envelope"] == source.meta["envelope"]
    for x, y in zip(_leaves(derived.params), _leaves(source.params), strict=True):
        np.testing.assert_array_equal(x, y)
    with pytest.raises(FileExistsError):
        derive_contact_model(str(whole_dir), out, overlap_limit=2e-4)
    # a change of the damping target changes what the fitted shares mean: it needs new ones
    with pytest.raises(ValueError, match="shares"):
        derive_contact_model(str(whole_dir), str(tmp_path / "split"), damping_target="contact")
    split = load_trained_model(derive_contact_model(
        str(whole_dir), str(tmp_path / "split2"), shares=(0.9, 0.8), damping_target="contact"))
    assert split.model.physics.damping_target == "contact"
    share = 1.0 / (1.0 + np.exp(-np.asarray(split.params["share_logit"], np.float64)))
    np.testing.assert_allclose(share, [0.9, 0.8], rtol=1e-5)

