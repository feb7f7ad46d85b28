"""Neighbour search for the DEM's Verlet list: a cell list whose cost grows with N, and the
all-pairs reference it must reproduce.

Both builders return the candidate pairs (i < j whose centre distance is below the pair cutoff
``r_i + r_j + skin``) compacted into ``n_slots`` slots, sorted by the key ``i * N + j`` with the
empty slots last (``i = j = 0``, ``valid`` False), and ``count``, the number of candidates
(``count > n_slots`` is the list's overflow: the slots then hold only some of the candidates).
The engine's rebuild matches an old and a new list by binary search on these keys, hence the
order.

The cell list bins the ball centres into a uniform grid of cubic cells (``CellGrid``, static)
whose origin is traced, so that the grid follows the moving jar. A cell holds at most
``cell_capacity`` balls (a static shape); ``cell_overflow`` reports a cell that held more, and
then pairs may be missing: the caller treats it as an error, like the list's overflow.
``cell_grid_for`` sizes the grid for a box, so that nobody sets the capacity by hand.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from sgn_jax.errors import SGNJaxError

# Densest sphere packing (Kepler, proved by Hales): no packing fills more than pi / sqrt(18).
_KEPLER_DENSITY = math.pi / math.sqrt(18.0)


class CellGridError(SGNJaxError, ValueError):
    """An invalid cell grid or box."""


@dataclasses.dataclass(frozen=True)
class CellGrid:
    """A uniform grid of cubic cells (static: hashable, a jit static argument).

    Attributes:
        cell_size: m, the side of a cell; a pair within its cutoff lies at most ``reach``
            cells apart along each axis, so ``cell_size * reach`` must be at least the largest
            pair cutoff (``cell_grid_for`` ensures it).
        dims: cells along x, y, z; the grid covers ``[origin, origin + dims * cell_size)``, and
            centres outside it are clipped into the edge cells (still found, but they crowd
            those cells).
        cell_capacity: the most balls one cell holds (slots per cell).
        reach: how many cells the search looks along each axis (1: the 3x3x3 block).
    """

    cell_size: float
    dims: tuple[int, int, int]
    cell_capacity: int
    reach: int = 1

    def __post_init__(self) -> None:
        dims = tuple(int(d) for d in self.dims)
        object.__setattr__(self, "dims", dims)
        object.__setattr__(self, "cell_size", float(self.cell_size))
        if not (self.cell_size > 0 and math.isfinite(self.cell_size)):
            raise CellGridError(f"cell_size must be positive and finite, got {self.cell_size}")
        if len(dims) != 3 or min(dims) < 1:
            raise CellGridError(f"dims must be three positive integers, got {self.dims}")
        if self.cell_capacity < 1 or self.reach < 1:
            raise CellGridError("cell_capacity and reach must be >= 1, got "
                                f"{self.cell_capacity} and {self.reach}")

    @property
    def n_cells(self) -> int:
        return self.dims[0] * self.dims[1] * self.dims[2]

    def stencil(self) -> np.ndarray:
        """Cell offsets (S,3) int32 searched from a ball's cell: the ball's own cell first, then
        the offsets lexicographically above zero, so that each pair of cells is visited once."""
        r = range(-self.reach, self.reach + 1)
        half = [(dx, dy, dz) for dx in r for dy in r for dz in r if (dx, dy, dz) > (0, 0, 0)]
        return np.asarray([(0, 0, 0)] + half, dtype=np.int32)


def cell_capacity_bound(cell_size: float, min_distance: float) -> int:
    """The most points with pairwise distance >= ``min_distance`` that a cube of side
    ``cell_size`` holds: the smaller of two upper bounds.

    - Sub-cubes: split the cube into m^3 sub-cubes whose diagonal is below ``min_distance``;
      each holds at most one point.
    - Density: spheres of diameter ``min_distance`` around the points lie in a cube of side
      ``cell_size + min_distance``; tiling space with that cube gives a packing, whose density
      is at most Kepler's pi / sqrt(18).
    """
    if min_distance <= 0:
        raise CellGridError(f"min_distance must be positive, got {min_distance}")
    m = math.floor(cell_size * math.sqrt(3.0) / min_distance) + 1
    ratio = (cell_size + min_distance) / min_distance
    # The small relative margin keeps float rounding from cutting an exact integer bound.
    density = math.floor(_KEPLER_DENSITY * 6.0 / math.pi * ratio**3 * (1 + 1e-12))
    return max(1, min(m**3, density))


def cell_grid_for(lower: Any, upper: Any, max_cutoff: float, min_radius: float, n_balls: int,
                  *, reach: int = 1, max_overlap: float = 0.05) -> CellGrid:
    """Size a cell grid for a box in which all ball centres lie (host-side, static).

    Args:
        lower, upper: (3,) m, corners of the box (in the frame whose origin the caller passes
            to ``build_pairs_cells`` as ``origin``: the grid's origin is ``lower``).
        max_cutoff: m, the largest pair cutoff, ``r_i + r_j + skin`` for the two largest balls.
        min_radius: m, the smallest ball radius.
        n_balls: N; the capacity never exceeds it.
        reach: cells searched along each axis; the cell side is ``max_cutoff / reach``.
        max_overlap: the largest overlap of two smallest balls the capacity allows for, as a
            fraction of their diameter (closer centres pack more balls into a cell).

    Returns:
        ``CellGrid`` with ``dims`` covering the box and ``cell_capacity`` from the densest
        packing of the smallest balls (``cell_capacity_bound``), capped at ``n_balls``.
    """
    lower = np.asarray(lower, dtype=np.float64).reshape(3)
    upper = np.asarray(upper, dtype=np.float64).reshape(3)
    if not np.all(upper > lower):
        raise CellGridError(f"upper {upper} must exceed lower {lower} on every axis")
    if not (max_cutoff > 0 and min_radius > 0 and 0 <= max_overlap < 1 and n_balls >= 1):
        raise CellGridError("need max_cutoff > 0, min_radius > 0, 0 <= max_overlap < 1, "
                            "n_balls >= 1")
    cell_size = float(max_cutoff) / reach
    dims = tuple(max(1, math.ceil(x)) for x in (upper - lower) / cell_size)
    capacity = cell_capacity_bound(cell_size, 2.0 * min_radius * (1.0 - max_overlap))
    return CellGrid(cell_size=cell_size, dims=dims, cell_capacity=min(capacity, n_balls),
                    reach=reach)


def _key_dtype(n: int) -> Any:
    if n * n < np.iinfo(np.int32).max:
        return jnp.int32
    if not jax.config.jax_enable_x64:
        raise CellGridError(f"{n} balls need int64 pair keys: enable jax_enable_x64")
    return jnp.int64


def _radii(radius: Any, n: int, dtype: Any) -> jnp.ndarray:
    return jnp.broadcast_to(jnp.asarray(radius, dtype), (n,))


def _compact(n: int, n_slots: int, candidate: jnp.ndarray, pair_at: Any, presorted: bool
             ) -> tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray, jnp.ndarray]:
    """The candidates of the flat mask ``candidate`` as ``n_slots`` slots sorted by the key
    ``i * N + j``, and their count; ``pair_at(flat indices) -> (i, j)`` with i < j. Without
    overflow the slots hold every candidate; with it, the first ``n_slots`` in the mask's order
    (the smallest keys when ``presorted``)."""
    count = jnp.sum(candidate, dtype=jnp.int32)
    key_dtype = _key_dtype(n)
    sentinel = jnp.asarray(n * n, key_dtype)
    (slots,) = jnp.nonzero(candidate, size=n_slots, fill_value=0)
    lo, hi = pair_at(slots)
    filled = jnp.arange(n_slots) < count
    keys = jnp.where(filled, lo.astype(key_dtype) * n + hi.astype(key_dtype), sentinel)
    if not presorted:
        keys = jnp.sort(keys)
    valid = keys < sentinel
    i = jnp.where(valid, keys // n, 0).astype(jnp.int32)
    j = jnp.where(valid, keys % n, 0).astype(jnp.int32)
    return i, j, valid, count


def _empty(n_slots: int) -> tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray, jnp.ndarray]:
    zero = jnp.zeros(n_slots, jnp.int32)
    return zero, zero, jnp.zeros(n_slots, bool), jnp.zeros((), jnp.int32)


def build_pairs_all(n_slots: int, pos: jnp.ndarray, radius: Any, skin: Any
                    ) -> tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray, jnp.ndarray]:
    """All-pairs reference: test every pair i < j (O(N^2) work).

    Args:
        n_slots: K, static.
        pos: (N,3) m, ball centres.
        radius: m, scalar or (N,) per ball.
        skin: m, the surface gap below which a pair is a candidate.

    Returns:
        ``(i (K,) int32, j (K,) int32, valid (K,) bool, count () int32)``: the candidates
        ``|x_j - x_i| < r_i + r_j + skin`` sorted by ``i * N + j``, empty slots last.
    """
    n = pos.shape[0]
    iu, ju = np.triu_indices(n, k=1)
    if len(iu) == 0:  # a single ball: empty slots only
        return _empty(n_slots)
    r = _radii(radius, n, pos.dtype)
    d = pos[ju] - pos[iu]
    dist_sq = jnp.sum(d * d, axis=-1)
    cutoff = r[iu] + r[ju] + skin
    candidate = dist_sq < cutoff * cutoff
    # triu_indices lists the pairs in key order already.
    iu, ju = jnp.asarray(iu, jnp.int32), jnp.asarray(ju, jnp.int32)
    return _compact(n, n_slots, candidate, lambda s: (iu[s], ju[s]), presorted=True)


def build_pairs_cells(grid: CellGrid, n_slots: int, pos: jnp.ndarray, radius: Any, skin: Any,
                      origin: Any
                      ) -> tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray, jnp.ndarray, jnp.ndarray]:
    """Cell-list search: the same ``(i, j, valid, count)`` as ``build_pairs_all`` (without
    overflow) from O(N * S * cell_capacity) pair tests, S = (2 * reach + 1)^3 // 2 + 1 cells.

    The balls are sorted by cell; each ball tests the balls in its own cell with a larger index
    and every ball in the half of the surrounding cells that lies lexicographically above it,
    so that each pair is tested once.

    Args:
        grid: static cell grid (``cell_grid_for``); ``grid.cell_size * grid.reach`` must be at
            least the largest cutoff ``r_i + r_j + skin``, which is not checked here.
        n_slots: K, static.
        pos: (N,3) m, ball centres.
        radius: m, scalar or (N,) per ball.
        skin: m.
        origin: (3,) m, traced: the grid's lower corner in the frame of ``pos``.

    Returns:
        ``(i, j, valid, count, cell_overflow)``: as ``build_pairs_all``, and ``cell_overflow``
        () bool, True when a cell held more than ``grid.cell_capacity`` balls (then pairs may be
        missing and ``count`` may be low).
    """
    n = pos.shape[0]
    if n < 2:
        return (*_empty(n_slots), jnp.zeros((), bool))
    r = _radii(radius, n, pos.dtype)
    dims = jnp.asarray(grid.dims, jnp.int32)
    # Clip in float first: a far-away (or non-finite) centre must not wrap around in int32.
    scaled = (pos - jnp.asarray(origin, pos.dtype)) / grid.cell_size
    scaled = jnp.clip(jnp.floor(scaled), 0, np.asarray(grid.dims) - 1)
    cell3 = jnp.clip(scaled.astype(jnp.int32), 0, dims - 1)  # (N,3)

    def flat(c3: jnp.ndarray) -> jnp.ndarray:
        return (c3[..., 0] * grid.dims[1] + c3[..., 1]) * grid.dims[2] + c3[..., 2]

    cell = flat(cell3)
    order = jnp.argsort(cell, stable=True).astype(jnp.int32)  # ball index by cell
    sorted_cell = cell[order]
    bounds = jnp.searchsorted(sorted_cell, jnp.arange(grid.n_cells + 1, dtype=cell.dtype),
                              side="left").astype(jnp.int32)  # (C+1,) start of each cell
    start, occupancy = bounds[:-1], bounds[1:] - bounds[:-1]
    cell_overflow = jnp.any(occupancy > grid.cell_capacity)

    # Neighbour cells of every ball (N,S); those off the grid hold nobody.
    stencil = jnp.asarray(grid.stencil())
    nb3 = cell3[:, None, :] + stencil[None, :, :]
    on_grid = jnp.all((nb3 >= 0) & (nb3 < dims), axis=-1)
    nb = jnp.where(on_grid, flat(jnp.clip(nb3, 0, dims - 1)), 0)
    nb_start = start[nb]
    nb_count = jnp.where(on_grid, jnp.minimum(occupancy[nb], grid.cell_capacity), 0)

    # Candidate slots (N,S,cap): the k-th ball of each neighbour cell, in the sorted order.
    k = jnp.arange(grid.cell_capacity, dtype=jnp.int32)
    slot = jnp.minimum(nb_start[:, :, None] + k, n - 1)
    occupied = k < nb_count[:, :, None]
    other = order[slot]
    me = jnp.arange(n, dtype=jnp.int32)[:, None, None]
    # Own cell (stencil 0): each pair once, from its smaller index.
    own = jnp.arange(stencil.shape[0]) == 0
    occupied = occupied & (~own[None, :, None] | (other > me))
    # The same decisions as build_pairs_all: |x_me - x_other|^2 is bitwise |x_j - x_i|^2
    # (negation is exact) and the sum of two radii does not depend on their order.
    d = pos[other] - pos[:, None, None, :]
    dist_sq = jnp.sum(d * d, axis=-1)
    cutoff = r[:, None, None] + r[other] + skin
    candidate = (occupied & (dist_sq < cutoff * cutoff)).reshape(-1)
    other = other.reshape(-1)
    row = other.shape[0] // n

    def pair_at(slots: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
        a, b = slots // row, other[slots]
        return jnp.minimum(a, b), jnp.maximum(a, b)

    i, j, valid, count = _compact(n, n_slots, candidate, pair_at, presorted=False)
    return i, j, valid, count, cell_overflow
