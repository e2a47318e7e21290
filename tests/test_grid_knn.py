"""The grid neighbour search (preprocess/grid_knn.py) finds what a k-d tree finds."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from surfel.cloud import scatter_rows, stable_order
from surfel.preprocess.grid_knn import sorted_k_nearest
from surfel.preprocess.neighbourhood import Neighbourhood
from surfel.preprocess.unsettled import scan_all_nearest


def assert_exact(points: np.ndarray, k: int) -> None:
    """The grid's k nearest of every point are at the k-d tree's k nearest distances, the
    point itself first, and the order is a permutation."""
    order, index, _ = sorted_k_nearest(points, k)
    assert np.array_equal(np.sort(order), np.arange(len(points)))
    ordered = points[order]
    assert index.shape == (len(points), k) and index.dtype == np.int32
    assert np.array_equal(index[:, 0], np.arange(len(points)))
    found = np.linalg.norm(ordered[index] - ordered[:, None], axis=2)
    expected, _ = cKDTree(ordered).query(ordered, k=k)
    expected = expected.reshape(len(points), k)
    assert np.allclose(np.sort(found, axis=1), np.sort(expected, axis=1), rtol=0, atol=1e-12)
    assert (np.diff(found[:, 1:], axis=1) >= 0).all()  # nearest first after the point itself
    # no neighbour twice
    assert (np.diff(np.sort(index, axis=1), axis=1) > 0).all()


rng = np.random.default_rng(7)


@pytest.mark.parametrize("name, points, k", [
    ("cube", rng.random((20_000, 3)), 16),
    ("plane", np.c_[rng.random((20_000, 2)), np.zeros(20_000)], 16),
    ("sphere", (lambda v: v / np.linalg.norm(v, axis=1, keepdims=True))(rng.normal(size=(20_000, 3))), 8),
    ("lattice", np.stack(np.meshgrid(np.arange(30), np.arange(30), np.arange(3)), -1).reshape(-1, 3) * 1.0, 16),
    ("far outlier and near duplicates", np.r_[rng.random((5_000, 3)), [[1e6, 0, 0]], rng.random((10, 3)) * 1e-9], 16),
    ("coincident", np.zeros((5_000, 3)), 16),
    ("clusters far apart", np.r_[rng.random((3_000, 3)), rng.random((3_000, 3)) * 1e-3 + 50.0], 16),
    ("fewer points than k", rng.random((5, 3)), 5),
    ("one point", rng.random((1, 3)), 1),
    ("georeferenced line", np.c_[np.linspace(0, 10, 4_000), np.zeros(4_000), np.zeros(4_000)] + 4e5, 6),
    # neighbour distances jumping from point to point: the bound from the point before fails
    ("dense blobs in a sparse plane", np.r_[np.c_[rng.random((8_000, 2)), np.zeros(8_000)],
                                            (rng.random((40, 1, 3)) * [1, 1, 0]
                                             + rng.normal(size=(40, 100, 3)) * 1e-4).reshape(-1, 3)], 16),
    ("uniform volume, k = 24", rng.random((20_000, 3)), 24),
])
def test_grid_matches_kd_tree(name, points, k):
    assert_exact(np.asarray(points, np.float64), k)


def test_neighbourhood_sorts_and_unsorts():
    points = rng.random((3_000, 3)) * [5.0, 1.0, 0.1]
    nbh = Neighbourhood.build(points, 12)
    assert np.allclose(nbh.unsort(nbh.points) + points.mean(axis=0), points)
    values = rng.random(3_000)
    assert np.array_equal(nbh.unsort(nbh.sort(values)), values)
    rows = rng.random((3_000, 2, 3)).astype(np.float32)  # rows of several values: a compiled scatter
    unsorted = nbh.unsort(rows)
    assert unsorted.dtype == np.float32 and np.array_equal(unsorted[nbh.order], rows)
    expected, _ = cKDTree(points).query(points, k=12)
    found = np.linalg.norm(nbh.points[nbh.index] - nbh.points[:, None], axis=2)
    assert np.allclose(np.sort(found, axis=1), nbh.sort(expected), atol=1e-12)


@pytest.mark.parametrize("values", [
    rng.integers(0, 255, 1_001).astype(np.uint8),            # rows of one byte
    rng.integers(-999, 999, (1_001, 3)).astype(np.int16),     # rows of 6 bytes
    rng.random((1_001, 3)),
    rng.random((1_001, 2, 3)).astype(np.float32),
    rng.random((1_001, 6))[:, ::2],                           # strided
    rng.random(1_001) < 0.5,
    np.zeros((0, 3), np.float32),
])
def test_scatter_rows_moves_each_row_to_its_destination(values):
    destination = rng.permutation(len(values))
    expected = np.empty_like(values)
    expected[destination] = values
    moved = scatter_rows(values, destination)
    assert moved.dtype == values.dtype and moved.shape == values.shape and np.array_equal(moved, expected)


def test_first_neighbours_are_contiguous():
    """Neighbourhood.first of a wider neighbourhood (prepare --smooth's 24) is a C-contiguous
    copy of its first columns, and the index itself when all of them are asked for: numba would
    compile every estimation taking a strided slice a second time."""
    nbh = Neighbourhood.build(rng.random((2_000, 3)), 24)
    first = nbh.first(16)
    assert first.flags.c_contiguous and np.array_equal(first, nbh.index[:, :16])
    for k in (24, 40):  # all of them: the index itself, not a copy
        assert np.shares_memory(nbh.first(k), nbh.index) and nbh.first(k).shape == (2_000, 24)


@pytest.mark.parametrize("name, points, k, wide", [
    ("plane", np.c_[rng.random((20_000, 2)), np.zeros(20_000)], 16, 64),
    ("cube", rng.random((20_000, 3)), 8, 40),
    ("far outlier and near duplicates",
     np.r_[rng.random((5_000, 3)), [[1e6, 0, 0]], rng.random((10, 3)) * 1e-9], 16, 64),
    ("coincident", np.zeros((5_000, 3)), 16, 64),
    ("clusters far apart", np.r_[rng.random((3_000, 3)), rng.random((3_000, 3)) * 1e-3 + 50.0], 16, 64),
    ("fewer points than k", rng.random((20, 3)), 4, 20),
])
def test_grid_queries_match_kd_tree(name, points, k, wide):
    """The grid's wider queries of some points (Grid.nearest) find the k-d tree's distances,
    the point itself first, nearest first, no neighbour twice."""
    points = np.asarray(points, np.float64)
    _, _, grid = sorted_k_nearest(points, k)
    rows = np.r_[np.arange(0, len(points), 7), len(points) - 1]
    index = grid.nearest(rows, wide)
    assert index.shape == (len(rows), wide)
    assert np.array_equal(index[:, 0], rows)
    found = np.linalg.norm(grid.points[index] - grid.points[rows][:, None], axis=2)
    expected, _ = cKDTree(grid.points).query(grid.points[rows], k=wide)
    assert np.allclose(np.sort(found, axis=1), expected, rtol=0, atol=1e-12)
    assert (np.diff(found[:, 1:], axis=1) >= 0).all()
    assert (np.diff(np.sort(index, axis=1), axis=1) > 0).all()


@pytest.mark.parametrize("name, points", [
    ("cube", rng.random((3_000, 3))),
    ("lattice, ties everywhere", np.stack(np.meshgrid(np.arange(12), np.arange(12), np.arange(12)), -1).reshape(-1, 3)),
    ("coincident", np.zeros((200, 3))),
    ("a line in order, the points beside each bounding it tightly", np.c_[np.arange(500), np.zeros((500, 2))]),
])
def test_scanning_all_points_finds_the_kd_trees_neighbours(name, points):
    """The fallback for the few points the grid's shells leave unsettled (scan_all_nearest)
    finds the k-d tree's distances, the point itself first, nearest first, no neighbour twice,
    equal distances in index order (whichever points bound its search)."""
    points = np.asarray(points, np.float64)
    rows = np.r_[0, np.arange(5, len(points), 97), len(points) - 1]
    index = scan_all_nearest(points, 40, rows)
    assert np.array_equal(index[:, 0], rows)
    for row, p in zip(index, rows, strict=True):
        others = np.delete(np.arange(len(points)), p)
        distance2 = ((points[others] - points[p]) ** 2).sum(axis=1)
        assert np.array_equal(row[1:], others[np.argsort(distance2, kind="stable")[:39]])
    found = np.linalg.norm(points[index] - points[rows][:, None], axis=2)
    expected, _ = cKDTree(points).query(points[rows], k=40)
    assert np.allclose(np.sort(found, axis=1), expected, rtol=0, atol=1e-12)
    assert (np.diff(found[:, 1:], axis=1) >= 0).all()
    assert (np.diff(np.sort(index, axis=1), axis=1) > 0).all()


def test_moved_neighbourhood_queries_its_own_points():
    """A neighbourhood whose points were replaced (moved) does not query the stale grid."""
    from dataclasses import replace

    points = rng.random((2_000, 3))
    nbh = Neighbourhood.build(points, 8)
    moved = replace(nbh, points=nbh.points[::-1].copy())
    rows = np.arange(0, 2_000, 10)
    found = np.linalg.norm(moved.points[moved.nearest(rows, 30)] - moved.points[rows][:, None], axis=2)
    expected, _ = cKDTree(moved.points).query(moved.points[rows], k=30)
    assert np.allclose(np.sort(found, axis=1), expected, atol=1e-12)


def test_stable_order_is_numpys():
    """The packed sort of the cell keys is numpy's stable argsort, duplicates in index order,
    and so is its fallback for keys too wide to pack."""
    keys = rng.integers(0, 1 << 20, 100_000) // 7
    assert np.array_equal(stable_order(keys), np.argsort(keys, kind="stable"))
    runs = np.sort(keys)
    runs[::50] = rng.integers(0, 1 << 20, len(runs[::50])) // 7  # mostly in order: merged, not partitioned
    assert np.array_equal(stable_order(runs), np.argsort(runs, kind="stable"))
    wide = rng.integers(0, 1 << 62, 1_000) | (1 << 61)
    wide[::3] = wide[0]
    assert np.array_equal(stable_order(wide), np.argsort(wide, kind="stable"))
    assert np.array_equal(stable_order(np.array([5], np.int64)), [0])


def test_ranked_candidates_are_the_stable_sorts_first():
    """Placing offered candidates by rank keeps the `take` nearest in a stable sort's order (ties
    in the order offered, as inserting them one by one did), whatever lands in the scratch entry."""
    from surfel.preprocess.grid_knn import _ranked

    for near, take in ((24, 15), (15, 15), (40, 15), (7, 3), (1, 0), (0, 0)):
        distances = rng.integers(0, 6, near).astype(np.float64)  # many ties
        candidates = rng.permutation(1000)[:near]
        best_d, best_i = np.full(take + 2, -1.0), np.full(take + 2, -1, np.int64)
        _ranked(distances, candidates, near, take, best_d, best_i)
        expected = np.argsort(distances, kind="stable")[:take]
        assert np.array_equal(best_d[1:take + 1], distances[expected])
        assert np.array_equal(best_i[1:take + 1], candidates[expected])
        assert best_d[0] == -1.0  # the point itself's entry is left alone


def test_cell_table_finds_every_occupied_cell_and_no_other():
    """The hash table of the occupied cells gives each key's run, and -1 for keys of empty
    cells (here the keys between and around the occupied ones)."""
    from surfel.preprocess.grid_knn import _find, cell_table

    keys = np.unique(rng.integers(0, 1 << 40, 5_000)) * 2  # even: the odd keys are empty cells
    slots = cell_table(keys)
    assert len(slots) >= 2 * len(keys)
    assert all(_find(key, keys, slots) == run for run, key in enumerate(keys.tolist()))
    assert all(_find(key + 1, keys, slots) == -1 for key in keys[::10].tolist())


@pytest.mark.parametrize("name, points", [
    ("plane", np.c_[rng.random((20_000, 2)), np.zeros(20_000)]),
    ("lattice", np.stack(np.meshgrid(np.arange(60), np.arange(60), np.arange(2)), -1).reshape(-1, 3) * 1.0),
    ("coincident", np.zeros((5_000, 3))),
])
def test_points_within_reach_are_among_the_nearest(name, points):
    """Grid.within lists, for each point, points that are among its k nearest whichever way
    ties are broken (fewer than k others lie strictly nearer), itself included, no point twice;
    on a plane most points get more than their grid neighbourhood's k."""
    k, wide = 16, 64
    _, _, grid = sorted_k_nearest(np.asarray(points, np.float64), k)
    rows = np.arange(0, len(points), 3)
    sure, count = grid.within(rows, wide)
    assert sure.shape == (len(rows), wide) and ((count >= -1) & (count <= wide)).all()
    tree = cKDTree(grid.points)
    for r in np.flatnonzero(count > 0):
        listed = sure[r, :count[r]]
        assert rows[r] in listed and len(np.unique(listed)) == count[r]
        distance = np.linalg.norm(grid.points[listed] - grid.points[rows[r]], axis=1).max()
        nearer = tree.query_ball_point(grid.points[rows[r]], distance * (1 - 1e-12))
        assert len(nearer) < wide
    if name == "coincident":
        assert (count == -1).all()  # a dense grid knows none
    elif name == "plane":
        assert (count > k).mean() > 0.5
