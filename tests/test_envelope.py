"""The motion envelope (sgn_jax.records.envelope) and the GNS training noise."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sgn_jax.config import ConfigError, MotionConfig, resolve_config
from sgn_jax.records.envelope import (
    envelope_notes,
    harmonic_axis_amplitudes,
    latin_hypercube_motions,
    load_envelope,
)
from sgn_jax.surrogate.train import random_walk_position_noise


def test_shipped_envelope_holds_motion1_and_motion2_but_not_the_post_jar_motion_speed():
    env = load_envelope()
    assert env.circle_rpm == (150.0, 500.0) and env.harmonic_max_axis_sum == pytest.approx(0.026)
    assert envelope_notes(resolve_config("motion1").motion, env) == []
    assert envelope_notes(resolve_config("motion2").motion, env) == []
    assert envelope_notes(resolve_config("emax_300rpm").motion, env) == []
    fast = MotionConfig(kind="circle", rpm=600.0, amplitude=0.017)
    assert any("rpm" in n for n in envelope_notes(fast, env))
    wide = MotionConfig(kind="harmonic", base_frequency_hz=5.0, x_sin=(0.02, 0.017))
    assert any("exceeds" in n for n in envelope_notes(wide, env))


def test_latin_hypercube_fills_the_envelope_and_is_reproducible():
    env = load_envelope()
    motions = latin_hypercube_motions(env, 8, 8, seed=3)
    assert motions == latin_hypercube_motions(env, 8, 8, seed=3)
    circles = [m for m in motions if m.kind == "circle"]
    rpms = sorted(m.rpm for m in circles)
    # a Latin hypercube puts one rpm in each of the 8 strata of [150, 500]
    strata = [int((r - 150.0) / (350.0 / 8)) for r in rpms]
    assert strata == list(range(8))
    for m in motions:
        assert envelope_notes(m, env) == []
    harmonic = [m for m in motions if m.kind == "harmonic"]
    assert len(harmonic) == 8
    assert all(3.0 <= m.base_frequency_hz <= 8.0 for m in harmonic)
    sums = [sum(harmonic_axis_amplitudes(m)["x"]) for m in harmonic]
    assert max(sums) <= 0.026 + 1e-9


def test_bad_envelope_file_is_named(tmp_path):
    bad = tmp_path / "env.toml"
    bad.write_text("[circle]\nrpm = [500.0, 150.0]\namplitude = [0.01, 0.02]\n"
                   "[harmonic]\nbase_frequency_hz = [3.0, 8.0]\nfirst_amplitude = [0.0, 0.02]\n"
                   "second_amplitude = [0.0, 0.017]\nmax_axis_sum = 0.026\n")
    with pytest.raises(ConfigError, match="rpm must be"):
        load_envelope(bad)


def test_random_walk_noise_has_the_stated_last_velocity_std_and_target_correction():
    rng = np.random.default_rng(0)
    dt, sigma, w = 1e-4, 0.01, 7
    noise, nu_last = random_walk_position_noise(rng, 4000, w, 3, sigma, dt)
    assert noise.shape == (4000, w + 1, 3, 3) and np.all(noise[:, 0] == 0)
    assert np.std(nu_last) == pytest.approx(sigma, rel=0.03)
    # the last finite-difference velocity of the noisy window is off by exactly nu_last
    assert np.allclose((noise[:, -1] - noise[:, -2]) / dt, nu_last)
    # with the corrected target a - nu/dt, one step from the noisy window lands on the true
    # next position shifted by the last position's noise (GNS)
    x = np.cumsum(rng.normal(size=(w + 2, 3, 3)) * 1e-5, axis=0)
    a_true = (x[-1] - 2 * x[-2] + x[-3]) / dt**2
    xn = x[None, :-1] + noise
    a_target = a_true - nu_last / dt
    x_next = 2 * xn[:, -1] - xn[:, -2] + a_target * dt**2
    assert np.allclose(x_next, x[-1] + noise[:, -1], atol=1e-12)
    assert math.isclose(float(np.std(noise[:, 1] / dt)), sigma / math.sqrt(w), rel_tol=0.05)


def test_train_config_rejects_bad_noise_and_stride():
    from sgn_jax.config import TrainConfig

    with pytest.raises(ConfigError, match="position_noise_std"):
        TrainConfig(position_noise_std=-1.0)
    with pytest.raises(ConfigError, match="window_stride"):
        TrainConfig(window_stride=0)


def test_contact_edge_features_give_gap_and_overlap():
    import jax.numpy as jnp

    from sgn_jax.surrogate.graph import GraphSpec, Window, build_graph

    r = 0.005
    spec = GraphSpec(n_particles=2, window=1, ball_radius=r, dt=1e-4, contact_features=True)
    x = jnp.array([[0.0, 0.0, 0.0], [2 * r - 4e-5, 0.0, 0.0]])  # 40 um overlap
    window = Window(positions=jnp.stack([x, x]), offsets=jnp.zeros((1, 3)),
                    offset_velocities=jnp.zeros((1, 3)), frequency_hz=jnp.asarray(5.0))

    def query(sdf, points, offset):  # a wall far away: phi = -0.02 m
        return jnp.full(points.shape[:-1], -0.02), jnp.zeros(points.shape)

    graph, _ = build_graph(window, None, spec, query)
    e = np.asarray(graph.edges["features"])
    pp = np.asarray(graph.edges["pp"])
    assert e.shape[1] == 5 and pp.sum() == 2
    assert np.allclose(e[pp][:, 3], -4e-5, atol=1e-9)
    assert np.allclose(e[pp][:, 4], 4e-5, atol=1e-9)
    assert np.allclose(np.abs(e[pp][:, 0]), 2 * r - 4e-5, atol=1e-9)
    off = GraphSpec(n_particles=2, window=1, ball_radius=r, dt=1e-4)
    assert np.asarray(build_graph(window, None, off, query)[0].edges["features"]).shape[1] == 3
