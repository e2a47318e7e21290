"""The terminal's one line when surfel's numba kernels compile (surfel.compile_notice)."""

from __future__ import annotations

import io

import numba

from surfel.compile_notice import NOTICE, compile_notice


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def fresh_kernel(module: str):
    """A function of `module` that numba has never compiled (no cache: compiled when called)."""
    def kernel(x):
        return x + 1

    kernel.__module__ = module
    return numba.njit(kernel)


def test_a_terminal_is_told_once_when_the_first_surfel_kernel_compiles():
    terminal = Terminal()
    with compile_notice(terminal) as listener:
        assert listener is not None
        fresh_kernel("someone.else")(1)
        assert terminal.getvalue() == ""  # another library's kernel: no notice
        fresh_kernel("surfel.probe")(1)
        fresh_kernel("surfel.probe")(1)
        compiled = fresh_kernel("surfel.probe")
        compiled(1)
        compiled(2)  # loaded, not compiled
    assert terminal.getvalue() == NOTICE + "\n"
    fresh_kernel("surfel.probe")(1)  # after the context: no listener left
    assert terminal.getvalue() == NOTICE + "\n"


def test_a_pipe_is_not_told():
    pipe = io.StringIO()
    with compile_notice(pipe) as listener:
        fresh_kernel("surfel.probe")(1)
    assert listener is None and pipe.getvalue() == ""
