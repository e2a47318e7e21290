"""Kernels run over rows on numba's number of threads, compiled as serial code.

A kernel compiled with `parallel=True` costs numba's parfor passes on top of its own compiling,
over the whole loop body with every `inline="always"` callee in it: two to four times as long
as the same kernel compiled serially (25 s against 6 s for the borders' kernel on a 2-core
machine). The kernels of a first render, a first `prepare` and a first hierarchy build after
installing are compiled once, but then take minutes; so the preprocessing, hierarchy and
pinhole kernels are serial functions `kernel(first, stop, *args)` of a range of rows, compiled
with `nogil=True`, and `over_rows` runs them on pieces of the rows from Python threads, which
run in parallel because the kernel releases the GIL. Pieces are handed out as threads come
free, so uneven rows balance.

The rasterizers (splatting, EWA, MLS) keep their parfors: a parfor's loop body is compiled
with its arrays marked as not aliasing one another, which their SIMD loops need (the
`deferred` frame of `surfel bench` took a fifth longer as serial kernels on threads), and
their compiling is mostly LLVM's own, which a serial kernel pays as well.

After each parallel region, OpenMP's workers (numba's "omp" threading layer) spin by default,
waiting for the next one: about 10 ms of a core each time on 2 cores. The row kernels that
follow on this module's Python threads, and llvmpipe's threads, then share the cores with
them. The command line makes them sleep at once instead (`passive_openmp_workers`), which
costs a parallel region a wake-up of tens of microseconds. On 2 cores, the bunny at 1M splats
and 1024 x 1024: `surfel bench`'s `deferred@cpu` frame took 70.0 -> 66.7 ms (medians of 5
alternated runs), its pinhole pass (pinholes.py) 7.2 -> 6.3 ms and `finish_surrounded` 1.3 ->
0.95 ms (4 runs).
"""

from __future__ import annotations

import math
import os
import threading
from concurrent.futures import ThreadPoolExecutor, wait

import numba

PIECES_PER_THREAD = 8  # pieces per thread: a thread that draws slow rows leaves the rest to the others
# the fewest rows of a piece of a pass over a frame's image: a piece costs a numba dispatch and a
# pool round trip (50-100 us), which at 16 pieces outweighed a 1024 x 1024 frame's pinhole passes
IMAGE_GRAIN = 256

_pools: dict[tuple[int, int], ThreadPoolExecutor] = {}  # (process, threads): a fork gets its own
_pools_lock = threading.Lock()


def passive_openmp_workers() -> None:
    """Idle OpenMP workers sleep at once (module docstring), for this process and those it
    starts, unless OMP_WAIT_POLICY in the environment says otherwise. It must run before the
    first parallel kernel: OpenMP reads the policy when numba first starts its threads."""
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def over_rows(kernel, rows: int, *args, grain: int = 1024) -> None:
    """Run kernel(first, stop, *args) over the rows [0, rows), on numba.get_num_threads()
    threads, in pieces of at least `grain` rows (one call when one thread, or one piece,
    suffices). The kernel writes its results into arrays among `args`."""
    threads = numba.get_num_threads()
    pieces = min(math.ceil(rows / grain), threads * PIECES_PER_THREAD)
    if threads == 1 or pieces <= 1:
        kernel(0, rows, *args)
        return
    bounds = [rows * piece // pieces for piece in range(pieces + 1)]
    _run(kernel, [(bounds[piece], bounds[piece + 1]) for piece in range(pieces)], args, threads)


def _run(kernel, pieces: list[tuple], args: tuple, threads: int) -> None:
    pool = _pool(threads)
    futures = [pool.submit(kernel, *piece, *args) for piece in pieces]
    wait(futures)  # all, so that no piece still writes once this returns or raises
    for future in futures:
        future.result()


def _pool(threads: int) -> ThreadPoolExecutor:
    key = (os.getpid(), threads)
    with _pools_lock:
        if key not in _pools:
            _pools[key] = ThreadPoolExecutor(max_workers=threads, thread_name_prefix="surfel-rows")
        return _pools[key]
