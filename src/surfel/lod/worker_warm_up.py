"""The warm-up of the out-of-core build's workers: loading, or from an empty numba cache (the
first build after an install) compiling, the kernels a partition is built with, shared among
the workers so that each kernel is compiled once.

`share(tasks, after, taken, done)`: a worker takes the next task (`taken`, a counter shared by
the workers) until none is left, a task listed in `after` once the task it needs is done
(`done`, an event per task). `finish(task)` then runs, before a job that needs them, the
tasks the other workers took, each once it is done: those load their kernels from numba's
cache instead of compiling them again. A worker whose own share is done meanwhile bins the
input (needing the binning's task only) and completes a partition while the other still
compiles the tree's kernels, which a partition needs only once its completion is done.

The tasks below, with `binning.warm_up` and outofcore's tree task, run what binning,
`preprocess.complete` and the tree build run, on a few points of the same types, so that they
compile the very signatures a partition needs.
"""

from __future__ import annotations

import threading
import time

import numpy as np

from ..cloud import PointCloud
from ..preprocess import complete
from ..preprocess.borders import BORDER_CONFIRM, border_outwards
from ..preprocess.cells import RADIUS_NEIGHBOURS, clip_lines
from ..preprocess.frames import tangent_frames, unit
from ..preprocess.neighbourhood import Neighbourhood
from ..preprocess.sharp_features import find_sharp_features
from ..preprocess.unsettled import scan_all_nearest

TIMEOUT = 600.0  # seconds of warm-up after which a worker stops waiting for the others


_pending = threading.local()  # per worker: the tasks, their events, and those not run here yet


def share(tasks, after: dict[int, int], taken, done) -> None:
    """Run this worker's share of `tasks` (module docstring); `finish` runs the others'."""
    deadline = time.monotonic() + TIMEOUT
    others = set(range(len(tasks)))
    while True:
        with taken.get_lock():
            index = taken.value
            taken.value += 1
        if index >= len(tasks):
            break
        if index in after:
            done[after[index]].wait(max(0.0, deadline - time.monotonic()))
        tasks[index]()
        done[index].set()
        others.discard(index)
    _pending.state = (tasks, done, others, deadline)


def finish(task=None, but=None) -> None:
    """Run the tasks that other workers took (only `task` if given, all but `but` if given),
    each once it is done there, so that this worker loads their kernels instead of compiling
    them; past the deadline (a worker died) it compiles them itself. Nothing outside a
    warmed-up worker."""
    state = getattr(_pending, "state", None)
    if state is None:
        return
    tasks, done, others, deadline = state
    for index in sorted(others):
        if (task is None or tasks[index] is task) and tasks[index] is not but:
            done[index].wait(max(0.0, deadline - time.monotonic()))
            tasks[index]()
            others.discard(index)


def neighbours() -> None:
    """The kernels of the neighbour search, and of the sharp features and clip lines that
    use it (cells.py, sharp_features.py)."""
    nbh, normals = _neighbourhood()
    features = find_sharp_features(nbh, normals, RADIUS_NEIGHBOURS)
    axes = tangent_frames(np.array(normals), np.ones(len(normals)))  # writable, as complete's normals are
    clip_lines(nbh, normals, axes, features, np.zeros((len(normals), 3)), np.zeros(len(normals)), False)


def borders() -> None:
    """The kernels of the borders (borders.py) and of the wider queries that confirm them
    (grid_knn.py), after `neighbours`."""
    nbh, normals = _neighbourhood()
    rows = np.arange(8)
    nbh.within(rows, BORDER_CONFIRM)
    nbh.nearest(rows, BORDER_CONFIRM)
    scan_all_nearest(nbh.points, BORDER_CONFIRM, rows)  # the rows the grid's shells leave unsettled
    border_outwards(nbh, normals, nbh.first(RADIUS_NEIGHBOURS), False, np.full(len(normals), np.inf))


def completion(normals: bool, geospatial: bool) -> None:
    """Everything else `preprocess.complete` runs on a partition: with its normals, or
    estimating them (PCA, propagated; for a geospatial cloud facing up)."""
    sphere = _sphere()
    complete(PointCloud(sphere, normals=sphere if normals else None, geospatial=geospatial), progress=False)


def _neighbourhood() -> tuple[Neighbourhood, np.ndarray]:
    """(neighbourhood, unit normals) of 64 points on a sphere."""
    nbh = Neighbourhood.build(_sphere(), RADIUS_NEIGHBOURS, progress=False)
    return nbh, unit(nbh.points)


def _sphere() -> np.ndarray:
    return np.random.default_rng(0).normal(size=(64, 3))
