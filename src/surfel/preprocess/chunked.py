"""The chunked, progress-reporting loop that every per-point pass of `surfel.preprocess` runs in.

A pass computes rows start:stop of its (N, ...) outputs for one chunk of CHUNK points at a time
(a numba kernel, parallel over the chunk's points, plus numpy around it), so that its
temporaries stay O(CHUNK k) whatever N is; only the outputs are O(N). A progress bar (tqdm, on
stderr) follows the chunks when asked, or by default when there are more than
PROGRESS_MIN_POINTS points.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from tqdm import tqdm

CHUNK = 1 << 18                  # points per step (bounds the temporary memory of a pass)
PROGRESS_MIN_POINTS = 1_000_000  # automatic progress bars above this many points


def map_chunks(function: Callable[[int, int], np.ndarray | tuple[np.ndarray, ...]], n: int,
               progress: bool | None = False, desc: str = "") -> np.ndarray | tuple[np.ndarray, ...]:
    """Run function(start, stop) over consecutive chunks of range(n) and gather its results.

    The function returns rows start:stop of one array, or of a tuple of arrays; the whole
    (n, ...) arrays come back, with the dtypes and trailing shapes of the first chunk's.
    progress: None shows a bar named `desc` above PROGRESS_MIN_POINTS points; True/False force it.
    """
    outputs: tuple[np.ndarray, ...] = ()
    single = False
    with progress_bar(n, desc, progress) as bar:
        for start in range(0, n, CHUNK):
            stop = min(start + CHUNK, n)
            parts = function(start, stop)
            single = isinstance(parts, np.ndarray)
            parts = (parts,) if single else parts
            if not outputs:
                outputs = tuple(np.empty((n, *part.shape[1:]), part.dtype) for part in parts)
            for output, part in zip(outputs, parts, strict=True):
                output[start:stop] = part
            bar.update(stop - start)
    return outputs[0] if single else outputs


def progress_bar(n: int, desc: str, progress: bool | None) -> tqdm:
    """A points/s bar named `desc` over n points (progress as `map_chunks`'s)."""
    show = n > PROGRESS_MIN_POINTS if progress is None else bool(progress)
    return tqdm(total=n, desc=f"surfel: {desc}", unit="pt", unit_scale=True, disable=not show, leave=False)
