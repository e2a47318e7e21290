"""`threads`: serial kernels run over pieces of the rows on numba's threads; commands let idle
OpenMP workers sleep."""

from __future__ import annotations

import os
import subprocess
import sys

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


# in a fresh interpreter: the statement, then a parallel kernel twice, then the CPU time the
# process takes while its main thread sleeps 0.3 s (OpenMP's idle workers spinning)
IDLE_PROBE = """
import os, time
import numba, numpy as np
{}
from surfel.lod.binning import fine_cells
points = np.random.default_rng(0).random((2_000_000, 3))
for _ in range(2):
    fine_cells(points, np.zeros(3), 128.0, 128)
start = time.process_time()
time.sleep(0.3)
print(numba.threading_layer(), os.environ.get("OMP_WAIT_POLICY"), 1000 * (time.process_time() - start))
"""


def _idle_cpu(statement: str, **environment: str) -> tuple[str, str, float]:
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"} | environment
    result = subprocess.run([sys.executable, "-c", IDLE_PROBE.format(statement)], capture_output=True, text=True,
                            check=True, env=env)
    layer, policy, milliseconds = result.stdout.split()[-3:]
    return layer, policy, float(milliseconds)


def test_a_command_lets_idle_openmp_workers_sleep():
    """A command sets OMP_WAIT_POLICY=PASSIVE before numba starts its threads, so that its
    OpenMP workers take no CPU between parallel kernels (by default they spin about 10 ms after
    each); a policy the environment gives stays."""
    command = "from surfel.cli import main; main(['methods'], standalone_mode=False)"
    layer, policy, idle = _idle_cpu(command)
    assert policy == "PASSIVE"
    if layer == "omp":
        assert idle < 2.0, f"{idle:.1f} ms of CPU while idle"
    layer, policy, idle = _idle_cpu(command, OMP_WAIT_POLICY="ACTIVE")
    assert policy == "ACTIVE"
    if layer == "omp" and numba.config.NUMBA_NUM_THREADS > 1:  # the other workers spin the whole 0.3 s
        assert idle > 100.0, f"{idle:.1f} ms of CPU while idle"
