"""How surfel's processes take memory from the operating system.

numpy asks Linux for transparent huge pages (madvise) for its large arrays, and the kernel
then zeroes 2 MB at each first touch of one. Where memory is lent by a hypervisor (a cloud VM,
a CI runner), that zeroing was most of surfel's time in the kernel (perf: clear_page_erms under
do_huge_pmd_anonymous_page). Measured on 2 cores of such a VM, alternated runs:
  * `surfel render c2m.ply --method deferred --backend cpu` (2M points with normals):
    9.9-10.8 s -> 6.6-6.9 s;
  * `surfel lod build c2m.ply -o c2m.lod.npz`: 7.4-10.6 s -> 5.6-5.7 s;
  * `surfel lod build` of 20M points out of core: 41.4-44.5 s -> 35.7-38.5 s.

`no_huge_pages` turns them off for the process and every process it starts (Linux's
PR_SET_THP_DISABLE is inherited across fork and exec); the command line does so first. A
NUMPY_MADVISE_HUGEPAGE set in the environment says what numpy should do, and is left to it.

`keep_freed_memory` has glibc serve every allocation from the process's heap and keep what it
frees (mallopt: no mmap, no trimming), so that a loop of large allocations (the out-of-core
build's workers: the chunks they bin, then their partitions) reuses the pages of the round
before instead of mapping fresh ones, which the kernel faults in and zeroes one by one; the
peak stays the largest round's. (20M points, 2 workers: system time 10.5 -> 8-9 s, wall time
3-5% less; binning 10% faster.)

`drop_when_written` takes a file just written out of the page cache, so that the next writes
reuse its pages instead of taking fresh ones (the out-of-core build's partitions: see
lod/outofcore.py). The pages are dropped once the disk has them (posix_fadvise drops only
clean pages), by a thread that waits for the disk (fdatasync) while the writer goes on. (20M
points, 2 workers: the workers waited 2-3% of their time in fdatasync.)
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import platform
import queue
import threading

PR_SET_THP_DISABLE = 41  # Linux's prctl option (linux/prctl.h)
M_TRIM_THRESHOLD, M_MMAP_MAX = -1, -4  # glibc's mallopt parameters (malloc.h)


def no_huge_pages() -> None:
    """This process and its children in 4 KB pages only (module docstring). Linux only; a
    kernel without the option (before 3.15) keeps them."""
    if platform.system() != "Linux" or "NUMPY_MADVISE_HUGEPAGE" in os.environ:
        return
    ctypes.CDLL(None).prctl(PR_SET_THP_DISABLE, 1, 0, 0, 0)


def keep_freed_memory() -> None:
    """This process's allocations from its heap, and what it frees kept there (module
    docstring). glibc only."""
    if platform.libc_ver()[0] != "glibc":
        return
    libc = ctypes.CDLL(None)  # the C library this process already uses
    libc.mallopt(M_MMAP_MAX, 0)
    libc.mallopt(M_TRIM_THRESHOLD, 2**31 - 1)


_dropping: tuple[int, queue.SimpleQueue] | None = None  # (the process it serves, its queue)
_starting = threading.Lock()


def drop_when_written(file) -> None:
    """Drop the pages of `file` (open, flushed) from the page cache once the disk has them, in
    a background thread of this process (module docstring); `file` may be closed, renamed or
    removed meanwhile. Only a saving: where the OS lacks posix_fadvise, nothing happens."""
    global _dropping
    if not hasattr(os, "posix_fadvise"):
        return
    with _starting:
        if _dropping is None or _dropping[0] != os.getpid():  # none yet, or one a forked parent started
            _dropping = (os.getpid(), queue.SimpleQueue())
            threading.Thread(target=_drop_pages, args=(_dropping[1],), name="surfel-drop-pages",
                             daemon=True).start()
        descriptors = _dropping[1]
    descriptors.put(os.dup(file.fileno()))


def _drop_pages(descriptors: queue.SimpleQueue) -> None:
    while True:
        descriptor = descriptors.get()
        # a file system without these (some FUSE mounts) keeps its pages, as before
        with contextlib.suppress(OSError):
            os.fdatasync(descriptor)
            os.posix_fadvise(descriptor, 0, 0, os.POSIX_FADV_DONTNEED)
        os.close(descriptor)
