"""Training of the charge-conditioned contact model (:mod:`sgn_jax.surrogate.contact_charge`)
on records of many charges: the contact kind's unrolled loss
(:mod:`sgn_jax.surrogate.contact_train`) with each stretch's charge and a mask of its balls.

**Batching charges of different ball counts**: every stretch is padded to one ball count
``n_max`` (the largest training charge) with absent balls (``BallCharge.present`` False),
parked at rest far outside the jar: they have no edges, the model leaves them where they are
and the loss leaves them out (a per-ball mean over the present balls). So one compiled program
trains on every charge, and a batch mixes charges; the cost is that of ``n_max`` balls per
stretch (the ball-ball candidates are tested over all n_max^2 pairs).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from sgn_jax.scene import SDFQuery, grid_query
from sgn_jax.surrogate.contact_charge import ContactChargeNet
from sgn_jax.surrogate.contact_train import StretchSource, UnrollSpec, per_ball_error
from sgn_jax.surrogate.graph import BallCharge, GraphSpec, Window, build_graph

F64 = jnp.float64
# m: where absent balls are parked (far outside any jar, 1 cm apart)
PARKING = np.array([10.0, 10.0, 10.0])


@flax.struct.dataclass
class ChargeUnrollBatch:
    """B stretches of charges padded to one ball count N (see the module docstring).

    Attributes: ``positions`` (B, W + 1 + K, N, 3) m; ``offsets``, ``offset_velocities``
    (B, W + K, 3); ``scale`` (B,) m/s; ``spins`` (B, 1 + K, N, 3) rad/s or None; ``charge``
    a :class:`sgn_jax.surrogate.graph.BallCharge` with a leading B axis."""

    positions: jax.Array
    offsets: jax.Array
    offset_velocities: jax.Array
    scale: jax.Array
    charge: BallCharge
    spins: jax.Array | None = None


def pad_balls(array: np.ndarray, n_max: int, fill: np.ndarray | float = 0.0) -> np.ndarray:
    """(T, n, 3) -> (T, n_max, 3), the absent balls at ``fill`` (parked positions or 0)."""
    t, n = array.shape[:2]
    out = np.empty((t, n_max, 3), np.float64)
    out[:, :n] = array
    if n_max > n:
        out[:, n:] = (np.asarray(fill, np.float64) if np.ndim(fill) == 2
                      else np.full((n_max - n, 3), fill))
    return out


def parked(n_absent: int) -> np.ndarray:
    """(n_absent, 3) m, the absent balls' positions, 1 cm apart."""
    return PARKING + 0.01 * np.arange(n_absent)[:, None]


TOUCH_SOFTNESS = 2e-6
"""m, the width of the soft touching indicator sigmoid(-gap / TOUCH_SOFTNESS) of the
contact-state term: a resting contact's static overlap is ~0.5-3 um for 6-15 mm balls, a
ball in flight is tens of um or more away."""


def touch_mismatch(x_model: jax.Array, x_dem: jax.Array, radius: jax.Array, present: jax.Array,
                   phi_model: jax.Array, phi_dem: jax.Array) -> jax.Array:
    """The contact-state term of one step: sum over ball pairs and ball-wall contacts of
    (t_model - t_DEM)^2 with t = sigmoid(-gap / TOUCH_SOFTNESS) the soft "touching" of each
    (gap = |x_j - x_i| - r_i - r_j, or -phi - r_i against the wall), per present ball.

    It asks the model's balls to touch where the DEM's do at the sample times, which the
    velocity loss leaves to chance at the um scale of a resting contact (the contact census,
    docs/contact_charge.md).

    Args:
        x_model, x_dem: (N, 3) m; radius: (N,) m; present: (N,) float 0/1;
        phi_model, phi_dem: (N,) m, each ball centre's wall SDF.
    Returns:
        () the mismatch per present ball.
    """
    n = x_model.shape[0]
    iu, ju = jnp.triu_indices(n, k=1)
    reach = radius[iu] + radius[ju]
    pair = present[iu] * present[ju]

    def touching(x: jax.Array) -> jax.Array:
        d = jnp.sqrt(jnp.sum((x[iu] - x[ju]) ** 2, axis=-1) + 1e-30)
        return jax.nn.sigmoid(-(d - reach) / TOUCH_SOFTNESS)

    pp = jnp.sum(pair * (touching(x_model) - touching(x_dem)) ** 2)
    wall = jnp.sum(present * (jax.nn.sigmoid((phi_model + radius) / TOUCH_SOFTNESS)
                              - jax.nn.sigmoid((phi_dem + radius) / TOUCH_SOFTNESS)) ** 2)
    return (pp + wall) / jnp.maximum(jnp.sum(present), 1.0)


