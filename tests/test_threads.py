"""`threads.over_rows`: serial kernels run over pieces of the rows on numba's threads."""

from __future__ import annotations

import numba
import numpy as np
import pytest

from surfel.threads import over_rows


@numba.njit(nogil=True)
def _count_rows(first, stop, visits, pieces):
    for row in range(first, stop):
        visits[row] += 1
        pieces[row] = first


@numba.njit(nogil=True)
def _fail_at(first, stop, bad):
    for row in range(first, stop):
        if row == bad:
            raise ValueError("row out of order")


@pytest.mark.parametrize("rows, grain", [(0, 8), (1, 8), (7, 8), (1000, 8), (10_001, 1), (10_001, 4096)])
@pytest.mark.parametrize("threads", [1, 2])
def test_every_row_is_run_once(rows, grain, threads):
    visits = np.zeros(rows, np.int64)
    pieces = np.full(rows, -1, np.int64)
    previous = numba.get_num_threads()
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    try:
        over_rows(_count_rows, rows, visits, pieces, grain=grain)
    finally:
        numba.set_num_threads(previous)
    assert np.all(visits == 1)
    starts = np.unique(pieces)
    # pieces of at least `grain` rows (the last may hold the remainder), and several of them
    # where the threads have enough rows
    assert len(starts) <= max(1, -(-rows // grain))
    if numba.get_num_threads() > 1 and threads > 1 and rows >= 4 * grain:
        assert len(starts) > 1


def test_a_kernel_error_reaches_the_caller():
    with pytest.raises(ValueError, match="row out of order"):
        over_rows(_fail_at, 10_000, 9_000, grain=16)
