"""The first compiling of one of surfel's numba kernels, as numba's event API reports it.

numba broadcasts "numba:compile" when it compiles a kernel for new argument types, not when it
loads the machine code from its cache (`cache=True`): the first such event of a kernel of
surfel's says that its cache is cold (the first run after installing). The terminal's notice
(compile_notice.py) and the helper that compiles a render's kernels ahead (compile_ahead.py)
both act on it, once.
"""

from __future__ import annotations

import threading

from numba.core import event


class FirstCompile(event.Listener):
    """While `watching`, calls `first()` once, in the compiling thread and before the kernel
    compiles, when a kernel of a module whose name starts with `prefix` starts compiling."""

    def __init__(self, prefix: str):
        self.prefix = prefix
        self._lock = threading.Lock()  # kernels may first be called from several threads
        self._seen = False

    def watching(self):
        """The context within which the events are watched (yields this listener)."""
        return event.install_listener("numba:compile", self)

    def on_start(self, ev) -> None:
        function = getattr(ev.data["dispatcher"], "py_func", None)
        if not getattr(function, "__module__", "").startswith(self.prefix):
            return
        with self._lock:
            if self._seen:
                return
            self._seen = True
        self.first()

    def on_end(self, ev) -> None:
        pass

    def first(self) -> None:
        raise NotImplementedError