def make_charge_unroll_loss(net: ContactChargeNet, spec: GraphSpec, sdf: Any,
                            query: SDFQuery | None, unroll: UnrollSpec
                            ) -> Callable[[Any, ChargeUnrollBatch, jax.Array], tuple]:
    """``loss(params, batch, key) -> (loss, per_step (K,))``: the contact kind's loss
    (``UnrollSpec.relative_floor`` > 0: the per-ball relative huber; else the squared error
    over the trajectory's scale) over the present balls; the spin's error is that of each
    ball's own contact-point speed, r |w - w_DEM|."""
    w, dt, k_steps = spec.window, spec.dt, unroll.unroll
    spin = bool(net.spin)
    wall_query = query if query is not None else grid_query

    def error(new, true, true_prev, scale, mask):
        per_ball = per_ball_error(new, true, true_prev, unroll.relative_floor)
        if not unroll.relative_floor > 0:
            per_ball = per_ball / scale ** 2
        return jnp.sum(per_ball * mask) / jnp.maximum(jnp.sum(mask), 1.0)

    def one(params, positions, offsets, offset_velocities, scale, spins, charge, key):
        del key   # (no position noise: the parked balls must stay parked)
        mask = jnp.asarray(charge.present, F64)
        radius = jnp.asarray(charge.radius, F64)[:, None]
        freq = jnp.zeros((), F64)

        def step(carry, k):
            win_pos, w_now = carry
            window = Window(positions=win_pos,
                            offsets=jax.lax.dynamic_slice_in_dim(offsets, k, w),
                            offset_velocities=jax.lax.dynamic_slice_in_dim(offset_velocities, k, w),
                            frequency_hz=freq, spins=w_now, charge=charge)
            graph, _ = build_graph(window, sdf, spec, query)
            terms = net.apply({"params": params}, graph, method=ContactChargeNet.step_terms)
            n = win_pos.shape[1]
            dv = terms["dv"][:n].astype(F64)
            v_next = (win_pos[-1] - win_pos[-2]) / dt + dv
            x_next = win_pos[-1] + v_next * dt
            x_true_next = jax.lax.dynamic_index_in_dim(positions, w + 1 + k, keepdims=False)
            x_true_now = jax.lax.dynamic_index_in_dim(positions, w + k, keepdims=False)
            x_true_prev = jax.lax.dynamic_index_in_dim(positions, w + k - 1, keepdims=False)
            err = error(v_next, (x_true_next - x_true_now) / dt,
                        (x_true_now - x_true_prev) / dt, scale, mask)
            if unroll.touch_weight > 0:
                # positions index p <-> offsets index p - 1 (the stretch's layout)
                off_next = jax.lax.dynamic_index_in_dim(offsets, w + k, keepdims=False)
                phi_m, _ = wall_query(sdf, x_next, off_next)
                phi_d, _ = wall_query(sdf, x_true_next, off_next)
                err = err + unroll.touch_weight * touch_mismatch(
                    x_next, x_true_next, radius[:, 0], mask, jnp.asarray(phi_m, F64),
                    jnp.asarray(phi_d, F64))
            w_next = None
            if spin:
                w_next = w_now + terms["dw"][:n].astype(F64)
                w_true = jax.lax.dynamic_index_in_dim(spins, k + 1, keepdims=False)
                w_true_now = jax.lax.dynamic_index_in_dim(spins, k, keepdims=False)
                err = err + unroll.spin_weight * error(radius * w_next, radius * w_true,
                                                       radius * w_true_now, scale, mask)
            new_pos = jnp.concatenate([win_pos[1:], x_next[None]])
            if unroll.pushforward:
                new_pos, w_next = jax.lax.stop_gradient((new_pos, w_next))
            return (new_pos, w_next), err

        w0 = spins[0] if spin else None
        _, errs = jax.lax.scan(step, (positions[: w + 1], w0), jnp.arange(k_steps))
        return errs

    def loss(params, batch: ChargeUnrollBatch, key):
        if spin and batch.spins is None:
            raise ValueError("a model with spin trains on stretches with spins")
        keys = jax.random.split(key, batch.scale.shape[0])
        spins = batch.spins if spin else None
        errs = jax.vmap(one, in_axes=(None, 0, 0, 0, 0, 0 if spin else None, 0, 0))(
            params, batch.positions, batch.offsets, batch.offset_velocities, batch.scale, spins,
            batch.charge, keys)
        per_step = jnp.mean(errs, axis=0)
        return jnp.mean(per_step).astype(jnp.float32), per_step

    return loss


@dataclasses.dataclass
class ChargeStretchSource(StretchSource):
    """The padded arrays of the training records and their charges (host side): a
    :class:`StretchSource` whose ``positions[i]`` (T_i, n_max, 3) hold the absent balls parked
    and ``spins[i]`` (T_i, n_max, 3) or None, with ``charges[i]`` the record's
    :class:`BallCharge` (n_max balls, one table size)."""

    charges: list[BallCharge] = dataclasses.field(default_factory=list)

    def draw(self, rng: np.random.Generator, batch_size: int) -> ChargeUnrollBatch:
        """B stretches: records uniformly (every charge weighs alike), ends uniformly."""
        picks, arrays = self._stretches(rng, batch_size)
        charge = jax.tree_util.tree_map(lambda *leaves: np.stack(leaves),
                                        *[self.charges[i] for i in picks])
        return ChargeUnrollBatch(**arrays, charge=charge)
