"""A trained contact model holds a resting ball at rest: on the floor of a still jar,
and on top of another ball. These are properties of the SHIPPED contact model's training, not
of its construction: a model that hovers, sinks or jitters fails them.

The jar does not move (a circle of zero amplitude), the balls start at rest at the DEM's static
overlap, and the rollout runs 0.2 s (2,000 steps) with neither snap-back nor separation.
"""

import jax.numpy as jnp
import numpy as np
import pytest

import sgn_jax.api as sj
from sgn_jax.scene import analytic_jar_query
from sgn_jax.surrogate.graph import GraphSpec, Window
from sgn_jax.surrogate.rollout import make_rollout, model_predictor

MODEL = "contact"
STEPS = 2000


@pytest.fixture(scope="module")
def model():
    return sj.load_surrogate(MODEL)


def rollout(model, centres):
    cfg = model.config
    spec = GraphSpec(n_particles=len(centres), window=cfg.graph.window,
                     ball_radius=cfg.balls.radius, dt=cfg.dem.dt, pp_skin=cfg.graph.pp_skin,
                     phi_pw=cfg.graph.phi_pw, pp_pair_capacity=4,
                     wall_patches=cfg.graph.wall_patches)
    still = sj.replace_section(cfg, "motion", kind="circle", rpm=300.0, amplitude=0.0)
    motion = sj.motion_from_config(still.motion)
    jar = sj.jar_params_from_config(cfg.jar)
    w = spec.window
    window = Window(positions=jnp.broadcast_to(jnp.asarray(centres), (w + 1, len(centres), 3)),
                    offsets=jnp.zeros((w, 3)), offset_velocities=jnp.zeros((w, 3)),
                    frequency_hz=jnp.asarray(5.0))
    run = make_rollout(spec, model_predictor(model.model), STEPS, 10, snap_back=False,
                       query=analytic_jar_query)
    res = run(model.params, model.norm_stats, window, motion, jar, 0.0)
    return np.asarray(res.positions), res


@pytest.mark.slow
def test_a_ball_on_the_floor_of_a_still_jar_stays_at_rest(model):
    r = model.config.balls.radius
    start = np.array([[0.0, r - 0.5e-6, 0.0]])        # the DEM's static overlap, 0.5 um
    pos, res = rollout(model, start)
    assert np.isfinite(pos).all()
    drift = np.abs(pos - start[None]).max()
    assert drift < 5e-6, f"the resting ball moved {drift * 1e6:.1f} um"
    gap = pos[:, 0, 1] - r
    assert (gap < 2e-6).mean() > 0.95, "the ball hovers or bounces instead of resting"
    v_end = (pos[-1] - pos[-2]) / (10 * model.config.dem.dt)
    assert np.linalg.norm(v_end) < 2e-3


@pytest.mark.slow
def test_a_ball_resting_on_another_ball_stays_on_it(model):
    r = model.config.balls.radius
    bottom = np.array([0.0, r - 0.5e-6, 0.0])
    top = bottom + np.array([0.0, 2 * r - 0.8e-6, 0.0])
    start = np.stack([bottom, top])
    pos, res = rollout(model, start)
    assert np.isfinite(pos).all()
    assert np.abs(pos - start[None]).max() < 10e-6
    d = np.linalg.norm(pos[:, 1] - pos[:, 0], axis=-1)
    assert (d - 2 * r < 2e-6).mean() > 0.95, "the top ball hovers or bounces"
    assert (2 * r - d).max() < 50e-6, "the top ball sinks into the bottom one"
