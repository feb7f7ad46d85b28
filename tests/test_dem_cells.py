"""The cell-list neighbour search (sgn_jax.dem.cells) against the all-pairs reference."""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import sgn_jax  # noqa: F401  (enables x64)
from sgn_jax.dem.cells import (
    CellGrid,
    CellGridError,
    build_pairs_all,
    build_pairs_cells,
    cell_capacity_bound,
    cell_grid_for,
)

SKIN = 0.001
SMALL, LARGE = 0.003, 0.0075


@functools.partial(jax.jit, static_argnums=0)
def _all(n_slots, pos, radius):
    return build_pairs_all(n_slots, pos, radius, SKIN)


@functools.partial(jax.jit, static_argnums=(0, 1))
def _cells(grid, n_slots, pos, radius, origin):
    return build_pairs_cells(grid, n_slots, pos, radius, SKIN, origin)


def _radii(n: int, mixture: bool, rng) -> np.ndarray:
    if not mixture:
        return np.full(n, SMALL)
    return np.where(rng.random(n) < 0.5, SMALL, LARGE)


def _packed(radii: np.ndarray, side: float, rng) -> np.ndarray:
    """Non-overlapping centres in [0, side)^3 by random sequential addition."""
    pos = np.empty((len(radii), 3))
    for k, r in enumerate(radii):
        for _ in range(100_000):
            x = rng.uniform(0, side, 3)
            gap = np.linalg.norm(pos[:k] - x, axis=1) - radii[:k] - r
            if k == 0 or gap.min() >= 0:
                pos[k] = x
                break
        else:
            raise RuntimeError("box too full")
    return pos


def _reference_set(pos: np.ndarray, radii: np.ndarray) -> set[tuple[int, int]]:
    """Candidate pairs by numpy over the full distance matrix (independent of both builders)."""
    d = pos[None, :, :] - pos[:, None, :]
    cutoff = radii[:, None] + radii[None, :] + SKIN
    a, b = np.nonzero(np.triu(np.sum(d * d, axis=-1) < cutoff**2, k=1))
    return set(zip(a.tolist(), b.tolist(), strict=True))


