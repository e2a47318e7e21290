"""One line on a terminal when surfel's numba kernels compile: the first run after installing,
or the first of a kind of render (a method, a backend) that needs kernels not compiled yet.

numba compiles a kernel the first time it meets new argument types and keeps the machine code
in its cache on disk (`cache=True`), so the first render after installing compiles for about
40 s on 2 cores (the README's first-run numbers; compile_ahead.py keeps both busy) with nothing
to show meanwhile. numba's
event API broadcasts "numba:compile" only when a kernel is compiled, not when it is loaded
from the cache: the first such event of a surfel kernel (compile_events.py) prints NOTICE, once. Only on a
terminal, so that a pipeline's logs stay as they were.
"""

from __future__ import annotations

import contextlib

from .compile_events import FirstCompile

NOTICE = ("surfel: compiling numba kernels the first time they are needed (up to a minute); "
          "they are cached for later runs")


class CompileNotice(FirstCompile):
    """Prints NOTICE to `stream` when the first surfel kernel starts compiling."""

    def __init__(self, stream):
        super().__init__("surfel.")
        self.stream = stream

    def first(self) -> None:
        print(NOTICE, file=self.stream, flush=True)


@contextlib.contextmanager
def compile_notice(stream):
    """Within the context, NOTICE on `stream`, if it is a terminal, when the first surfel
    kernel compiles; yields the listener, or None when `stream` is no terminal."""
    if not stream.isatty():
        yield None
        return
    with CompileNotice(stream).watching() as listener:
        yield listener
