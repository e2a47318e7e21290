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
build's partitions) reuses the pages of the round before instead of mapping fresh ones, which
the kernel faults in and zeroes one by one; the peak stays the largest round's. (20M points,
2 workers: system time 10.5 -> 8-9 s, wall time 3-5% less.)
"""

from __future__ import annotations

import ctypes
import os
import platform

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
