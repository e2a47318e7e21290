"""Compiling a CPU render's kernels in a second process while this one compiles the
preprocessing's: the first render after installing, on two cores instead of one.

numba compiles one kernel at a time in a process (its compiler lock) and keeps the machine code
in its cache on disk. The first CPU render after installing compiles the kernels that complete
the cloud (normals, radii, clip lines: `preprocess`), then the method's (binning,
rasterizing, pinholes, the box filter), one after the other on one core: `surfel render
--demo` took 59-63 s on 2 cores of an AMD EPYC VM, 26 s of it before the method's kernels.

`CompileAhead` watches numba's "numba:compile" events (broadcast when a kernel is compiled,
not when it is loaded from the cache: compile_events.py) while the cloud is completed. When the first
preprocessing kernel starts compiling, the cache is cold, and a helper process
(`python -m surfel.compile_ahead_worker SPEC`) renders a small synthetic cloud with the same
method on the CPU, with the argument types the real render will pass (its clip lines, its
shading, its supersampling: `render_spec`), which compiles the method's kernels into the
cache on the other core. Before its own render, this process waits for the helper
(`wait`), then loads those kernels from the cache instead of compiling them. A helper that
fails or cannot start costs nothing but the attempt: whatever it left uncompiled compiles
here, as before. With the cache warm no event comes and no helper starts. (`surfel render
--demo` from an empty cache: 59-63 s -> 38-41 s, its render then loading every kernel.)
"""

from __future__ import annotations

import json
import subprocess
import sys

from .compile_events import FirstCompile

WORKER_MODULE = "surfel.compile_ahead_worker"
WAIT_LIMIT = 600.0  # seconds this process waits for the helper before compiling on its own
TRIGGER_PREFIX = "surfel.preprocess."  # a kernel of these modules compiling: the cache is cold


def render_spec(method: str, params, *, clip: bool, width: int, height: int, shading: str,
                supersample: int | None) -> str | None:
    """The helper's command-line argument: what fixes the types of the method's kernel
    arguments (JSON), or None when the parameters do not serialise."""
    try:
        values = {name: getattr(params, name) for name in type(params).names()}
        return json.dumps({"method": method, "params": values, "clip": clip, "size": [width, height],
                           "shading": shading, "supersample": supersample})
    except (TypeError, ValueError):
        return None


class CompileAhead(FirstCompile):
    """Starts the helper for `spec` (render_spec's; None: never) at the first compiling of a
    preprocessing kernel while `watching`; `wait` then waits for it (module docstring)."""

    def __init__(self, spec: str | None):
        super().__init__(TRIGGER_PREFIX)
        self.spec = spec
        self.helper: subprocess.Popen | None = None

    def __enter__(self) -> CompileAhead:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def first(self) -> None:
        if self.spec is None:
            return
        try:
            self.helper = subprocess.Popen([sys.executable, "-m", WORKER_MODULE, self.spec],
                                           stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                           stderr=subprocess.DEVNULL)
        except OSError:  # no interpreter to start (an embedded Python): compile here, as before
            self.helper = None

    def wait(self) -> None:
        """Wait for the helper, if one started (killed past WAIT_LIMIT)."""
        if self.helper is None:
            return
        try:
            self.helper.wait(WAIT_LIMIT)
        except subprocess.TimeoutExpired:
            pass
        self.close()

    def close(self) -> None:
        """Stop the helper if it still runs (the render failed, or the helper ran too long)."""
        if self.helper is not None and self.helper.poll() is None:
            self.helper.kill()
            self.helper.wait()
        self.helper = None
