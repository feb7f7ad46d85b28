"""Initial ball placement: random sequential insertion inside any jar, from a seed.

Candidates are drawn uniformly in the cavity's bounding box (``numpy.random.default_rng(seed)``,
so a seed always gives the same packing); a candidate is accepted when it is inside the cavity
with a clearance (``phi < -R - gap``) and at least ``R_i + R_j + gap`` from every ball accepted
so far. Balls of several sizes are placed largest first (the small ones fill the gaps the large
ones leave), each keeping its index. The balls start at rest; the DEM then lets them settle with
the jar at rest.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from sgn_jax.errors import SGNJaxError


class PlacementError(SGNJaxError, ValueError):
    """The balls cannot be placed (too many, too large, or a jar without room)."""


PLACEMENT_GAP = 5e-4
"""m: the clearance kept from the wall and between balls when they are placed."""

PLACEMENT_BATCH = 4096
"""Candidates drawn (and SDF-evaluated) at a time by :func:`place_balls`; the first batch is
what :func:`placement_candidates` gives :func:`place_balls_traced`."""


def placement_candidates(seed: int, count: int = PLACEMENT_BATCH) -> np.ndarray:
    """(count, 3) float64 uniforms in [0, 1): the first ``count`` candidates of ``seed``'s
    stream, in the unit box (``lower + (upper - lower) * u`` places them in a jar's box), the
    very numbers :func:`place_balls` draws first."""
    return np.random.default_rng(int(seed)).random((int(count), 3))


def place_balls_traced(sdf_fn: Callable[[jnp.ndarray], jnp.ndarray], lower: jax.Array,
                       upper: jax.Array, candidates: jax.Array, n_balls: int, radius: float,
                       gap: float = PLACEMENT_GAP) -> tuple[jax.Array, jax.Array]:
    """:func:`place_balls` as a jittable function of the jar: the same random sequential
    insertion over fixed unit-box ``candidates`` (C, 3) (:func:`placement_candidates`), so
    that the box ``lower``, ``upper`` (3,) m and ``sdf_fn`` may depend on traced jar
    parameters (a design study places each packing in every jar it evaluates).

    Returns ``(positions (n_balls, 3) m jar frame, placed ())``: the balls in the order
    accepted, the same as :func:`place_balls` whenever its first batch of candidates places
    them all (the default one holds 4096); slots left empty (``placed < n_balls``: the jar
    has no room for them among the candidates) are NaN, so that whatever runs from them is
    visibly non-finite.
    """
    lower, upper = jnp.asarray(lower, jnp.float64), jnp.asarray(upper, jnp.float64)
    points = lower + (upper - lower) * jnp.asarray(candidates, jnp.float64)
    inside = sdf_fn(points) < -radius - gap
    min_dist_sq = (2 * radius + gap) ** 2

    def accept(carry, item):
        placed, count = carry
        x, ok = item
        d = placed - x
        filled = jnp.arange(n_balls) < count
        clear = jnp.all(jnp.where(filled, jnp.einsum("ij,ij->i", d, d) >= min_dist_sq, True))
        take = ok & clear & (count < n_balls)
        placed = jnp.where(take, placed.at[jnp.minimum(count, n_balls - 1)].set(x), placed)
        return (placed, count + take.astype(jnp.int32)), None

    start = (jnp.full((n_balls, 3), jnp.nan, jnp.float64), jnp.zeros((), jnp.int32))
    (placed, count), _ = jax.lax.scan(accept, start, (points, inside))
    return placed, count


def place_balls(
    sdf_fn: Callable[[jnp.ndarray], jnp.ndarray],
    lower: np.ndarray,
    upper: np.ndarray,
    n_balls: int,
    radius: float | np.ndarray,
    seed: int,
    gap: float = PLACEMENT_GAP,
    batch: int = PLACEMENT_BATCH,
    max_candidates: int = 2_000_000,
) -> np.ndarray:
    """Positions (N,3) float64, jar frame, of ``n_balls`` non-overlapping balls inside the jar.

    Args:
        sdf_fn: combined jar SDF, ``phi (M,) = sdf_fn(x (M,3))`` in the jar frame (negative
            inside the cavity).
        lower, upper: (3,) corners of a box containing the cavity (m).
        n_balls, radius: how many balls of which radius (m): one radius for all, or (N,) one
            per ball (placed largest first; row k of the result is ball k).
        seed: integer seed of the candidate stream.
        gap: clearance (m) kept from the wall and between balls.
        batch: candidates drawn (and SDF-evaluated) at a time.
        max_candidates: give up after this many candidates.

    Raises:
        PlacementError saying how many balls fitted and what to change.
    """
    radii = np.broadcast_to(np.asarray(radius, np.float64), (n_balls,)) if n_balls >= 1 else None
    if n_balls < 1 or not np.all(radii > 0) or gap < 0:
        raise PlacementError(f"need n_balls >= 1, radius > 0, gap >= 0; got {n_balls}, {radius}, "
                             f"{gap}")
    lower = np.asarray(lower, np.float64)
    upper = np.asarray(upper, np.float64)
    rng = np.random.default_rng(seed)
    sdf_jit = jax.jit(sdf_fn)
    # Largest first; a stable sort keeps one size's balls in index order (one size: as is).
    order = np.argsort(-radii, kind="stable")
    placed: list[np.ndarray] = []
    placed_radii: list[float] = []
    drawn = 0
    while len(placed) < n_balls and drawn < max_candidates:
        cand = lower + (upper - lower) * rng.random((batch, 3))
        drawn += batch
        phi = np.asarray(sdf_jit(jnp.asarray(cand)))
        for x, phi_x in zip(cand, phi, strict=True):
            r = radii[order[len(placed)]]
            if not phi_x < -r - gap:
                continue
            if placed:
                d = np.asarray(placed) - x
                reach = np.asarray(placed_radii) + r + gap
                if np.any(np.einsum("ij,ij->i", d, d) < reach * reach):
                    continue
            placed.append(x)
            placed_radii.append(r)
            if len(placed) == n_balls:
                break
    if len(placed) < n_balls:
        sizes = (f"radius {radii[0]} m" if np.all(radii == radii[0])
                 else f"radii {sorted(set(radii.tolist()), reverse=True)} m")
        raise PlacementError(
            f"could place only {len(placed)} of {n_balls} balls of {sizes} with a gap "
            f"of {gap} m after {drawn} random candidates; the jar is too small or too full for "
            "random insertion: use fewer or smaller balls, or a smaller gap"
        )
    out = np.empty((n_balls, 3))
    out[order] = np.asarray(placed)
    return out
