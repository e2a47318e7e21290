"""The k nearest neighbours of every point, the step every estimation starts from.

The neighbours come from a uniform grid of Morton-ordered cells (`grid_knn.py`, exact: the 16
nearest of 1.4M scanned points in 0.8 s on one core, where scipy's cKDTree queries take 8.5 s),
and the points are kept in that cell order:
a point's neighbours then lie close to it in memory, which makes every gather of the kernels
several times faster than in the input's order. The k nearest of a few points (`nearest`) come from
the same grid; widening the neighbourhood of every point queries a k-d tree (scipy's cKDTree,
Maneewongvatana & Mount's sliding midpoint rule). `Neighbourhood.sort`
takes a per-point array into that order, `unsort` back into the input's. Positions are made
relative to their centroid, so that georeferenced coordinates (hundreds of kilometres from
their origin) keep their precision.

Memory: the neighbour lists (N x k int32 indices) are the only O(N k) array; widening queries
them in chunks (`chunked.map_chunks`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree

from ..cloud import scatter_rows, take_rows
from .chunked import map_chunks, progress_bar
from .grid_knn import Grid, sorted_k_nearest


def as_points(positions: np.ndarray) -> np.ndarray:
    """Positions as (N, 3) float64, N > 0, or a ValueError saying what they are instead."""
    points = np.asarray(positions, np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
        raise ValueError(f"positions must have shape (N, 3) with N > 0, got {points.shape}")
    return points


@dataclass(frozen=True)
class Neighbourhood:
    """The points and their k nearest neighbours (nearest first, the point itself first), in
    the grid's Morton cell order (grid_knn.py), positions relative to their centroid."""

    points: np.ndarray  # (N, 3) float64, sorted
    index: np.ndarray   # (N, k) int32 into the sorted points
    order: np.ndarray   # (N,) input index of each sorted point
    grid: Grid | None = None  # the grid of the points (of these very points: see `nearest`)

    @classmethod
    def build(cls, positions: np.ndarray, k: int, workers: int = -1,
              progress: bool | None = None) -> Neighbourhood:
        """The k nearest neighbours (at most N) of each of `positions` (N, 3), N < 2^31; the
        grid search runs on numba's threads, its k-d tree fallback on `workers` (-1: all cores)."""
        if not isinstance(k, (int, np.integer)) or isinstance(k, bool) or k < 1:
            raise TypeError(f"k must be a positive integer, got {type(k).__name__} {k!r:.40}")
        centred = as_points(positions)
        centred = centred - centred.mean(axis=0)
        n = len(centred)
        k = max(1, min(k, n))
        with progress_bar(n, "neighbours", progress) as bar:
            order, index, grid = sorted_k_nearest(centred, k, workers)
            bar.update(n)
        return cls(grid.points, index, order, grid)

    def widened(self, k: int, workers: int = -1, progress: bool | None = None) -> Neighbourhood:
        """The same points, in the same order, with their k nearest neighbours (self if it has
        as many already)."""
        n = len(self.points)
        k = max(1, min(k, n))
        if k <= self.index.shape[1]:
            return self
        tree = cKDTree(self.points, balanced_tree=False)  # on the sorted points: indices are sorted ones

        def query(start: int, stop: int) -> np.ndarray:
            _, found = tree.query(self.points[start:stop], k=k, workers=workers)
            return found.reshape(stop - start, k).astype(self.index.dtype)

        return replace(self, index=map_chunks(query, n, progress, "neighbours"))

    def nearest(self, rows: np.ndarray, k: int, workers: int = -1) -> np.ndarray:
        """(len(rows), k): the k nearest (at most N; nearest first, the point itself first) of
        the points `rows`, from the grid, or from a k-d tree when the points are not the
        grid's (moved: `replace(nbh, points=...)`)."""
        k = max(1, min(k, len(self.points)))
        if self.grid is not None and self.grid.points is self.points:
            return self.grid.nearest(rows, k, workers)
        _, found = cKDTree(self.points, balanced_tree=False).query(self.points[rows], k=k, workers=workers)
        return found.reshape(len(rows), k)

    def within(self, rows: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """(index, count): for each of the points `rows`, index[r, :count[r]] are certainly among
        its k nearest (`Grid.within`; count -1 where none are known, as for points not the grid's)."""
        k = max(1, min(k, len(self.points)))
        if self.grid is not None and self.grid.points is self.points:
            return self.grid.within(rows, k)
        return np.empty((len(rows), k), np.int32), np.full(len(rows), -1, np.int64)

    def first(self, k: int) -> np.ndarray:
        """The k nearest neighbours of each point (all of them if there are fewer), C-contiguous:
        numba compiles a kernel apart for a strided slice of a wider index (the 24 neighbours of
        `prepare --smooth`), so every estimation taking one would be compiled twice."""
        index = self.index[:, :min(k, self.index.shape[1])]
        return index if index.flags.c_contiguous else np.ascontiguousarray(index)

    def sort(self, values: np.ndarray) -> np.ndarray:
        """Per-point values in the input's order, taken into the sorted order."""
        return take_rows(np.asarray(values), self.order)

    def unsort(self, values: np.ndarray) -> np.ndarray:
        """Per-point values in the sorted order, put back into the input's order."""
        return scatter_rows(np.asarray(values), self.order)
