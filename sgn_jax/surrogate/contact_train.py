"""Training of the contact-impulse surrogate (:mod:`sgn_jax.surrogate.contact`): short unrolled rollouts.

The featurizer runs inside the jitted step: a training sample is a stretch of a DEM trajectory
(``W + 1 + K`` positions and the jar state at the ``W + K`` slot times), and the loss unrolls
the model ``K`` steps from the first window, each step on the graph of the model's OWN state
(the rollout's featurizer, the same integrator), so the states a rollout reaches and its drift
are what the model is trained on::

    loss = mean_k mean_balls |v_{n+k+1}^model - v_{n+k+1}^DEM|^2 / scale_traj^2

``scale_traj`` is the RMS velocity change per step of the sample's own trajectory, so that a
quiet, low-power motion weighs as much as a violent one (the targets span 570x in power).
Velocities are the integrator's (``v_j = (x_j - x_{j-1}) / dt``), so one velocity error is
one step's integrated acceleration error. Gradients flow through the whole unroll
(backpropagation through the K steps), optionally cut between steps (``pushforward=True``:
each step is trained on the state the previous one reached, without differentiating through
how it got there, as in GNS pushforward training).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
import optax

from sgn_jax.dem.contact import head_on_normal_force
from sgn_jax.scene import SDFQuery
from sgn_jax.surrogate.contact import ContactNet
from sgn_jax.surrogate.graph import GraphSpec, Window, build_graph

F64 = jnp.float64


@flax.struct.dataclass
class UnrollBatch:
    """B training stretches (float64 positions; float32 elsewhere is fine).

    Attributes:
        positions: (B, W + 1 + K, N, 3) m, ``x_{n-W} .. x_{n+K}``.
        offsets: (B, W + K, 3) m, jar offset at ``t_{n-W+1} .. t_{n+K}``.
        offset_velocities: (B, W + K, 3) m/s.
        scale: (B,) m/s, the loss scale of each sample's trajectory.
        spins: (B, 1 + K, N, 3) rad/s, the balls' angular velocities at ``t_n .. t_{n+K}``
            (the DEM's ``omega``), or None; a model with spin state needs them.
    """

    positions: jax.Array
    offsets: jax.Array
    offset_velocities: jax.Array
    scale: jax.Array
    spins: jax.Array | None = None


@dataclasses.dataclass(frozen=True)
class UnrollSpec:
    """Static settings of the unrolled loss: ``unroll`` K steps; ``pushforward`` cuts the
    gradient between steps; ``position_noise`` (m) perturbs the first window's positions by a
    random walk (std per slot) so the model sees states slightly off the DEM's;
    ``relative_floor`` > 0 (m/s) switches to the per-ball relative loss
    ``huber(|v - v_DEM| / sqrt(|dv_DEM|^2 + floor^2))``, in which a resting ball weighs as
    much as a hard impact (else the squared error over the trajectory's scale).
    ``spin_weight``: for a model with spin state, the weight of the same error of the
    contact-point speed of the spin, R |w - w_DEM| (against R |dw_DEM|), beside the velocity's.
    ``touch_weight`` (the charge kind's loss only,
    :func:`sgn_jax.surrogate.contact_charge_train.make_charge_unroll_loss`): the weight of the
    contact-state term, how far the model's balls touch where the DEM's do (0: off)."""

    unroll: int = 4
    pushforward: bool = False
    position_noise: float = 0.0
    relative_floor: float = 0.0
    spin_weight: float = 1.0
    touch_weight: float = 0.0


def per_ball_error(new: jax.Array, true: jax.Array, true_prev: jax.Array,
                   relative_floor: float) -> jax.Array:
    """(N,) each ball's error of a velocity (or r times a spin) against the DEM's: with
    ``relative_floor`` > 0 (m/s) ``huber(|new - true| / sqrt(|true - true_prev|^2 + floor^2))``,
    relative to the ball's own change (a resting ball, |dv| ~ g dt, weighs as much as a ball in
    a hard impact, |dv| ~ 1 m/s); else the squared error |new - true|^2 (the caller divides by
    the trajectory's scale squared)."""
    if relative_floor > 0:
        ref = jnp.sqrt(jnp.sum((true - true_prev) ** 2, axis=-1) + relative_floor ** 2)
        ratio = jnp.sqrt(jnp.sum((new - true) ** 2, axis=-1) + 1e-30) / ref
        return optax.huber_loss(ratio, delta=1.0)
    return jnp.sum((new - true) ** 2, axis=-1)


def init_on_first_stretch(net: Any, spec: GraphSpec, sdf: Any, query: SDFQuery | None,
                          batch: Any, key: jax.Array) -> Any:
    """The module's fresh parameters, initialised on the graph of ``batch``'s first stretch's
    first window (with its spins and, for a batch of charges, its charge), in one jitted
    program (op by op, the graph and the init are ~300 small compilations, ~15 s)."""
    window = Window(positions=batch.positions[0, : spec.window + 1],
                    offsets=batch.offsets[0, : spec.window],
                    offset_velocities=batch.offset_velocities[0, : spec.window],
                    frequency_hz=jnp.zeros(()),
                    spins=None if batch.spins is None else batch.spins[0, 0],
                    charge=(None if getattr(batch, "charge", None) is None
                            else jax.tree_util.tree_map(lambda a: a[0], batch.charge)))

    @jax.jit
    def init(key, window, sdf):
        return net.init(key, build_graph(window, sdf, spec, query)[0])["params"]

    return init(key, window, sdf)


def make_unroll_loss(net: ContactNet, spec: GraphSpec, sdf: Any, query: SDFQuery | None,
                     unroll: UnrollSpec
                     ) -> Callable[[Any, UnrollBatch, jax.Array], tuple[jax.Array, jax.Array]]:
    """``loss(params, batch, key) -> (loss, per_step (K,))`` (jittable)."""
    w, n, dt, k_steps = spec.window, spec.n_particles, spec.dt, unroll.unroll
    spin, radius = bool(net.spin), spec.ball_radius

    def error(new, true, true_prev, scale):
        """The balls' mean error of a velocity (or R times a spin) against the DEM's."""
        per_ball = per_ball_error(new, true, true_prev, unroll.relative_floor)
        if unroll.relative_floor > 0:
            return jnp.mean(per_ball)
        return jnp.mean(per_ball) / scale ** 2

    def one(params, positions, offsets, offset_velocities, scale, spins, key):
        pos0 = positions[: w + 1]
        if unroll.position_noise > 0:
            steps = unroll.position_noise * jax.random.normal(key, pos0.shape, F64)
            # random walk ending at zero at the newest slot: the velocities are perturbed, the
            # newest position (where the targets start) is not
            walk = jnp.cumsum(steps[::-1], axis=0)[::-1] - steps[-1:]
            pos0 = pos0 + walk
        freq = jnp.zeros((), F64)

        def step(carry, k):
            win_pos, w_now = carry
            window = Window(positions=win_pos,
                            offsets=jax.lax.dynamic_slice_in_dim(offsets, k, w),
                            offset_velocities=jax.lax.dynamic_slice_in_dim(offset_velocities, k, w),
                            frequency_hz=freq, spins=w_now)
            graph, _ = build_graph(window, sdf, spec, query)
            terms = net.apply({"params": params}, graph, method=ContactNet.step_terms)
            dv = terms["dv"][:n].astype(F64)
            v_now = (win_pos[-1] - win_pos[-2]) / dt
            v_next = v_now + dv
            x_next = win_pos[-1] + v_next * dt
            x_true_next = jax.lax.dynamic_index_in_dim(positions, w + 1 + k, keepdims=False)
            x_true_now = jax.lax.dynamic_index_in_dim(positions, w + k, keepdims=False)
            x_true_prev = jax.lax.dynamic_index_in_dim(positions, w + k - 1, keepdims=False)
            v_true = (x_true_next - x_true_now) / dt
            err = error(v_next, v_true, (x_true_now - x_true_prev) / dt, scale)
            w_next = None
            if spin:
                w_next = w_now + terms["dw"][:n].astype(F64)
                w_true = jax.lax.dynamic_index_in_dim(spins, k + 1, keepdims=False)
                w_true_now = jax.lax.dynamic_index_in_dim(spins, k, keepdims=False)
                err = err + unroll.spin_weight * error(radius * w_next, radius * w_true,
                                                       radius * w_true_now, scale)
            new_pos = jnp.concatenate([win_pos[1:], x_next[None]])
            if unroll.pushforward:
                new_pos, w_next = jax.lax.stop_gradient((new_pos, w_next))
            return (new_pos, w_next), err

        w0 = spins[0] if spin else None
        _, errs = jax.lax.scan(step, (pos0, w0), jnp.arange(k_steps))
        return errs

    def loss(params, batch: UnrollBatch, key):
        keys = jax.random.split(key, batch.scale.shape[0])
        if spin and batch.spins is None:
            raise ValueError("a contact model with spin trains on stretches with spins "
                             "(UnrollBatch.spins, the DEM's omega)")
        spins = batch.spins if spin else None
        errs = jax.vmap(one, in_axes=(None, 0, 0, 0, 0, 0 if spin else None, 0))(
            params, batch.positions, batch.offsets, batch.offset_velocities, batch.scale, spins,
            keys)
        per_step = jnp.mean(errs, axis=0)
        return jnp.mean(per_step).astype(jnp.float32), per_step

    return loss


@flax.struct.dataclass
class ContactTrainState:
    params: Any
    opt_state: Any
    step: jax.Array


def make_optimizer(lr: Callable[[int], float] | float, clip: float = 1.0
                   ) -> optax.GradientTransformation:
    """Adam with global-norm clipping (a rare violent collision must not wreck the step)."""
    return optax.chain(optax.clip_by_global_norm(clip), optax.adam(lr))


def make_train_step(loss: Callable, tx: optax.GradientTransformation) -> Callable:
    """Jitted ``step(state, batch, key) -> (state, loss, per_step)``."""

    @jax.jit
    def step(state: ContactTrainState, batch: UnrollBatch, key: jax.Array):
        (value, per_step), grads = jax.value_and_grad(loss, has_aux=True)(state.params, batch, key)
        # The dissipation shares are fitted from data, not by this loss.
        grads = {**grads, "share_logit": jnp.zeros_like(grads["share_logit"])}
        updates, opt_state = tx.update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        return ContactTrainState(params, opt_state, state.step + 1), value, per_step

    return step


# --------------------------------------------------------------------------------------------
# Host-side sampling of stretches (numpy; no file I/O: the driver passes arrays)


@dataclasses.dataclass
class StretchSource:
    """The arrays of the training trajectories and how to draw stretches from them.

    ``positions[i]`` (T_i, N, 3), ``offsets[i]`` and ``offset_velocities[i]`` (T_i, 3) per
    trajectory; ``scales[i]`` its loss scale (m/s); ``spins[i]`` (T_i, N, 3) rad/s its
    angular velocities (the DEM's ``omega``), or None (a model without spin state).
    """

    positions: list[np.ndarray]
    offsets: list[np.ndarray]
    offset_velocities: list[np.ndarray]
    scales: np.ndarray
    window: int
    unroll: int
    spins: list[np.ndarray] | None = None

    def draw(self, rng: np.random.Generator, batch_size: int) -> UnrollBatch:
        """B stretches: trajectories uniformly (every motion weighs alike), ends uniformly."""
        return UnrollBatch(**self._stretches(rng, batch_size)[1])

    def _stretches(self, rng: np.random.Generator, batch_size: int
                   ) -> tuple[np.ndarray, dict[str, Any]]:
        """The trajectories drawn (B,) and the stacked arrays of their stretches (the fields
        of :class:`UnrollBatch`)."""
        w, k = self.window, self.unroll
        traj = rng.integers(0, len(self.positions), batch_size)
        pos, off, offv, spins = [], [], [], []
        for i in traj:
            t = len(self.positions[i])
            n = int(rng.integers(w, t - 1 - k))  # the first window ends at sample n
            pos.append(self.positions[i][n - w: n + k + 1])
            off.append(self.offsets[i][n - w + 1: n + k + 1])
            offv.append(self.offset_velocities[i][n - w + 1: n + k + 1])
            if self.spins is not None:
                spins.append(self.spins[i][n: n + k + 1])
        return traj, {"positions": np.stack(pos), "offsets": np.stack(off),
                      "offset_velocities": np.stack(offv),
                      "scale": np.asarray(self.scales[traj], np.float64),
                      "spins": np.stack(spins) if self.spins is not None else None}


def velocity_change_scale(positions: np.ndarray, dt: float, floor: float = 1e-3) -> float:
    """RMS per-step velocity change (m/s) of one trajectory's balls, at least ``floor``."""
    v = np.diff(positions, axis=0) / dt
    dv = np.diff(v, axis=0)
    return float(max(np.sqrt(np.mean(np.sum(dv * dv, axis=-1))), floor))


def _damping_share(trajectories: list[Any], damping_kinds: tuple[str, ...],
                   other_kinds: tuple[str, ...]) -> tuple[float, float]:
    """Per contact kind (ball-ball, ball-wall), the DEM's summed ``diss_<kind>_<d>`` losses of
    ``damping_kinds`` over those plus ``other_kinds``, over the trajectories (1 where there
    are no such losses). A record without the slip and rolling arrays (synthetic data) has no
    such losses."""
    def one(t: Any, kind: str, name: str) -> float:
        values = getattr(t, f"diss_{kind}_{name}", None)
        return 0.0 if values is None else float(np.sum(values))

    def total(kind: str, names: tuple[str, ...]) -> float:
        return sum(sum(one(t, kind, name) for name in names) for t in trajectories)

    out = []
    for kind in ("pp", "pw"):
        damping = total(kind, damping_kinds)
        losses = damping + total(kind, other_kinds)
        out.append(damping / losses if losses > 0 else 1.0)
    return out[0], out[1]


def dissipation_shares(trajectories: list[Any]) -> tuple[float, float]:
    """The DEM's damping share of all contact losses, ball-ball and ball-wall, over the
    trajectories: (normal + tangential damping) / (damping + slip + rolling), per kind."""
    return _damping_share(trajectories, ("normal", "tangential"), ("slip", "rolling"))


def tangential_damping_shares(trajectories: list[Any]) -> tuple[float, float]:
    """The DEM's tangential damping share of its tangential losses (damping + Coulomb slip),
    ball-ball and ball-wall, over the trajectories (1 where a record has no slip arrays)."""
    return _damping_share(trajectories, ("tangential",), ("slip",))


def share_logits(shares: tuple[float, float]) -> jax.Array:
    s = np.clip(np.asarray(shares, np.float64), 1e-4, 1 - 1e-4)
    return jnp.asarray(np.log(s / (1 - s)), jnp.float32)


# --------------------------------------------------------------------------------------------
# Isolated head-on impacts from the DEM's contact law (numpy): a second, cheap training signal


def impact_stretches(law_pw: Any, law_pp: Any, ball_radius: float, dt: float, window: int,
                     unroll: int, n_impacts: int, seed: int, gravity: float = 9.81,
                     speed_range: tuple[float, float] = (0.02, 2.0),
                     integration_dt: float = 1e-7) -> UnrollBatch:
    """``n_impacts`` stretches of 2 balls (half ball-on-floor, half ball-on-ball, head-on) whose
    positions are the DEM contact law's exact 1-D answer, sampled every ``dt``.

    Why: in the envelope's runs most contacts are in beds; an isolated impact, and so the
    coefficient of restitution the DEM's damping is chosen for (the config's ``restitution``
    at every speed), is rare, and a model trained on them alone rebounds at e = 0.4-0.7 at
    0.2-0.5 m/s in an isolated head-on impact: a bed that bounces too much agitates
    too early. These stretches teach the impact itself.

    Each stretch: ``window + 1 + unroll`` positions; approach speed log-uniform in
    ``speed_range`` (m/s); the contact starts at a random time within 1.5 steps either side
    of the window's newest slot, so every phase of the contact within a step is seen.
    Ball on floor: ball 0 falls onto the plane y = 0 (gravity on), ball 1 falls freely far
    above it (a bystander with no contact). Ball on ball: both balls move along x towards each
    other at half the approach speed each, 20 mm above the floor, and fall together. The
    normal force is the DEM's (:func:`sgn_jax.dem.contact.head_on_normal_force`: the Hertz
    spring plus its damping, not clipped), integrated at ``integration_dt``.

    Args:
        law_pw: :class:`sgn_jax.dem.contact.ContactLaw` of ball-wall contacts.
        law_pp: :class:`sgn_jax.dem.contact.ContactLaw` of ball-ball contacts.
    Returns:
        an :class:`UnrollBatch` (positions (n_impacts, window + 1 + unroll, 2, 3), zero jar
        offsets and velocities, scale 1, zero spins).
    """
    rng = np.random.default_rng([int(seed), 0x1A7C])
    n_slots = window + 1 + unroll
    speed = np.exp(rng.uniform(np.log(speed_range[0]), np.log(speed_range[1]), n_impacts))
    onset = window * dt + rng.uniform(-1.5 * dt, 1.5 * dt, n_impacts)   # contact start (s)
    is_wall = np.arange(n_impacts) % 2 == 0
    y_centre = 0.02
    # 1-D normal problem: overlap d(t) with d(onset) = 0, rate +speed at the onset.
    # Before the onset the motion is ballistic; integrate from the onset to the last slot.
    t_slots = np.arange(n_slots) * dt
    # each impact's law (fields of shape (n_impacts,))
    law = jax.tree_util.tree_map(lambda w, p: np.where(is_wall, float(w), float(p)),
                                 law_pw, law_pp)
    accel_free = np.where(is_wall, gravity, 0.0)   # gravity pushes a floor contact in (d up)
    d = np.zeros(n_impacts)
    rate = speed.copy()
    # integration step of each slot at or after the onset (-1 before it) and its remainder
    since = t_slots[None, :] - onset[:, None]
    step_of = np.where(since >= 0, np.floor(since / integration_dt), -1).astype(np.int64)
    frac = since - np.maximum(step_of, 0) * integration_dt
    overlap = np.zeros((n_impacts, n_slots))
    for i in range(int(step_of.max()) + 1):
        now = step_of == i
        if now.any():
            r, c = np.nonzero(now)
            overlap[r, c] = d[r] + rate[r] * frac[r, c]
        force = head_on_normal_force(law, d, rate)
        rate = rate + (accel_free - force / law.mass_eff) * integration_dt
        d = d + rate * integration_dt
    before = t_slots[None, :] < onset[:, None]
    dt_before = t_slots[None, :] - onset[:, None]      # < 0 before the onset
    ballistic = speed[:, None] * dt_before + 0.5 * accel_free[:, None] * dt_before ** 2
    overlap = np.where(before, ballistic, overlap)
    positions = np.zeros((n_impacts, n_slots, 2, 3))
    fall = -0.5 * gravity * t_slots ** 2                # free fall from rest at slot 0
    # ball on floor: height r - overlap; bystander 30 mm up
    positions[is_wall, :, 0, 1] = ball_radius - overlap[is_wall]
    positions[is_wall, :, 1, 1] = 0.03 + fall
    # ball on ball: centres at -/+ (r - overlap / 2) along x, both falling
    pp = ~is_wall
    positions[pp, :, 0, 0] = -(ball_radius - 0.5 * overlap[pp])
    positions[pp, :, 1, 0] = ball_radius - 0.5 * overlap[pp]
    positions[pp, :, :, 1] = (y_centre + fall)[None, :, None]
    return UnrollBatch(positions=positions,
                       offsets=np.zeros((n_impacts, n_slots - 1, 3)),
                       offset_velocities=np.zeros((n_impacts, n_slots - 1, 3)),
                       scale=np.ones(n_impacts),
                       spins=np.zeros((n_impacts, 1 + unroll, 2, 3)))   # head-on: no spin