def _check_same(pos, radii, grid, n_slots, origin=(0.0, 0.0, 0.0), radius_arg=None):
    """The cell list equals the all-pairs list slot for slot, without any overflow."""
    pos = jnp.asarray(pos)
    radius = jnp.asarray(radii if radius_arg is None else radius_arg)
    ref = _all(n_slots, pos, radius)
    i, j, valid, count, cell_overflow = _cells(grid, n_slots, pos, radius, jnp.asarray(origin))
    assert not bool(cell_overflow)
    assert int(count) <= n_slots
    for a, b in zip(ref, (i, j, valid, count), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    _check_sorted(i, j, valid, count, len(pos))
    return i, j, valid, count


def _check_sorted(i, j, valid, count, n):
    i, j, valid = np.asarray(i), np.asarray(j), np.asarray(valid)
    filled = min(int(count), len(valid))
    assert valid[:filled].all() and not valid[filled:].any()
    assert (i[~valid] == 0).all() and (j[~valid] == 0).all()
    assert (i[valid] < j[valid]).all()
    keys = i[valid].astype(np.int64) * n + j[valid]
    assert (np.diff(keys) > 0).all()


@pytest.mark.parametrize(("n", "mixture", "fraction"), [
    (1, False, 0.3), (2, True, 0.3), (24, False, 0.05), (24, True, 0.3), (220, False, 0.3),
    (220, True, 0.05), (220, True, 0.3)])
def test_packed_balls_match_all_pairs(n, mixture, fraction):
    """Non-overlapping packings, sparse and dense, equal radii (given as a scalar) and a
    3 / 7.5 mm mixture (per ball), with the grid and its capacity sized by cell_grid_for."""
    rng = np.random.default_rng(n + 1000 * mixture)
    radii = _radii(n, mixture, rng)
    side = (np.sum(4 / 3 * np.pi * radii**3) / fraction) ** (1 / 3)
    pos = _packed(radii, side, rng)
    grid = cell_grid_for([0, 0, 0], [side] * 3, 2 * radii.max() + SKIN, radii.min(), n)
    n_slots = max(1, 6 * n)
    i, j, valid, count = _check_same(pos, radii, grid, n_slots,
                                     radius_arg=None if mixture else SMALL)
    got = set(zip(np.asarray(i)[np.asarray(valid)].tolist(),
                  np.asarray(j)[np.asarray(valid)].tolist(), strict=True))
    assert got == _reference_set(pos, radii)
    if n >= 24 and fraction == 0.3:
        assert int(count) > n // 8  # a dense packing has neighbours to find


def test_random_overlapping_balls_match_all_pairs():
    """Uniform random centres (deep overlaps, many pairs) with a capacity of N per cell, and
    reach 2 (a 5x5x5 stencil of half-size cells)."""
    rng = np.random.default_rng(7)
    n = 220
    radii = _radii(n, True, rng)
    pos = rng.uniform(0, 0.05, (n, 3))
    cutoff = 2 * LARGE + SKIN
    for reach in (1, 2):
        grid = CellGrid(cell_size=cutoff / reach, dims=(8 * reach,) * 3, cell_capacity=n,
                        reach=reach)
        _, _, _, count = _check_same(pos, radii, grid, 40 * n)
        assert int(count) > 5 * n


def test_balls_on_cell_boundaries():
    """Centres exactly on cell faces, edges and corners (a lattice of the cell size and of half
    of it, so pairs straddle the faces), and pairs exactly at the cutoff (not candidates)."""
    cutoff = 2 * SMALL + SKIN
    grid = CellGrid(cell_size=cutoff, dims=(3, 3, 3), cell_capacity=27)
    origin = np.array([0.01, -0.02, 0.005])
    for spacing in (cutoff, 0.5 * cutoff):
        ticks = np.arange(4) * spacing
        pos = origin + np.stack(np.meshgrid(ticks, ticks, ticks, indexing="ij"), -1).reshape(-1, 3)
        radii = np.full(len(pos), SMALL)
        i, j, valid, count = _check_same(pos, radii, grid, 2000, origin=origin)
        # Distances are computed, not exact: the count is whatever the reference decides, but
        # at spacing = cutoff the face neighbours sit on the boundary of the test.
        assert int(count) == len(_reference_set(pos, radii))
    # One pair straddling a face just inside the cutoff, one just outside.
    pos = origin + np.array([[cutoff - 1e-6, 0.001, 0.001], [2 * cutoff - 2e-6, 0.001, 0.001],
                             [0.001, 0.019, cutoff + 0.0005],
                             [0.001, 0.019, 2 * cutoff + 0.0005 + 1e-6]])
    i, j, valid, count = _check_same(pos, np.full(4, SMALL), grid, 10, origin=origin)
    assert int(count) == 1 and (int(i[0]), int(j[0])) == (0, 1)


def test_balls_outside_the_box_are_clipped_not_dropped():
    """Centres beyond every face of the grid (near and far, and a traced origin that is not
    zero) still find their pairs: they sit in the edge cells."""
    rng = np.random.default_rng(11)
    n = 60
    radii = _radii(n, True, rng)
    origin = np.array([-0.01, 0.02, 0.0])
    grid = CellGrid(cell_size=2 * LARGE + SKIN, dims=(3, 3, 3), cell_capacity=n)
    extent = grid.cell_size * 3
    pos = origin + rng.uniform(-0.5 * extent, 1.5 * extent, (n, 3))
    pos[:4] = origin + np.array([[-1.0, 0.0, 0.0], [-1.0, 0.001, 0.0], [0.0, 5.0, 0.0],
                                 [0.0, 5.0, 0.004]])  # far out, in close pairs
    outside = np.any((pos < origin) | (pos >= origin + extent), axis=1)
    assert outside.sum() > n // 2
    i, j, valid, count = _check_same(pos, radii, grid, 20 * n, origin=origin)
    got = set(zip(np.asarray(i)[np.asarray(valid)].tolist(),
                  np.asarray(j)[np.asarray(valid)].tolist(), strict=True))
    assert {(0, 1), (2, 3)} <= got


def test_list_overflow_counts_every_candidate():
    """Too few slots: count is the full candidate count (> n_slots), every slot holds a true
    candidate, sorted, as in the all-pairs list."""
    rng = np.random.default_rng(5)
    n = 220
    radii = _radii(n, False, rng)
    pos = rng.uniform(0, 0.04, (n, 3))
    grid = CellGrid(cell_size=2 * SMALL + SKIN, dims=(6, 6, 6), cell_capacity=n)
    truth = _reference_set(pos, radii)
    n_slots = len(truth) // 3
    for i, j, valid, count in (_all(n_slots, jnp.asarray(pos), jnp.asarray(radii)),
                               _cells(grid, n_slots, jnp.asarray(pos), jnp.asarray(radii),
                                      jnp.zeros(3))[:4]):
        assert int(count) == len(truth) > n_slots
        assert np.asarray(valid).all()
        _check_sorted(i, j, valid, count, n)
        assert set(zip(np.asarray(i).tolist(), np.asarray(j).tolist(), strict=True)) <= truth


def test_cell_overflow_is_flagged():
    """A cell holding more balls than its capacity raises cell_overflow; one ball fewer per
    cell does not."""
    cutoff = 2 * SMALL + SKIN
    rng = np.random.default_rng(2)
    # Three balls in one cell, the others alone.
    pos = np.array([[0.001, 0.001, 0.001], [0.002, 0.006, 0.001], [0.006, 0.001, 0.0065],
                    [0.02, 0.02, 0.02], [0.03, 0.001, 0.02]]) + rng.uniform(0, 1e-4, (5, 3))
    radii = np.full(5, SMALL)
    for capacity, flagged in ((2, True), (3, False)):
        grid = CellGrid(cell_size=cutoff, dims=(5, 5, 5), cell_capacity=capacity)
        out = _cells(grid, 10, jnp.asarray(pos), jnp.asarray(radii), jnp.zeros(3))
        assert bool(out[4]) is flagged
    # Clipping crowds the edge cells: the whole packing in a one-cell grid overflows.
    grid = CellGrid(cell_size=cutoff, dims=(1, 1, 1), cell_capacity=4)
    assert bool(_cells(grid, 10, jnp.asarray(pos), jnp.asarray(radii), jnp.zeros(3))[4])


def test_traced_origin_follows_the_jar_without_recompiling():
    """Moving the balls and the origin together gives the same list from one compilation."""
    rng = np.random.default_rng(4)
    n = 24
    radii = _radii(n, True, rng)
    pos = _packed(radii, 0.05, rng)
    grid = cell_grid_for([0, 0, 0], [0.05] * 3, 2 * LARGE + SKIN, SMALL, n)
    fn = jax.jit(functools.partial(build_pairs_cells, grid, 100))
    first = fn(jnp.asarray(pos), jnp.asarray(radii), SKIN, jnp.zeros(3))
    # A shift that is exact in binary floating point, so that the distances are identical.
    shift = np.array([0.25, -0.125, 0.0625])
    moved = fn(jnp.asarray(pos + shift), jnp.asarray(radii), SKIN, jnp.asarray(shift))
    assert fn._cache_size() == 1
    assert not bool(first[4]) and int(first[3]) > 0
    for a, b in zip(first, moved, strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    ref = _all(100, jnp.asarray(pos), jnp.asarray(radii))
    for a, b in zip(ref, first[:4], strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_densest_packing_fits_the_sized_capacity():
    """An FCC packing of touching smallest balls (the densest there is), at random offsets,
    never overflows the capacity cell_grid_for derives; the bound is tight enough to matter."""
    rng = np.random.default_rng(8)
    d = 2 * SMALL
    a = d * math.sqrt(2)  # FCC cube edge for touching spheres
    basis = np.array([[0, 0, 0], [0.5, 0.5, 0], [0.5, 0, 0.5], [0, 0.5, 0.5]]) * a
    cells = np.stack(np.meshgrid(*[np.arange(5)] * 3, indexing="ij"), -1).reshape(-1, 3) * a
    lattice = (cells[:, None, :] + basis[None]).reshape(-1, 3)
    n = len(lattice)
    for reach in (1, 2):
        grid = cell_grid_for([0, 0, 0], [5 * a] * 3, d + SKIN, SMALL, n, reach=reach,
                             max_overlap=0.0)
        assert grid.cell_capacity < 20
        for _ in range(10):
            pos = jnp.asarray(lattice + rng.uniform(0, a, 3))
            out = _cells(grid, 12 * n, pos, SMALL, jnp.zeros(3))
            assert not bool(out[4])


def test_cell_grid_for_sizes_the_grid():
    grid = cell_grid_for([-0.05, -0.05, -0.1], [0.05, 0.05, 0.1], 0.016, 0.003, 1000)
    assert grid.cell_size >= 0.016 and grid.reach == 1
    assert grid.dims == (7, 7, 13)  # ceil(0.1 / 0.016), ceil(0.2 / 0.016)
    assert all(d * grid.cell_size >= e for d, e in zip(grid.dims, (0.1, 0.1, 0.2), strict=True))
    assert cell_grid_for([0, 0, 0], [1, 1, 1], 0.016, 0.003, 5).cell_capacity == 5
    half = cell_grid_for([0, 0, 0], [0.1] * 3, 0.016, 0.003, 1000, reach=2)
    assert half.cell_size == pytest.approx(0.008) and half.dims == (13, 13, 13)
    hash(grid)  # a jit static argument
    with pytest.raises(CellGridError):
        cell_grid_for([0, 0, 0], [0, 1, 1], 0.016, 0.003, 10)
    with pytest.raises(CellGridError):
        CellGrid(cell_size=0.01, dims=(0, 1, 1), cell_capacity=1)


def test_cell_capacity_bound():
    # A cube whose diagonal is below the distance holds one point; a cube of side d holds 8
    # (its corners) and no more; the density bound takes over for large cells.
    assert cell_capacity_bound(0.99 / math.sqrt(3), 1.0) == 1
    assert cell_capacity_bound(1.0, 1.0) == 8
    assert cell_capacity_bound(1.0 / math.sqrt(2), 1.0) >= 2  # two opposite face diagonals
    big = cell_capacity_bound(10.0, 1.0)
    assert big == math.floor(math.sqrt(2) * 11.0**3)
    assert big < 18**3  # the sub-cube bound, floor(10 sqrt(3)) + 1 = 18 per axis
