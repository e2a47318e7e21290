"""Errors surfel reports to users as one line (the CLI turns them into exit status 2)."""

from __future__ import annotations

import os


class SurfelError(Exception):
    """A problem the user can fix; its message is printed as one line, without traceback."""


class InputError(SurfelError):
    """A file that cannot be read: the message names the file and the problem."""

    def __init__(self, path: str | os.PathLike | None, problem: str):
        self.path = None if path is None else os.fspath(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}" if self.path else problem)


def points_have(count: int) -> str:
    """'1 point has' or 'N points have': the subject of a message that counts bad points."""
    return "1 point has" if count == 1 else f"{count} points have"


class NoOpenGLError(SurfelError):
    """No OpenGL context could be created."""
